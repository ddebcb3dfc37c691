// Algorithm II (OoCS grid clustering with quadrics) on the DML. See Cluster.h and
// docs/architecture.md. Every structure that grows with the input lives in DML blocks:
//   vertices   : per input vertex {x, y, z, cell}                      (16 B)
//   cell map   : open-addressing map grid key -> dense cell id          (16 B a slot, load <= 1/2),
//                behind a fixed 8192-entry cache of recent lookups
//   cells      : per cell: quadric (10 doubles), vertex sum, count, first vertex, bucket counter
//   cell attrs : per cell sums of the point data (normals, colors, texcoords, scalars)
//   candidates : faces over three distinct cells, appended in input order; after the read they
//                are bucketed by smallest cell and deduplicated per bucket (TriangleSet)
//   edges      : only with boundary quadrics: every face's edges, bucketed by smaller vertex
// Out of core, element access goes through a few pinned pages per block (PinWindow), so runs of
// nearby accesses in scanner-ordered input cost one page lookup. The input is parsed on a second
// thread (Prefetched) while this one clusters; the output does not depend on it. The records,
// structures and bounds pass are in cluster/Structures.inl (part of this translation unit).
#include "sipmss/algorithms/Cluster.h"

#include "Distributed.h"
#include "Gather.h"
#include "StoredMesh.h"

#include "sipmss/algorithms/Prefetch.h"
#include "sipmss/algorithms/Quadric.h"
#include "sipmss/algorithms/Vector.h"
#include "sipmss/storage/Access.h"
#include "sipmss/storage/Sort.h"
#include "sipmss/storage/Threads.h"

#include <Eigen/Dense>

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstring>
#include <limits>
#include <memory>
#include <new>
#include <optional>
#include <system_error>
#include <thread>
#include <tuple>
#ifdef __SSE2__
#include <emmintrin.h>
#endif

// The structures (one translation unit with this file).
#include "cluster/Structures.inl"

