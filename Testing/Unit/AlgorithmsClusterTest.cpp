// Algorithm II (grid clustering) on tiny hand-built meshes: exact results, in core == out of core,
// abort, bad input.
#include "sipmss/algorithms/Cluster.h"

#include "AlgorithmsTestUtil.h"

#include "../../Algorithms/src/Gather.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cmath>
#include <filesystem>
#include <iterator>
#include <map>
#include <random>
#include <set>

using namespace sipmss;
using namespace sipmss::algorithms;
using sipmss::testing::Collect;
using sipmss::testing::MemorySource;
using sipmss::testing::Mesh;

namespace
{
// A cube [0,2]^3 as 12 triangles (outward orientation).
Mesh Cube()
{
  Mesh m;
  for (int i = 0; i < 8; ++i)
  {
    m.p.insert(m.p.end(), { float(2 * (i & 1)), float(2 * ((i >> 1) & 1)), float(2 * ((i >> 2) & 1)) });
  }
  const std::uint32_t q[6][4] = { { 0, 2, 3, 1 }, { 4, 5, 7, 6 }, { 0, 1, 5, 4 }, { 2, 6, 7, 3 },
    { 0, 4, 6, 2 }, { 1, 3, 7, 5 } };
  for (auto& f : q)
  {
    m.t.insert(m.t.end(), { f[0], f[1], f[2], f[0], f[2], f[3] });
  }
  return m;
}

// An n x n grid of the unit square in the plane z = 0 (2 n^2 triangles).
Mesh Plane(int n)
{
  Mesh m;
  for (int j = 0; j <= n; ++j)
    for (int i = 0; i <= n; ++i)
    {
      m.p.insert(m.p.end(), { float(i) / n, float(j) / n, 0.f });
      m.scalar.push_back(float(i) / n);
    }
  sipmss::testing::GridTriangles(n, m.t);
  return m;
}

Collect RunCluster(const Mesh& m, int grid, storage::ModePolicy policy = storage::ModePolicy::Automatic,
  std::uint64_t budget = 0, RunStats* statsOut = nullptr)
{
  ClusterOptions o;
  o.maximumGridDimension = grid;
  o.storage.policy = policy;
  o.storage.memoryBudget = budget;
  Collect out;
  NullProgress progress;
  RunStats s = Cluster(MemorySource(m), out, o, progress);
  if (statsOut)
  {
    *statsOut = s;
  }
  return out;
}
} // namespace

TEST(Cluster, CubeCornersAreExact)
{
  const Mesh cube = Cube();
  Collect out = RunCluster(cube, 2);
  ASSERT_EQ(out.m.t.size() / 3, 12u);
  ASSERT_EQ(out.m.p.size() / 3, 8u);
  std::set<std::array<float, 3>> corners;
  for (std::size_t i = 0; i < 8; ++i)
  {
    for (int k = 0; k < 3; ++k)
    {
      const float c = out.m.p[3 * i + k];
      EXPECT_TRUE(std::abs(c) < 1e-5f || std::abs(c - 2.f) < 1e-5f) << c;
    }
    corners.insert({ std::round(out.m.p[3 * i]), std::round(out.m.p[3 * i + 1]),
      std::round(out.m.p[3 * i + 2]) });
  }
  EXPECT_EQ(corners.size(), 8u);
}

TEST(Cluster, OneCellLeavesNothing)
{
  Collect out = RunCluster(Cube(), 1);
  EXPECT_EQ(out.m.t.size(), 0u);
  EXPECT_EQ(out.m.p.size(), 0u);
}

