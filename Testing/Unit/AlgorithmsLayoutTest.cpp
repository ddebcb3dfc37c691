// The layout step: StoredMesh::Reorder keeps the mesh (the same triangles over the same points,
// orientation kept, point data with its vertex) and makes it coherent; the probe tells scanner
// order from shuffled; clustering and decimation of a shuffled input out of core reorder it.
#include "AlgorithmsTestUtil.h"

#include "../../Algorithms/src/StoredMesh.h"

#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/Compare.h"
#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/TwoStage.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <map>
#include <numeric>
#include <random>
#include <set>
#include <vector>

namespace
{
using namespace sipmss;
using namespace sipmss::algorithms;

// A collecting sink.
struct Collect final : io::MeshSink
{
  io::MeshHeader header;
  std::vector<float> xyz, scalars;
  std::vector<std::uint32_t> tris;
  void Begin(const io::MeshHeader& h) override { this->header = h; }
  void Vertices(const io::VertexChunk& c) override
  {
    this->xyz.insert(this->xyz.end(), c.xyz, c.xyz + 3 * c.count);
    if (c.scalars)
    {
      const std::size_t ns = this->header.layout.scalars.size();
      this->scalars.insert(this->scalars.end(), c.scalars, c.scalars + ns * c.count);
    }
  }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    this->tris.insert(this->tris.end(), idx, idx + 3 * count);
  }
  void End(const io::ReadStats&) override {}
};

// A grid surface of n x n quads (2 n^2 triangles) with two scalars per vertex, in scanner order
// or shuffled (vertices and faces by a fixed seed).
struct Mesh
{
  std::vector<float> xyz, scalars;
  std::vector<std::uint32_t> tris;
};
Mesh Grid(int n, bool shuffled)
{
  Mesh m;
  const int V = (n + 1) * (n + 1);
  std::vector<std::uint32_t> perm(V);
  std::iota(perm.begin(), perm.end(), 0u);
  std::mt19937 rng(7);
  if (shuffled)
  {
    std::shuffle(perm.begin(), perm.end(), rng);
  }
  m.xyz.resize(3 * V);
  m.scalars.resize(2 * V);
  for (int j = 0; j <= n; ++j)
  {
    for (int i = 0; i <= n; ++i)
    {
      const int v = j * (n + 1) + i;
      const std::uint32_t p = perm[v];
      m.xyz[3 * p] = float(i);
      m.xyz[3 * p + 1] = float(j);
      m.xyz[3 * p + 2] = float(3.0 * std::sin(i / 7.0) * std::cos(j / 9.0)); // curved everywhere
      m.scalars[2 * p] = float(v);
      m.scalars[2 * p + 1] = -float(v);
    }
  }
  for (int j = 0; j < n; ++j)
  {
    for (int i = 0; i < n; ++i)
    {
      const std::uint32_t a = perm[j * (n + 1) + i], b = perm[j * (n + 1) + i + 1];
      const std::uint32_t c = perm[(j + 1) * (n + 1) + i], d = perm[(j + 1) * (n + 1) + i + 1];
      m.tris.insert(m.tris.end(), { a, b, d, a, d, c });
    }
  }
  if (shuffled)
  {
    const std::size_t F = m.tris.size() / 3;
    std::vector<std::size_t> fp(F);
    std::iota(fp.begin(), fp.end(), std::size_t(0));
    std::shuffle(fp.begin(), fp.end(), rng);
    std::vector<std::uint32_t> t(m.tris.size());
    for (std::size_t f = 0; f < F; ++f)
    {
      std::copy_n(&m.tris[3 * fp[f]], 3, &t[3 * f]);
    }
    m.tris.swap(t);
  }
  return m;
}

// announce: the header gives the counts (as a PLY's does; else as a source that cannot).
// faces: the header's face count when not the triangles' (a PLY counts polygons, of which the
// reader drops some and splits others into several triangles).
MeshSource SourceOf(const Mesh& m, bool announce = true, std::uint64_t faces = 0)
{
  return [&m, announce, faces](io::MeshSink& sink, const io::ReadOptions&) {
    io::MeshHeader h;
    h.format = io::Format::PlyBinaryLE;
    h.vertexCount = announce ? m.xyz.size() / 3 : 0;
    h.faceCount = announce ? (faces ? faces : m.tris.size() / 3) : 0;
    h.layout.scalars = { "s", "t" };
    sink.Begin(h);
    io::VertexChunk c;
    c.count = m.xyz.size() / 3;
    c.xyz = m.xyz.data();
    c.scalars = m.scalars.data();
    sink.Vertices(c);
    sink.Triangles(m.tris.data(), m.tris.size() / 3);
    io::ReadStats st;
    st.vertices = m.xyz.size() / 3;
    st.triangles = st.polygons = m.tris.size() / 3;
    sink.End(st);
    return st;
  };
}