namespace sipmss::algorithms
{
namespace
{
using FaceGatherer = detail::Gatherer<VertexRec>;

// The clustering pass: vertices to cells, faces to quadrics and output triangles. Its state is
// one struct (the grid, the run's options and progress, its blocks in the DML); its steps are
// free functions over it, called by the reader's sink (ClusterSink) and then by ClusterRun.
struct ClusterState
{
  ClusterState(DML& dml, const ClusterGrid& grid, const ClusterOptions& options, bool configure,
    Progress& progress)
    : dml(dml)
    , grid(grid)
    , units(FixedUnits::Make(grid.origin, grid.cellSize, grid.dims,
        options.boundaryQuadrics ? options.boundaryWeight : 1.0))
    , options(options)
    , configure(configure)
    , progress(progress)
    , cellMap(dml, progress)
    , triangles(dml)
  {
  }
  // The blocks opened by id (the arrays close themselves): freed with the run, also in a
  // caller's DML (two-stage goes on in it).
  ~ClusterState()
  {
    for (storage::BlockId id : { this->attrBlock, this->chanBlock, this->extBlock })
    {
      try
      {
        if (id >= 0)
        {
          this->dml.CloseBlock(id);
        }
      }
      catch (...)
      {
        // (a destructor: the DML frees every block when it goes)
      }
    }
  }
  ClusterState(const ClusterState&) = delete;
  ClusterState& operator=(const ClusterState&) = delete;
  DML& dml;
  ClusterGrid grid;
  FixedUnits units; // of the exact cell sums
  const ClusterOptions& options;
  bool configure;
  Progress& progress;
  io::MeshHeader header;
  io::VertexLayout layout;
  double achievedErr2 = 0; // the largest representative's error (Emit; RunStats::achievedError)
  std::size_t attrStride = 0;
  std::vector<float> attrBuf;
  // Attribute-aware error (ClusterOptions::attributes): the channels, their values per input
  // vertex (chanBlock: k floats) and the extension per cell (extBlock: xSize doubles).
  std::vector<AttributeChannel> channels;
  std::size_t xSize = 0;
  storage::BlockId chanBlock = -1, extBlock = -1;
  std::uint64_t chanCap = 0;
  std::vector<std::uint8_t> recBuf;
  std::vector<float> chanBuf;
  std::vector<double> extBuf, faceExt, cornerValues;
  Array<VertexRec> vertices;
  Array<CellRec> cells;
  // (a face's corners are in as many index ranges as a subdivided scan has levels)
  PinWindow<VertexRec> vertexWindow{ dml, storage::Access::Write, PinWindow<VertexRec>::kMaxWays };
  PinWindow<CellRec> cellWindow{ dml, storage::Access::Write };
  storage::BlockId attrBlock = -1;
  CellMap cellMap;
  // Direct-mapped cache of recent key -> cell lookups in front of the cell map (a fixed 128 KiB
  // working set): scanner-ordered input revisits the cells of the sweep front all the time, and
  // this keeps those lookups off the DML's pages.
  static constexpr std::size_t kRecent = 8192;
  std::vector<KeySlot> recent = std::vector<KeySlot>(kRecent, KeySlot{ 0, 0 });
  TriangleSet triangles;
  Array<TriSlot> deferred;
  Array<EdgeRec> edges;
  Array<std::uint32_t> edgeCount;
  Array<std::uint64_t> cellKey; // ClusterOptions::gridOrder: each cell's grid key (KeepCellKeys)
  std::uint64_t numEdges = 0;
  std::uint64_t deferredCount = 0;
  std::uint32_t numCells = 0;
  std::uint64_t verticesSeen = 0;
  std::uint64_t expected = 0, done = 0;
  std::uint64_t expectedHint = 0; // see ExpectSizes
  // In core, faces out of spatial order: the helper thread that gathers their vertex records
  // (Gather.h; started at the first such chunk, with more than one thread; last, so that it
  // stops first).
  bool gatherTried = false;
  std::unique_ptr<FaceGatherer> gatherer;
};

// A vertex record's position, and n / len (componentwise).
inline Vec3 Position(const VertexRec& v)
{
  return { double(v.x), double(v.y), double(v.z) };
}
inline Vec3 Unit(const Vec3& n, double len)
{
  return { n.x / len, n.y / len, n.z / len };
}

// The clustering pass, as free functions over the state.
void BeginInput(ClusterState& cluster, const io::MeshHeader& h);
void AddVertices(ClusterState& cluster, const io::VertexChunk& c);
void AddTriangles(ClusterState& cluster, const std::uint32_t* idx, std::size_t count);
void EndInput(ClusterState& cluster, const io::ReadStats&);
void KeepCellKeys(ClusterState& cluster);
void ReleaseInputBlocks(ClusterState& cluster);
void FinishTriangles(ClusterState& cluster);
void FinishBoundaries(ClusterState& cluster);
void ExpectSizes(ClusterState& cluster, std::uint64_t verticesAndFaces);
std::uint64_t Cells(const ClusterState& cluster);
std::uint64_t Candidates(const ClusterState& cluster);
std::uint64_t OutputTriangles(const ClusterState& cluster);
struct DistributedOutput;
void Emit(ClusterState& cluster, io::MeshSink& out, RunStats& stats, DistributedOutput* dist);
void Tick(ClusterState& cluster, std::uint64_t more = 0);
void AddCell(ClusterState& cluster);
void AccumulateAttributes(
  ClusterState& cluster, const io::VertexChunk& c, std::size_t i, std::uint32_t cell);
void Defer(ClusterState& cluster, const std::uint32_t* f);
void AppendEdges(ClusterState& cluster, const std::uint32_t* f);
void AddBoundaryQuadrics(ClusterState& cluster);
void AddBoundaryPlane(ClusterState& cluster, const EdgeRec& e);
template <class F>
void UpdateCell(ClusterState& cluster, std::uint32_t cell, F&& f);
void AddTriangle(ClusterState& cluster, const std::uint32_t* f);
void AddTriangleRecords(ClusterState& cluster, const std::uint32_t* f, const VertexRec& a,
  const VertexRec& b, const VertexRec& c);
void AddCandidate(ClusterState& cluster, const VertexRec& a, const VertexRec& b, const VertexRec& c);
void AddTrianglePlain(ClusterState& cluster, const std::uint32_t* f, const VertexRec& a,
  const VertexRec& b, const VertexRec& c);
void Representative(ClusterState& cluster, const CellRec& rec, const Quadric& Q, double p[3]);
void OptimalCellAttributes(ClusterState& cluster, const double p[3], std::vector<float>& normals,
  std::vector<std::uint8_t>& rgba, std::vector<float>& texcoords, std::vector<float>& scalars);
void AddFaceAttributeTerms(ClusterState& cluster, const std::uint32_t* f, const VertexRec& a,
  const VertexRec& b, const VertexRec& c, double area);

// The cell records' first size. In core, from the header: the occupied cells a scan is expected
// to have (EstimatedCells, at most the Config's declared maximum). An in-core block is zeroed
// lazily (calloc), so only the records in use are ever touched, and the growth's copies into
// fresh memory, which these machines make slow on first touch, are not made (Dragon-size at
// grid 300: 175K cells of 256 bytes, grown from 1,024 by halves). Out of core (or without
// counts) the records grow from 1,024.
std::uint64_t InitialCells(const ClusterState& cluster, const io::MeshHeader& h)
{
  constexpr std::uint64_t kFirst = 1024;
  if (!h.vertexCount || cluster.dml.GetMode() != storage::Mode::InCore)
  {
    return kFirst;
  }
  const std::uint64_t gridCells =
    std::uint64_t(cluster.grid.dims[0]) * cluster.grid.dims[1] * cluster.grid.dims[2];
  const int m = int(std::max({ cluster.grid.dims[0], cluster.grid.dims[1], cluster.grid.dims[2] }));
  std::uint64_t cells = std::min({ std::uint64_t(EstimatedCells(h.vertexCount, m)), gridCells,
    std::uint64_t(kNoCell - 1) });
  // (within half of what the budget has left, with the candidates' share: an estimate must not
  // be what moves a run out of core)
  const std::uint64_t budget = cluster.dml.GetProfile().memoryBudget;
  if (budget)
  {
    const std::uint64_t held = cluster.dml.GetStats().bytesHeld;
    const std::uint64_t room = budget > held ? (budget - held) / 2 : 0;
    const double perCell = sizeof(CellRec) + kWork::kCandidatesPerCell * sizeof(TriSlot);
    cells = std::min<std::uint64_t>(cells, std::uint64_t(double(room) / perCell));
  }
  return std::max(kFirst, cells);
}

void BeginInput(ClusterState& cluster, const io::MeshHeader& h)
{
  cluster.channels = AttributeChannels(h.layout, cluster.options.attributes);
  cluster.xSize = AttributeExtraSize(cluster.channels.size());
  if (cluster.configure && h.vertexCount)
  {
    // The paper's Config: the table of structures with their maximum counts decides the mode.
    storage::Profile profile = cluster.options.storage;
    const std::uint64_t gridCells =
      std::uint64_t(cluster.grid.dims[0]) * cluster.grid.dims[1] * cluster.grid.dims[2];
    profile.structures.clear();
    AddClusterStructures(profile, h.vertexCount, h.faceCount, gridCells, cluster.channels.size());
    cluster.dml.Config(profile);
  }
  cluster.header = h;
  cluster.layout = h.layout;
  cluster.attrStride = (h.layout.normals ? 3 : 0) + (h.layout.colors ? 4 : 0) +
    (h.layout.texcoords ? 2 : 0) + h.layout.scalars.size();
  cluster.vertices = Array<VertexRec>(cluster.dml, std::max<std::uint64_t>(h.vertexCount, 1024));
  std::uint64_t cells = InitialCells(cluster, h);
  try
  {
    cluster.cells = Array<CellRec>(cluster.dml, cells);
  }
  catch (const std::bad_alloc&)
  {
    cells = 1024; // (an estimate the system would not map: grown as they come instead)
    cluster.cells = Array<CellRec>(cluster.dml, cells);
  }
  cluster.triangles.Presize(
    std::uint64_t(kWork::kCandidatesPerCell * double(cells)), h.faceCount);
  if (cluster.attrStride)
  {
    cluster.attrBlock = cluster.dml.OpenBlock(cluster.attrStride * sizeof(float), cells);
    cluster.attrBuf.assign(cluster.attrStride, 0.f);
  }
  if (cluster.xSize)
  {
    const std::size_t k = cluster.channels.size();
    cluster.chanCap = std::max<std::uint64_t>(h.vertexCount, 1024);
    cluster.chanBlock = cluster.dml.OpenBlock(k * sizeof(float), cluster.chanCap);
    cluster.extBlock = cluster.dml.OpenBlock(cluster.xSize * sizeof(double), 1024);
    cluster.recBuf.assign(RecordSize(h.layout), 0);
    cluster.chanBuf.assign(3 * k, 0.f);
    cluster.extBuf.assign(cluster.xSize, 0.0);
    cluster.faceExt.assign(cluster.xSize, 0.0);
  }
  cluster.expected = h.vertexCount + h.faceCount;
  if (!cluster.expected)
  {
    cluster.expected = cluster.expectedHint; // (compressed inputs announce no sizes)
  }
  else
  {
    // (nothing done yet in this phase: the announced sizes replace the estimate)
    cluster.progress.Sized(h.vertexCount, h.faceCount);
    cluster.progress.BeginPhase("cluster", kWork::kCluster * double(cluster.expected),
      ClusterWorkAfterRead(
        h.vertexCount, h.faceCount, cluster.options.maximumGridDimension, cluster.options));
  }
}

void AddVertices(ClusterState& cluster, const io::VertexChunk& c)
{
  if (c.first + c.count > cluster.vertices.Size())
  {
    cluster.vertexWindow.Release();
    cluster.vertices.Resize(
      std::max<std::uint64_t>(c.first + c.count, cluster.vertices.Size() * 2));
  }
  std::uint64_t lastKey = std::numeric_limits<std::uint64_t>::max();
  std::uint32_t lastCell = kNoCell;
  // Each vertex's key is computed kAhead vertices early, and the cache entry and map slot it
  // will look up are fetched then: in an input whose vertices are not in spatial order those
  // lookups go anywhere in the map.
  constexpr std::size_t kAhead = 8;
  std::uint64_t keys[kAhead];
  std::uint64_t lastAhead = lastKey;
  auto lookAhead = [&](std::size_t j) {
    const float* q = c.xyz + 3 * j;
    const std::uint64_t key = cluster.grid.Key(q[0], q[1], q[2]);
    keys[j % kAhead] = key;
    if (key != lastAhead)
    {
      lastAhead = key;
      __builtin_prefetch(&cluster.recent[Mix(key) & (ClusterState::kRecent - 1)]);
      cluster.cellMap.Prefetch(key);
    }
  };
  for (std::size_t j = 0; j < std::min(kAhead, c.count); ++j)
  {
    lookAhead(j);
  }
  for (std::size_t i = 0; i < c.count; ++i)
  {
    if ((i & 4095) == 4095)
    {
      Tick(cluster, i);
    }
    const float* p = c.xyz + 3 * i;
    const std::uint64_t key = keys[i % kAhead];
    if (i + kAhead < c.count)
    {
      lookAhead(i + kAhead);
    }
    std::uint32_t cell = lastCell;
    if (key != lastKey)
    {
      KeySlot& cached = cluster.recent[Mix(key) & (ClusterState::kRecent - 1)];
      if (cached.key == key + 1)
      {
        cell = static_cast<std::uint32_t>(cached.cell);
      }
      else
      {
        bool inserted = false;
        cell = cluster.cellMap.FindOrInsert(key, cluster.numCells, &inserted);
        if (inserted)
        {
          AddCell(cluster);
        }
        cached = KeySlot{ key + 1, cell };
      }
      lastKey = key;
      lastCell = cell;
    }
    cluster.vertexWindow.At(cluster.vertices.Id(), c.first + i) =
      VertexRec{ p[0], p[1], p[2], cell };
    if (cluster.attrStride)
    {
      UpdateCell(cluster, cell, [](CellRec& rec) { ++rec.vertices; });
      AccumulateAttributes(cluster, c, i, cell);
    }
    if (cluster.xSize)
    {
      // The vertex's weighted channel values (its faces' attribute terms need them).
      const std::size_t k = cluster.channels.size();
      if (c.first + i >= cluster.chanCap)
      {
        cluster.chanCap = std::max<std::uint64_t>(c.first + c.count, 2 * cluster.chanCap);
        cluster.dml.Resize(cluster.chanBlock, cluster.chanCap);
      }
      PackRecord(cluster.layout, c, i, cluster.recBuf.data());
      float* chans = static_cast<float*>(cluster.dml.BasePointer(cluster.chanBlock));
      float* v = chans ? chans + (c.first + i) * k : cluster.chanBuf.data();
      for (std::size_t j = 0; j < k; ++j)
      {
        v[j] = float(ChannelValue(cluster.channels[j], cluster.recBuf.data()));
      }
      if (!chans)
      {
        cluster.dml.Write(cluster.chanBlock, k * sizeof(float), c.first + i, v);
      }
    }
  }
  cluster.verticesSeen = std::max<std::uint64_t>(cluster.verticesSeen, c.first + c.count);
  cluster.done += c.count;
  Tick(cluster);
}

// Whether a chunk of faces comes in spatial order: of its first 64 faces, at most a quarter
// start more than 4,096 vertices away from the previous face's start (scanner order and fans
// almost none, a shuffled input almost all; the measure of LayoutMeter on a sample).
bool ComeInOrder(const std::uint32_t* idx, std::size_t count)
{
  const std::size_t n = std::min<std::size_t>(count, 65);
  std::size_t far = 0;
  for (std::size_t t = 1; t < n; ++t)
  {
    const std::uint32_t a = idx[3 * t], b = idx[3 * (t - 1)];
    far += (a > b ? a - b : b - a) > 4096;
  }
  return 4 * far <= n;
}

// The bytes of a cell record that a face's update touches: the sums, and the smallest corner
// for the sampled-vertex fallback.
std::size_t CellUpdateBytes(const ClusterState& cluster)
{
  return cluster.options.fallback == ClusterFallback::SampledVertex
    ? sizeof(CellRec)
    : (cluster.options.exactSums ? offsetof(CellRec, first) : kPlainBytes);
}

// Fetches every cache line of the cell records that a face over the vertex records r[0..2]
// will update (each distinct cell once). Always inlined: GCC 12 takes a function whose only
// effect is a prefetch for one without effects and drops the calls (no prefetch was left).
SIPMSS_ALWAYS_INLINE void PrefetchCells(
  const ClusterState& cluster, const char* cellBase, std::size_t cellBytes, const VertexRec* r)
{
  for (int k = 0; k < 3; ++k)
  {
    const std::uint32_t cell = r[k].cell;
    if (cell < cluster.numCells && (k == 0 || cell != r[0].cell) && (k < 2 || cell != r[1].cell))
    {
      const std::uintptr_t first =
        reinterpret_cast<std::uintptr_t>(cellBase + std::size_t(cell) * sizeof(CellRec));
      for (std::uintptr_t line = first & ~std::uintptr_t(63); line < first + cellBytes; line += 64)
      {
        __builtin_prefetch(reinterpret_cast<const void*>(line), 1);
      }
    }
  }
}

inline bool Deferred(const ClusterState& cluster, const std::uint32_t* f)
{
  return f[0] >= cluster.verticesSeen || f[1] >= cluster.verticesSeen ||
    f[2] >= cluster.verticesSeen;
}

// Adds faces idx[0, count), the first of them face `done` of the chunk (for the progress), on
// this thread alone; `inOrder`: the chunk's faces come in spatial order (ComeInOrder).
void AddTrianglesHere(ClusterState& cluster, const std::uint32_t* idx, std::size_t count,
  std::size_t done, bool inOrder)
{
  // In core, the vertex records of the face kAhead faces ahead are fetched while this one is
  // added, and (from those records, by then in the cache) the cell records of the face
  // kCellAhead ahead: in an input whose faces are not in spatial order both go anywhere in
  // memory, and their loads then overlap the faces' arithmetic.
  const auto* base = static_cast<const VertexRec*>(cluster.dml.BasePointer(cluster.vertices.Id()));
  // (cell records only for faces out of spatial order: in scanner order they are in the cache
  // already, and fetching them cost 5% of the Lucy-size clustering)
  const auto* cellBase =
    inOrder ? nullptr : static_cast<const char*>(cluster.dml.BasePointer(cluster.cells.Id()));
  constexpr std::size_t kAhead = 16, kCellAhead = 8;
  const std::size_t cellBytes = CellUpdateBytes(cluster);
  // (with boundary quadrics or attributes a face appends to blocks of their own, which may grow)
  const bool faceGrows = cluster.options.boundaryQuadrics || cluster.xSize;
  auto bases = [&] {
    base = static_cast<const VertexRec*>(cluster.dml.BasePointer(cluster.vertices.Id()));
    cellBase =
      cellBase ? static_cast<const char*>(cluster.dml.BasePointer(cluster.cells.Id())) : nullptr;
  };
  for (std::size_t t = 0; t < count; ++t)
  {
    if (((done + t) & 4095) == 4095)
    {
      Tick(cluster, done + t);
    }
    const std::uint32_t* f = idx + 3 * t;
    if (base && t + kAhead < count)
    {
      const std::uint32_t* g = f + 3 * kAhead;
      for (int k = 0; k < 3; ++k)
      {
        if (g[k] < cluster.verticesSeen)
        {
          __builtin_prefetch(base + g[k]);
        }
      }
    }
    if (base && cellBase && t + kCellAhead < count)
    {
      const std::uint32_t* g = f + 3 * kCellAhead;
      if (!Deferred(cluster, g))
      {
        const VertexRec r[3] = { base[g[0]], base[g[1]], base[g[2]] };
        PrefetchCells(cluster, cellBase, cellBytes, r);
      }
    }
    if (Deferred(cluster, f))
    {
      // faces before their vertices (e.g. a PLY with the face element first): keep for End()
      Defer(cluster, f);
      bases(); // (a resize, which may move the blocks or take the DML out of core)
      continue;
    }
    const bool grows = faceGrows || cluster.triangles.Full();
    AddTriangle(cluster, f);
    if (grows)
    {
      bases();
    }
  }
}

// Adds faces idx[0, count) (at most FaceGatherer::kMaxFaces; the first is face `done` of the
// chunk) with the records gathered by the helper. Returns how many it added: fewer at a face
// before its vertices, or when the candidates' block is full (its resize may move the vertex
// block, which the helper reads), and the caller then adds the rest.
std::size_t AddTrianglesGathered(
  ClusterState& cluster, const std::uint32_t* idx, std::size_t count, std::size_t done)
{
  constexpr std::size_t kBlock = FaceGatherer::kBlock, kCellAhead = 16;
  FaceGatherer& g = *cluster.gatherer;
  const auto* cellBase = static_cast<const char*>(cluster.dml.BasePointer(cluster.cells.Id()));
  const std::size_t cellBytes = CellUpdateBytes(cluster);
  g.Post(static_cast<const VertexRec*>(cluster.dml.BasePointer(cluster.vertices.Id())),
    cluster.verticesSeen, idx, count);
  struct StopOnExit // (also on a throw: the helper reads the caller's faces)
  {
    FaceGatherer& g;
    ~StopOnExit() { this->g.Stop(); }
  } stop{ g };
  std::size_t taken = 0;   // faces [0, taken) are copied, and this thread knows it
  std::size_t horizon = 0; // the same, looked at without waiting (for the cell prefetch)
  for (std::size_t t = 0; t < count; ++t)
  {
    if (((done + t) & 4095) == 4095)
    {
      Tick(cluster, done + t);
    }
    if (t == taken)
    {
      g.Take(t / kBlock);
      taken = std::min(count, t + kBlock);
      horizon = std::max(horizon, taken);
    }
    const std::size_t u = t + kCellAhead;
    if (u < count)
    {
      if (u >= horizon && horizon < count && g.Ready(horizon / kBlock))
      {
        horizon = std::min(count, horizon + kBlock);
      }
      if (u < horizon) // (a vertex not read, of a face deferred, has cell 0: a harmless fetch)
      {
        PrefetchCells(cluster, cellBase, cellBytes, g.Records(u));
      }
    }
    const std::uint32_t* f = idx + 3 * t;
    if (Deferred(cluster, f) || cluster.triangles.Full())
    {
      return t; // (Defer, or a candidate's Append, resizes a block: not while the helper reads)
    }
    const VertexRec* r = g.Records(t);
    AddTriangleRecords(cluster, f, r[0], r[1], r[2]);
  }
  return count;
}

void AddTriangles(ClusterState& cluster, const std::uint32_t* idx, std::size_t count)
{
  // In core, faces out of spatial order, more than one thread: the vertex records are gathered
  // by a helper (Gather.h). Not with boundary quadrics or attributes, whose per-face work
  // reads and resizes blocks of their own.
  const bool inOrder = ComeInOrder(idx, count);
  const bool gather = cluster.dml.BasePointer(cluster.vertices.Id()) &&
    !cluster.options.boundaryQuadrics && !cluster.xSize && count > FaceGatherer::kBlock &&
    !inOrder;
  if (gather && !cluster.gatherTried)
  {
    cluster.gatherTried = true;
    if (storage::ResolveThreads(cluster.options.threads) > 1)
    {
      try
      {
        cluster.gatherer = std::make_unique<FaceGatherer>();
      }
      catch (const std::system_error&)
      {
        // (no thread to be had: the faces are added on this one)
      }
      catch (const std::bad_alloc&)
      {
        // (nor its buffer)
      }
    }
  }
  // In parts of at most kMaxFaces faces. The loops below keep the blocks' base pointers (and
  // the helper reads the vertex block): a call that may resize a block (which may move it, or
  // take the DML out of core) is followed by a fresh look at them, or not made while the helper
  // runs.
  std::size_t t = 0;
  while (t < count)
  {
    const std::size_t n = std::min(count - t, FaceGatherer::kMaxFaces);
    std::size_t added = 0;
    if (gather && cluster.gatherer && cluster.dml.BasePointer(cluster.vertices.Id()))
    {
      added = AddTrianglesGathered(cluster, idx + 3 * t, n, t);
    }
    if (added < n)
    {
      AddTrianglesHere(cluster, idx + 3 * (t + added), n - added, t + added, inOrder);
    }
    t += n;
  }
  cluster.done += count;
  Tick(cluster);
}

void EndInput(ClusterState& cluster, const io::ReadStats&)
{
  if (cluster.deferredCount)
  {
    for (std::uint64_t i = 0; i < cluster.deferredCount; ++i)
    {
      TriSlot s = cluster.deferred.Get(i);
      if (s.v[0] >= cluster.verticesSeen || s.v[1] >= cluster.verticesSeen ||
        s.v[2] >= cluster.verticesSeen)
      {
        throw io::MeshIOError("a face references vertex " +
          std::to_string(std::max({ s.v[0], s.v[1], s.v[2] })) + " but the mesh has only " +
          std::to_string(cluster.verticesSeen) + " vertices");
      }
      AddTriangle(cluster, s.v);
    }
    cluster.deferred.Close();
  }
}

// --- after the read
// ClusterOptions::gridOrder: each cell's grid key, kept from the cell map (which the input's
// blocks release) for Emit.
void KeepCellKeys(ClusterState& cluster)
{
  cluster.cellKey = Array<std::uint64_t>(cluster.dml, std::max<std::uint64_t>(cluster.numCells, 1));
  cluster.cellMap.ForEach([&](std::uint64_t key, std::uint64_t cell) {
    cluster.cellKey.Set(cell, key);
  });
}

void ReleaseInputBlocks(ClusterState& cluster)
{
  cluster.vertexWindow.Release();
  cluster.cellWindow.Release();
  cluster.vertices.Close();
  cluster.cellMap.Release();
  if (cluster.chanBlock >= 0)
  {
    cluster.dml.CloseBlock(cluster.chanBlock);
    cluster.chanBlock = -1;
  }
}

void FinishTriangles(ClusterState& cluster)
{
  cluster.triangles.Finish(cluster.cells, cluster.numCells, cluster.progress);
}

void FinishBoundaries(ClusterState& cluster) { AddBoundaryQuadrics(cluster); }

// The bounds pass's estimate of vertices + faces, for inputs whose header has no sizes.
void ExpectSizes(ClusterState& cluster, std::uint64_t verticesAndFaces)
{
  cluster.expectedHint = verticesAndFaces;
}

std::uint64_t Cells(const ClusterState& cluster) { return cluster.numCells; }

std::uint64_t Candidates(const ClusterState& cluster) { return cluster.triangles.Candidates(); }

std::uint64_t OutputTriangles(const ClusterState& cluster) { return cluster.triangles.Size(); }

// Output vertices, gathered in chunks.
struct VertexBuffers
{
  std::vector<float> xyz, normals, texcoords, scalars;
  std::vector<std::uint8_t> rgba;
  std::size_t Count() const { return this->xyz.size() / 3; }
  void Clear()
  {
    this->xyz.clear();
    this->normals.clear();
    this->texcoords.clear();
    this->scalars.clear();
    this->rgba.clear();
  }
};

// Appends the vertex of a cell: its representative (the cell quadric with its attribute error;
// the extension in cluster.extBuf) and its point data from the sums `attr`. `index` is the
// output vertex's number (for exportQuadric).
void AppendVertex(ClusterState& cluster, const CellRec& rec, const float* attr, VertexBuffers& v,
  std::uint64_t index)
{
  // The quadric to minimize: the cell's, with its attribute error (Attributes.h).
  const Quadric cellQ = cluster.options.exactSums ? cluster.units.ToDouble(rec.q) : rec.plain.q;
  Quadric Q = cellQ;
  if (cluster.xSize)
  {
    AddAttributeError(cluster.extBuf.data(), cluster.channels.size(), Q);
  }
  double p[3];
  Representative(cluster, rec, Q, p);
  // The representative's error, at its position as written (the quadrics are about the centre).
  const double* centre = cluster.units.centre.data();
  const double trace = QuadricTrace(cellQ.q);
  if (trace > 0)
  {
    cluster.achievedErr2 = std::max(cluster.achievedErr2,
      QuadricValue(Q.q, double(float(p[0])) - centre[0], double(float(p[1])) - centre[1],
        double(float(p[2])) - centre[2]) /
        trace);
  }
  if (cluster.options.exportQuadric)
  {
    const Quadric absolute = Translated(cellQ, centre);
    cluster.options.exportQuadric(index, absolute.q);
  }
  v.xyz.insert(v.xyz.end(), { float(p[0]), float(p[1]), float(p[2]) });
  if (!cluster.attrStride)
  {
    return;
  }
  const float inv = rec.vertices ? 1.0f / float(rec.vertices) : 0.f;
  std::size_t k = 0;
  if (cluster.layout.normals)
  {
    const float n[3] = { attr[0], attr[1], attr[2] };
    const float len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    const float s = len > 0 ? 1.0f / len : 0.f;
    v.normals.insert(v.normals.end(), { n[0] * s, n[1] * s, n[2] * s });
    k = 3;
  }
  if (cluster.layout.colors)
  {
    for (int j = 0; j < 4; ++j)
    {
      const float c = std::round(attr[k + j] * inv);
      v.rgba.push_back(static_cast<std::uint8_t>(std::clamp(c, 0.f, 255.f)));
    }
    k += 4;
  }
  if (cluster.layout.texcoords)
  {
    v.texcoords.insert(v.texcoords.end(), { attr[k] * inv, attr[k + 1] * inv });
    k += 2;
  }
  for (std::size_t j = 0; j < cluster.layout.scalars.size(); ++j)
  {
    v.scalars.push_back(attr[k + j] * inv);
  }
  if (cluster.xSize && cluster.extBuf[0] > 0)
  {
    const double rel[3] = { p[0] - centre[0], p[1] - centre[1], p[2] - centre[2] };
    OptimalCellAttributes(cluster, rel, v.normals, v.rgba, v.texcoords, v.scalars);
  }
}

// A distributed run's output (ClusterDistributed): which of this rank's triangles it writes
// (the others are another rank's) and its vertices, computed by the cells' owners (records of
// VertexRecordSize bytes by output number).
struct DistributedOutput
{
  Array<std::uint8_t> keep;    // per triangle of Order(): 1 written here
  Array<std::uint32_t> index;  // the cells' output numbers (NumberUsedCells)
  std::uint32_t numOut = 0;
  std::uint64_t outTris = 0;
  storage::BlockId vertices = -1;
  std::size_t recordSize = 0;
};

// Numbers the cells that the written triangles use (those `keep` marks, every one without it),
// in cell order, in `index` (kNoCell: unused); returns their count and the written triangles'.
// `tick(step)` is called every 4096 of the numTris + numCells steps.
template <class Tick>
std::uint32_t NumberUsedCells(ClusterState& cluster, const Array<std::uint8_t>* keep,
  Array<std::uint32_t>& index, std::uint64_t& outTris, Tick&& tick)
{
  const std::uint64_t numTris = cluster.triangles.Size();
  index = Array<std::uint32_t>(cluster.dml, std::max<std::uint64_t>(cluster.numCells, 1));
  {
    const std::uint32_t unused = kNoCell;
    cluster.dml.Fill(index.Id(), &unused);
  }
  outTris = 0;
  cluster.triangles.Order().ForEachChunk(0, numTris, storage::Access::Read,
    [&](TriSlot* d, std::uint64_t f, std::uint64_t n) {
      for (std::uint64_t j = 0; j < n; ++j)
      {
        if (((f + j) & 4095) == 0)
        {
          tick(f + j);
        }
        if (!keep || keep->Get(f + j))
        {
          ++outTris;
          for (int k = 0; k < 3; ++k)
          {
            index.Set(d[j].v[k], 0);
          }
        }
      }
    });
  std::uint32_t numOut = 0;
  for (std::uint32_t c = 0; c < cluster.numCells; ++c)
  {
    if ((c & 4095) == 0)
    {
      tick(numTris + c);
    }
    if (index.Get(c) != kNoCell)
    {
      index.Set(c, numOut++);
    }
  }
  return numOut;
}

// A vertex record as the owners send it: xyz, normals, texture coordinates, scalars (floats),
// then RGBA.
std::size_t VertexRecordSize(const io::VertexLayout& l)
{
  return sizeof(float) *
    (3 + (l.normals ? 3 : 0) + (l.texcoords ? 2 : 0) + l.scalars.size()) +
    (l.colors ? 4 : 0);
}

void PackVertex(const io::VertexLayout& l, const VertexBuffers& v, std::size_t i, std::uint8_t* out)
{
  auto put = [&out](const float* f, std::size_t n) {
    std::memcpy(out, f, n * sizeof(float));
    out += n * sizeof(float);
  };
  put(v.xyz.data() + 3 * i, 3);
  if (l.normals)
  {
    put(v.normals.data() + 3 * i, 3);
  }
  if (l.texcoords)
  {
    put(v.texcoords.data() + 2 * i, 2);
  }
  put(v.scalars.data() + l.scalars.size() * i, l.scalars.size());
  if (l.colors)
  {
    std::memcpy(out, v.rgba.data() + 4 * i, 4);
  }
}

void UnpackVertex(const io::VertexLayout& l, const std::uint8_t* in, VertexBuffers& v)
{
  auto get = [&in](std::vector<float>& dst, std::size_t n) {
    const std::size_t at = dst.size();
    dst.resize(at + n);
    std::memcpy(dst.data() + at, in, n * sizeof(float));
    in += n * sizeof(float);
  };
  get(v.xyz, 3);
  if (l.normals)
  {
    get(v.normals, 3);
  }
  if (l.texcoords)
  {
    get(v.texcoords, 2);
  }
  get(v.scalars, l.scalars.size());
  if (l.colors)
  {
    v.rgba.insert(v.rgba.end(), in, in + 4);
  }
}

void Emit(ClusterState& cluster, io::MeshSink& out, RunStats& stats, DistributedOutput* dist)
{
  const std::uint64_t numTris = cluster.triangles.Size();
  auto& order = cluster.triangles.Order();
  auto kept = [dist](std::uint64_t t) { return !dist || dist->keep.Get(t) != 0; };
  // Progress: 4 steps over cells + triangles (mark, number, vertices, triangles).
  const double total = 2.0 * double(cluster.numCells) + 2.0 * double(numTris) + 1.0;
  // The output numbers of the cells used by output triangles (a distributed run numbered them
  // before fetching their vertices).
  Array<std::uint32_t> ownIndex;
  std::uint64_t outTris = dist ? dist->outTris : 0;
  const std::uint32_t numOut = dist ? dist->numOut
                                    : NumberUsedCells(cluster, nullptr, ownIndex, outTris,
                                        [&](std::uint64_t step) {
                                          cluster.progress.Tick(double(step) / total);
                                        });
  const Array<std::uint32_t>& outIndex = dist ? dist->index : ownIndex;
  if (!dist)
  {
    cluster.dml.Reconfigure(); // the input-sized blocks are gone: in core from here if it fits
  }
  // ClusterOptions::gridOrder: the used cells sorted by their grid key, and ownIndex renumbered
  // in that order.
  struct KeyedCell
  {
    std::uint64_t key;
    std::uint32_t cell, pad;
  };
  // (only while the cell records are in memory: out of core, reading them in another order than
  // they were made would cost a page read a record)
  const bool gridOrder = !dist && cluster.cellKey.IsOpen() &&
    cluster.dml.BasePointer(cluster.cells.Id()) != nullptr;
  if (cluster.cellKey.IsOpen() && !gridOrder)
  {
    cluster.cellKey.Close();
  }
  Array<KeyedCell> byKey;
  if (gridOrder)
  {
    // (numOut elements; one, unused, when there are none)
    byKey = Array<KeyedCell>(cluster.dml, std::max<std::uint32_t>(numOut, 1));
    for (std::uint32_t c = 0; c < cluster.numCells; ++c)
    {
      const std::uint32_t i = ownIndex.Get(c);
      if (i != kNoCell)
      {
        byKey.Set(i, KeyedCell{ cluster.cellKey.Get(c), c, 0 });
      }
    }
    cluster.cellKey.Close();
    const std::uint64_t gridCells = std::uint64_t(cluster.grid.dims[0]) * cluster.grid.dims[1] *
      cluster.grid.dims[2];
    storage::SortByKey(
      cluster.dml, byKey, [](const KeyedCell& a, const KeyedCell& b) { return a.key < b.key; },
      [](const KeyedCell& a) { return a.key; }, detail::BitsFor(gridCells), {}, 1);
    for (std::uint32_t r = 0; r < numOut; ++r)
    {
      ownIndex.Set(byKey.Get(r).cell, r);
    }
  }

  io::MeshHeader h;
  h.format = cluster.header.format;
  h.vertexCount = numOut;
  h.faceCount = outTris;
  h.layout = cluster.layout;
  out.Begin(h);

  const std::size_t chunk = 1 << 13;
  VertexBuffers v;
  v.xyz.reserve(3 * chunk);
  std::vector<float> attr(cluster.attrStride);
  std::vector<std::uint8_t> record(dist ? dist->recordSize : 0);
  std::uint64_t first = 0;
  auto flush = [&]() {
    io::VertexChunk vc;
    vc.first = first;
    vc.count = v.Count();
    vc.xyz = v.xyz.data();
    vc.normals = cluster.layout.normals ? v.normals.data() : nullptr;
    vc.rgba = cluster.layout.colors ? v.rgba.data() : nullptr;
    vc.texcoords = cluster.layout.texcoords ? v.texcoords.data() : nullptr;
    vc.scalars = cluster.layout.scalars.empty() ? nullptr : v.scalars.data();
    if (vc.count)
    {
      out.Vertices(vc);
    }
    first += vc.count;
    v.Clear();
  };
  for (std::uint32_t k = 0; k < (gridOrder ? numOut : cluster.numCells); ++k)
  {
    const std::uint32_t c = gridOrder ? byKey.Get(k).cell : k;
    // (in grid order the cells come at random: in core their records are fetched ahead; the
    // pointers are read each time, as exportQuadric may grow a block and move the DML out of core)
    const auto* keyed =
      gridOrder ? static_cast<const KeyedCell*>(cluster.dml.BasePointer(byKey.Id())) : nullptr;
    const auto* cellBase = static_cast<const char*>(cluster.dml.BasePointer(cluster.cells.Id()));
    if (keyed && cellBase && k + 8 < numOut)
    {
      const char* rec = cellBase + std::size_t(keyed[k + 8].cell) * sizeof(CellRec);
      for (std::size_t line = 0; line < sizeof(CellRec); line += 64)
      {
        __builtin_prefetch(rec + line);
      }
    }
    const std::uint32_t index = outIndex.Get(c);
    if (index == kNoCell)
    {
      continue;
    }
    if (dist)
    {
      // (computed by the cell's owner)
      cluster.dml.Read(dist->vertices, dist->recordSize, index, record.data());
      UnpackVertex(cluster.layout, record.data(), v);
    }
    else
    {
      if (cluster.xSize)
      {
        cluster.dml.Read(cluster.extBlock, cluster.xSize * sizeof(double), c, cluster.extBuf.data());
      }
      if (cluster.attrStride)
      {
        cluster.dml.Read(cluster.attrBlock, cluster.attrStride * sizeof(float), c, attr.data());
      }
      AppendVertex(cluster, cluster.cells.Get(c), attr.data(), v, first + v.Count());
    }
    if (v.Count() == chunk)
    {
      flush();
      cluster.progress.Tick(double(numTris + cluster.numCells + k) / total);
    }
  }
  flush();
  if (gridOrder)
  {
    byKey.Close();
    // The triangles in the new numbers, each from its lowest vertex (orientation kept), sorted.
    // (outTris = numTris elements: every triangle is written without `dist`)
    Array<TriSlot> sorted(cluster.dml, std::max<std::uint64_t>(outTris, 1));
    std::uint64_t m = 0;
    order.ForEachChunk(0, numTris, storage::Access::Read,
      [&](TriSlot* d, std::uint64_t, std::uint64_t n) {
        for (std::uint64_t j = 0; j < n; ++j)
        {
          TriSlot t{ { 0, 0, 0 }, 1 };
          for (int k = 0; k < 3; ++k)
          {
            t.v[k] = outIndex.Get(d[j].v[k]);
          }
          detail::LowestFirst(t);
          sorted.Set(m++, t);
        }
      });
    storage::SortByKey(
      cluster.dml, sorted,
      [](const TriSlot& a, const TriSlot& b) {
        return a.v[0] != b.v[0] ? a.v[0] < b.v[0]
                                : (a.v[1] != b.v[1] ? a.v[1] < b.v[1] : a.v[2] < b.v[2]);
      },
      [](const TriSlot& a) { return std::uint64_t(a.v[0]); }, detail::BitsFor(numOut), {}, 1);
    std::swap(cluster.triangles.Order(), sorted);
  }

  std::vector<std::uint32_t> tri;
  tri.reserve(3 * chunk);
  order.ForEachChunk(0, numTris, storage::Access::Read,
    [&](TriSlot* d, std::uint64_t f, std::uint64_t n) {
      for (std::uint64_t j = 0; j < n; ++j)
      {
        if (((f + j) & 4095) == 0)
        {
          cluster.progress.Tick(
            double(numTris + 2 * std::uint64_t(cluster.numCells) + f + j) / total);
        }
        if (!kept(f + j))
        {
          continue;
        }
        for (int k = 0; k < 3; ++k)
        {
          tri.push_back(gridOrder ? d[j].v[k] : outIndex.Get(d[j].v[k])); // (sorted: numbered)
        }
        if (tri.size() == 3 * chunk)
        {
          out.Triangles(tri.data(), chunk);
          tri.clear();
        }
      }
    });
  if (!tri.empty())
  {
    out.Triangles(tri.data(), tri.size() / 3);
  }
  io::ReadStats os;
  os.vertices = numOut;
  os.triangles = outTris;
  os.polygons = outTris;
  out.End(os);
  stats.outputVertices = numOut;
  stats.outputTriangles = outTris;
}

void Tick(ClusterState& cluster, std::uint64_t more)
{
  const double done = double(cluster.done + more);
  cluster.progress.Tick(cluster.expected ? done / double(cluster.expected) : 0.0);
}

void AddCell(ClusterState& cluster)
{
  if (cluster.numCells == kNoCell - 1)
  {
    throw std::runtime_error("more than 4 billion grid cells are occupied");
  }
  if (cluster.numCells == cluster.cells.Size())
  {
    cluster.cellWindow.Release();
    cluster.cells.Resize(cluster.cells.Size() * 2);
    if (cluster.attrStride)
    {
      cluster.dml.Resize(cluster.attrBlock, cluster.cells.Size());
    }
  }
  if (cluster.xSize && cluster.numCells >= cluster.dml.Count(cluster.extBlock))
  {
    cluster.dml.Resize(cluster.extBlock, cluster.cells.Size());
  }
  CellRec rec{};
  std::fill_n(rec.first, 3, std::numeric_limits<float>::infinity());
  cluster.cells.Set(cluster.numCells, rec);
  ++cluster.numCells;
}

void AccumulateAttributes(
  ClusterState& cluster, const io::VertexChunk& c, std::size_t i, std::uint32_t cell)
{
  const std::size_t es = cluster.attrStride * sizeof(float);
  cluster.dml.Read(cluster.attrBlock, es, cell, cluster.attrBuf.data());
  std::size_t k = 0;
  if (c.normals)
  {
    for (int j = 0; j < 3; ++j)
    {
      cluster.attrBuf[k + j] += c.normals[3 * i + j];
    }
    k += 3;
  }
  if (c.rgba)
  {
    for (int j = 0; j < 4; ++j)
    {
      cluster.attrBuf[k + j] += c.rgba[4 * i + j];
    }
    k += 4;
  }
  if (c.texcoords)
  {
    cluster.attrBuf[k] += c.texcoords[2 * i];
    cluster.attrBuf[k + 1] += c.texcoords[2 * i + 1];
    k += 2;
  }
  const std::size_t ns = cluster.layout.scalars.size();
  if (c.scalars)
  {
    for (std::size_t j = 0; j < ns; ++j)
    {
      cluster.attrBuf[k + j] += c.scalars[ns * i + j];
    }
  }
  cluster.dml.Write(cluster.attrBlock, es, cell, cluster.attrBuf.data());
}

void Defer(ClusterState& cluster, const std::uint32_t* f)
{
  if (!cluster.deferred.IsOpen())
  {
    cluster.deferred = Array<TriSlot>(cluster.dml, 1024);
  }
  if (cluster.deferredCount == cluster.deferred.Size())
  {
    cluster.deferred.Resize(cluster.deferred.Size() * 2);
  }
  cluster.deferred.Set(cluster.deferredCount++, TriSlot{ { f[0], f[1], f[2] }, 1 });
}

// Boundary quadrics (optional): every face's three undirected edges are kept in a DML block and
// counted per smaller vertex; after the read they are bucketed by that vertex (the same
// counting sort as the output triangles), and an edge met exactly once is a boundary edge of
// the input: a plane through it, perpendicular to its face, weighted by boundaryWeight times
// its squared length, goes into the quadrics of both endpoints' cells.
void AppendEdges(ClusterState& cluster, const std::uint32_t* f)
{
  if (!cluster.edges.IsOpen())
  {
    // Three edges per face: sized from the header when it announces the faces (as the
    // vertices are), so that no doubling copies the whole block at once (a gap in the polls
    // that grows with the input).
    cluster.edges = Array<EdgeRec>(
      cluster.dml, std::max<std::uint64_t>(1024, 3 * cluster.header.faceCount));
    cluster.edgeCount =
      Array<std::uint32_t>(cluster.dml, std::max<std::uint64_t>(cluster.vertices.Size(), 1));
  }
  for (int k = 0; k < 3; ++k)
  {
    const std::uint32_t u = f[k], v = f[(k + 1) % 3], w = f[(k + 2) % 3];
    const EdgeRec e{ std::min(u, v), std::max(u, v), w, u > v ? 1u : 0u };
    if (cluster.numEdges == cluster.edges.Size())
    {
      cluster.edges.Resize(cluster.edges.Size() * 2);
    }
    cluster.edges.Set(cluster.numEdges++, e);
    if (e.a >= cluster.edgeCount.Size())
    {
      cluster.edgeCount.Resize(std::max<std::uint64_t>(e.a + 1, 2 * cluster.edgeCount.Size()));
    }
    cluster.edgeCount.Set(e.a, cluster.edgeCount.Get(e.a) + 1);
  }
}

void AddBoundaryQuadrics(ClusterState& cluster)
{
  if (!cluster.edges.IsOpen())
  {
    return;
  }
  cluster.vertexWindow.Release();
  cluster.cellWindow.Release();
  const std::uint64_t nv = cluster.edgeCount.Size();
  std::uint64_t total = 0;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    total += cluster.edgeCount.Get(v);
    cluster.edgeCount.Set(v, static_cast<std::uint32_t>(total)); // bucket end
  }
  Array<EdgeRec> buckets(cluster.dml, std::max<std::uint64_t>(total, 1));
  for (std::uint64_t i = 0; i < cluster.numEdges; ++i)
  {
    const EdgeRec e = cluster.edges.Get(i);
    const std::uint32_t end = cluster.edgeCount.Get(e.a) - 1;
    cluster.edgeCount.Set(e.a, end);
    buckets.Set(end, e);
    if ((i & 1023) == 0)
    {
      cluster.progress.Tick(0.5 * double(i) / double(cluster.numEdges));
    }
  }
  cluster.edges.Close();
  std::vector<EdgeRec> bucket;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    const std::uint64_t begin = cluster.edgeCount.Get(v);
    const std::uint64_t end = v + 1 < nv ? cluster.edgeCount.Get(v + 1) : total;
    if (begin == end)
    {
      continue;
    }
    bucket.resize(end - begin);
    buckets.Read(begin, end - begin, bucket.data());
    std::sort(bucket.begin(), bucket.end(),
      [](const EdgeRec& x, const EdgeRec& y) { return x.b < y.b; });
    for (std::size_t k = 0; k < bucket.size(); ++k)
    {
      const bool single = (k == 0 || bucket[k - 1].b != bucket[k].b) &&
        (k + 1 == bucket.size() || bucket[k + 1].b != bucket[k].b);
      if (single)
      {
        AddBoundaryPlane(cluster, bucket[k]);
      }
    }
    if ((v & 1023) == 0)
    {
      cluster.progress.Tick(0.5 + 0.5 * double(v) / double(nv));
    }
  }
  cluster.edgeCount.Close();
}

