// A mesh kept in DML blocks, replayable as a MeshSource, and the layout step of incoherent
// inputs: the two-stage hand-off, and the reordered copy of a file whose vertices and faces are
// not in a spatially coherent order (docs/architecture.md, "Input layout").
#pragma once

#include "sipmss/algorithms/Common.h"
#include "sipmss/algorithms/Vector.h"
#include "sipmss/storage/DML.h"

#include <algorithm>
#include <array>
#include <cstdint>
#include <functional>
#include <stdexcept>
#include <vector>

namespace sipmss::algorithms::detail
{

// The bits of the numbers below n (at least 1): a SortByKey key's.
inline int BitsFor(std::uint64_t n)
{
  int bits = 1;
  while (bits < 64 && ((n - 1) >> bits) != 0)
  {
    ++bits;
  }
  return bits;
}

// Division of 32-bit numbers by a divisor d >= 2 fixed at run time, with one multiplication
// instead of a 64-bit `div` (tens of cycles): c = ceil(2^64 / d), and n / d = floor(c n / 2^64)
// for every n below 2^32 (Lemire, Kaser and Kurz 2019, "Faster remainder by direct
// computation"). The slices path divides each of a face's corners by the slice length, three
// passes over the faces.
class Divider32
{
public:
  explicit Divider32(std::uint64_t d)
    : c_(~std::uint64_t(0) / Checked(d) + 1)
  {
  }
  std::uint64_t operator()(std::uint32_t n) const
  {
    return static_cast<std::uint64_t>((static_cast<unsigned __int128>(this->c_) * n) >> 64);
  }

private:
  static std::uint64_t Checked(std::uint64_t d)
  {
    if (d < 2)
    {
      throw std::invalid_argument("Divider32: the divisor must be at least 2");
    }
    return d;
  }
  std::uint64_t c_;
};

// Rotates a triangle so that its lowest vertex comes first (its orientation is kept).
template <class Tri>
void LowestFirst(Tri& t)
{
  // (no index into t.v: a local triangle stays in registers)
  const std::uint32_t a = t.v[0], b = t.v[1], c = t.v[2];
  if (a < b && a < c)
  {
    return;
  }
  const bool second = !(a < b) && b < c;
  t.v[0] = second ? b : c;
  t.v[1] = second ? c : a;
  t.v[2] = second ? a : b;
}

// Above this share of far faces an input is incoherent: scanner-ordered files measure below 1%,
// shuffled ones above 90%.
constexpr double kIncoherentFarFraction = 0.05;
// The faces the probe measures.
constexpr std::uint64_t kProbeFaces = std::uint64_t(1) << 17;

// Extends xmin xmax ymin ymax zmin zmax by n points (x y z floats).
inline void ExtendBounds(std::array<double, 6>& b, const float* xyz, std::size_t n)
{
  for (std::size_t i = 0; i < n; ++i)
  {
    for (int k = 0; k < 3; ++k)
    {
      const double v = xyz[3 * i + k];
      b[2 * k] = std::min(b[2 * k], v);
      b[2 * k + 1] = std::max(b[2 * k + 1], v);
    }
  }
}

// How far apart consecutive faces are in index order, measured as faces stream by (Isenburg and
// Lindstrom's layout coherence, reduced to one number): a face is far when its middle vertex
// index and the previous face's are more than `window` apart. Scanner order (faces along a sweep
// of the vertices) and fans (one vertex in many faces, the others in order) are near; shuffled
// vertices or faces are far.
class LayoutMeter
{
public:
  void Start(std::uint64_t vertexCount)
  {
    // (a row of a scan, a slice of a sorted volume: well inside 1/64 of the vertices)
    this->window_ = std::max<std::uint64_t>(4096, vertexCount / 64);
  }
  void Face(const std::uint32_t* f)
  {
    const std::uint32_t mid = std::max(std::min(f[0], f[1]), std::min(std::max(f[0], f[1]), f[2]));
    const std::uint64_t jump = mid > this->last_ ? mid - this->last_ : this->last_ - mid;
    this->far_ += (this->faces_ > 0 && jump > this->window_) ? 1 : 0;
    this->last_ = mid;
    ++this->faces_;
  }
  // Measures a chunk's faces up to the first kProbeFaces of the input; true once that many are.
  bool Chunk(const std::uint32_t* idx, std::size_t count)
  {
    for (std::size_t t = 0; t < count && this->faces_ < kProbeFaces; ++t)
    {
      this->Face(idx + 3 * t);
    }
    return this->faces_ >= kProbeFaces;
  }
  std::uint64_t Faces() const { return this->faces_; }
  // Share of far faces (0: none measured).
  double FarFraction() const
  {
    return this->faces_ ? double(this->far_) / double(this->faces_) : 0.0;
  }

private:
  std::uint64_t window_ = 4096;
  std::uint64_t faces_ = 0, far_ = 0;
  std::uint32_t last_ = 0;
};


// Progress weights of the layout step (seconds per input vertex + face, measured in core on the
// shuffled Dragon-size input: 0.01 s and 0.13 s for 401,457 + 810,080 elements;
// docs/architecture.md "Progress and abort").
constexpr double kLayoutReadWork = 1.0e-8;
constexpr double kLayoutReorderWork = 1.1e-7;

// Thrown by a sink that has measured enough faces (the read stops there; a FIFO is still copied).
struct ProbeDone : io::StopRead
{
};
// Thrown by a core's sink that found its input incoherent while reading it: the run starts again
// on a reordered copy (the cores' entry points catch it).
struct ReorderNeeded : io::StopRead
{
};

struct LayoutProbe
{
  std::uint64_t vertices = 0, faces = 0; // from the header (0: not announced)
  std::uint64_t verticesSeen = 0;
  std::array<double, 6> bounds{};
  bool measured = false;  // faces were measured
  bool complete = false;  // the probe read the whole input (verticesSeen are all)
  double farFraction = 0; // of the first kProbeFaces faces
  bool Incoherent() const { return this->measured && this->farFraction > kIncoherentFarFraction; }
};

// A bounds pass that also measures the layout of the first kProbeFaces faces (the readers parse
// the vertices before them): the vertices' bounds and count, the header's counts, the layout.
LayoutProbe ProbeLayout(const MeshSource& input, Progress& progress);

// The structures of the layout step for V vertices, F triangles and `stride` words of point data
// per vertex (the stored mesh and the largest sort's second block), for a DML's Config.
void AddLayoutStructures(
  storage::Profile& profile, std::uint64_t V, std::uint64_t F, std::size_t stride);

class StoredMesh;

// Point data as StoredMesh keeps it: `stride` 4-byte words per vertex (normals, colour, texture
// coordinates, scalars, as the layout has them).
inline std::size_t PointDataWords(const io::VertexLayout& l)
{
  return (l.normals ? 3 : 0) + (l.colors ? 1 : 0) + (l.texcoords ? 2 : 0) + l.scalars.size();
}
void PackPointData(const io::VertexChunk& c, const io::VertexLayout& layout, std::size_t stride,
  std::uint32_t* words);
// ... and back into a chunk's arrays (held here).
struct PointDataBuffers
{
  std::vector<float> normals, tex, scalars;
  std::vector<std::uint8_t> rgba;
  void Unpack(const std::uint32_t* words, std::size_t n, const io::VertexLayout& layout,
    std::size_t stride, io::VertexChunk& c);
};

// The layout step of a core's run: reads `input` into `mesh`, configuring `dml` when the header
// gives the sizes (the layout step's structures and, from addStructures, the core's), and
// reorders it; the phases "layout read" and "layout reorder" go into `stats`, their progress
// planned against workAfter(V, F), the core's work after them.
void ReadAndReorder(const MeshSource& input, StoredMesh& mesh, storage::DML& dml,
  const storage::Profile& storage,
  const std::function<void(storage::Profile&, std::uint64_t V, std::uint64_t F)>& addStructures,
  const std::function<double(std::uint64_t V, std::uint64_t F)>& workAfter, Progress& progress,
  RunStats& stats, int threads);

// A mesh in DML blocks (positions, point data as 4-byte words, triangles), with its bounds.
class StoredMesh final : public io::MeshSink
{
public:
  explicit StoredMesh(storage::DML& dml);
  ~StoredMesh() override;
  StoredMesh(const StoredMesh&) = delete;
  StoredMesh& operator=(const StoredMesh&) = delete;