// The triangles as sorted triples of their corners' (x, y, z, s, t), each rotated so that the
// smallest corner comes first (orientation kept).
using Corner = std::array<float, 5>;
std::vector<std::array<Corner, 3>> Geometry(const std::vector<float>& xyz,
  const std::vector<float>& scalars, const std::vector<std::uint32_t>& tris)
{
  std::vector<std::array<Corner, 3>> out;
  for (std::size_t f = 0; f < tris.size() / 3; ++f)
  {
    std::array<Corner, 3> t;
    for (int k = 0; k < 3; ++k)
    {
      const std::uint32_t v = tris[3 * f + k];
      t[k] = { xyz[3 * v], xyz[3 * v + 1], xyz[3 * v + 2], scalars[2 * v], scalars[2 * v + 1] };
    }
    std::rotate(t.begin(), std::min_element(t.begin(), t.end()), t.end());
    out.push_back(t);
  }
  std::sort(out.begin(), out.end());
  return out;
}

void CheckReorderKeepsTheMesh(std::uint64_t budget, std::uint64_t announcedFaces = 0)
{
  const Mesh m = Grid(120, true); // 14,641 vertices, 28,800 triangles
  storage::Profile p;
  p.memoryBudget = budget;
  p.policy = budget ? storage::ModePolicy::OutOfCore : storage::ModePolicy::Automatic;
  storage::DML dml;
  dml.Config(p);
  detail::StoredMesh mesh(dml);
  SourceOf(m, true, announcedFaces)(mesh, io::ReadOptions{});
  EXPECT_GT(mesh.Layout().FarFraction(), 0.3); // (random jumps of 14,641 vertices, window 4,096)
  NullProgress progress;
  progress.BeginPhase("test", 1, 0);
  mesh.Reorder(progress);
  Collect out;
  mesh.Replay(out, io::ReadOptions{});
  ASSERT_EQ(out.xyz.size(), m.xyz.size());
  ASSERT_EQ(out.tris.size(), m.tris.size());
  EXPECT_TRUE(Geometry(out.xyz, out.scalars, out.tris) == Geometry(m.xyz, m.scalars, m.tris))
    << "budget " << budget;
  // coherent now: faces ascend by their lowest vertex, few far apart
  detail::LayoutMeter meter;
  meter.Start(out.xyz.size() / 3);
  std::uint32_t last = 0;
  for (std::size_t f = 0; f < out.tris.size() / 3; ++f)
  {
    const std::uint32_t lo = std::min({ out.tris[3 * f], out.tris[3 * f + 1], out.tris[3 * f + 2] });
    EXPECT_GE(lo, last);
    last = lo;
    meter.Face(&out.tris[3 * f]);
  }
  EXPECT_LT(meter.FarFraction(), detail::kIncoherentFarFraction) << meter.FarFraction();
}

// The slices path's one-multiplication division gives the quotient of every 32-bit number:
// exhaustive near the ends and near multiples of the divisor, random elsewhere, for divisors
// small and large, powers of two and not.
TEST(AlgorithmsLayout, Divider32GivesTheQuotientOfEvery32BitNumber)
{
  std::mt19937_64 rng(7);
  std::vector<std::uint64_t> divisors = { 2, 3, 7, 1024, 1025, 375000, 524288, 1u << 31,
    (1u << 31) + 1, 0xffffffffu, std::uint64_t(1) << 32, (std::uint64_t(1) << 32) + 5 };
  for (int i = 0; i < 200; ++i)
  {
    divisors.push_back(2 + rng() % 0xffffffffu);
  }
  for (const std::uint64_t d : divisors)
  {
    const detail::Divider32 div(d);
    auto check = [&](std::uint64_t n) {
      const auto v = static_cast<std::uint32_t>(n);
      ASSERT_EQ(div(v), std::uint64_t(v) / d) << v << " / " << d;
    };
    for (std::uint64_t n = 0; n < 4096; ++n)
    {
      check(n);
      check(0xffffffffu - n);
    }
    for (std::uint64_t m = d; m <= 0xffffffffu && m < 64 * d; m += d)
    {
      for (std::uint64_t n = m - 1; n <= std::min<std::uint64_t>(m + 1, 0xffffffffu); ++n)
      {
        check(n);
      }
    }
    for (int i = 0; i < 20000; ++i)
    {
      check(rng() & 0xffffffffu);
    }
  }
  EXPECT_THROW(detail::Divider32(1), std::invalid_argument);
  EXPECT_THROW(detail::Divider32(0), std::invalid_argument);
}