TEST(Cluster, PlaneStaysInItsPlaneAndKeepsOrientation)
{
  // 16x16 grid into 4 cells per axis: representatives are on z = 0 (the quadric is rank 1, the
  // pseudo-inverse keeps the in-plane mean of the cell's face corners), every triangle faces +z.
  const Mesh plane = Plane(16);
  Collect out = RunCluster(plane, 4);
  ASSERT_GT(out.m.t.size(), 0u);
  for (std::size_t i = 0; i < out.m.p.size(); i += 3)
  {
    EXPECT_NEAR(out.m.p[i + 2], 0.f, 1e-6f);
  }
  for (std::size_t f = 0; f < out.m.t.size(); f += 3)
  {
    const float* a = &out.m.p[3 * out.m.t[f]];
    const float* b = &out.m.p[3 * out.m.t[f + 1]];
    const float* c = &out.m.p[3 * out.m.t[f + 2]];
    const float nz = (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0]);
    EXPECT_GT(nz, 0.f);
  }
  // Per cell: the mean of the face corners in it (each vertex once per face: the position's
  // expansion point) and the mean of its vertices (the scalar s = x is averaged per vertex).
  auto cellOf = [](const float* p) {
    return std::min(3, int(p[0] * 4)) * 4 + std::min(3, int(p[1] * 4));
  };
  double corner[16][3] = {}, vertexX[16] = {};
  int corners[16] = {}, vertices[16] = {};
  for (std::uint32_t v : plane.t)
  {
    const int c = cellOf(&plane.p[3 * v]);
    corner[c][0] += plane.p[3 * v];
    corner[c][1] += plane.p[3 * v + 1];
    ++corners[c];
  }
  for (std::size_t v = 0; v < plane.p.size() / 3; ++v)
  {
    vertexX[cellOf(&plane.p[3 * v])] += plane.scalar[v];
    ++vertices[cellOf(&plane.p[3 * v])];
  }
  ASSERT_EQ(out.m.scalar.size(), out.m.p.size() / 3);
  for (std::size_t i = 0; i < out.m.scalar.size(); ++i)
  {
    const int c = cellOf(&out.m.p[3 * i]);
    ASSERT_GT(corners[c], 0);
    EXPECT_NEAR(out.m.p[3 * i], corner[c][0] / corners[c], 1e-6);
    EXPECT_NEAR(out.m.p[3 * i + 1], corner[c][1] / corners[c], 1e-6);
    EXPECT_NEAR(out.m.scalar[i], vertexX[c] / vertices[c], 1e-6);
  }
}

TEST(Cluster, TwoCellsMakeNoTriangle)
{
  // A single triangle with two corners in one cell: dropped (needs three distinct cells).
  Mesh m;
  m.p = { 0.f, 0.f, 0.f, 0.1f, 0.f, 0.f, 1.f, 1.f, 0.f };
  m.t = { 0, 1, 2 };
  EXPECT_EQ(RunCluster(m, 2).m.t.size(), 0u);
  // three cells: kept, exactly once even if the input repeats it
  m.t = { 0, 1, 2, 0, 1, 2 };
  EXPECT_EQ(RunCluster(m, 20).m.t.size(), 3u);
}

TEST(Cluster, InCoreEqualsOutOfCore)
{
  const Mesh plane = Plane(120);
  RunStats a, b;
  Collect in = RunCluster(plane, 30, storage::ModePolicy::InCore, 0, &a);
  Collect out = RunCluster(plane, 30, storage::ModePolicy::OutOfCore, 64 * 1024, &b);
  EXPECT_EQ(in.m.p, out.m.p);
  EXPECT_EQ(in.m.t, out.m.t);
  EXPECT_EQ(in.m.scalar, out.m.scalar);
  EXPECT_TRUE(b.storage.usedOutOfCore);
  EXPECT_LE(b.storage.peakBytes, 64u * 1024u);
  EXPECT_GT(b.storage.misses, 0u);
  EXPECT_EQ(a.outputTriangles, in.m.t.size() / 3);
}

TEST(Cluster, AbortThrows)
{
  struct AbortAfter final : Progress
  {
    int calls = 0;
    void Report(double, const char*) override {}
    bool Aborted() override { return ++this->calls > 2; }
  } progress;
  progress.SetInterval(0);
  const Mesh plane = Plane(50);
  ClusterOptions o;
  Collect out;
  EXPECT_THROW(Cluster(MemorySource(plane), out, o, progress), AbortedError);
}