  // Frees the stored mesh (Replay is not possible afterwards).
  void Release();

  void Begin(const io::MeshHeader& h) override;
  void Vertices(const io::VertexChunk& c) override;
  void Triangles(const std::uint32_t* idx, std::size_t count) override;
  void End(const io::ReadStats& stats) override;
  bool AbortRequested() override { return this->progress_ && this->progress_->Aborted(); }

  // Polls `progress` while it is filled (nullptr: never).
  void SetProgress(Progress* progress) { this->progress_ = progress; }
  // Called with the header's counts before any block is opened (e.g. to Config the DML).
  void OnHeader(std::function<void(std::uint64_t V, std::uint64_t F)> f)
  {
    this->onHeader_ = std::move(f);
  }
  // What the read reported (dropped faces) and the layout of the faces as they came.
  const io::ReadStats& ReadStats() const { return this->read_; }
  const LayoutMeter& Layout() const { return this->layout_; }
  const std::array<double, 6>& Bounds() const { return this->bounds_; }
  std::size_t Stride() const { return this->stride_; }
  std::uint64_t VertexCount() const { return this->header_.vertexCount; }
  std::uint64_t TriangleCount() const { return this->triangleCount_; }

  // Renumbers the vertices along a Morton curve over the bounds (ties by the old index) and
  // sorts the faces (each rotated to start at its lowest new vertex, orientation kept) by their
  // vertices: every step a storage::Sort or a sequential scan, no random access. Point data
  // follows its vertex.
  // Returns how the faces were renumbered: the inverse permutation in memory, in slices of it
  // (the corners distributed to a bucket per slice), or by sorting their corners.
  enum class Renumbering
  {
    InMemory,
    Slices,
    SortedCorners
  };
  // threads: for the sorts in core (1: the calling thread only; 0: all cores).
  Renumbering Reorder(Progress& progress, int threads = 0);
  // The number of slices of the last Reorder (0 unless Renumbering::Slices).
  std::uint64_t Slices() const { return this->slices_; }
  // The last Reorder's parts, timed, with the DML's I/O (RunStats::layoutSteps).
  const std::vector<LayoutStepStat>& Steps() const { return this->steps_; }

