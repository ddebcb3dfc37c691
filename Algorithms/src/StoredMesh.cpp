#include "StoredMesh.h"
#include "Morton.h"

#include "sipmss/storage/Sort.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstring>
#include <limits>
#include <optional>
#include <vector>

namespace sipmss::algorithms::detail
{
namespace
{
using storage::Array;

class ProbeSink final : public io::MeshSink
{
public:
  ProbeSink(LayoutProbe& probe, Progress& progress)
    : probe_(probe)
    , progress_(progress)
  {
  }
  void Begin(const io::MeshHeader& h) override
  {
    this->probe_.vertices = h.vertexCount;
    this->probe_.faces = h.faceCount;
    this->meter_.Start(h.vertexCount);
  }
  void Vertices(const io::VertexChunk& c) override
  {
    ExtendBounds(this->probe_.bounds, c.xyz, c.count);
    this->probe_.verticesSeen = std::max<std::uint64_t>(this->probe_.verticesSeen, c.first + c.count);
    this->progress_.Poll();
  }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    if (this->meter_.Chunk(idx, count))
    {
      this->Done();
    }
  }
  void End(const io::ReadStats&) override { this->Record(); }
  bool AbortRequested() override { return this->progress_.Aborted(); }

private:
  void Record()
  {
    this->probe_.measured = this->meter_.Faces() > 0;
    this->probe_.farFraction = this->meter_.FarFraction();
  }
  void Done()
  {
    this->Record();
    throw ProbeDone{};
  }
  LayoutProbe& probe_;
  Progress& progress_;
  LayoutMeter meter_;
};

struct KeyRec
{
  std::uint64_t key;
  std::uint32_t old;
  float p[3];
};
struct OldNew
{
  std::uint32_t old, now;
};
struct AttrRec
{
  std::uint32_t now;
  std::uint32_t w[16];
};
struct Corner
{
  std::uint32_t v, face, k;
};

// Reads a block's elements [first, first + n) in chunks of at most kChunk and calls
// f(data, first, count) (sequential access through the page cache either way).
constexpr std::uint64_t kChunk = 2048;
template <class T, class F>
void Scan(Array<T>& a, std::uint64_t n, std::vector<T>& buf, F&& f, std::uint64_t chunk = kChunk)
{
  for (std::uint64_t first = 0; first < n; first += chunk)
  {
    const std::uint64_t c = std::min(chunk, n - first);
    buf.resize(static_cast<std::size_t>(c));
    a.Read(first, c, buf.data());
    f(buf.data(), first, c);
  }
}
// Appends elements to consecutive regions of one block, region b from starts[b] on, through a
// write buffer of `per` elements a region flushed when full (the slices path's buckets).
template <class T>
class BucketWriter
{
public:
  BucketWriter(storage::DML& dml, Array<T>& block, std::vector<std::uint64_t> starts,
    std::size_t per)
    : block_(block)
    , at_(std::move(starts))
    , fill_(at_.size(), 0)
    , per_(per)
    , buf_(dml, at_.size() * per)
  {
  }
  void Add(std::size_t b, const T& x)
  {
    this->buf_[b * this->per_ + this->fill_[b]++] = x;
    if (this->fill_[b] == this->per_)
    {
      this->Flush(b);
    }
  }
  void Finish()
  {
    for (std::size_t b = 0; b < this->at_.size(); ++b)
    {
      this->Flush(b);
    }
  }

private:
  void Flush(std::size_t b)
  {
    if (this->fill_[b])
    {
      this->block_.Write(this->at_[b], this->fill_[b], this->buf_.Data() + b * this->per_);
      this->at_[b] += this->fill_[b];
      this->fill_[b] = 0;
    }
  }
  Array<T>& block_;
  std::vector<std::uint64_t> at_;
  std::vector<std::size_t> fill_;
  std::size_t per_;
  storage::CountedBuffer<T> buf_;
};
} // namespace

void AddLayoutStructures(
  storage::Profile& profile, std::uint64_t V, std::uint64_t F, std::size_t stride)
{
  auto add = [&profile](const char* name, std::size_t size, std::uint64_t count) {
    if (size)
    {
      profile.structures.push_back(storage::StructureSpec{ name, size, count, 0.0 });
    }
  };
  // (every block the step may open, each sort's second block as large as the first, and the
  // keys' third for a range of crowded Morton keys distributed again: storage::SortByKey; a
  // range crowded again below it, or one that must be merged, adds up to its own size more)
  add("layout.points", 12, V);
  add("layout.pointData", 4 * stride, V);
  add("layout.triangles", 12, F);
  add("layout.keys", sizeof(KeyRec), 3 * V);
  add("layout.inverse", sizeof(OldNew), 2 * V);
  add("layout.corners", sizeof(Corner), 2 * 3 * F);
}