TEST(Cluster, BadInput)
{
  Mesh m;
  m.p = { 0.f, 0.f, 0.f, 1.f, 0.f, 0.f, 0.f, 1.f, 0.f };
  m.t = { 0, 1, 7 }; // vertex 7 does not exist
  Collect out;
  ClusterOptions o;
  NullProgress progress;
  EXPECT_THROW(Cluster(MemorySource(m), out, o, progress), io::MeshIOError);
  o.maximumGridDimension = 0;
  EXPECT_THROW(Cluster(MemorySource(m), out, o, progress), std::invalid_argument);
  Collect out2;
  ClusterOptions o2;
  EXPECT_THROW(Cluster(FileSource("/nonexistent/missing.ply"), out2, o2, progress), std::exception);
}

TEST(Cluster, SameOutputForAnyThreadCount)
{
  const Mesh plane = Plane(90);
  Collect outs[2];
  for (int t = 1; t <= 2; ++t)
  {
    ClusterOptions o;
    o.maximumGridDimension = 17;
    o.threads = t;
    NullProgress progress;
    Cluster(MemorySource(plane), outs[t - 1], o, progress);
  }
  EXPECT_EQ(outs[0].m.p, outs[1].m.p);
  EXPECT_EQ(outs[0].m.t, outs[1].m.t);
  EXPECT_EQ(outs[0].m.scalar, outs[1].m.scalar);
}

TEST(Cluster, BoundaryQuadricsPinTheCorners)
{
  // A flat square: its corner cells hold the face plane z = 0 and, with boundary quadrics, the
  // border planes x = 0 / x = 1 and y = 0 / y = 1: full rank, so the representative is exactly
  // the square's corner. Without them it is the mean of the cell's vertices.
  const Mesh plane = Plane(16);
  auto hasCorners = [](const Mesh& m) {
    int found = 0;
    for (std::size_t i = 0; i < m.p.size(); i += 3)
    {
      const bool x = std::abs(m.p[i]) < 1e-6f || std::abs(m.p[i] - 1.f) < 1e-6f;
      const bool y = std::abs(m.p[i + 1]) < 1e-6f || std::abs(m.p[i + 1] - 1.f) < 1e-6f;
      found += x && y;
    }
    return found;
  };
  EXPECT_EQ(hasCorners(RunCluster(plane, 4).m), 0);
  ClusterOptions o;
  o.maximumGridDimension = 4;
  o.boundaryQuadrics = true;
  Collect out;
  NullProgress progress;
  RunStats s = Cluster(MemorySource(plane), out, o, progress);
  EXPECT_EQ(hasCorners(out.m), 4);
  bool boundaryPhase = false;
  for (const auto& p : s.phases)
  {
    boundaryPhase |= p.name == "boundaries";
  }
  EXPECT_TRUE(boundaryPhase);
  // the same out of core
  o.storage.policy = storage::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  Collect out2;
  Cluster(MemorySource(plane), out2, o, progress);
  EXPECT_EQ(out.m.p, out2.m.p);
  EXPECT_EQ(out.m.t, out2.m.t);
}

// The reported error: each representative's RMS distance to its cell's planes. Every such plane
// passes through a vertex in the cell, and the representative lies in the cell widened by
// placementSlack cells, so the error is at most sqrt(3) (1 + slack) cell sizes.
TEST(Cluster, AchievedErrorIsBoundedByTheCells)
{
  Mesh wavy = Plane(40);
  for (std::size_t i = 0; i < wavy.p.size(); i += 3)
  {
    wavy.p[i + 2] = float(0.3 * std::sin(3.0 * wavy.p[i]) * std::cos(2.0 * wavy.p[i + 1]));
  }
  double previous = 1;
  for (int grid : { 4, 8, 16 })
  {
    RunStats s;
    RunCluster(wavy, grid, storage::ModePolicy::Automatic, 0, &s);
    ClusterOptions o;
    const double D = s.errorDiagonal; // (x and y over [0, 1], |z| below 0.3)
    EXPECT_GT(D, std::sqrt(2.0));
    EXPECT_LT(D, std::sqrt(2.0 + 0.36));
    const double cellSize = 1.0 / grid; // (the longest side over the grid)
    EXPECT_GT(s.achievedError, 0.0) << grid;
    EXPECT_LE(s.achievedError, std::sqrt(3.0) * (1 + o.placementSlack) * cellSize / D) << grid;
    EXPECT_LT(s.achievedError, previous) << grid; // finer cells, smaller error
    previous = s.achievedError;
  }
  // A plane: every representative is on it.
  RunStats flat;
  RunCluster(Plane(16), 4, storage::ModePolicy::Automatic, 0, &flat);
  EXPECT_GE(flat.achievedError, 0.0);
  EXPECT_LT(flat.achievedError, 1e-6);
}

