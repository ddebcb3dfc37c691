// Algorithm II: its progress weights, the records and structures of its blocks (vertices,
// cells, the cell map, the candidate triangles, boundary edges), their page windows, and the
// bounds pass. (Part of Cluster.cpp's translation unit, as Algorithm I's passes are of
// Decimate.cpp: everything stays internal and inlinable.)
namespace sipmss::algorithms
{
namespace
{
using storage::Array;
using storage::DML;

// Progress weights: seconds per element of each phase, measured in core on one thread on a
// 2M-triangle scan at grid 300 (docs/architecture.md, "Progress and abort"). Only their ratios
// matter.
namespace kWork
{
constexpr double kBounds = 1.2e-8;     // per input vertex (a vertices-only read)
constexpr double kCluster = 2.3e-7;    // per input vertex + face
constexpr double kBoundaries = 1.0e-7; // per input face (its three edges)
constexpr double kTriangles = 1.8e-7;  // per candidate triangle + occupied cell
constexpr double kOutput = 1.9e-7;     // per occupied cell + output triangle
// Before the clustering pass: a surface occupies about kSurfaceCells * m^2 cells of a grid of
// maximum dimension m, and there are about kCandidatesPerCell candidate triangles per cell.
constexpr double kSurfaceCells = 3.0;
constexpr double kCandidatesPerCell = 2.0;
}

double EstimatedCells(std::uint64_t V, int m)
{
  return std::min(double(V), kWork::kSurfaceCells * double(m) * double(m));
}

// The work after the clustering pass's read, for the (estimated or counted) occupied cells and
// candidate triangles.
double ClusterWorkAfter(double cells, double candidates, std::uint64_t F, const ClusterOptions& o)
{
  return (o.boundaryQuadrics ? kWork::kBoundaries * double(F) : 0.0) +
    kWork::kTriangles * (candidates + cells) + kWork::kOutput * (cells + candidates);
}

double ClusterWorkAfterRead(std::uint64_t V, std::uint64_t F, int m, const ClusterOptions& o)
{
  const double cells = EstimatedCells(V, m);
  return ClusterWorkAfter(cells, std::min(double(F), kWork::kCandidatesPerCell * cells), F, o);
}

struct VertexRec
{
  float x, y, z;
  std::uint32_t cell;
};

// Exact cell sums. A cell's quadric and the sum of its faces' corners are kept in fixed point,
// in 128-bit integers: integer addition is associative, so the sums (and the representative)
// do not depend on the order in which the faces come, nor on how they are split into pieces
// whose sums are added later (the distributed clustering). docs/architecture.md, "Exact cell
// sums".
__extension__ typedef __int128 Fixed;
__extension__ typedef unsigned __int128 FixedSum; // (sums wrap, defined, instead of overflowing)

// A weighted plane w (n.p + d)^2 is the square of (u.p + delta) with u = sqrt(w) n and delta =
// sqrt(w) d: its quadric's ten coefficients are the products u_i u_j, u_i delta, delta^2. Each
// face's u and delta are rounded once to 64-bit integers, and the products are exact in 128 bits:
// four conversions a face, not ten. The positions are relative to the grid's centre, so that
// |delta| <= sqrt(w) D / 2 for a box of diagonal D wherever the scan lies.
struct FixedQuadric
{
  FixedSum q[10]; // the layout of Quadric
};

inline void AddTo(FixedQuadric& dst, const FixedQuadric& src)
{
  for (int i = 0; i < 10; ++i)
  {
    dst.q[i] += src.q[i];
  }
}

// Rounds y (in fixed units) toward zero, within +-2^53 (a vertex far outside the grid's given
// bounds saturates), NaN as 0.
inline std::int64_t ToFixed(double y)
{
  constexpr double kLimit = 0x1p53;
  if (!(std::abs(y) < kLimit))
  {
    y = y > 0 ? kLimit : (y < 0 ? -kLimit : 0.0);
  }
  return static_cast<std::int64_t>(y);
}

// The units of a run's fixed-point numbers, from the grid's box (diagonal D): u in 2^-53 of the
// largest sqrt(w) (max(1, boundary weight) D^2 bounds a face's area and a boundary plane's
// weight), delta in 2^-53 of that times D / 2, both powers of two. A sum of 2^21 planes of that
// largest weight fits in 2^127; a face whose area is 10^12 times below the largest keeps 10
// digits in u (its sqrt(w) is 10^6 times smaller), a face 10^6 times below it 13.
// Corner positions are in 2^-15 cell sizes from the grid's origin (within 2^31 on a grid of
// 65535 cells; clamped beyond, a vertex outside the grid's given bounds), in single precision.
struct FixedUnits
{
  double u = 1, delta = 1;     // fixed units per unit of u, of delta
  double back[10];             // a coefficient's value per fixed unit
  float origin[4] = {};        // the grid's origin, rounded to float (the corners' zero)
  float position = 1;          // fixed units per unit of length
  double positionBack = 1;
  std::array<double, 3> centre{};
  static FixedUnits Make(const std::array<double, 3>& origin, double cellSize,
    const std::array<std::uint32_t, 3>& dims, double boundaryWeight)
  {
    FixedUnits f;
    double d2 = 0;
    for (int k = 0; k < 3; ++k)
    {
      const double extent = dims[k] * cellSize;
      f.centre[k] = origin[k] + 0.5 * extent;
      d2 += extent * extent;
    }
    const double D = std::max(std::sqrt(d2), 1e-150);
    const double largestU = std::sqrt(std::max(1.0, boundaryWeight)) * D;
    f.u = std::ldexp(1.0, 53 - (std::ilogb(largestU) + 1));
    f.delta = std::ldexp(1.0, 53 - (std::ilogb(largestU * 0.5 * D) + 1));
    const double uu = 1.0 / (f.u * f.u), ud = 1.0 / (f.u * f.delta), dd = 1.0 / (f.delta * f.delta);
    const double back[10] = { uu, uu, uu, ud, uu, uu, ud, uu, ud, dd };
    std::copy_n(back, 10, f.back);
    for (int k = 0; k < 3; ++k)
    {
      f.origin[k] = static_cast<float>(origin[k]);
    }
    f.position = static_cast<float>(0x1p15 / cellSize);
    f.positionBack = 1.0 / double(f.position);
    return f;
  }
  // The quadric of the plane n.(p - centre) + d = 0 (unit n) with weight w.
  FixedQuadric Plane(const double n[3], double d, double w) const
  {
    const double s = std::sqrt(w);
    const Fixed a = ToFixed(s * n[0] * this->u), b = ToFixed(s * n[1] * this->u),
                c = ToFixed(s * n[2] * this->u), e = ToFixed(s * d * this->delta);
    return { { FixedSum(a * a), FixedSum(a * b), FixedSum(a * c), FixedSum(a * e),
      FixedSum(b * b), FixedSum(b * c), FixedSum(b * e), FixedSum(c * c), FixedSum(c * e),
      FixedSum(e * e) } };
  }
  // A corner's position (x, y, z of the record; the fourth lane is ignored), in one vector
  // conversion where there is SSE2.
  void Corner(const float* xyz, std::int32_t out[4]) const
  {
    constexpr float kLimit = 2147483520.f; // (the largest float below 2^31)
#ifdef __SSE2__
    __m128 p = _mm_mul_ps(_mm_sub_ps(_mm_loadu_ps(xyz), _mm_loadu_ps(this->origin)),
      _mm_set1_ps(this->position));
    p = _mm_min_ps(_mm_max_ps(p, _mm_set1_ps(-kLimit)), _mm_set1_ps(kLimit));
    _mm_storeu_si128(reinterpret_cast<__m128i*>(out), _mm_cvttps_epi32(p));
#else
    for (int k = 0; k < 3; ++k)
    {
      const float p = (xyz[k] - this->origin[k]) * this->position;
      out[k] = p == p ? static_cast<std::int32_t>(std::min(std::max(p, -kLimit), kLimit)) : 0;
    }
#endif
  }
  // The quadric (about the centre) in doubles.
  Quadric ToDouble(const FixedQuadric& f) const
  {
    Quadric q;
    for (int i = 0; i < 10; ++i)
    {
      q.q[i] = double(Fixed(f.q[i])) * this->back[i];
    }
    return q;
  }
};

// With ClusterOptions::exactSums off: a cell's quadric and corner sum in doubles, added in the
// input's order (the corners about FixedUnits::centre).
struct PlainSums
{
  Quadric q;
  double sum[3];
};

struct CellRec
{
  std::uint64_t corners;   // corners of faces in the cell (the mean's count)
  std::uint64_t triangles; // candidate output triangles whose smallest cell is this one (the
                           // size of its bucket in TriangleSet::Finish)
  // The cell's plane quadric sums (Quadric.h) about FixedUnits::centre, and the sum of its faces'
  // corners: exact (q and sum; FixedUnits::position from the grid's origin), or in doubles
  // (plain). What a face's update touches comes first: with plain sums the record's first
  // kPlainBytes (120), two cache lines of a record that starts on one (256-byte records: a block
  // grown by DML::Resize starts on a huge page; the presized in-core block, InitialCells, comes
  // from calloc and starts 16 bytes past a page, three lines then: docs/architecture.md).
  union
  {
    FixedQuadric q;
    PlainSums plain;
  };
  FixedSum sum[3];
  float first[3]; // its lexicographically smallest corner (the paper's sampled-vertex fallback)
  std::uint32_t vertices; // input vertices in the cell (the point data's mean)
  std::uint8_t pad[16];   // (to 256 bytes: a record per four cache lines)
};
static_assert(sizeof(CellRec) == 256, "CellRec: four cache lines");
constexpr std::size_t kPlainBytes = offsetof(CellRec, plain) + sizeof(PlainSums);

struct KeySlot
{
  std::uint64_t key; // grid key + 1; 0 = empty
  std::uint64_t cell;
};

struct EdgeRec
{
  std::uint32_t a, b;  // a < b
  std::uint32_t third; // the face's third vertex (to rebuild the face's plane)
  std::uint32_t flip;  // 1 when the face runs b -> a
};

struct TriSlot
{
  std::uint32_t v[3]; // canonical rotation (smallest first), orientation kept
  std::uint32_t used; // 0 = empty
};

// The structures of a clustering run on V vertices and F faces over a grid of gridCells cells
// (the paper's Config table).
// channels: the attribute channels (ClusterOptions::attributes; an upper bound before the header
// is known): k floats per vertex, an extension per cell.
void AddClusterStructures(storage::Profile& profile, std::uint64_t V, std::uint64_t F,
  std::uint64_t gridCells, std::size_t channels)
{
  const std::uint64_t maxCells = std::min<std::uint64_t>(V, gridCells);
  if (channels)
  {
    profile.structures.push_back({ "vertex attributes", channels * sizeof(float), V, 0.0 });
    profile.structures.push_back(
      { "cell attribute quadrics", AttributeExtraSize(channels) * sizeof(double), maxCells, 0.0 });
  }
  profile.structures.push_back({ "vertices", sizeof(VertexRec), V, 0.0 });
  profile.structures.push_back({ "cells", sizeof(CellRec), maxCells, 0.0 });
  profile.structures.push_back({ "cell map", sizeof(KeySlot), 2 * maxCells, 0.0 });
  profile.structures.push_back({ "candidate triangles", sizeof(TriSlot), F, 0.0 });
}

using storage::PinWindow;

using detail::Mix; // (Distributed.h)

constexpr std::uint32_t kNoCell = std::numeric_limits<std::uint32_t>::max();

// Hash map grid key -> dense cell id in a DML block; doubles when half full.
class CellMap
{
public:
  CellMap(DML& dml, Progress& progress)
    : dml_(dml)
    , slots_(dml, 1u << 12)
    , progress_(progress)
  {
  }
  // Returns the cell of `key`, inserting it as `next` if absent (then *inserted = true).
  std::uint32_t FindOrInsert(std::uint64_t key, std::uint32_t next, bool* inserted)
  {
    if ((this->size_ + 1) * 2 > this->slots_.Size())
    {
      this->Grow();
    }
    const std::uint64_t mask = this->slots_.Size() - 1;
    std::uint64_t i = this->Home(key, this->slots_.Size());
    for (;;)
    {
      KeySlot s = this->slots_.Get(i);
      if (s.key == 0)
      {
        this->slots_.Set(i, KeySlot{ key + 1, next });
        ++this->size_;
        *inserted = true;
        return next;
      }
      if (s.key == key + 1)
      {
        *inserted = false;
        return static_cast<std::uint32_t>(s.cell);
      }
      i = (i + 1) & mask;
    }
  }
  void Release() { this->slots_.Close(); }
  // In core, starts loading the home slot of `key` (a lookup a few vertices later finds it in
  // the cache); out of core nothing.
  void Prefetch(std::uint64_t key) const
  {
    if (const auto* base = static_cast<const KeySlot*>(this->dml_.BasePointer(this->slots_.Id())))
    {
      __builtin_prefetch(base + this->Home(key, this->slots_.Size()));
    }
  }
  // The cell of `key`, or kNoCell.
  std::uint32_t Find(std::uint64_t key) const
  {
    const std::uint64_t mask = this->slots_.Size() - 1;
    for (std::uint64_t i = this->Home(key, this->slots_.Size());; i = (i + 1) & mask)
    {
      const KeySlot s = this->slots_.Get(i);
      if (s.key == 0)
      {
        return kNoCell;
      }
      if (s.key == key + 1)
      {
        return static_cast<std::uint32_t>(s.cell);
      }
    }
  }
  // f(key, cell) for every entry, in slot order.
  template <class F>
  void ForEach(F&& f)
  {
    this->slots_.ForEachChunk(0, this->slots_.Size(), storage::Access::Read,
      [&](KeySlot* data, std::uint64_t, std::uint64_t count) {
        for (std::uint64_t j = 0; j < count; ++j)
        {
          if (data[j].key != 0)
          {
            f(data[j].key - 1, static_cast<std::uint32_t>(data[j].cell));
          }
        }
      });
  }

private:
  static std::uint64_t Home(std::uint64_t key, std::uint64_t capacity)
  {
    return Mix(key) & (capacity - 1);
  }
  void Grow()
  {
    Array<KeySlot> bigger(this->dml_, this->slots_.Size() * 2);
    const std::uint64_t mask = bigger.Size() - 1;
    const std::uint64_t n = this->slots_.Size();
    this->slots_.ForEachChunk(0, n, storage::Access::Read,
      [&](KeySlot* data, std::uint64_t, std::uint64_t count) {
        for (std::uint64_t j = 0; j < count; ++j)
        {
          if ((j & 4095) == 4095)
          {
            this->progress_.Poll();
          }
          if (data[j].key == 0)
          {
            continue;
          }
          std::uint64_t i = this->Home(data[j].key - 1, mask + 1);
          while (bigger.Get(i).key != 0)
          {
            i = (i + 1) & mask;
          }
          bigger.Set(i, data[j]);
        }
      });
    this->slots_ = std::move(bigger);
  }