LayoutProbe ProbeLayout(const MeshSource& input, Progress& progress)
{
  LayoutProbe probe;
  const double inf = std::numeric_limits<double>::infinity();
  probe.bounds = { inf, -inf, inf, -inf, inf, -inf };
  ProbeSink sink(probe, progress);
  try
  {
    input(sink, io::ReadOptions{});
    probe.complete = true;
  }
  catch (const ProbeDone&)
  {
  }
  return probe;
}

void ReadAndReorder(const MeshSource& input, StoredMesh& mesh, storage::DML& dml,
  const storage::Profile& storage,
  const std::function<void(storage::Profile&, std::uint64_t, std::uint64_t)>& addStructures,
  const std::function<double(std::uint64_t, std::uint64_t)>& workAfter, Progress& progress,
  RunStats& stats, int threads)
{
  double V = 0, F = 0, after = 1;
  {
    progress.BeginPhase("layout: read", 0.0, 1.0); // (its share once the header gives the sizes)
    PhaseTimer timer(stats, dml, "layout read");
    mesh.SetProgress(&progress);
    mesh.OnHeader([&](std::uint64_t v, std::uint64_t f) {
      // The paper's Config: the copy's and the core's structures decide the mode.
      storage::Profile profile = storage;
      AddLayoutStructures(profile, v, f, 0);
      addStructures(profile, v, f);
      dml.Config(profile);
      V = double(v);
      F = double(f);
      after = workAfter(v, f);
      progress.BeginPhase("layout: read", kLayoutReadWork * (V + F),
        kLayoutReorderWork * (V + F) + after);
    });
    input(mesh, io::ReadOptions{});
  }
  progress.BeginPhase("layout: reorder", kLayoutReorderWork * (V + F), after);
  PhaseTimer timer(stats, dml, "layout reorder");
  mesh.Reorder(progress, threads);
  stats.layoutSteps = mesh.Steps();
}

StoredMesh::StoredMesh(storage::DML& dml)
  : dml_(dml)
{
  const double inf = std::numeric_limits<double>::infinity();
  this->bounds_ = { inf, -inf, inf, -inf, inf, -inf };
}

StoredMesh::~StoredMesh()
{
  this->Release();
}

void StoredMesh::Release()
{
  if (this->attrs_ >= 0)
  {
    this->dml_.CloseBlock(this->attrs_);
    this->attrs_ = -1;
  }
  this->points_.Close();
  this->triangles_.Close();
}

void StoredMesh::Begin(const io::MeshHeader& h)
{
  if (this->onHeader_)
  {
    this->onHeader_(h.vertexCount, h.faceCount);
  }
  this->header_ = h;
  this->stride_ = PointDataWords(h.layout);
  this->points_ = Array<Float3>(this->dml_, std::max<std::uint64_t>(h.vertexCount, 1));
  this->triangles_ = Array<Triangle>(this->dml_, std::max<std::uint64_t>(h.faceCount, 1));
  if (this->stride_)
  {
    this->attrs_ =
      this->dml_.OpenBlock(4 * this->stride_, std::max<std::uint64_t>(h.vertexCount, 1));
  }
  this->layout_.Start(h.vertexCount);
}

void PackPointData(const io::VertexChunk& c, const io::VertexLayout& L, std::size_t stride,
  std::uint32_t* words)
{
  const std::size_t ns = L.scalars.size();
  for (std::size_t i = 0; i < c.count; ++i)
  {
    std::uint32_t* r = words + stride * i;
    std::size_t k = 0;
    auto put = [&](const float* src, std::size_t n) {
      std::memcpy(r + k, src, 4 * n);
      k += n;
    };
    if (c.normals)
      put(c.normals + 3 * i, 3);
    if (c.rgba)
    {
      std::memcpy(r + k, c.rgba + 4 * i, 4);
      ++k;
    }
    if (c.texcoords)
      put(c.texcoords + 2 * i, 2);
    if (c.scalars)
      put(c.scalars + ns * i, ns);
  }
}

void PointDataBuffers::Unpack(const std::uint32_t* words, std::size_t n,
  const io::VertexLayout& L, std::size_t stride, io::VertexChunk& c)
{
  const std::size_t ns = L.scalars.size();
  this->normals.resize(L.normals ? 3 * n : 0);
  this->rgba.resize(L.colors ? 4 * n : 0);
  this->tex.resize(L.texcoords ? 2 * n : 0);
  this->scalars.resize(ns * n);
  for (std::size_t i = 0; i < n; ++i)
  {
    const std::uint32_t* r = words + stride * i;
    std::size_t k = 0;
    if (L.normals)
    {
      std::memcpy(&this->normals[3 * i], r + k, 12);
      k += 3;
    }
    if (L.colors)
    {
      std::memcpy(&this->rgba[4 * i], r + k, 4);
      ++k;
    }
    if (L.texcoords)
    {
      std::memcpy(&this->tex[2 * i], r + k, 8);
      k += 2;
    }
    if (ns)
    {
      std::memcpy(&this->scalars[ns * i], r + k, 4 * ns);
    }
  }
  c.normals = L.normals ? this->normals.data() : nullptr;
  c.rgba = L.colors ? this->rgba.data() : nullptr;
  c.texcoords = L.texcoords ? this->tex.data() : nullptr;
  c.scalars = ns ? this->scalars.data() : nullptr;
}