void AddBoundaryPlane(ClusterState& cluster, const EdgeRec& e)
{
  VertexRec a = cluster.vertices.Get(e.a);
  VertexRec b = cluster.vertices.Get(e.b);
  const VertexRec c = cluster.vertices.Get(e.third);
  if (std::tie(b.x, b.y, b.z) < std::tie(a.x, a.y, a.z))
  {
    std::swap(a, b); // (the plane from the same corners in any numbering: exact sums)
  }
  const Vec3 pa = Position(a);
  const Vec3 ed = Position(b) - pa;
  const Vec3 fn = Cross(ed, Position(c) - pa);
  // normal of the constraint plane: perpendicular to the edge, in the face's plane
  const Vec3 n = Cross(ed, fn);
  const double len = std::sqrt(Dot(n, n));
  const double el2 = Dot(ed, ed);
  if (!(len > 0) || !(el2 > 0))
  {
    return;
  }
  const Vec3 u = Unit(n, len);
  const double* centre = cluster.units.centre.data();
  const double d = -Dot(u, Vec3{ pa.x - centre[0], pa.y - centre[1], pa.z - centre[2] });
  const double w = cluster.options.boundaryWeight * el2;
  const double un[3] = { u.x, u.y, u.z };
  const bool exact = cluster.options.exactSums;
  const FixedQuadric q = exact ? cluster.units.Plane(un, d, w) : FixedQuadric{};
  const Quadric plain = exact ? Quadric{} : PlaneQuadric(u.x, u.y, u.z, d, w);
  for (std::uint32_t cell : { a.cell, b.cell })
  {
    UpdateCell(cluster, cell, [&](CellRec& rec) {
      if (exact)
      {
        AddTo(rec.q, q);
      }
      else
      {
        AddTo(rec.plain.q, plain);
      }
    });
  }
}