  // Random access, for a mesh put together from parts (the distributed decimation's gather):
  // triangles written at a position (the count grows to cover them), and ranges read back
  // (positions, and the point data as PackPointData's words).
  void TrianglesAt(std::uint64_t first, const std::uint32_t* idx, std::size_t count);
  void ReadTriangles(std::uint64_t first, std::size_t count, std::uint32_t* idx);
  void ReadVertices(std::uint64_t first, std::size_t count, std::vector<float>& xyz,
    std::vector<std::uint32_t>& words);
  const io::VertexLayout& PointLayout() const { return this->header_.layout; }
  io::Format Format() const { return this->header_.format; }

  // Streams the stored mesh (the same chunk protocol as the readers).
  io::ReadStats Replay(io::MeshSink& sink, const io::ReadOptions& options);

private:
  struct Triangle
  {
    std::uint32_t v[3];
  };
  storage::DML& dml_;
  Progress* progress_ = nullptr;
  std::function<void(std::uint64_t, std::uint64_t)> onHeader_;
  io::MeshHeader header_;
  io::ReadStats read_;
  std::size_t stride_ = 0; // point data, in 4-byte words per vertex
  storage::Array<Float3> points_;
  storage::Array<Triangle> triangles_;
  storage::BlockId attrs_ = -1;
  std::uint64_t triangleCount_ = 0;
  std::uint64_t slices_ = 0;
  std::vector<LayoutStepStat> steps_;
  LayoutMeter layout_;
  std::array<double, 6> bounds_;
};

} // namespace sipmss::algorithms::detail