// A face rotated to start at its lowest vertex keeps its cyclic order; with a repeated lowest
// vertex the rotation is fixed (the last of the positions 0, 1, 2 that holds the lowest, by the
// strict comparisons of the code before it was written without an index), which the sorts and
// the byte-identical outputs rely on.
TEST(AlgorithmsLayout, LowestFirstRotatesToTheLowestVertex)
{
  struct Tri
  {
    std::uint32_t v[3];
  };
  for (std::uint32_t a = 0; a < 3; ++a)
  {
    for (std::uint32_t b = 0; b < 3; ++b)
    {
      for (std::uint32_t c = 0; c < 3; ++c)
      {
        Tri t{ { a, b, c } };
        detail::LowestFirst(t);
        const int m = a < b ? (a < c ? 0 : 2) : (b < c ? 1 : 2);
        const std::uint32_t in[3] = { a, b, c };
        for (int k = 0; k < 3; ++k)
        {
          EXPECT_EQ(t.v[k], in[(m + k) % 3]) << a << " " << b << " " << c;
        }
        EXPECT_EQ(t.v[0], std::min({ a, b, c }));
      }
    }
  }
}

TEST(AlgorithmsLayout, ReorderKeepsTheMeshInCore)
{
  CheckReorderKeepsTheMesh(0);
}

TEST(AlgorithmsLayout, ReorderKeepsTheMeshOutOfCore)
{
  CheckReorderKeepsTheMesh(256 << 10);
}

// A header that counts more faces than come (dropped ones) or fewer (polygons split into
// triangles, the block then grown past them): the copy's block is longer than its triangles.
TEST(AlgorithmsLayout, ReorderKeepsTheMeshWhenTheHeaderMiscountsFaces)
{
  for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(256) << 10 })
  {
    for (std::uint64_t faces : { std::uint64_t(28800 + 1000), std::uint64_t(20000) })
    {
      SCOPED_TRACE("budget " + std::to_string(budget) + ", header faces " + std::to_string(faces));
      CheckReorderKeepsTheMesh(budget, faces);
    }
  }
}

TEST(AlgorithmsLayout, ScannerOrderIsCoherentShuffledIsNot)
{
  for (bool shuffled : { false, true })
  {
    const Mesh m = Grid(200, shuffled);
    detail::LayoutMeter meter;
    meter.Start(m.xyz.size() / 3);
    for (std::size_t f = 0; f < m.tris.size() / 3; ++f)
    {
      meter.Face(&m.tris[3 * f]);
    }
    if (shuffled)
    {
      EXPECT_GT(meter.FarFraction(), 0.5);
    }
    else
    {
      EXPECT_LT(meter.FarFraction(), 0.01);
    }
  }
}