// Applies f to cell record `cell` in place: the block's memory in core, a pinned page out of
// core (no read and write of the whole record).
template <class F>
void UpdateCell(ClusterState& cluster, std::uint32_t cell, F&& f)
{
  f(cluster.cellWindow.At(cluster.cells.Id(), cell));
}

// A face over three distinct cells is a candidate output triangle.
void AddCandidate(ClusterState& cluster, const VertexRec& a, const VertexRec& b, const VertexRec& c)
{
  if (a.cell != b.cell && b.cell != c.cell && a.cell != c.cell)
  {
    // rotate the smallest cell first (orientation kept) and count it in that cell's bucket
    std::uint32_t t[3] = { a.cell, b.cell, c.cell };
    const int m = t[0] < t[1] ? (t[0] < t[2] ? 0 : 2) : (t[1] < t[2] ? 1 : 2);
    const std::uint32_t r0 = t[m], r1 = t[(m + 1) % 3], r2 = t[(m + 2) % 3];
    UpdateCell(cluster, r0, [](CellRec& rec) { ++rec.triangles; });
    cluster.triangles.Append(r0, r1, r2);
  }
}

// AddTriangle with ClusterOptions::exactSums off: doubles, in the input's order.
void AddTrianglePlain(ClusterState& cluster, const std::uint32_t* f, const VertexRec& a,
  const VertexRec& b, const VertexRec& c)
{
  const double* centre = cluster.units.centre.data();
  const Vec3 pa = Position(a);
  const Vec3 n = Cross(Position(b) - pa, Position(c) - pa);
  const double len = std::sqrt(Dot(n, n));
  Quadric q{};
  if (len > 0)
  {
    const Vec3 u = Unit(n, len);
    const double d = -Dot(u, Vec3{ pa.x - centre[0], pa.y - centre[1], pa.z - centre[2] });
    const double w = 0.5 * len; // area
    q = PlaneQuadric(u.x, u.y, u.z, d, w);
    if (cluster.xSize)
    {
      AddFaceAttributeTerms(cluster, f, a, b, c, w);
    }
  }
  const bool sampled = cluster.options.fallback == ClusterFallback::SampledVertex;
  for (const VertexRec* v : { &a, &b, &c })
  {
    UpdateCell(cluster, v->cell, [&](CellRec& rec) {
      AddTo(rec.plain.q, q);
      rec.plain.sum[0] += double(v->x) - centre[0];
      rec.plain.sum[1] += double(v->y) - centre[1];
      rec.plain.sum[2] += double(v->z) - centre[2];
      ++rec.corners;
      if (sampled &&
        std::tie(v->x, v->y, v->z) < std::tie(rec.first[0], rec.first[1], rec.first[2]))
      {
        rec.first[0] = v->x;
        rec.first[1] = v->y;
        rec.first[2] = v->z;
      }
    });
  }
  AddCandidate(cluster, a, b, c);
}