void StoredMesh::Vertices(const io::VertexChunk& c)
{
  if (c.first + c.count > this->points_.Size())
  {
    const std::uint64_t n = std::max<std::uint64_t>(c.first + c.count, 2 * this->points_.Size());
    this->points_.Resize(n);
    if (this->stride_)
    {
      this->dml_.Resize(this->attrs_, n);
    }
  }
  this->points_.Write(c.first, c.count, reinterpret_cast<const Float3*>(c.xyz));
  ExtendBounds(this->bounds_, c.xyz, c.count);
  if (this->stride_)
  {
    std::vector<std::uint32_t> rec(this->stride_ * c.count);
    PackPointData(c, this->header_.layout, this->stride_, rec.data());
    this->dml_.WriteRange(this->attrs_, c.first, c.count, rec.data());
  }
  this->header_.vertexCount = std::max<std::uint64_t>(this->header_.vertexCount, c.first + c.count);
}

void StoredMesh::TrianglesAt(std::uint64_t first, const std::uint32_t* idx, std::size_t count)
{
  if (first + count > this->triangles_.Size())
  {
    this->triangles_.Resize(std::max<std::uint64_t>(first + count, 2 * this->triangles_.Size()));
  }
  this->triangles_.Write(first, count, reinterpret_cast<const Triangle*>(idx));
  this->triangleCount_ = std::max<std::uint64_t>(this->triangleCount_, first + count);
}

void StoredMesh::ReadTriangles(std::uint64_t first, std::size_t count, std::uint32_t* idx)
{
  this->triangles_.Read(first, count, reinterpret_cast<Triangle*>(idx));
}

void StoredMesh::ReadVertices(std::uint64_t first, std::size_t n, std::vector<float>& xyz,
  std::vector<std::uint32_t>& words)
{
  xyz.resize(3 * n);
  this->points_.Read(first, n, reinterpret_cast<Float3*>(xyz.data()));
  words.resize(this->stride_ * n);
  if (this->stride_)
  {
    this->dml_.ReadRange(this->attrs_, first, n, words.data());
  }
}

void StoredMesh::Triangles(const std::uint32_t* idx, std::size_t count)
{
  if (this->triangleCount_ + count > this->triangles_.Size())
  {
    this->triangles_.Resize(
      std::max<std::uint64_t>(this->triangleCount_ + count, 2 * this->triangles_.Size()));
  }
  this->triangles_.Write(this->triangleCount_, count, reinterpret_cast<const Triangle*>(idx));
  this->layout_.Chunk(idx, count); // (the layout of the first faces, as every measurement of it)
  this->triangleCount_ += count;
}

void StoredMesh::End(const io::ReadStats& stats)
{
  this->read_ = stats;
  this->header_.faceCount = this->triangleCount_;
}