// The three ways to renumber the faces (the inverse in memory, in slices, by sorting corners)
// give the same bytes; in slices also with many of them (small bucket buffers, each filled and
// read many times).
TEST(AlgorithmsLayout, ReorderIsTheSameInMemoryInSlicesAndBySorting)
{
  const Mesh m = Grid(300, true); // 90,601 vertices, 180,000 triangles
  constexpr int kRuns = 4;
  std::vector<Collect> outs(kRuns);
  const std::uint64_t budgets[kRuns] = { 0, std::uint64_t(1) << 20, std::uint64_t(64) << 10,
    std::uint64_t(400) << 10 };
  const detail::StoredMesh::Renumbering paths[kRuns] = {
    detail::StoredMesh::Renumbering::InMemory, detail::StoredMesh::Renumbering::Slices,
    detail::StoredMesh::Renumbering::SortedCorners, detail::StoredMesh::Renumbering::Slices };
  std::uint64_t mostSlices = 0;
  for (int k = 0; k < kRuns; ++k)
  {
    storage::Profile p;
    p.memoryBudget = budgets[k];
    p.policy = budgets[k] ? storage::ModePolicy::OutOfCore : storage::ModePolicy::Automatic;
    storage::DML dml;
    dml.Config(p);
    detail::StoredMesh mesh(dml);
    SourceOf(m)(mesh, io::ReadOptions{});
    NullProgress progress;
    progress.BeginPhase("test", 1, 0);
    EXPECT_EQ(int(mesh.Reorder(progress)), int(paths[k])) << "budget " << budgets[k];
    mostSlices = std::max(mostSlices, mesh.Slices());
    // Its parts, in order, with the DML's I/O: none in core; out of core each part moves
    // data, and the block files at the end hold the points, the scalars and the triangles.
    const std::vector<std::string> names = { "vertices by key", "inverse", "point data",
      "faces renumbered", "faces sorted" };
    ASSERT_EQ(mesh.Steps().size(), names.size()) << k;
    for (std::size_t i = 0; i < names.size(); ++i)
    {
      const LayoutStepStat& st = mesh.Steps()[i];
      EXPECT_EQ(st.name, names[i]) << k;
      EXPECT_GE(st.seconds, 0.0) << k;
      if (budgets[k] == 0)
      {
        EXPECT_EQ(st.bytesRead + st.bytesWritten + st.fileBytes, 0u) << k << " " << st.name;
      }
      else
      {
        EXPECT_GT(st.bytesRead + st.bytesWritten, 0u) << k << " " << st.name;
      }
    }
    if (budgets[k])
    {
      EXPECT_GE(mesh.Steps().back().fileBytes, m.xyz.size() * 4 + m.tris.size() * 4) << k;
    }
    mesh.Replay(outs[k], io::ReadOptions{});
  }
  EXPECT_GE(mostSlices, 4u);
  for (int k = 1; k < kRuns; ++k)
  {
    EXPECT_TRUE(outs[0].xyz == outs[k].xyz) << k;
    EXPECT_TRUE(outs[0].scalars == outs[k].scalars) << k;
    EXPECT_TRUE(outs[0].tris == outs[k].tris) << k;
  }
  EXPECT_TRUE(Geometry(outs[2].xyz, outs[2].scalars, outs[2].tris) ==
    Geometry(m.xyz, m.scalars, m.tris));
}

struct CoreRun
{
  Collect out;
  RunStats stats;
};

CoreRun Simplify(const Mesh& m, const std::string& algorithm, std::uint64_t budget,
  LayoutPolicy layout = LayoutPolicy::Automatic)
{
  CoreRun r;
  NullProgress progress;
  storage::Profile p;
  p.memoryBudget = budget;
  if (algorithm == "cluster")
  {
    ClusterOptions o;
    o.maximumGridDimension = 40;
    o.storage = p;
    o.layout = layout;
    r.stats = Cluster(SourceOf(m), r.out, o, progress);
  }
  else
  {
    DecimateOptions o;
    o.targetTriangles = 2000;
    o.storage = p;
    o.layout = layout;
    if (algorithm == "decimate")
    {
      r.stats = Decimate(SourceOf(m), r.out, o, progress);
    }
    else
    {
      TwoStageOptions t;
      t.gridDimension = 60;
      t.decimate = o;
      r.stats = TwoStage(SourceOf(m), r.out, t, progress);
    }
  }
  return r;
}

double Rms(const Mesh& reference, const Collect& out)
{
  TriangleMesh a, b;
  a.points = reference.xyz;
  a.triangles = reference.tris;
  b.points = out.xyz;
  b.triangles = out.tris;
  CompareOptions co;
  co.samples = 200000;
  return CompareMeshes(a, b, co).rms;
}

// The triangles of a run's output as positions alone (Geometry without point data).
std::vector<std::array<Corner, 3>> Positions(const Collect& out)
{
  return Geometry(out.xyz, std::vector<float>(2 * out.xyz.size() / 3, 0.f), out.tris);
}