void AddTriangle(ClusterState& cluster, const std::uint32_t* f)
{
  if (cluster.options.boundaryQuadrics)
  {
    AppendEdges(cluster, f);
  }
  const storage::BlockId vid = cluster.vertices.Id();
  const VertexRec a = cluster.vertexWindow.At(vid, f[0]);
  const VertexRec b = cluster.vertexWindow.At(vid, f[1]);
  const VertexRec c = cluster.vertexWindow.At(vid, f[2]);
  AddTriangleRecords(cluster, f, a, b, c);
}

// A face from its vertex records (the boundary edges appended by the caller).
void AddTriangleRecords(ClusterState& cluster, const std::uint32_t* f, const VertexRec& a,
  const VertexRec& b, const VertexRec& c)
{
  if (!cluster.options.exactSums)
  {
    AddTrianglePlain(cluster, f, a, b, c);
    return;
  }
  // Area-weighted plane quadric of the face (Garland-Heckbert) and the corner, added to each
  // corner's cell, exactly (FixedUnits). The plane is computed from the lexicographically
  // smallest corner on (orientation kept), so a face gives the same bits in any numbering.
  const VertexRec* r[3] = { &a, &b, &c };
  {
    auto less = [](const VertexRec* x, const VertexRec* y) {
      return std::tie(x->x, x->y, x->z) < std::tie(y->x, y->y, y->z);
    };
    const int m = less(r[1], r[0]) ? (less(r[2], r[1]) ? 2 : 1) : (less(r[2], r[0]) ? 2 : 0);
    std::rotate(r, r + m, r + 3);
  }
  const Vec3 pa = Position(*r[0]);
  const Vec3 n = Cross(Position(*r[1]) - pa, Position(*r[2]) - pa);
  const double len = std::sqrt(Dot(n, n));
  FixedQuadric q{};
  if (len > 0)
  {
    const Vec3 u = Unit(n, len);
    const double* centre = cluster.units.centre.data();
    const double d = -Dot(u, Vec3{ pa.x - centre[0], pa.y - centre[1], pa.z - centre[2] });
    const double w = 0.5 * len; // area
    const double un[3] = { u.x, u.y, u.z };
    q = cluster.units.Plane(un, d, w);
    if (cluster.xSize)
    {
      AddFaceAttributeTerms(cluster, f, a, b, c, w);
    }
  }
  const bool sampled = cluster.options.fallback == ClusterFallback::SampledVertex;
  FixedSum pos[3][3];
  for (int i = 0; i < 3; ++i)
  {
    const VertexRec& v = i == 0 ? a : (i == 1 ? b : c);
    std::int32_t corner[4];
    cluster.units.Corner(&v.x, corner);
    for (int k = 0; k < 3; ++k)
    {
      pos[i][k] = FixedSum(Fixed(corner[k]));
    }
  }
  auto add = [&](std::uint32_t cell, const FixedQuadric& fq, const FixedSum* p, int corners,
               const VertexRec* smallest) {
    UpdateCell(cluster, cell, [&](CellRec& rec) {
      AddTo(rec.q, fq);
      rec.sum[0] += p[0];
      rec.sum[1] += p[1];
      rec.sum[2] += p[2];
      rec.corners += corners;
      if (sampled &&
        std::tie(smallest->x, smallest->y, smallest->z) <
          std::tie(rec.first[0], rec.first[1], rec.first[2]))
      {
        rec.first[0] = smallest->x;
        rec.first[1] = smallest->y;
        rec.first[2] = smallest->z;
      }
    });
  };
  if (a.cell == b.cell && b.cell == c.cell)
  {
    // (most faces at fine grids: one update with the sums of the three corners; integer sums,
    // so q + q + q is the same as three updates)
    FixedQuadric q3 = q;
    AddTo(q3, q);
    AddTo(q3, q);
    const FixedSum p3[3] = { pos[0][0] + pos[1][0] + pos[2][0], pos[0][1] + pos[1][1] + pos[2][1],
      pos[0][2] + pos[1][2] + pos[2][2] };
    const VertexRec* smallest = &a;
    for (const VertexRec* v : { &b, &c })
    {
      if (std::tie(v->x, v->y, v->z) < std::tie(smallest->x, smallest->y, smallest->z))
      {
        smallest = v;
      }
    }
    add(a.cell, q3, p3, 3, smallest);
  }
  else
  {
    add(a.cell, q, pos[0], 1, &a);
    add(b.cell, q, pos[1], 1, &b);
    add(c.cell, q, pos[2], 1, &c);
  }
  AddCandidate(cluster, a, b, c);
}