  DML& dml_;
  Array<KeySlot> slots_;
  Progress& progress_; // polled while the table grows
  std::uint64_t size_ = 0;
};

// Output triangles. Candidates (faces over three distinct cells) are appended as they come;
// after the read they are bucketed by their smallest cell (a counting sort over the dense cell
// ids, which follow the input's order, so both passes touch the DML page by page) and each
// bucket is deduplicated on its own. Linear time, no random-access hash set over all triangles.
class TriangleSet
{
public:
  explicit TriangleSet(DML& dml)
    : dml_(dml)
    , candidates_(dml, 1u << 10)
  {
  }
  // a < b and a < c must hold (the caller rotates the smallest cell first, keeping orientation)
  void Append(std::uint32_t a, std::uint32_t b, std::uint32_t c)
  {
    if (this->numCandidates_ == this->candidates_.Size())
    {
      this->candidates_.Resize(this->candidates_.Size() * 2);
    }
    this->candidates_.Set(this->numCandidates_++, TriSlot{ { a, b, c }, 1 });
  }
  // Before the first Append, in core: room for `expected` candidates (at most `faces`), zeroed
  // lazily like the cells (BeginInput), instead of growing from 1,024 by doubling.
  void Presize(std::uint64_t expected, std::uint64_t faces)
  {
    const std::uint64_t n = std::min(expected, faces);
    if (this->numCandidates_ == 0 && n > this->candidates_.Size() &&
      this->dml_.GetMode() == storage::Mode::InCore)
    {
      try
      {
        this->candidates_ = Array<TriSlot>(this->dml_, n);
      }
      catch (const std::bad_alloc&)
      {
        // (left to grow as they come)
      }
    }
  }
  // Whether the next Append resizes the block.
  bool Full() const { return this->numCandidates_ == this->candidates_.Size(); }