TEST(Cluster, TheOrderOfTheInputDoesNotChangeTheResult)
{
  // The cells' sums are exact (fixed point): the same faces in any order, with their corners
  // rotated, give the same triangles at the same coordinates, bit for bit. Far from the origin
  // too, with boundary planes (an open surface) and with the sampled-vertex fallback.
  Mesh open = Plane(24);
  for (std::size_t i = 0; i < open.p.size(); i += 3)
  {
    open.p[i + 2] = 0.1f * std::sin(7.f * open.p[i]) * std::cos(5.f * open.p[i + 1]);
  }
  const Mesh meshes[] = { sipmss::testing::BumpyUVSphere(30),
    sipmss::testing::BumpyUVSphere(30, { 1e4, -3e3, 2e4 }), open };
  for (const Mesh& m : meshes)
  {
    for (int variant = 0; variant < 3; ++variant)
    {
      ClusterOptions o;
      o.maximumGridDimension = variant == 1 ? 23 : 9;
      o.boundaryQuadrics = variant == 2;
      o.fallback = variant == 1 ? ClusterFallback::SampledVertex : ClusterFallback::Mean;
      o.layout = LayoutPolicy::Keep;
      NullProgress progress;
      Collect a, b;
      Cluster(MemorySource(m), a, o, progress);
      const Mesh shuffled = sipmss::testing::Shuffled(m, 7u + variant);
      Cluster(MemorySource(shuffled), b, o, progress);
      ASSERT_GT(a.m.t.size(), 30u);
      const auto ta = sipmss::testing::TrianglesByCoordinates(a.m),
                 tb = sipmss::testing::TrianglesByCoordinates(b.m);
      std::vector<std::array<float, 9>> onlyA, onlyB;
      std::set_difference(ta.begin(), ta.end(), tb.begin(), tb.end(), std::back_inserter(onlyA));
      std::set_difference(tb.begin(), tb.end(), ta.begin(), ta.end(), std::back_inserter(onlyB));
      EXPECT_TRUE(onlyA.empty() && onlyB.empty())
        << "variant " << variant << ": " << onlyA.size() << " triangles only in the first run, "
        << onlyB.size() << " only in the shuffled one, of " << ta.size();
      for (std::size_t i = 0; i < std::min({ std::size_t(2), onlyA.size(), onlyB.size() }); ++i)
      {
        ADD_FAILURE() << onlyA[i][0] << " " << onlyA[i][1] << " " << onlyA[i][2] << " / "
                      << onlyB[i][0] << " " << onlyB[i][1] << " " << onlyB[i][2];
      }
      EXPECT_EQ(a.m.p.size(), b.m.p.size());
    }
  }
}