// The face's attribute terms (Attributes.h), added to each corner's cell extension (in the
// clustering's coordinates: the cells' quadrics are absolute).
void AddFaceAttributeTerms(ClusterState& cluster, const std::uint32_t* f, const VertexRec& a,
  const VertexRec& b, const VertexRec& c, double area)
{
  const std::size_t k = cluster.channels.size();
  // (in core the blocks' memory directly: BasePointer is null out of core)
  const float* chans = static_cast<const float*>(cluster.dml.BasePointer(cluster.chanBlock));
  std::vector<double>& s = cluster.cornerValues;
  s.resize(3 * k);
  for (int i = 0; i < 3; ++i)
  {
    const float* v = chans ? chans + std::size_t(f[i]) * k : cluster.chanBuf.data() + k * i;
    if (!chans)
    {
      cluster.dml.Read(cluster.chanBlock, k * sizeof(float), f[i], cluster.chanBuf.data() + k * i);
    }
    for (std::size_t j = 0; j < k; ++j)
    {
      s[k * i + j] = v[j];
    }
  }
  // (about the centre, as the cells' quadrics)
  const double* o = cluster.units.centre.data();
  const double p0[3] = { a.x - o[0], a.y - o[1], a.z - o[2] },
               p1[3] = { b.x - o[0], b.y - o[1], b.z - o[2] },
               p2[3] = { c.x - o[0], c.y - o[1], c.z - o[2] };
  std::fill(cluster.faceExt.begin(), cluster.faceExt.end(), 0.0);
  AddFaceAttributes(p0, p1, p2, s.data(), s.data() + k, s.data() + 2 * k, k, area,
    cluster.faceExt.data());
  const std::size_t es = cluster.xSize * sizeof(double);
  double* exts = static_cast<double*>(cluster.dml.BasePointer(cluster.extBlock));
  for (const std::uint32_t cell : { a.cell, b.cell, c.cell })
  {
    double* e = exts ? exts + std::size_t(cell) * cluster.xSize : cluster.extBuf.data();
    if (!exts)
    {
      cluster.dml.Read(cluster.extBlock, es, cell, e);
    }
    for (std::size_t i = 0; i < cluster.xSize; ++i)
    {
      e[i] += cluster.faceExt[i];
    }
    if (!exts)
    {
      cluster.dml.Write(cluster.extBlock, es, cell, e);
    }
  }
}