  // cells[i].triangles holds the number of candidates whose smallest cell is i. Fills Order()
  // with the distinct triangles, sorted by (smallest cell, second, third).
  void Finish(Array<CellRec>& cells, std::uint32_t numCells, Progress& progress)
  {
    // Bucket ends by prefix sums, in an array of their own: the scatter then updates 8 bytes a
    // candidate, not a 256-byte cell record read and written back.
    Array<std::uint64_t> ends(this->dml_, std::uint64_t(numCells) + 1);
    std::uint64_t total = 0;
    cells.ForEachChunk(0, numCells, storage::Access::Read,
      [&](CellRec* d, std::uint64_t first, std::uint64_t count) {
        for (std::uint64_t j = 0; j < count; ++j)
        {
          total += d[j].triangles;
          ends.Set(first + j, total); // decremented while scattering: then the bucket's start
        }
      });
    ends.Set(numCells, total);
    Array<TriSlot> buckets(this->dml_, std::max<std::uint64_t>(total, 1));
    const std::uint64_t n = this->numCandidates_;
    this->candidates_.ForEachChunk(0, n, storage::Access::Read,
      [&](TriSlot* d, std::uint64_t first, std::uint64_t count) {
        for (std::uint64_t j = 0; j < count; ++j)
        {
          if (((first + j) & 4095) == 0)
          {
            progress.Tick(0.5 * double(first + j) / double(std::max<std::uint64_t>(n, 1)));
          }
          const std::uint64_t at = ends.Get(d[j].v[0]) - 1;
          ends.Set(d[j].v[0], at);
          buckets.Set(at, d[j]);
        }
      });
    this->candidates_.Close();
    // each bucket [begin, end) now starts at ends[c] (and ends where the next starts, the last at
    // ends[numCells]); dedup within it
    this->order_ = Array<TriSlot>(this->dml_, std::max<std::uint64_t>(total, 1));
    std::vector<TriSlot> bucket;
    std::uint64_t begin = numCells ? ends.Get(0) : 0;
    for (std::uint32_t c = 0; c < numCells; ++c)
    {
      const std::uint64_t end = ends.Get(std::uint64_t(c) + 1);
      if (begin == end)
      {
        continue;
      }
      bucket.resize(end - begin);
      buckets.Read(begin, end - begin, bucket.data());
      begin = end;
      std::sort(bucket.begin(), bucket.end(), [](const TriSlot& x, const TriSlot& y) {
        return x.v[1] != y.v[1] ? x.v[1] < y.v[1] : x.v[2] < y.v[2];
      });
      for (std::size_t k = 0; k < bucket.size(); ++k)
      {
        if (k == 0 || bucket[k].v[1] != bucket[k - 1].v[1] || bucket[k].v[2] != bucket[k - 1].v[2])
        {
          this->order_.Set(this->size_++, bucket[k]);
        }
      }
      if ((c & 1023) == 0)
      {
        progress.Tick(0.5 + 0.5 * double(c) / double(numCells));
      }
    }
  }
  std::uint64_t Size() const { return this->size_; }
  std::uint64_t Candidates() const { return this->numCandidates_; }
  Array<TriSlot>& Order() { return this->order_; }

private:
  DML& dml_;
  Array<TriSlot> candidates_;
  std::uint64_t numCandidates_ = 0;
  Array<TriSlot> order_;
  std::uint64_t size_ = 0;
};

// Bounds pass: a vertices-only read.
class BoundsSink final : public io::MeshSink
{
public:
  BoundsSink(Progress& p, std::function<double(std::uint64_t, std::uint64_t)> afterBounds)
    : progress_(p)
    , afterBounds_(std::move(afterBounds))
  {
  }
  std::uint64_t Faces() const { return this->faces_; }
  std::uint64_t VerticesSeen() const { return this->seen_; }
  std::uint64_t Announced() const { return this->expected_; } // (the header's vertex count)
  void Begin(const io::MeshHeader& h) override
  {
    this->expected_ = h.vertexCount;
    this->faces_ = h.faceCount;
    this->meter_.Start(h.vertexCount);
    if (h.vertexCount)
    {
      this->progress_.Sized(h.vertexCount, h.faceCount);
      this->progress_.BeginPhase("bounds", kWork::kBounds * double(h.vertexCount),
        this->afterBounds_(h.vertexCount, h.faceCount));
    }
  }
  void Vertices(const io::VertexChunk& c) override
  {
    detail::ExtendBounds(this->b, c.xyz, c.count);
    this->seen_ += c.count;
    this->progress_.Tick(this->expected_ ? double(this->seen_) / double(this->expected_) : 0.0);
  }
  // With MeasureLayout, the read goes on past the vertices until kProbeFaces faces are measured
  // (then the sink throws detail::ProbeDone) or the input ends.
  void MeasureLayout() { this->measure_ = true; }
  const detail::LayoutMeter& Layout() const { return this->meter_; }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    if (this->meter_.Chunk(idx, count))
    {
      throw detail::ProbeDone{};
    }
  }
  void End(const io::ReadStats&) override {}
  bool AbortRequested() override { return this->progress_.Aborted(); }
  bool Measures() const { return this->measure_; }

  std::array<double, 6> b{ std::numeric_limits<double>::max(), -std::numeric_limits<double>::max(),
    std::numeric_limits<double>::max(), -std::numeric_limits<double>::max(),
    std::numeric_limits<double>::max(), -std::numeric_limits<double>::max() };

private:
  Progress& progress_;
  std::function<double(std::uint64_t, std::uint64_t)> afterBounds_;
  std::uint64_t expected_ = 0, seen_ = 0, faces_ = 0;
  bool measure_ = false;
  detail::LayoutMeter meter_;
};

} // namespace
} // namespace sipmss::algorithms