TEST(Cluster, InGridOrderTheOutputIsTheSameForAnyOrderOfTheInput)
{
  // ClusterOptions::gridOrder: the vertices by their cell's grid key, the triangles from their
  // lowest vertex and sorted. With exact sums the output of a shuffled input is then the
  // ordered input's, byte for byte (without it, the same triangles in another numbering). Out
  // of core the order stays the first-seen one: the same triangles.
  const Mesh meshes[] = { sipmss::testing::BumpyUVSphere(30),
    sipmss::testing::BumpyUVSphere(24, { 1e4, -3e3, 2e4 }) };
  for (const Mesh& m : meshes)
  {
    const Mesh shuffled = sipmss::testing::Shuffled(m, 11u);
    // Each output vertex's exported cell quadric by position (first-seen order's, then checked
    // against grid order's: the index exportQuadric gets is the vertex's).
    std::map<std::array<float, 3>, std::array<double, 10>> quadricAt;
    for (const bool gridOrder : { false, true })
    {
      ClusterOptions o;
      o.maximumGridDimension = 11;
      o.layout = LayoutPolicy::Keep;
      o.gridOrder = gridOrder;
      std::vector<std::array<double, 10>> exported;
      o.exportQuadric = [&exported](std::uint64_t v, const double q[10]) {
        exported.resize(std::max<std::size_t>(exported.size(), std::size_t(v) + 1));
        std::copy_n(q, 10, exported[std::size_t(v)].begin());
      };
      NullProgress progress;
      Collect a, b, c;
      Cluster(MemorySource(m), a, o, progress);
      ASSERT_EQ(exported.size() * 3, a.m.p.size());
      for (std::size_t v = 0; v < exported.size(); ++v)
      {
        const std::array<float, 3> at = { a.m.p[3 * v], a.m.p[3 * v + 1], a.m.p[3 * v + 2] };
        if (!gridOrder)
        {
          quadricAt[at] = exported[v];
        }
        else
        {
          ASSERT_TRUE(quadricAt.count(at) && quadricAt[at] == exported[v]) << v;
        }
      }
      o.exportQuadric = nullptr;
      Cluster(MemorySource(shuffled), b, o, progress);
      ASSERT_GT(a.m.t.size(), 3u * 100u);
      EXPECT_EQ(a.m.p.size(), b.m.p.size());
      if (!gridOrder)
      {
        EXPECT_FALSE(a.m.t == b.m.t && a.m.p == b.m.p); // (the cells' first-seen order)
        continue;
      }
      EXPECT_TRUE(a.m.p == b.m.p);
      EXPECT_TRUE(a.m.t == b.m.t);
      o.storage.policy = storage::ModePolicy::OutOfCore;
      o.storage.memoryBudget = 256 << 10;
      Cluster(MemorySource(shuffled), c, o, progress);
      EXPECT_FALSE(a.m.t == c.m.t);
      EXPECT_TRUE(sipmss::testing::TrianglesByCoordinates(a.m) ==
        sipmss::testing::TrianglesByCoordinates(c.m));
      // Each triangle from its lowest vertex, the triangles in increasing order.
      for (std::size_t i = 0; i < a.m.t.size(); i += 3)
      {
        ASSERT_LT(a.m.t[i], a.m.t[i + 1]);
        ASSERT_LT(a.m.t[i], a.m.t[i + 2]);
        if (i > 0)
        {
          ASSERT_TRUE(std::lexicographical_compare(a.m.t.begin() + std::ptrdiff_t(i) - 3,
            a.m.t.begin() + std::ptrdiff_t(i), a.m.t.begin() + std::ptrdiff_t(i),
            a.m.t.begin() + std::ptrdiff_t(i) + 3));
        }
      }
    }
  }
}