// The last output vertex's weighted channels (the tails of the output arrays) take their optimal
// values at the representative p from the cell's extension in cluster.extBuf; normals are
// renormalized.
void OptimalCellAttributes(ClusterState& cluster, const double p[3], std::vector<float>& normals,
  std::vector<std::uint8_t>& rgba, std::vector<float>& texcoords, std::vector<float>& scalars)
{
  const io::VertexLayout& l = cluster.layout;
  std::vector<std::uint8_t>& rec = cluster.recBuf;
  const std::size_t ns = l.scalars.size();
  // Pack the vertex's record from the tails (the layout of PackRecord), set, unpack.
  io::VertexChunk one;
  one.count = 1;
  one.normals = l.normals ? normals.data() + normals.size() - 3 : nullptr;
  one.rgba = l.colors ? rgba.data() + rgba.size() - 4 : nullptr;
  one.texcoords = l.texcoords ? texcoords.data() + texcoords.size() - 2 : nullptr;
  one.scalars = ns ? scalars.data() + scalars.size() - ns : nullptr;
  PackRecord(l, one, 0, rec.data());
  bool normal = false;
  for (std::size_t j = 0; j < cluster.channels.size(); ++j)
  {
    SetChannelValue(
      cluster.channels[j], OptimalAttribute(cluster.extBuf.data(), j, p[0], p[1], p[2]), rec.data());
    normal |= cluster.channels[j].normal;
  }
  std::size_t at = 0;
  auto get = [&]() {
    float f;
    std::memcpy(&f, rec.data() + at, sizeof(float));
    at += sizeof(float);
    return f;
  };
  if (l.normals)
  {
    float* n = normals.data() + normals.size() - 3;
    for (int d = 0; d < 3; ++d)
    {
      n[d] = get();
    }
    const float len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    for (int d = 0; d < 3 && normal && len > 0; ++d)
    {
      n[d] /= len;
    }
  }
  if (l.texcoords)
  {
    texcoords[texcoords.size() - 2] = get();
    texcoords[texcoords.size() - 1] = get();
  }
  for (std::size_t d = 0; d < ns; ++d)
  {
    scalars[scalars.size() - ns + d] = get();
  }
  if (l.colors)
  {
    std::copy_n(rec.data() + at, 4, rgba.data() + rgba.size() - 4);
  }
}

// Minimizes the cell quadric with a pseudo-inverse about the cell's mean (Lindstrom); when the
// minimizer leaves the cell (by more than placementSlack), the fallback is used. The eigen-
// decomposition is Eigen's closed form for 3x3 matrices (computeDirect): the iterative one took
// a tenth of a one-thread two-stage run on Dragon-size, and the written points were the same
// floats but one coordinate of Dragon-size's clustering (docs/benchmarks.md).
void Representative(ClusterState& cluster, const CellRec& rec, const Quadric& Q, double p[3])
{
  // The mean of the corners (exact sums, one rounding), about the centre as the quadric is.
  const double* centre = cluster.units.centre.data();
  const float* o = cluster.units.origin;
  const double inv = cluster.units.positionBack / double(std::max<std::uint64_t>(rec.corners, 1));
  const double plainInv = 1.0 / double(std::max<std::uint64_t>(rec.corners, 1));
  const Eigen::Vector3d mean = cluster.options.exactSums
    ? Eigen::Vector3d(double(Fixed(rec.sum[0])) * inv + (double(o[0]) - centre[0]),
        double(Fixed(rec.sum[1])) * inv + (double(o[1]) - centre[1]),
        double(Fixed(rec.sum[2])) * inv + (double(o[2]) - centre[2]))
    : Eigen::Vector3d(
        rec.plain.sum[0] * plainInv, rec.plain.sum[1] * plainInv, rec.plain.sum[2] * plainInv);
  Eigen::Matrix3d A;
  const double* q = Q.q;
  A << q[0], q[1], q[2], q[1], q[4], q[5], q[2], q[5], q[7];
  const Eigen::Vector3d b(q[3], q[6], q[8]);
  Eigen::Vector3d x = mean;
  Eigen::SelfAdjointEigenSolver<Eigen::Matrix3d> es;
  es.computeDirect(A);
  const Eigen::Vector3d ev = es.eigenvalues();
  const double maxEv = ev.cwiseAbs().maxCoeff();
  if (maxEv > 0)
  {
    Eigen::Vector3d inverse = Eigen::Vector3d::Zero();
    for (int k = 0; k < 3; ++k)
    {
      if (std::abs(ev[k]) > cluster.options.singularThreshold * maxEv)
      {
        inverse[k] = 1.0 / ev[k];
      }
    }
    const Eigen::Matrix3d& V = es.eigenvectors();
    x = mean + V * inverse.asDiagonal() * V.transpose() * (-b - A * mean);
  }
  for (int d = 0; d < 3; ++d)
  {
    x[d] += centre[d];
  }
  const Eigen::Vector3d meanAbsolute(mean[0] + centre[0], mean[1] + centre[1], mean[2] + centre[2]);
  // inside the cell (with a tolerance for points on its faces)?
  const std::uint64_t key = cluster.grid.Key(meanAbsolute[0], meanAbsolute[1], meanAbsolute[2]);
  const double eps = std::max(cluster.options.placementSlack, 1e-6) * cluster.grid.cellSize;
  bool inside = true;
  {
    std::uint64_t k = key;
    const std::uint32_t iz = k % cluster.grid.dims[2];
    k /= cluster.grid.dims[2];
    const std::uint32_t iy = k % cluster.grid.dims[1];
    const std::uint32_t ix = static_cast<std::uint32_t>(k / cluster.grid.dims[1]);
    const std::uint32_t idx[3] = { ix, iy, iz };
    for (int d = 0; d < 3; ++d)
    {
      const double lo = cluster.grid.origin[d] + idx[d] * cluster.grid.cellSize;
      const double hi = lo + cluster.grid.cellSize;
      if (x[d] < lo - eps || x[d] > hi + eps)
      {
        inside = false;
      }
    }
  }
  if (!std::isfinite(x[0]) || !std::isfinite(x[1]) || !std::isfinite(x[2]))
  {
    inside = false;
  }
  if (inside)
  {
    p[0] = x[0];
    p[1] = x[1];
    p[2] = x[2];
    return;
  }
  if (cluster.options.fallback == ClusterFallback::SampledVertex)
  {
    p[0] = rec.first[0];
    p[1] = rec.first[1];
    p[2] = rec.first[2];
  }
  else
  {
    p[0] = meanAbsolute[0];
    p[1] = meanAbsolute[1];
    p[2] = meanAbsolute[2];
  }
}

// The reader's sink: the clustering pass reads as it comes.
class ClusterSink final : public io::MeshSink
{
public:
  explicit ClusterSink(ClusterState& cluster)
    : cluster_(cluster)
  {
  }
  void Begin(const io::MeshHeader& h) override { BeginInput(this->cluster_, h); }
  void Vertices(const io::VertexChunk& c) override { AddVertices(this->cluster_, c); }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    AddTriangles(this->cluster_, idx, count);
  }
  void End(const io::ReadStats& stats) override { EndInput(this->cluster_, stats); }
  bool AbortRequested() override { return this->cluster_.progress.Aborted(); }

private:
  ClusterState& cluster_;
};


} // namespace
} // namespace sipmss::algorithms

// The run across ranks (one translation unit with this file).
#include "cluster/Distributed.inl"