StoredMesh::Renumbering StoredMesh::Reorder(Progress& progress, int threads)
{
  const std::uint64_t V = this->header_.vertexCount;
  const std::uint64_t T = this->triangleCount_;
  this->steps_.clear();
  if (V < 2 || T == 0)
  {
    return Renumbering::InMemory;
  }
  if (T > std::numeric_limits<std::uint32_t>::max())
  {
    throw std::length_error("the layout step numbers faces in 32 bits: " + std::to_string(T) +
      " triangles are too many");
  }
  // (the block was sized by the header's count of polygons, and grown by doubling: the sorts
  // below take the whole block, so it holds just the triangles)
  if (this->triangles_.Size() != T)
  {
    this->triangles_.Resize(T);
  }
  // The inverse permutation (for each old index its new one): in memory when it fits the
  // budget's spare memory (then faces are renumbered in one scan), else a block sorted by old
  // index and joined with the faces' corners by sorting them.
  std::optional<storage::CountedBuffer<std::uint32_t>> newOf;
  if (this->dml_.SpareMemory(8) / 2 >= 4 * V + (std::uint64_t(1) << 16))
  {
    newOf.emplace(this->dml_, static_cast<std::size_t>(V));
  }
  // Else, when the inverse is read in slices of what the spare memory holds and every slice's
  // bucket of corners gets a buffer of bucketMin corners in the other half, the faces are
  // renumbered by distributing their corners to the slices' buckets (linear, no comparisons,
  // nine sequential passes of 4 bytes a corner for any number of slices); else by sorting their
  // corners (n log n, for any size; 12 bytes a corner sorted twice). bucketMin: 1,024 corners,
  // and at least 1/16 of a page (a bucket's transfers then go straight to and from the file,
  // docs/storage.md). At 8 MB a 397M-triangle file's 199M vertices leave about 2,100 corners a
  // bucket (434 slices); sorting its 14.3 GB of corners instead (beyond what SortByKey
  // distributes at 8 MB) made its layout step 760 s against 172 s (docs/benchmarks.md).
  const std::uint64_t spare = this->dml_.SpareMemory(8);
  const std::uint64_t sliceLength = std::max<std::uint64_t>(1024, spare / 2 / sizeof(OldNew));
  const std::uint64_t slices = newOf ? 0 : (V + sliceLength - 1) / sliceLength;
  const std::uint64_t bucketMin =
    std::max<std::uint64_t>(1024, this->dml_.PageBytes() / 16 / sizeof(std::uint32_t));
  const std::uint64_t bucketLength = slices ? spare / 2 / sizeof(std::uint32_t) / slices : 0;
  const Renumbering path = newOf ? Renumbering::InMemory
    : bucketLength >= bucketMin ? Renumbering::Slices
                                 : Renumbering::SortedCorners;
  this->slices_ = path == Renumbering::Slices ? slices : 0;
  const Divider32 sliceOf(sliceLength);
  // Progress: each sort and scan's share by the bytes it moves.
  const std::size_t groups = (this->stride_ + 15) / 16;
  const double faceBytes = path == Renumbering::InMemory ? 0.0
    : path == Renumbering::Slices ? 9.0 * double(sizeof(Triangle))
                                  : 4.0 * 3 * sizeof(Corner);
  const double total =
    double(V) * (2 * sizeof(KeyRec) + (newOf ? 0 : 2 * sizeof(OldNew)) +
                  (path == Renumbering::Slices ? 2 * sizeof(OldNew) : 0) +
                  2.0 * double(groups) * sizeof(AttrRec)) +
    double(T) * (faceBytes + 2 * sizeof(Triangle));
  double done = 0;
  auto step = [&](double bytes) {
    const double from = done / total, span = bytes / total;
    done += bytes;
    return [&progress, from, span](double f) { progress.Tick(from + span * f); };
  };
  auto tick = [&progress](std::uint64_t i) {
    if ((i & (kChunk * 16 - 1)) == 0)
    {
      progress.Poll();
    }
  };

  // Each part's time and I/O (RunStats::layoutSteps).
  auto partStart = std::chrono::steady_clock::now();
  storage::Stats partStats = this->dml_.GetStats();
  auto part = [&](const char* name) {
    const auto now = std::chrono::steady_clock::now();
    const storage::Stats s = this->dml_.GetStats();
    this->steps_.push_back(LayoutStepStat{ name,
      std::chrono::duration<double>(now - partStart).count(), s.bytesRead - partStats.bytesRead,
      s.bytesWritten - partStats.bytesWritten, s.fileBytes });
    partStart = now;
    partStats = s;
  };

  // 1. Vertices by Morton key (ties by the old index), positions carried.
  Array<OldNew> inverse;
  if (!newOf)
  {
    inverse = Array<OldNew>(this->dml_, V);
  }
  {
    Array<KeyRec> keys(this->dml_, V);
    const double lo[3] = { this->bounds_[0], this->bounds_[2], this->bounds_[4] };
    double extent = 0;
    for (int k = 0; k < 3; ++k)
    {
      extent = std::max(extent, this->bounds_[2 * k + 1] - this->bounds_[2 * k]);
    }
    const double scale = extent > 0 ? double((1u << 21) - 1) / extent : 0.0;
    std::vector<Float3> pts;
    std::vector<KeyRec> recs;
    Scan(this->points_, V, pts, [&](const Float3* p, std::uint64_t first, std::uint64_t n) {
      tick(first);
      recs.resize(static_cast<std::size_t>(n));
      for (std::uint64_t i = 0; i < n; ++i)
      {
        std::uint64_t q[3];
        for (int k = 0; k < 3; ++k)
        {
          const double t = std::floor((double(p[i][k]) - lo[k]) * scale);
          q[k] = t <= 0 ? 0 : (t >= double((1u << 21) - 1) ? (1u << 21) - 1 : std::uint64_t(t));
        }
        recs[i].key = Spread21(q[0]) | Spread21(q[1]) << 1 | Spread21(q[2]) << 2;
        recs[i].old = static_cast<std::uint32_t>(first + i);
        std::memcpy(recs[i].p, &p[i], 12);
      }
      keys.Write(first, n, recs.data());
    });
    // The sorted records go straight from the sort to this (storage::SortByKeyInto: out of core
    // not written back and read again): positions in the new order, and the inverse (in memory;
    // else its (old, new) pairs in new order).
    std::vector<OldNew> map;
    std::uint64_t polled = 0;
    auto sorted = [&](const KeyRec* r, std::uint64_t first, std::uint64_t count) {
      for (std::uint64_t from = 0; from < count; from += kChunk)
      {
        if ((polled += kChunk) >= 16 * kChunk)
        {
          polled = 0;
          progress.Poll();
        }
        const std::uint64_t n = std::min(kChunk, count - from);
        const KeyRec* const c = r + from;
        const std::uint64_t at = first + from;
        pts.resize(static_cast<std::size_t>(n));
        for (std::uint64_t i = 0; i < n; ++i)
        {
          std::memcpy(&pts[i], c[i].p, 12);
        }
        this->points_.Write(at, n, pts.data());
        if (newOf)
        {
          for (std::uint64_t i = 0; i < n; ++i)
          {
            (*newOf)[c[i].old] = static_cast<std::uint32_t>(at + i);
          }
        }
        else
        {
          map.resize(static_cast<std::size_t>(n));
          for (std::uint64_t i = 0; i < n; ++i)
          {
            map[i] = OldNew{ c[i].old, static_cast<std::uint32_t>(at + i) };
          }
          inverse.Write(at, n, map.data());
        }
      }
    };
    storage::SortByKeyInto(this->dml_, keys,
      [](const KeyRec& a, const KeyRec& b) { return a.key != b.key ? a.key < b.key : a.old < b.old; },
      [](const KeyRec& r) { return r.key; }, 63, storage::SortSink<KeyRec>(sorted),
      step(2.0 * double(V) * sizeof(KeyRec)), threads);
  }
  part("vertices by key");
  if (path == Renumbering::Slices)
  {
    // The (old, new) pairs go to their slice of the inverse (slice b holds the old indices
    // [b sliceLength, (b + 1) sliceLength), so it starts there), through a buffer per slice;
    // step 2 then orders each slice in memory.
    Array<OldNew> sliced(this->dml_, V);
    {
      std::vector<std::uint64_t> starts;
      for (std::uint64_t b = 0; b < slices; ++b)
      {
        starts.push_back(b * sliceLength);
      }
      BucketWriter<OldNew> dist(
        this->dml_, sliced, std::move(starts), static_cast<std::size_t>(bucketLength / 2));
      std::vector<OldNew> pairs;
      auto done1 = step(2.0 * double(V) * sizeof(OldNew));
      Scan(inverse, V, pairs, [&](const OldNew* q, std::uint64_t first, std::uint64_t n) {
        tick(first);
        for (std::uint64_t i = 0; i < n; ++i)
        {
          dist.Add(static_cast<std::size_t>(sliceOf(q[i].old)), q[i]);
        }
        done1(double(first + n) / double(V));
      });
      dist.Finish();
    }
    inverse.Swap(sliced); // (the pairs in new order close with `sliced`)
  }
  // 2. The inverse: for each old index (in order) its new one.
  if (path == Renumbering::Slices)
  {
    // (each slice holds its own old indices: put in place in memory, the new numbers scattered
    // to their old index's place, then the pairs rebuilt in order; independent stores, where
    // following the permutation's cycles waited on each swap's cache miss)
    storage::CountedBuffer<OldNew> slice(this->dml_, static_cast<std::size_t>(sliceLength));
    storage::CountedBuffer<std::uint32_t> nowOf(this->dml_, static_cast<std::size_t>(sliceLength));
    auto done2 = step(2.0 * double(V) * sizeof(OldNew));
    for (std::uint64_t lo = 0; lo < V; lo += sliceLength)
    {
      progress.Poll();
      const std::uint64_t n = std::min(sliceLength, V - lo);
      inverse.Read(lo, n, slice.Data());
      OldNew* const pairs = slice.Data();
      std::uint32_t* const now = nowOf.Data();
      for (std::uint64_t i = 0; i < n; ++i)
      {
        now[pairs[i].old - lo] = pairs[i].now;
      }
      for (std::uint64_t i = 0; i < n; ++i)
      {
        pairs[i] = OldNew{ static_cast<std::uint32_t>(lo + i), now[i] };
      }
      inverse.Write(lo, n, slice.Data());
      done2(double(lo + n) / double(V));
    }
  }
  else if (!newOf)
  {
    storage::SortByKey(this->dml_, inverse,
      [](const OldNew& a, const OldNew& b) { return a.old < b.old; },
      [](const OldNew& x) { return x.old; }, BitsFor(V), step(2.0 * double(V) * sizeof(OldNew)),
      threads);
  }

  part("inverse");
  // 3. Point data, 16 words at a time: (new index, words) in old order, sorted by new index.
  if (this->stride_)
  {
    // (chunks of at most 1 MiB of point data, whatever the number of properties)
    const std::uint64_t ac =
      std::max<std::uint64_t>(1, std::min<std::uint64_t>(kChunk, (1u << 20) / (4 * this->stride_)));
    std::vector<std::uint32_t> words;
    std::vector<OldNew> map;
    std::vector<AttrRec> recs;
    for (std::size_t g = 0; g < groups; ++g)
    {
      const std::size_t w0 = 16 * g, nw = std::min<std::size_t>(16, this->stride_ - w0);
      Array<AttrRec> moved(this->dml_, V);
      for (std::uint64_t first = 0; first < V; first += ac)
      {
        progress.Poll();
        const std::uint64_t n = std::min(ac, V - first);
        words.resize(static_cast<std::size_t>(n) * this->stride_);
        map.resize(static_cast<std::size_t>(n));
        recs.assign(static_cast<std::size_t>(n), AttrRec{});
        this->dml_.ReadRange(this->attrs_, first, n, words.data());
        if (!newOf)
        {
          inverse.Read(first, n, map.data());
        }
        for (std::uint64_t i = 0; i < n; ++i)
        {
          recs[i].now = newOf ? (*newOf)[first + i] : map[i].now;
          std::memcpy(recs[i].w, &words[i * this->stride_ + w0], 4 * nw);
        }
        moved.Write(first, n, recs.data());
      }
      storage::SortByKey(this->dml_, moved,
        [](const AttrRec& a, const AttrRec& b) { return a.now < b.now; },
        [](const AttrRec& r) { return r.now; }, BitsFor(V), step(2.0 * double(V) * sizeof(AttrRec)),
        threads);
      for (std::uint64_t first = 0; first < V; first += ac)
      {
        progress.Poll();
        const std::uint64_t n = std::min(ac, V - first);
        words.resize(static_cast<std::size_t>(n) * this->stride_);
        recs.resize(static_cast<std::size_t>(n));
        this->dml_.ReadRange(this->attrs_, first, n, words.data());
        moved.Read(first, n, recs.data());
        for (std::uint64_t i = 0; i < n; ++i)
        {
          std::memcpy(&words[i * this->stride_ + w0], recs[i].w, 4 * nw);
        }
        this->dml_.WriteRange(this->attrs_, first, n, words.data());
      }
    }
  }

  if (this->stride_)
  {
    part("point data");
  }
  // 4. Faces: renumbered in one scan when the inverse is in memory; else corners sorted by old
  //    vertex, joined with the inverse in one sequential scan, sorted back by face.
  //    Out of core the last pass of each hands the renumbered faces (each rotated to start at its
  //    lowest vertex, orientation kept) to a BucketSorter by that vertex: their sort (5.) is then
  //    one read and write more (docs/architecture.md, "Input layout").
  auto faceLess = [](const Triangle& a, const Triangle& b) {
    const std::uint64_t ka = std::uint64_t(a.v[0]) << 32 | a.v[1];
    const std::uint64_t kb = std::uint64_t(b.v[0]) << 32 | b.v[1];
    return ka != kb ? ka < kb : a.v[2] < b.v[2];
  };
  auto lowest = [](const Triangle& t) { return std::uint64_t(t.v[0]); };
  using FaceSorter = storage::BucketSorter<Triangle, decltype(lowest), decltype(faceLess)>;
  std::optional<FaceSorter> sorter;
  const bool bucketed = this->dml_.BasePointer(this->triangles_.Id()) == nullptr;
  auto startSorter = [&] {
    if (bucketed)
    {
      sorter.emplace(this->dml_, T, V, lowest, faceLess);
      if (sorter->OneBucket())
      {
        sorter.reset(); // (written in place and sorted by SortByKey, step 5)
      }
    }
  };
  // (a pass's renumbered faces: to the sorter, else written back in place)
  auto emit = [&](Triangle* t, std::uint64_t first, std::uint64_t n) {
    if (sorter)
    {
      for (std::uint64_t i = 0; i < n; ++i)
      {
        sorter->Add(t[i]);
      }
    }
    else
    {
      this->triangles_.Write(first, n, t);
    }
  };
  if (newOf)
  {
    std::vector<Triangle> tris;
    startSorter();
    Scan(this->triangles_, T, tris, [&](Triangle* t, std::uint64_t first, std::uint64_t n) {
      tick(first);
      for (std::uint64_t i = 0; i < n; ++i)
      {
        for (int k = 0; k < 3; ++k)
        {
          t[i].v[k] = (*newOf)[t[i].v[k]];
        }
        LowestFirst(t[i]);
      }
      emit(t, first, n);
    });
    newOf.reset();
  }
  else if (path == Renumbering::Slices)
  {
    // The corners go to one bucket per slice of the inverse (their old vertices, in face order);
    // each bucket is renumbered with its slice in memory; then the faces are read again in their
    // old numbering and each corner takes the next new number from its slice's bucket: the
    // buckets hand them out in the order they went in.
    std::vector<std::uint64_t> begin(static_cast<std::size_t>(slices) + 1, 0);
    std::vector<Triangle> tris;
    auto bucketOf = [sliceOf](std::uint32_t v) { return std::size_t(sliceOf(v)); };
    {
      auto done1 = step(double(T) * sizeof(Triangle));
      Scan(this->triangles_, T, tris, [&](const Triangle* t, std::uint64_t first, std::uint64_t n) {
        tick(first);
        for (std::uint64_t i = 0; i < n; ++i)
        {
          for (int k = 0; k < 3; ++k)
          {
            ++begin[bucketOf(t[i].v[k]) + 1];
          }
        }
        done1(double(first + n) / double(T));
      });
    }
    for (std::size_t b = 0; b < slices; ++b)
    {
      begin[b + 1] += begin[b];
    }
    Array<std::uint32_t> refs(this->dml_, 3 * T);
    const std::size_t per = static_cast<std::size_t>(bucketLength);
    {
      BucketWriter<std::uint32_t> buckets(
        this->dml_, refs, std::vector<std::uint64_t>(begin.begin(), begin.end() - 1), per);
      auto done2 = step(2.0 * double(T) * sizeof(Triangle));
      Scan(this->triangles_, T, tris, [&](const Triangle* t, std::uint64_t first, std::uint64_t n) {
        tick(first);
        for (std::uint64_t i = 0; i < n; ++i)
        {
          for (int k = 0; k < 3; ++k)
          {
            buckets.Add(bucketOf(t[i].v[k]), t[i].v[k]);
          }
        }
        done2(double(first + n) / double(T));
      });
      buckets.Finish();
    }
    {
      storage::CountedBuffer<OldNew> slice(this->dml_, static_cast<std::size_t>(sliceLength));
      std::vector<std::uint32_t> chunk;
      auto done3 = step(2.0 * double(T) * sizeof(Triangle));
      for (std::size_t b = 0; b < slices; ++b)
      {
        const std::uint64_t lo = b * sliceLength, n = std::min(sliceLength, V - lo);
        inverse.Read(lo, n, slice.Data());
        for (std::uint64_t first = begin[b]; first < begin[b + 1]; first += 3 * kChunk)
        {
          tick(first);
          const std::uint64_t c = std::min<std::uint64_t>(3 * kChunk, begin[b + 1] - first);
          chunk.resize(static_cast<std::size_t>(c));
          refs.Read(first, c, chunk.data());
          for (std::uint32_t& v : chunk)
          {
            v = slice[v - lo].now;
          }
          refs.Write(first, c, chunk.data());
          done3(double(first + c) / double(3 * T));
        }
      }
    }
    inverse.Close();
    std::optional<Array<Triangle>> renumbered;
    {
      // (the buckets' read buffers, each refilled when used up)
      storage::CountedBuffer<std::uint32_t> buf(this->dml_, static_cast<std::size_t>(slices) * per);
      startSorter();
      if (!sorter)
      {
        renumbered.emplace(this->dml_, T);
      }
      std::vector<std::uint64_t> at(begin.begin(), begin.end() - 1);
      std::vector<std::size_t> next(static_cast<std::size_t>(slices), 0), held(next);
      std::vector<Triangle> dst;
      auto done4 = step(3.0 * double(T) * sizeof(Triangle));
      Scan(this->triangles_, T, tris, [&](const Triangle* t, std::uint64_t first, std::uint64_t n) {
        tick(first);
        dst.resize(static_cast<std::size_t>(n));
        // (locals, kept in registers across the refills' calls)
        Triangle* const d = dst.data();
        std::uint32_t* const held0 = buf.Data();
        std::size_t* const nextOf = next.data();
        std::size_t* const heldOf = held.data();
        auto take = [&](std::uint32_t v) {
          const std::size_t b = bucketOf(v);
          if (nextOf[b] == heldOf[b])
          {
            heldOf[b] = static_cast<std::size_t>(std::min<std::uint64_t>(per, begin[b + 1] - at[b]));
            refs.Read(at[b], heldOf[b], held0 + b * per);
            at[b] += heldOf[b];
            nextOf[b] = 0;
          }
          return held0[b * per + nextOf[b]++];
        };
        for (std::uint64_t i = 0; i < n; ++i)
        {
          // (built in registers and stored whole: three stores read back as one load would
          // stall on store forwarding)
          Triangle r;
          r.v[0] = take(t[i].v[0]);
          r.v[1] = take(t[i].v[1]);
          r.v[2] = take(t[i].v[2]);
          LowestFirst(r);
          d[i] = r;
        }
        if (sorter)
        {
          emit(dst.data(), first, n);
        }
        else
        {
          renumbered->Write(first, n, dst.data());
        }
        done4(double(first + n) / double(T));
      });
    }
    refs.Close();
    if (renumbered)
    {
      this->triangles_.Swap(*renumbered); // (the old numbering closes with `renumbered`)
    }
  }
  else
  {
    Array<Corner> corners(this->dml_, 3 * T);
    std::vector<Triangle> tris;
    std::vector<Corner> cs;
    Scan(this->triangles_, T, tris, [&](const Triangle* t, std::uint64_t first, std::uint64_t n) {
      tick(first);
      cs.resize(static_cast<std::size_t>(3 * n));
      for (std::uint64_t i = 0; i < n; ++i)
      {
        for (std::uint32_t k = 0; k < 3; ++k)
        {
          cs[3 * i + k] = Corner{ t[i].v[k], static_cast<std::uint32_t>(first + i), k };
        }
      }
      corners.Write(3 * first, 3 * n, cs.data());
    });
    // (a vertex is in a face once: (vertex, face) orders the corners totally, one 64-bit compare)
    auto byVertex = [](const Corner& a, const Corner& b) {
      return (std::uint64_t(a.v) << 32 | a.face) < (std::uint64_t(b.v) << 32 | b.face);
    };
    storage::SortByKey(this->dml_, corners, byVertex, [](const Corner& c) { return c.v; },
      BitsFor(V), step(2.0 * 3.0 * double(T) * sizeof(Corner)), threads);
    std::vector<OldNew> map;
    std::uint64_t mapFirst = 0;
    Scan(corners, 3 * T, cs, [&](Corner* c, std::uint64_t first, std::uint64_t n) {
      tick(first);
      for (std::uint64_t i = 0; i < n; ++i)
      {
        // (corners ascend by vertex: the window of the inverse only moves forward)
        if (c[i].v >= mapFirst + map.size())
        {
          mapFirst = c[i].v;
          const std::uint64_t m = std::min(kChunk, V - mapFirst);
          map.resize(static_cast<std::size_t>(m));
          inverse.Read(mapFirst, m, map.data());
        }
        c[i].v = map[c[i].v - mapFirst].now;
      }
      corners.Write(first, n, c);
    });
    inverse.Close();
    auto byFace = [](const Corner& a, const Corner& b) {
      return (std::uint64_t(a.face) << 2 | a.k) < (std::uint64_t(b.face) << 2 | b.k);
    };
    storage::SortByKey(this->dml_, corners, byFace, [](const Corner& c) { return c.face; },
      BitsFor(T), step(2.0 * 3.0 * double(T) * sizeof(Corner)), threads);
    startSorter();
    Scan(corners, 3 * T, cs, [&](const Corner* c, std::uint64_t first, std::uint64_t n) {
      tick(first);
      tris.resize(static_cast<std::size_t>(n / 3));
      for (std::uint64_t i = 0; i < n / 3; ++i)
      {
        for (int k = 0; k < 3; ++k)
        {
          tris[i].v[k] = c[3 * i + k].v;
        }
        LowestFirst(tris[i]);
      }
      emit(tris.data(), first / 3, n / 3);
    }, 3 * (kChunk / 3)); // (whole faces per chunk)
  }
  part("faces renumbered");
  // 5. Faces (each rotated to start at its lowest vertex, orientation kept) by their vertices:
  //    out of core the sorter's buckets, in core a radix sort in place (storage::SortByKey).
  if (sorter)
  {
    sorter->Finish(this->triangles_, step(2.0 * double(T) * sizeof(Triangle)), threads);
    sorter.reset();
  }
  else
  {
    storage::SortByKey(this->dml_, this->triangles_, faceLess, lowest, BitsFor(V),
      step(2.0 * double(T) * sizeof(Triangle)), threads);
  }
  part("faces sorted");
  return path;
}