TEST(Cluster, TheGatherHelperCopiesEachFacesRecords)
{
  // detail::Gatherer (the clustering of faces out of spatial order in core): whoever copies a
  // block, Records(t) are the records of face t's vertices, Rec{} for a vertex at or past
  // `seen`; a post stopped part way leaves the blocks taken so far, and the next post starts
  // over.
  struct Rec
  {
    float x = -1;
    std::uint32_t id = ~0u;
  };
  std::vector<Rec> base(5000);
  for (std::uint32_t i = 0; i < base.size(); ++i)
  {
    base[i] = Rec{ float(i) * 0.5f, i };
  }
  std::mt19937 rng(7);
  using G = detail::Gatherer<Rec>;
  // (the faces outlive the gatherer: its helper may read them until it stops)
  std::vector<std::uint32_t> last(3 * G::kMaxFaces, 3);
  std::vector<std::uint32_t> idx;
  G g;
  struct StopAtExit // (also when an assertion returns early)
  {
    G& g;
    ~StopAtExit() { this->g.Stop(); }
  };
  for (const std::size_t count : { std::size_t(1), G::kBlock - 1, G::kBlock, G::kBlock + 1,
         std::size_t(1000), G::kMaxFaces, G::kMaxFaces, std::size_t(77) })
  {
    StopAtExit stopAtExit{ g };
    idx.assign(3 * count, 0);
    for (auto& v : idx)
    {
      v = std::uint32_t(rng() % 5200); // (some at or past `seen`)
    }
    const std::uint64_t seen = 4900;
    g.Post(base.data(), seen, idx.data(), count);
    const bool stopEarly = count == 1000;
    for (std::size_t t = 0; t < count; ++t)
    {
      if (t % G::kBlock == 0)
      {
        if (stopEarly && t == 5 * G::kBlock)
        {
          g.Stop(); // (then only the blocks taken are read)
          break;
        }
        g.Take(t / G::kBlock);
      }
      const Rec* r = g.Records(t);
      for (int k = 0; k < 3; ++k)
      {
        const std::uint32_t v = idx[3 * t + std::size_t(k)];
        ASSERT_EQ(r[k].id, v < seen ? v : ~0u) << count << " " << t;
        ASSERT_EQ(r[k].x, v < seen ? float(v) * 0.5f : -1.f);
      }
    }
  }
  // A post that was stopped before the helper began it is withdrawn (Stop returns at once);
  // destroyed with a post in flight, it stops and joins.
  g.Post(base.data(), base.size(), last.data(), G::kMaxFaces);
  g.Stop();
  g.Post(base.data(), base.size(), last.data(), G::kMaxFaces);
  EXPECT_THROW(g.Post(base.data(), base.size(), last.data(), G::kMaxFaces + 1), std::length_error);
  g.Post(base.data(), base.size(), last.data(), G::kMaxFaces);
}

TEST(Cluster, ShuffledFacesGiveTheSameOutputWithTheGatherHelper)
{
  // In core, faces out of spatial order on two threads: their vertex records are copied by a
  // helper (Gather.h) and the faces added in the same order, so the output is the one-thread
  // run's, bit for bit, with exact and with plain sums; also when some faces come before their
  // vertices (deferred part way through a post).
  const Mesh m = sipmss::testing::Shuffled(sipmss::testing::BumpyUVSphere(120, { 3, -1, 2 }), 5u);
  ASSERT_GT(m.t.size() / 3, 3 * 8192u); // (several posts)
  // The vertices in two chunks, the faces between them: the faces that use a vertex of the
  // second chunk wait for it.
  auto split = [&m](io::MeshSink& sink, const io::ReadOptions&) {
    io::MeshHeader h;
    h.vertexCount = m.p.size() / 3;
    h.faceCount = m.t.size() / 3;
    sink.Begin(h);
    const std::size_t half = h.vertexCount / 2;
    io::VertexChunk c;
    c.count = half;
    c.xyz = m.p.data();
    sink.Vertices(c);
    sink.Triangles(m.t.data(), m.t.size() / 3);
    c.first = half;
    c.count = h.vertexCount - half;
    c.xyz = m.p.data() + 3 * half;
    sink.Vertices(c);
    io::ReadStats s;
    s.vertices = h.vertexCount;
    s.triangles = h.faceCount;
    sink.End(s);
    return s;
  };
  for (const bool exact : { true, false })
  {
    for (const bool deferred : { false, true })
    {
      Collect outs[2];
      for (int t = 1; t <= 2; ++t)
      {
        const std::uint64_t posts = detail::GatherPosts().load();
        ClusterOptions o;
        o.maximumGridDimension = 40;
        o.exactSums = exact;
        o.layout = LayoutPolicy::Keep;
        o.threads = t;
        NullProgress progress;
        if (deferred)
        {
          Cluster(split, outs[t - 1], o, progress);
        }
        else
        {
          Cluster(MemorySource(m), outs[t - 1], o, progress);
        }
        // (the helper's posts: none on one thread; on two, some even where faces are deferred)
        if (t == 1)
        {
          EXPECT_EQ(detail::GatherPosts().load(), posts);
        }
        else
        {
          EXPECT_GT(detail::GatherPosts().load(), posts + (deferred ? 0 : 2));
        }
      }
      EXPECT_GT(outs[0].m.t.size(), 3000u);
      EXPECT_TRUE(outs[0].m.p == outs[1].m.p) << exact << deferred;
      EXPECT_TRUE(outs[0].m.t == outs[1].m.t) << exact << deferred;
    }
  }
}