namespace sipmss::algorithms
{

double EstimateClusterWork(std::uint64_t V, std::uint64_t F, const ClusterOptions& options)
{
  return (options.useBounds ? 0.0 : kWork::kBounds * double(V)) + kWork::kCluster * double(V + F) +
    ClusterWorkAfterRead(V, F, options.maximumGridDimension, options);
}

double EstimateClusterFaces(std::uint64_t V, std::uint64_t F, const ClusterOptions& options)
{
  return std::min(
    double(F), kWork::kCandidatesPerCell * EstimatedCells(V, options.maximumGridDimension));
}

ClusterGrid ClusterGrid::Make(const std::array<double, 6>& b, int maximumGridDimension)
{
  if (maximumGridDimension < 1)
  {
    throw std::invalid_argument("the maximum grid dimension must be at least 1");
  }
  ClusterGrid g;
  double longest = 0;
  for (int d = 0; d < 3; ++d)
  {
    if (!(b[2 * d] <= b[2 * d + 1]) || !std::isfinite(b[2 * d]) || !std::isfinite(b[2 * d + 1]))
    {
      throw std::invalid_argument("invalid bounds (empty mesh or non-finite coordinates)");
    }
    longest = std::max(longest, b[2 * d + 1] - b[2 * d]);
  }
  g.cellSize = longest > 0 ? longest / maximumGridDimension : 1.0;
  for (int d = 0; d < 3; ++d)
  {
    g.origin[d] = b[2 * d];
    const double extent = b[2 * d + 1] - b[2 * d];
    g.dims[d] = std::max<std::uint32_t>(1,
      static_cast<std::uint32_t>(
        std::min<double>(maximumGridDimension, std::ceil(extent / g.cellSize))));
  }
  return g;
}

std::uint64_t ClusterGrid::Key(double x, double y, double z) const
{
  const double p[3] = { x, y, z };
  std::uint64_t idx[3];
  for (int d = 0; d < 3; ++d)
  {
    // (compared before the conversion: a cell size that underflows makes f infinite)
    const double f = (p[d] - this->origin[d]) / this->cellSize;
    const std::uint32_t last = this->dims[d] - 1;
    idx[d] = f > 0 ? (f < double(last) ? static_cast<std::uint64_t>(f) : last) : 0;
  }
  return (idx[0] * this->dims[1] + idx[1]) * this->dims[2] + idx[2];
}

namespace
{
RunStats ClusterRun(const MeshSource& source, io::MeshSink& output, const ClusterOptions& options,
  Progress& progress)
{
  const int threads = storage::ResolveThreads(options.threads);
  const MeshSource input =
    threads > 1 ? Prefetched(source, PrefetchDepth(options.storage.memoryBudget)) : source;
  RunStats stats;
  std::optional<DML> own;
  DML& dml = options.dml ? *options.dml : own.emplace();
  if (own)
  {
    // Before the read the sizes are unknown; ClusterSink::Begin configures again with the table
    // of structures once the header announces the counts.
    dml.Config(options.storage);
  }

  // Progress: each phase's work (kWork) against the rest's, re-planned as the sizes become known
  // (the header, then the occupied cells and candidates).
  std::array<double, 6> bounds = options.bounds;
  std::uint64_t V = 0, F = 0; // from the bounds pass's header, if any
  if (!options.useBounds)
  {
    progress.BeginPhase("bounds", 0.0, 1.0); // (its share once the header gives the sizes)
    PhaseTimer timer(stats, dml, "bounds");
    BoundsSink bs(progress, [&options](std::uint64_t v, std::uint64_t f) {
      return kWork::kCluster * double(v + f) +
        ClusterWorkAfterRead(v, f, options.maximumGridDimension, options);
    });
    io::ReadOptions ro;
    // A run on a DML of its own also measures the layout of the first faces here.
    const bool measure = own && options.layout == LayoutPolicy::Automatic;
    ro.verticesOnly = !measure;
    if (measure)
    {
      bs.MeasureLayout();
    }
    bool stoppedEarly = false;
    try
    {
      // (measuring, the read stops early: on this thread, where the stop reaches the reader)
      (measure ? source : input)(bs, ro);
    }
    catch (const detail::ProbeDone&)
    {
      stoppedEarly = true;
    }
    bounds = bs.b;
    V = bs.VerticesSeen();
    F = bs.Faces();
    if (F == 0)
    {
      F = 2 * V; // (no sizes in the header: a closed surface has about two faces per vertex)
    }
    if (measure && bs.Layout().Faces() > 0)
    {
      stats.layoutFarFraction = bs.Layout().FarFraction();
      if (stats.layoutFarFraction > detail::kIncoherentFarFraction &&
        ClusterGoesOutOfCore(options, stoppedEarly && !bs.Announced() ? 0 : V, F, bounds))
      {
        throw detail::ReorderNeeded{};
      }
    }
  }
  const ClusterGrid grid = ClusterGrid::Make(bounds, options.maximumGridDimension);

  ClusterState cluster(dml, grid, options, own.has_value(), progress);
  ExpectSizes(cluster, V + F);
  ClusterSink sink(cluster);
  {
    // (re-planned by the sink when the header announces the sizes)
    progress.BeginPhase("cluster", kWork::kCluster * double(V + F),
      V + F ? ClusterWorkAfterRead(V, F, options.maximumGridDimension, options) : 1.0);
    PhaseTimer timer(stats, dml, "cluster");
    const io::ReadStats read = input(sink, io::ReadOptions{});
    stats.inputVertices = read.vertices;
    stats.inputTriangles = read.triangles;
    stats.droppedInputFaces = read.droppedFaces;
  }
  if (options.sourceConsumed)
  {
    options.sourceConsumed();
  }
  const double cells = double(Cells(cluster)), candidates = double(Candidates(cluster));
  ClusterOptions noBoundaries = options;
  noBoundaries.boundaryQuadrics = false;
  if (options.boundaryQuadrics)
  {
    progress.BeginPhase("boundaries", kWork::kBoundaries * double(stats.inputTriangles),
      ClusterWorkAfter(cells, candidates, 0, noBoundaries));
    PhaseTimer timer(stats, dml, "boundaries");
    FinishBoundaries(cluster);
  }
  if (options.gridOrder && dml.BasePointer(cluster.cells.Id()))
  {
    KeepCellKeys(cluster); // (out of core Emit keeps the first-seen order)
  }
  ReleaseInputBlocks(cluster);
  {
    progress.BeginPhase("triangles", kWork::kTriangles * (candidates + cells),
      kWork::kOutput * (cells + candidates));
    PhaseTimer timer(stats, dml, "triangles");
    FinishTriangles(cluster);
  }
  {
    progress.BeginPhase("output", kWork::kOutput * (cells + double(OutputTriangles(cluster))), 0.0);
    PhaseTimer timer(stats, dml, "output");
    Emit(cluster, output, stats, nullptr);
  }
  stats.errorDiagonal = std::sqrt((bounds[1] - bounds[0]) * (bounds[1] - bounds[0]) +
    (bounds[3] - bounds[2]) * (bounds[3] - bounds[2]) +
    (bounds[5] - bounds[4]) * (bounds[5] - bounds[4]));
  stats.achievedError = RelativeError(cluster.achievedErr2, stats.errorDiagonal);
  progress.Finish();
  stats.storage = dml.GetStats();
  return stats;
}

// The structures of a clustering run on V vertices and F faces (the Config of ClusterSink).
// Before the bounds the grid has at most m^3 cells.
std::uint64_t MaxGridCells(const ClusterOptions& options)
{
  const std::uint64_t m = std::uint64_t(std::max(options.maximumGridDimension, 1));
  return m * m * m;
}

} // namespace

bool ClusterGoesOutOfCore(const ClusterOptions& options, std::uint64_t V, std::uint64_t F,
  const std::array<double, 6>& bounds)
{
  // (in core the clustering's lookups are fetched ahead, AddVertices and AddTriangles, and cost
  // less than the layout step)
  const ClusterGrid grid = ClusterGrid::Make(bounds, options.maximumGridDimension);
  storage::Profile profile = options.storage;
  profile.structures.clear();
  if (V == 0)
  {
    profile.structures.push_back({ "input of unknown size", 1, std::uint64_t(1) << 60, 0.0 });
  }
  else
  {
    AddClusterStructures(profile, V, F,
      std::uint64_t(grid.dims[0]) * grid.dims[1] * grid.dims[2], 4 * options.attributes.size());
  }
  return storage::PlannedMode(profile) == storage::Mode::OutOfCore;
}

double EstimateClusterBytes(std::uint64_t V, std::uint64_t F, const ClusterOptions& options)
{
  storage::Profile p;
  AddClusterStructures(p, V, F, MaxGridCells(options), 4 * options.attributes.size());
  double bytes = 0;
  for (const auto& s : p.structures)
  {
    bytes += double(s.elementSize) * double(s.maxCount);
  }
  return bytes;
}

namespace
{
// The layout step, then the clustering on the reordered copy (in the same DML, freed once read).
RunStats ClusterReordered(const MeshSource& source, io::MeshSink& output,
  const ClusterOptions& options, Progress& progress)
{
  DML dml;
  dml.Config(options.storage);
  RunStats before;
  detail::StoredMesh mesh(dml);
  detail::ReadAndReorder(source, mesh, dml, options.storage,
    [&options](storage::Profile& p, std::uint64_t v, std::uint64_t f) {
      AddClusterStructures(p, v, f, MaxGridCells(options), 4 * options.attributes.size());
    },
    [&options](std::uint64_t v, std::uint64_t f) {
      return kWork::kCluster * double(v + f) +
        ClusterWorkAfterRead(v, f, options.maximumGridDimension, options);
    },
    progress, before, options.threads);
  ClusterOptions o = options;
  o.dml = &dml;
  o.useBounds = true;
  o.bounds = mesh.Bounds();
  o.layout = LayoutPolicy::Keep;
  o.threads = 1; // (no reader thread: the copy is read from this DML, which is single-threaded)
  o.sourceConsumed = [&mesh, &options] {
    mesh.Release();
    if (options.sourceConsumed)
    {
      options.sourceConsumed();
    }
  };
  RunStats stats = ClusterRun(
    [&mesh](io::MeshSink& sink, const io::ReadOptions& ro) { return mesh.Replay(sink, ro); },
    output, o, progress);
  stats.phases.insert(stats.phases.begin(), before.phases.begin(), before.phases.end());
  stats.layoutSteps = before.layoutSteps;
  stats.reordered = true;
  stats.layoutFarFraction = mesh.Layout().FarFraction();
  return stats;
}
} // namespace

RunStats Cluster(const MeshSource& source, io::MeshSink& output, const ClusterOptions& options,
  Progress& progress)
{
  RunStats stats = TranslateOutOfMemory(progress, options.storage, [&] {
    if (options.communicator)
    {
      if (options.exportQuadric || !options.exactSums)
      {
        throw std::invalid_argument("the distributed clustering runs with exact sums and "
                                    "exports no quadrics");
      }
      return ClusterDistributed(source, output, options, progress);
    }
    if (!options.dml && options.layout == LayoutPolicy::Reorder)
    {
      return ClusterReordered(source, output, options, progress);
    }
    try
    {
      return ClusterRun(source, output, options, progress);
    }
    catch (const detail::ReorderNeeded&)
    {
      // (the bounds pass found the first faces far apart: the run goes on a reordered copy)
      return ClusterReordered(source, output, options, progress);
    }
  });
  stats.gridDimension = options.maximumGridDimension;
  return stats;
}
} // namespace sipmss::algorithms