io::ReadStats StoredMesh::Replay(io::MeshSink& sink, const io::ReadOptions& options)
{
  sink.Begin(this->header_);
  const io::VertexLayout& L = this->header_.layout;
  const std::size_t ns = L.scalars.size();
  // at most about 1 MiB of buffers per chunk, whatever the number of vertex properties
  const std::size_t perVertex =
    12 + (L.normals ? 12 : 0) + (L.texcoords ? 8 : 0) + 8 * ns + (L.colors ? 8 : 0);
  const std::size_t chunk = std::clamp<std::size_t>((std::size_t(1) << 20) / perVertex, 1,
    options.chunkElements ? options.chunkElements : 16384);
  std::vector<float> xyz;
  std::vector<std::uint32_t> rec;
  PointDataBuffers buffers;
  for (std::uint64_t first = 0; first < this->header_.vertexCount; first += chunk)
  {
    const std::size_t n =
      std::size_t(std::min<std::uint64_t>(chunk, this->header_.vertexCount - first));
    this->ReadVertices(first, n, xyz, rec);
    io::VertexChunk c;
    c.first = first;
    c.count = n;
    c.xyz = xyz.data();
    if (this->stride_)
    {
      buffers.Unpack(rec.data(), n, L, this->stride_, c);
    }
    sink.Vertices(c);
    if (sink.AbortRequested())
    {
      throw AbortedError();
    }
  }
  io::ReadStats st;
  st.vertices = this->header_.vertexCount;
  st.droppedFaces = this->read_.droppedFaces;
  if (options.verticesOnly)
  {
    return st;
  }
  std::vector<Triangle> tris;
  for (std::uint64_t first = 0; first < this->triangleCount_; first += chunk)
  {
    const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, this->triangleCount_ - first));
    tris.resize(n);
    this->triangles_.Read(first, n, tris.data());
    sink.Triangles(reinterpret_cast<const std::uint32_t*>(tris.data()), n);
    if (sink.AbortRequested())
    {
      throw AbortedError();
    }
  }
  st.triangles = this->triangleCount_;
  st.polygons = this->read_.polygons ? this->read_.polygons : this->triangleCount_;
  sink.End(st);
  return st;
}

} // namespace sipmss::algorithms::detail