// A shuffled input is reordered by the decimation in every mode, and by the clustering and
// two-stage only out of core (in core their lookups are fetched ahead and cost less than the
// layout step). The decimation gives the same bytes in both modes; the clustering (exact sums)
// the same triangles over the same points, numbered in another order; every run's error is
// within 1% of the run on the input in scanner order.
TEST(AlgorithmsLayout, ShuffledInputsAreReorderedWhereItPays)
{
  const Mesh ordered = Grid(250, false);  // 63,001 vertices, 125,000 triangles
  const Mesh shuffled = Grid(250, true);
  for (const std::string algorithm : { "cluster", "decimate", "two-stage" })
  {
    const bool reorderedInCore = algorithm == "decimate";
    const CoreRun a = Simplify(ordered, algorithm, 0);
    EXPECT_FALSE(a.stats.reordered) << algorithm;
    EXPECT_LT(a.stats.layoutFarFraction, detail::kIncoherentFarFraction) << algorithm;
    const CoreRun inCore = Simplify(shuffled, algorithm, 0);
    const CoreRun outOfCore = Simplify(shuffled, algorithm, 512 << 10);
    EXPECT_EQ(inCore.stats.reordered, reorderedInCore) << algorithm;
    EXPECT_FALSE(inCore.stats.storage.usedOutOfCore) << algorithm;
    EXPECT_TRUE(outOfCore.stats.reordered) << algorithm;
    EXPECT_TRUE(outOfCore.stats.storage.usedOutOfCore) << algorithm;
    EXPECT_GT(inCore.stats.layoutFarFraction, 0.5) << algorithm;
    EXPECT_GT(outOfCore.stats.layoutFarFraction, 0.5) << algorithm;
    if (algorithm == "decimate")
    {
      EXPECT_TRUE(inCore.out.xyz == outOfCore.out.xyz) << algorithm;
      EXPECT_TRUE(inCore.out.tris == outOfCore.out.tris) << algorithm;
    }
    if (algorithm == "cluster")
    {
      EXPECT_FALSE(inCore.out.tris == outOfCore.out.tris); // (another numbering)
      EXPECT_TRUE(Positions(inCore.out) == Positions(outOfCore.out));
      EXPECT_TRUE(Positions(inCore.out) == Positions(a.out));
    }
    const double e0 = Rms(ordered, a.out);
    for (const CoreRun* run : { &inCore, &outOfCore })
    {
      EXPECT_NEAR(Rms(ordered, run->out), e0, 0.01 * e0) << algorithm;
      EXPECT_NEAR(double(run->out.tris.size()), double(a.out.tris.size()),
        0.01 * double(a.out.tris.size())) << algorithm;
    }
    // Keep: the input's own order, no layout step (the clustering also out of core, where
    // Automatic reorders; a shuffled decimation out of core is slow); Reorder: the step also in
    // core
    const CoreRun kept =
      Simplify(shuffled, algorithm, algorithm == "cluster" ? 512 << 10 : 0, LayoutPolicy::Keep);
    EXPECT_FALSE(kept.stats.reordered) << algorithm;
    const CoreRun forced = Simplify(shuffled, algorithm, 0, LayoutPolicy::Reorder);
    EXPECT_TRUE(forced.stats.reordered) << algorithm;
  }
}

// A source that announces no sizes, whose first faces show it shuffled: when the probe stops
// before the end the size is unknown, so the clustering and two-stage reorder it under any
// bounded budget (as an input of any size might go out of core), and not when unbounded; when the
// probe reads it all (a small input), the counted size decides.
TEST(AlgorithmsLayout, AnInputOfUnknownSizeIsReorderedUnderABoundedBudget)
{
  const Mesh big = Grid(260, true); // 135,200 triangles: more than the probe measures
  const Mesh small = Grid(200, true); // 80,000: the probe reads it all
  ASSERT_GT(big.tris.size() / 3, detail::kProbeFaces);
  ASSERT_LT(small.tris.size() / 3, detail::kProbeFaces);
  for (const std::string algorithm : { "cluster", "two-stage" })
  {
    for (const std::uint64_t budget : { std::uint64_t(0), std::uint64_t(1) << 30 })
    {
      for (const Mesh* m : { &big, &small })
      {
        NullProgress progress;
        storage::Profile p;
        p.memoryBudget = budget;
        Collect out;
        RunStats stats;
        if (algorithm == "cluster")
        {
          ClusterOptions o;
          o.maximumGridDimension = 40;
          o.storage = p;
          stats = Cluster(SourceOf(*m, false), out, o, progress);
        }
        else
        {
          TwoStageOptions t;
          t.gridDimension = 60;
          t.decimate.targetTriangles = 2000;
          t.decimate.storage = p;
          stats = TwoStage(SourceOf(*m, false), out, t, progress);
        }
        EXPECT_EQ(stats.reordered, budget != 0 && m == &big)
          << algorithm << " budget " << budget << " triangles " << m->tris.size() / 3;
        EXPECT_FALSE(stats.storage.usedOutOfCore) << algorithm;
        EXPECT_GT(stats.layoutFarFraction, 0.5) << algorithm;
        EXPECT_GT(out.tris.size(), 0u) << algorithm;
      }
    }
  }
}

} // namespace