TEST(Cluster, ShuffledFacesGoingOutOfCoreMidChunkGiveTheSameOutput)
{
  // Faces out of spatial order, in core at first: with boundary quadrics each face appends its
  // edges to a block of their own, whose growth takes the DML out of core part way through the
  // faces (the faces' loop then looks at the blocks' base pointers again). The output is the
  // one of a run in core, for every budget tried; some of them switch.
  const Mesh m = sipmss::testing::Shuffled(sipmss::testing::BumpyUVSphere(90, { 1, 2, 3 }), 9u);
  auto run = [&m](std::uint64_t budget, int threads, RunStats* stats) {
    ClusterOptions o;
    o.maximumGridDimension = 30;
    o.boundaryQuadrics = true;
    o.boundaryWeight = 1.0;
    o.layout = LayoutPolicy::Keep;
    o.threads = threads;
    o.storage.memoryBudget = budget;
    Collect out;
    NullProgress progress;
    const RunStats s = Cluster(MemorySource(m), out, o, progress);
    if (stats)
    {
      *stats = s;
    }
    return out;
  };
  const Collect inCore = run(0, 1, nullptr);
  int switched = 0;
  for (std::uint64_t budget = 512 << 10; budget <= (6u << 20); budget += 256 << 10)
  {
    RunStats s;
    const Collect out = run(budget, 2, &s);
    switched += s.storage.usedInCore && s.storage.usedOutOfCore;
    EXPECT_TRUE(out.m.p == inCore.m.p && out.m.t == inCore.m.t) << budget;
  }
  EXPECT_GT(switched, 0);
}

TEST(Cluster, FacesInOneLargeCallHoldNoMoreThanTheirCandidates)
{
  // A source may hand all faces in one call (MemorySource, a caller's): the candidates' block
  // grows with the candidates, never with the faces of a call (no room is reserved ahead for
  // the helper). 180,000 faces over about 100 cells: the DML's peak is the vertex records and
  // little more, not 16 bytes a face.
  const Mesh plane = sipmss::testing::Shuffled(Plane(300), 3u);
  for (int threads : { 1, 2 })
  {
    ClusterOptions o;
    o.maximumGridDimension = 10;
    o.threads = threads;
    o.layout = LayoutPolicy::Keep;
    Collect out;
    NullProgress progress;
    const RunStats s = Cluster(MemorySource(plane), out, o, progress);
    const std::uint64_t vertexBytes = 16 * (plane.p.size() / 3);
    EXPECT_GT(out.m.t.size(), 0u);
    EXPECT_LT(s.storage.peakBytes, vertexBytes + (1u << 20)) << threads;
  }
}

TEST(Cluster, PlainSumsGiveTheExactResultToRounding)
{
  // ClusterOptions::exactSums off (two-stage's first stage): the same triangles, the vertices
  // within rounding of the exact sums' (not always bit for bit).
  const Mesh m = sipmss::testing::BumpyUVSphere(40, { 2.0, 1.0, -3.0 });
  ClusterOptions o;
  o.maximumGridDimension = 19;
  NullProgress progress;
  Collect exact, plain;
  const RunStats se = Cluster(MemorySource(m), exact, o, progress);
  o.exactSums = false;
  const RunStats sp = Cluster(MemorySource(m), plain, o, progress);
  ASSERT_EQ(exact.m.t, plain.m.t); // (the same cells in the same order)
  ASSERT_EQ(exact.m.p.size(), plain.m.p.size());
  for (std::size_t i = 0; i < exact.m.p.size(); ++i)
  {
    EXPECT_NEAR(exact.m.p[i], plain.m.p[i], 1e-5f * (1.f + std::abs(exact.m.p[i])));
  }
  EXPECT_NEAR(se.achievedError, sp.achievedError, 1e-6 * se.achievedError);
  EXPECT_GT(exact.m.t.size(), 100u);
}
