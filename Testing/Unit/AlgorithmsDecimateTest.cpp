// Tests of Algorithm I (sipmss::algorithms::Decimate): topology guarantees, geometry, point data,
// levels of detail, mode independence, abort, and timings on real and generated meshes.
#include "sipmss/algorithms/Compare.h"
#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/Simplify.h"

#include "StorageTestUtil.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <map>
#include <limits>
#include <numeric>
#include <set>
#include <string>
#include <vector>

#include <unistd.h>

namespace
{
namespace alg = sipmss::algorithms;
namespace io = sipmss::io;
namespace st = sipmss::storage;

struct Mesh
{
  std::vector<float> xyz;
  std::vector<std::uint32_t> tris;
  std::vector<float> normals;
  std::vector<std::uint8_t> rgba;
  std::vector<float> scalars; // scalarNames.size() per vertex
  std::vector<std::string> scalarNames;
  std::vector<std::uint8_t> faceFlags; // one per triangle: the face scalar faceName (a selection)
  std::string faceName;
  std::size_t Vertices() const { return this->xyz.size() / 3; }
  std::size_t Triangles() const { return this->tris.size() / 3; }
  std::array<double, 3> P(std::size_t i) const
  {
    return { this->xyz[3 * i], this->xyz[3 * i + 1], this->xyz[3 * i + 2] };
  }
};

// Streams a Mesh in chunks. announce=false: counts 0 in the header (like OBJ/STL);
// interleave=true: triangles are sent as soon as their vertices have been (like OBJ).
alg::MeshSource MemorySource(const Mesh& m, bool announce = true, bool interleave = false)
{
  return [&m, announce, interleave](io::MeshSink& sink, const io::ReadOptions& options) {
    io::MeshHeader h;
    h.format = io::Format::Unknown;
    h.vertexCount = announce ? m.Vertices() : 0;
    h.faceCount = announce ? m.Triangles() : 0;
    h.layout.normals = !m.normals.empty();
    h.layout.colors = !m.rgba.empty();
    h.layout.scalars = m.scalarNames;
    if (!m.faceName.empty())
    {
      h.faceScalars = { "other", m.faceName };
    }
    sink.Begin(h);
    const bool flags = !m.faceName.empty() && options.faceFlag == m.faceName;
    auto send = [&](std::size_t first, std::size_t count) {
      sink.Triangles(&m.tris[3 * first], count);
      if (flags)
      {
        sink.TriangleFlags(&m.faceFlags[first], count);
      }
    };
    const std::size_t chunk = interleave ? 37 : std::max<std::size_t>(options.chunkElements, 1);
    const std::size_t ns = m.scalarNames.size();
    std::size_t sentTris = 0;
    auto sendTris = [&](std::size_t verticesSent) {
      std::size_t end = sentTris;
      while (end < m.Triangles())
      {
        const std::uint32_t* t = &m.tris[3 * end];
        if (std::max({ t[0], t[1], t[2] }) >= verticesSent)
        {
          break;
        }
        ++end;
      }
      if (end > sentTris)
      {
        send(sentTris, end - sentTris);
        sentTris = end;
      }
    };
    for (std::size_t first = 0; first < m.Vertices(); first += chunk)
    {
      io::VertexChunk c;
      c.first = first;
      c.count = std::min(chunk, m.Vertices() - first);
      c.xyz = &m.xyz[3 * first];
      c.normals = m.normals.empty() ? nullptr : &m.normals[3 * first];
      c.rgba = m.rgba.empty() ? nullptr : &m.rgba[4 * first];
      c.scalars = ns ? &m.scalars[ns * first] : nullptr;
      sink.Vertices(c);
      if (interleave)
      {
        sendTris(first + c.count);
      }
    }
    io::ReadStats rs;
    rs.vertices = m.Vertices();
    if (!options.verticesOnly)
    {
      for (std::size_t first = sentTris; first < m.Triangles(); first += chunk)
      {
        send(first, std::min(chunk, m.Triangles() - first));
      }
      rs.triangles = m.Triangles();
      rs.polygons = m.Triangles();
    }
    sink.End(rs);
    return rs;
  };
}

class CollectSink final : public io::MeshSink
{
public:
  Mesh mesh;
  io::MeshHeader header;
  bool ended = false;
  void Begin(const io::MeshHeader& h) override
  {
    this->header = h;
    this->mesh = Mesh();
    this->mesh.scalarNames = h.layout.scalars;
    this->ended = false;
  }
  void Vertices(const io::VertexChunk& c) override
  {
    EXPECT_EQ(c.first, this->mesh.Vertices());
    const std::size_t ns = this->mesh.scalarNames.size();
    this->mesh.xyz.insert(this->mesh.xyz.end(), c.xyz, c.xyz + 3 * c.count);
    if (c.normals)
    {
      this->mesh.normals.insert(this->mesh.normals.end(), c.normals, c.normals + 3 * c.count);
    }
    if (c.rgba)
    {
      this->mesh.rgba.insert(this->mesh.rgba.end(), c.rgba, c.rgba + 4 * c.count);
    }
    if (c.scalars)
    {
      this->mesh.scalars.insert(this->mesh.scalars.end(), c.scalars, c.scalars + ns * c.count);
    }
  }
  void Triangles(const std::uint32_t* idx, std::size_t n) override
  {
    this->mesh.tris.insert(this->mesh.tris.end(), idx, idx + 3 * n);
  }
  void End(const io::ReadStats&) override { this->ended = true; }
};

// ---- generators

Mesh Tetrahedron()
{
  Mesh m;
  m.xyz = { 0, 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1 };
  m.tris = { 0, 2, 1, 0, 1, 3, 0, 3, 2, 1, 2, 3 };
  return m;
}

// n x n quads on [0,1]^2 split into triangles; quads with hole(i, j) true are left out.
template <class Hole>
Mesh Grid(int n, Hole hole, double (*height)(double, double) = nullptr)
{
  Mesh m;
  for (int j = 0; j <= n; ++j)
  {
    for (int i = 0; i <= n; ++i)
    {
      double x = double(i) / n, y = double(j) / n;
      m.xyz.push_back(float(x));
      m.xyz.push_back(float(y));
      m.xyz.push_back(float(height ? height(x, y) : 0.0));
    }
  }
  auto id = [n](int i, int j) { return std::uint32_t(j * (n + 1) + i); };
  for (int j = 0; j < n; ++j)
  {
    for (int i = 0; i < n; ++i)
    {
      if (hole(i, j))
      {
        continue;
      }
      // alternate the diagonal so that the mesh is not biased
      if ((i + j) % 2 == 0)
      {
        m.tris.insert(m.tris.end(), { id(i, j), id(i + 1, j), id(i + 1, j + 1) });
        m.tris.insert(m.tris.end(), { id(i, j), id(i + 1, j + 1), id(i, j + 1) });
      }
      else
      {
        m.tris.insert(m.tris.end(), { id(i, j), id(i + 1, j), id(i, j + 1) });
        m.tris.insert(m.tris.end(), { id(i + 1, j), id(i + 1, j + 1), id(i, j + 1) });
      }
    }
  }
  return m;
}
Mesh Grid(int n, double (*height)(double, double) = nullptr)
{
  return Grid(n, [](int, int) { return false; }, height);
}

double Bumps(double x, double y)
{
  return 0.05 * std::sin(9.0 * x) * std::cos(7.0 * y) + 0.02 * std::sin(23.0 * x + 11.0 * y);
}

double SphereBump(double x, double y, double z)
{
  return 1.0 + 0.06 * std::sin(5.0 * x) * std::sin(6.0 * y) * std::sin(4.0 * z + 1.0);
}

// A subdivided icosahedron (closed, 20 * 4^levels triangles) with radial bumps.
Mesh BumpySphere(int levels)
{
  Mesh m;
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<std::array<double, 3>> p = { { -1, t, 0 }, { 1, t, 0 }, { -1, -t, 0 }, { 1, -t, 0 },
    { 0, -1, t }, { 0, 1, t }, { 0, -1, -t }, { 0, 1, -t }, { t, 0, -1 }, { t, 0, 1 },
    { -t, 0, -1 }, { -t, 0, 1 } };
  for (auto& q : p)
  {
    double l = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
    q = { q[0] / l, q[1] / l, q[2] / l };
  }
  std::vector<std::uint32_t> f = { 0, 11, 5, 0, 5, 1, 0, 1, 7, 0, 7, 10, 0, 10, 11, 1, 5, 9, 5, 11,
    4, 11, 10, 2, 10, 7, 6, 7, 1, 8, 3, 9, 4, 3, 4, 2, 3, 2, 6, 3, 6, 8, 3, 8, 9, 4, 9, 5, 2, 4,
    11, 6, 2, 10, 8, 6, 7, 9, 8, 1 };
  for (int l = 0; l < levels; ++l)
  {
    std::map<std::pair<std::uint32_t, std::uint32_t>, std::uint32_t> mid;
    auto midpoint = [&](std::uint32_t a, std::uint32_t b) {
      auto key = std::make_pair(std::min(a, b), std::max(a, b));
      auto it = mid.find(key);
      if (it != mid.end())
      {
        return it->second;
      }
      std::array<double, 3> q = { p[a][0] + p[b][0], p[a][1] + p[b][1], p[a][2] + p[b][2] };
      double len = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2]);
      p.push_back({ q[0] / len, q[1] / len, q[2] / len });
      mid[key] = std::uint32_t(p.size() - 1);
      return std::uint32_t(p.size() - 1);
    };
    std::vector<std::uint32_t> g;
    for (std::size_t i = 0; i < f.size(); i += 3)
    {
      std::uint32_t a = f[i], b = f[i + 1], c = f[i + 2];
      std::uint32_t ab = midpoint(a, b), bc = midpoint(b, c), ca = midpoint(c, a);
      g.insert(g.end(), { a, ab, ca, b, bc, ab, c, ca, bc, ab, bc, ca });
    }
    f.swap(g);
  }
  for (auto& q : p)
  {
    double r = SphereBump(q[0], q[1], q[2]);
    m.xyz.insert(m.xyz.end(), { float(q[0] * r), float(q[1] * r), float(q[2] * r) });
  }
  m.tris = f;
  return m;
}

// ---- topology and geometry helpers

using Edge = std::pair<std::uint32_t, std::uint32_t>;
std::map<Edge, int> EdgeUse(const Mesh& m)
{
  std::map<Edge, int> use;
  for (std::size_t i = 0; i < m.tris.size(); i += 3)
  {
    for (int k = 0; k < 3; ++k)
    {
      std::uint32_t a = m.tris[i + k], b = m.tris[i + (k + 1) % 3];
      ++use[{ std::min(a, b), std::max(a, b) }];
    }
  }
  return use;
}

int BoundaryLoops(const Mesh& m)
{
  std::map<std::uint32_t, std::vector<std::uint32_t>> adj;
  for (auto& [e, n] : EdgeUse(m))
  {
    if (n == 1)
    {
      adj[e.first].push_back(e.second);
      adj[e.second].push_back(e.first);
    }
  }
  std::set<std::uint32_t> seen;
  int loops = 0;
  for (auto& [v, nbs] : adj)
  {
    if (seen.count(v))
    {
      continue;
    }
    ++loops;
    std::vector<std::uint32_t> stack = { v };
    while (!stack.empty())
    {
      std::uint32_t x = stack.back();
      stack.pop_back();
      if (!seen.insert(x).second)
      {
        continue;
      }
      for (std::uint32_t y : adj[x])
      {
        stack.push_back(y);
      }
    }
  }
  return loops;
}

std::array<double, 3> FaceNormal(const Mesh& m, std::size_t f)
{
  auto a = m.P(m.tris[3 * f]), b = m.P(m.tris[3 * f + 1]), c = m.P(m.tris[3 * f + 2]);
  double u[3] = { b[0] - a[0], b[1] - a[1], b[2] - a[2] };
  double v[3] = { c[0] - a[0], c[1] - a[1], c[2] - a[2] };
  return { u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0] };
}

bool HasVertex(const Mesh& m, double x, double y, double z)
{
  for (std::size_t i = 0; i < m.Vertices(); ++i)
  {
    auto p = m.P(i);
    if (p[0] == float(x) && p[1] == float(y) && p[2] == float(z))
    {
      return true;
    }
  }
  return false;
}

struct Outcome
{
  Mesh out;
  alg::RunStats stats;
  double seconds = 0;
};

Outcome Simplify(const alg::MeshSource& src, const alg::DecimateOptions& o)
{
  Outcome r;
  CollectSink sink;
  alg::NullProgress progress;
  auto t0 = std::chrono::steady_clock::now();
  r.stats = alg::Decimate(src, sink, o, progress);
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  EXPECT_TRUE(sink.ended);
  EXPECT_EQ(sink.header.vertexCount, sink.mesh.Vertices());
  EXPECT_EQ(sink.header.faceCount, sink.mesh.Triangles());
  r.out = std::move(sink.mesh);
  return r;
}

// The message of the error a run ends with (empty: it ran).
std::string RunError(const Mesh& m, const alg::DecimateOptions& o)
{
  try
  {
    Simplify(MemorySource(m), o);
  }
  catch (const std::exception& e)
  {
    return e.what();
  }
  return {};
}

// The same output bytes: vertices, triangles, positions and point data.
void ExpectSameOutput(const Outcome& a, const Outcome& b, const std::string& what)
{
  ASSERT_EQ(a.out.Vertices(), b.out.Vertices()) << what;
  EXPECT_TRUE(a.out.tris == b.out.tris) << what;
  auto sameBytes = [](const std::vector<float>& x, const std::vector<float>& y) {
    return x.size() == y.size() &&
      (x.empty() || std::memcmp(x.data(), y.data(), x.size() * sizeof(float)) == 0);
  };
  EXPECT_TRUE(sameBytes(a.out.xyz, b.out.xyz)) << what;
  EXPECT_TRUE(sameBytes(a.out.scalars, b.out.scalars)) << what;
  EXPECT_TRUE(a.out.rgba == b.out.rgba) << what;
}

void ExpectValid(const Mesh& m)
{
  std::set<std::array<std::uint32_t, 3>> seen;
  std::vector<bool> used(m.Vertices(), false);
  for (std::size_t i = 0; i < m.tris.size(); i += 3)
  {
    std::array<std::uint32_t, 3> t = { m.tris[i], m.tris[i + 1], m.tris[i + 2] };
    for (auto v : t)
    {
      ASSERT_LT(v, m.Vertices());
      used[v] = true;
    }
    ASSERT_NE(t[0], t[1]);
    ASSERT_NE(t[1], t[2]);
    ASSERT_NE(t[0], t[2]);
    std::sort(t.begin(), t.end());
    EXPECT_TRUE(seen.insert(t).second) << "duplicate triangle";
  }
  EXPECT_EQ(std::count(used.begin(), used.end(), false), 0) << "unreferenced output vertices";
}

std::string PhaseSummary(const alg::RunStats& s)
{
  std::string out;
  for (const auto& p : s.phases)
  {
    char buf[96];
    std::snprintf(buf, sizeof(buf), "%s %.3fs (%s) ", p.name.c_str(), p.seconds,
      st::ToString(p.mode));
    out += buf;
  }
  return out;
}

// ---- tests

TEST(AlgorithmsDecimate, TetrahedronStaysClosed)
{
  Mesh tet = Tetrahedron();
  alg::DecimateOptions o;
  o.targetTriangles = 1;
  Outcome r = Simplify(MemorySource(tet), o);
  ASSERT_EQ(r.out.Triangles(), 4u);
  EXPECT_EQ(r.out.Vertices(), 4u);
  for (auto& [e, n] : EdgeUse(r.out))
  {
    EXPECT_EQ(n, 2) << "edge " << e.first << "-" << e.second;
  }
  EXPECT_EQ(r.stats.inputTriangles, 4u);
  EXPECT_EQ(r.stats.outputTriangles, 4u);
}

TEST(AlgorithmsDecimate, ClosedSphereStaysClosedAndManifold)
{
  Mesh s = BumpySphere(3); // 1280 triangles
  alg::DecimateOptions o;
  o.targetTriangles = 20;
  Outcome r = Simplify(MemorySource(s), o);
  ExpectValid(r.out);
  EXPECT_LE(r.out.Triangles(), 20u);
  EXPECT_GE(r.out.Triangles(), 4u);
  for (auto& [e, n] : EdgeUse(r.out))
  {
    EXPECT_EQ(n, 2);
  }
  // Euler characteristic of a sphere.
  EXPECT_EQ(
    std::int64_t(r.out.Vertices()) - std::int64_t(EdgeUse(r.out).size()) + std::int64_t(r.out.Triangles()),
    2);
}

// s decimated to 300 triangles on `threads` threads within `budget` (0: unbounded).
Outcome ToThreeHundred(const Mesh& s, int threads, std::uint64_t budget)
{
  alg::DecimateOptions o;
  o.targetTriangles = 300;
  o.threads = threads;
  o.storage.memoryBudget = budget;
  return Simplify(MemorySource(s), o);
}

// RunStats::passes: each pass's sizes chain from the input's to the output's, the first pass
// places every edge of a closed surface once, and the counts do not depend on the threads or
// the mode (only the times and the I/O do).
TEST(AlgorithmsDecimate, PassesAreReported)
{
  Mesh s = BumpySphere(5); // 20480 triangles, closed
  const std::uint64_t F = s.Triangles();
  auto run = [&](int threads, std::uint64_t budget) { return ToThreeHundred(s, threads, budget); };
  const Outcome one = run(1, 0), two = run(2, 0), paged = run(1, 64 * 1024);
  for (const Outcome* r : { &one, &two, &paged })
  {
    const auto& P = r->stats.passes;
    ASSERT_GE(P.size(), 2u);
    EXPECT_EQ(P.front().triangles, F);
    EXPECT_EQ(P.front().activeVertices, P.front().vertices); // every vertex starts afresh
    EXPECT_EQ(P.front().edgesPlaced, 3 * F / 2); // each edge of the closed surface once
    EXPECT_EQ(P.back().trianglesAfter, r->out.Triangles());
    double seconds = 0;
    for (std::size_t i = 0; i < P.size(); ++i)
    {
      const alg::PassStat& p = P[i];
      EXPECT_EQ(p.run, "");
      EXPECT_LE(p.trianglesAfter, p.triangles) << i;
      EXPECT_GE(p.trianglesAfter + 1, p.goal) << i; // (a collapse takes two; levels exactly)
      EXPECT_LE(p.activeVertices, p.vertices) << i;
      EXPECT_LE(p.collapses + p.illegal, p.candidates) << i;
      EXPECT_GT(p.collapses, 0u) << i;
      if (i + 1 < P.size())
      {
        EXPECT_EQ(P[i + 1].triangles, p.trianglesAfter) << i;
        EXPECT_LT(P[i + 1].vertices, p.vertices) << i;
      }
      seconds += p.sweep.seconds + p.order.seconds + p.step.seconds + p.compact.seconds;
    }
    double collapse = -1;
    for (const auto& ph : r->stats.phases)
    {
      collapse = ph.name == "collapse" ? ph.seconds : collapse;
    }
    EXPECT_LE(seconds, collapse + 1e-6); // (the passes' steps are laps inside that phase)
  }
  ASSERT_EQ(one.stats.passes.size(), two.stats.passes.size());
  ASSERT_EQ(one.stats.passes.size(), paged.stats.passes.size());
  bool outOfCore = false;
  for (std::size_t i = 0; i < one.stats.passes.size(); ++i)
  {
    for (const Outcome* r : { &two, &paged })
    {
      const alg::PassStat &a = one.stats.passes[i], &b = r->stats.passes[i];
      EXPECT_EQ(a.vertices, b.vertices) << i;
      EXPECT_EQ(a.triangles, b.triangles) << i;
      EXPECT_EQ(a.goal, b.goal) << i;
      EXPECT_EQ(a.trianglesAfter, b.trianglesAfter) << i;
      EXPECT_EQ(a.activeVertices, b.activeVertices) << i;
      EXPECT_EQ(a.edgesPlaced, b.edgesPlaced) << i;
      EXPECT_EQ(a.candidates, b.candidates) << i;
      EXPECT_EQ(a.collapses, b.collapses) << i;
      EXPECT_EQ(a.illegal, b.illegal) << i;
    }
    EXPECT_EQ(one.stats.passes[i].sweep.bytesRead + one.stats.passes[i].compact.bytesWritten, 0u) << i;
    const alg::PassStat& p = paged.stats.passes[i];
    outOfCore = outOfCore ||
      (p.mode == st::Mode::OutOfCore && p.sweep.bytesRead > 0 && p.step.misses > 0 &&
        p.compact.bytesWritten > 0);
  }
  EXPECT_TRUE(outOfCore) << "the 64 KiB run read no pass from its files";
}

// PassStat::Step::arrays: out of core, each step's I/O by array, in the documented order, adding
// up to the step's totals (on one thread and through a forked helper); in core, none.
TEST(AlgorithmsDecimate, PassesReportTheirIoByArray)
{
  Mesh s = BumpySphere(5); // 20480 triangles
  auto run = [&](int threads, std::uint64_t budget) { return ToThreeHundred(s, threads, budget); };
  const std::vector<std::string> names = { "positions", "quadrics", "faces", "ring offsets",
    "ring faces", "states", "candidates", "order", "remap", "attributes", "attribute terms",
    "fit samples", "face selection", "fitted positions", "other" };
  const Outcome inCore = run(2, 0);
  for (const alg::PassStat& p : inCore.stats.passes)
  {
    for (const auto* st : { &p.sweep, &p.order, &p.step, &p.compact })
    {
      EXPECT_TRUE(st->arrays.empty());
    }
  }
  std::map<std::string, std::uint64_t> sweepMisses;
  for (int threads : { 1, 2 })
  {
    const Outcome paged = run(threads, 64 * 1024);
    ASSERT_EQ(paged.out.Triangles(), inCore.out.Triangles());
    std::uint64_t listed = 0;
    for (std::size_t i = 0; i < paged.stats.passes.size(); ++i)
    {
      const alg::PassStat& p = paged.stats.passes[i];
      for (const auto* st : { &p.sweep, &p.order, &p.step, &p.compact })
      {
        std::uint64_t misses = 0, read = 0, written = 0;
        std::size_t at = 0;
        for (const alg::PassStat::ArrayIo& a : st->arrays)
        {
          const auto k = std::find(names.begin(), names.end(), a.name);
          ASSERT_NE(k, names.end()) << a.name;
          const std::size_t rank = std::size_t(k - names.begin());
          EXPECT_GE(rank + 1, at + 1) << a.name << " out of order";
          EXPECT_GT(a.misses + a.bytesRead + a.bytesWritten, 0u) << a.name;
          at = rank + 1;
          misses += a.misses;
          read += a.bytesRead;
          written += a.bytesWritten;
          if (threads == 1 && st == &p.sweep && i == 0)
          {
            sweepMisses[a.name] += a.misses;
          }
        }
        EXPECT_EQ(misses, st->misses) << i;
        EXPECT_EQ(read, st->bytesRead) << i;
        EXPECT_EQ(written, st->bytesWritten) << i;
        listed += st->arrays.size();
      }
    }
    EXPECT_GT(listed, 0u) << threads;
  }
  // The first sweep reads every vertex's position and quadric and its ring's faces.
  for (const char* a : { "positions", "quadrics", "faces", "ring faces" })
  {
    EXPECT_GT(sweepMisses[a], 0u) << a;
  }
  EXPECT_EQ(sweepMisses["other"], 0u);
}

TEST(AlgorithmsDecimate, FlatSquareCollapsesToTwoTrianglesOnItsCorners)
{
  Mesh g = Grid(8); // 128 triangles
  alg::DecimateOptions o;
  o.targetTriangles = 2;
  Outcome r = Simplify(MemorySource(g), o);
  ASSERT_EQ(r.out.Triangles(), 2u);
  ASSERT_EQ(r.out.Vertices(), 4u);
  EXPECT_TRUE(HasVertex(r.out, 0, 0, 0));
  EXPECT_TRUE(HasVertex(r.out, 1, 0, 0));
  EXPECT_TRUE(HasVertex(r.out, 0, 1, 0));
  EXPECT_TRUE(HasVertex(r.out, 1, 1, 0));
  // Same orientation as the input (+z).
  for (std::size_t f = 0; f < r.out.Triangles(); ++f)
  {
    EXPECT_GT(FaceNormal(r.out, f)[2], 0.0);
  }
}

TEST(AlgorithmsDecimate, HoleKeepsItsBoundary)
{
  // 12 x 12 grid with a 4 x 4 square hole in the middle.
  Mesh g = Grid(12, [](int i, int j) { return i >= 4 && i < 8 && j >= 4 && j < 8; });
  ASSERT_EQ(BoundaryLoops(g), 2);
  for (std::uint64_t target : { 100u, 40u, 8u })
  {
    alg::DecimateOptions o;
    o.targetTriangles = target;
    Outcome r = Simplify(MemorySource(g), o);
    ExpectValid(r.out);
    EXPECT_LE(r.out.Triangles(), std::max<std::uint64_t>(target, 16)) << "target " << target;
    int boundaryEdges = 0;
    for (auto& [e, n] : EdgeUse(r.out))
    {
      EXPECT_LE(n, 2);
      boundaryEdges += n == 1;
    }
    EXPECT_GT(boundaryEdges, 0);
    EXPECT_EQ(BoundaryLoops(r.out), 2) << "the hole must stay open, target " << target;
    for (double x : { 0.0, 1.0 })
    {
      for (double y : { 0.0, 1.0 })
      {
        EXPECT_TRUE(HasVertex(r.out, x, y, 0)) << x << "," << y << " target " << target;
      }
    }
    // The hole's corners too.
    for (double x : { 4.0 / 12, 8.0 / 12 })
    {
      for (double y : { 4.0 / 12, 8.0 / 12 })
      {
        EXPECT_TRUE(HasVertex(r.out, x, y, 0)) << x << "," << y << " target " << target;
      }
    }
  }
}

// A flat disc: one center vertex with n faces around it. Collapsing the center into a rim vertex
// costs nothing, so the step meets rings of n and 2 faces (above LegalFaces' product bound:
// the sorted-table path), and later rings of every size down to a few faces.
TEST(AlgorithmsDecimate, HighValenceFanStaysAFlatDisc)
{
  const std::uint32_t n = 600;
  Mesh d;
  d.xyz = { 0, 0, 0 };
  for (std::uint32_t i = 0; i < n; ++i)
  {
    const double a = 2 * 3.14159265358979323846 * i / n;
    d.xyz.insert(d.xyz.end(), { float(std::cos(a)), float(std::sin(a)), 0.0f });
  }
  for (std::uint32_t i = 0; i < n; ++i)
  {
    d.tris.insert(d.tris.end(), { 0, 1 + i, 1 + (i + 1) % n });
  }
  alg::DecimateOptions o;
  o.targetTriangles = 60;
  Outcome a = Simplify(MemorySource(d), o);
  ExpectValid(a.out);
  EXPECT_LE(a.out.Triangles(), 60u);
  EXPECT_GE(a.out.Triangles(), 40u);
  EXPECT_EQ(BoundaryLoops(a.out), 1);
  for (auto& [e, c] : EdgeUse(a.out))
  {
    EXPECT_LE(c, 2);
  }
  for (std::size_t f = 0; f < a.out.Triangles(); ++f)
  {
    EXPECT_GT(FaceNormal(a.out, f)[2], 0.0) << "face " << f << " flipped or degenerate";
  }
  for (std::size_t i = 0; i < a.out.Vertices(); ++i)
  {
    const auto p = a.out.P(i);
    EXPECT_EQ(p[2], 0.0);
    // (Boundary constraint lines of neighbouring rim edges meet just outside the circle.)
    EXPECT_LE(std::sqrt(p[0] * p[0] + p[1] * p[1]), 1.01) << "vertex " << i << " left the disc";
  }
  o.storage.policy = st::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  Outcome b = Simplify(MemorySource(d), o);
  EXPECT_TRUE(b.stats.storage.usedOutOfCore);
  ExpectSameOutput(a, b, "disc in core / out of core");
}

TEST(AlgorithmsDecimate, LockBoundaryKeepsEveryBoundaryVertex)
{
  Mesh g = Grid(16, Bumps);
  alg::DecimateOptions o;
  o.targetTriangles = 150;
  o.lockBoundary = true;
  Outcome r = Simplify(MemorySource(g), o);
  ExpectValid(r.out);
  for (int i = 0; i <= 16; ++i)
  {
    double s = double(i) / 16;
    EXPECT_TRUE(HasVertex(r.out, s, 0, Bumps(s, 0)));
    EXPECT_TRUE(HasVertex(r.out, s, 1, Bumps(s, 1)));
    EXPECT_TRUE(HasVertex(r.out, 0, s, Bumps(0, s)));
    EXPECT_TRUE(HasVertex(r.out, 1, s, Bumps(1, s)));
  }
}

// Locks by a point array: every vertex where it is not 0 keeps its position and stays, in core
// and out of core; without the array they would go (the same target removes some of them).
// Puts an unused vertex far away first: positions are kept relative to the first vertex, so the
// mesh's own are then large numbers with fine digits (a float would round them), and a locked
// vertex must still come back bit for bit.
void PrependFarVertex(Mesh& m)
{
  m.xyz.insert(m.xyz.begin(), { -1000.0f, 700.0f, -300.0f });
  for (std::uint32_t& v : m.tris)
  {
    ++v;
  }
  m.scalars.insert(m.scalars.begin(), m.scalarNames.size(), 0.0f);
}

TEST(AlgorithmsDecimate, LockArrayKeepsItsVerticesWhereTheyAre)
{
  Mesh g = Grid(24, Bumps);
  PrependFarVertex(g);
  g.scalarNames = { "lock" };
  std::vector<std::size_t> locked;
  for (std::size_t i = 0; i < g.Vertices(); ++i)
  {
    const bool lock = (i % 7) == 3;
    g.scalars.push_back(lock ? 1.0f : 0.0f);
    if (lock)
    {
      locked.push_back(i);
    }
  }
  alg::DecimateOptions o;
  o.targetTriangles = 200;
  Outcome free = Simplify(MemorySource(g), o);
  std::size_t kept = 0;
  for (std::size_t i : locked)
  {
    auto p = g.P(i);
    kept += HasVertex(free.out, p[0], p[1], p[2]) ? 1 : 0;
  }
  EXPECT_LT(kept, locked.size() / 2) << "the test needs a target that removes locked vertices";
  o.lockArray = "lock";
  for (const bool outOfCore : { false, true })
  {
    o.storage.policy = outOfCore ? st::ModePolicy::OutOfCore : st::ModePolicy::Automatic;
    o.storage.memoryBudget = outOfCore ? 64 * 1024 : 0;
    Outcome r = Simplify(MemorySource(g), o);
    ExpectValid(r.out);
    EXPECT_LT(r.out.Triangles(), g.Triangles() / 2);
    for (std::size_t i : locked)
    {
      auto p = g.P(i);
      EXPECT_TRUE(HasVertex(r.out, p[0], p[1], p[2])) << "locked vertex " << i << " moved or went";
    }
  }
  // An array the input does not have is an error that names it and the input's arrays.
  o.lockArray = "missing";
  const std::string missing = RunError(g, o);
  EXPECT_NE(missing.find("'missing'"), std::string::npos) << missing;
  EXPECT_NE(missing.find("its point arrays: lock)"), std::string::npos) << missing;
  // Welding would merge locked vertices into others: refused by the request's rules.
  alg::SimplifyRequest request;
  request.algorithm = alg::Algorithm::Decimate;
  request.lockArray = "lock";
  request.weldDistance = 0.01;
  const auto problems = alg::Problems(request);
  ASSERT_EQ(problems.size(), 1u);
  EXPECT_EQ(problems[0].parameter, alg::Parameter::WeldDistance);
}

// A selection by a point array: every triangle with no selected vertex is in the output as it
// was (the same corners, the same order); the selected part is simplified.
TEST(AlgorithmsDecimate, SelectionArrayKeepsEverythingOutsideIt)
{
  Mesh g = Grid(24, Bumps);
  g.scalarNames = { "region" };
  for (std::size_t i = 0; i < g.Vertices(); ++i)
  {
    g.scalars.push_back(g.P(i)[0] > 0.5 ? 1.0f : 0.0f);
  }
  PrependFarVertex(g);
  alg::DecimateOptions o;
  o.targetTriangles = 10;
  o.selectionArray = "region";
  Outcome r = Simplify(MemorySource(g), o);
  ExpectValid(r.out);
  EXPECT_LT(r.out.Triangles(), g.Triangles() * 3 / 4) << "the selected half is simplified";
  using Corner = std::array<float, 3>;
  auto corners = [](const Mesh& m, std::size_t f) {
    std::array<Corner, 3> c;
    for (int k = 0; k < 3; ++k)
    {
      const std::uint32_t v = m.tris[3 * f + k];
      c[k] = { m.xyz[3 * v], m.xyz[3 * v + 1], m.xyz[3 * v + 2] };
    }
    // (a rotation that starts at the smallest corner: the same triangle whatever its first)
    const int m0 = int(std::min_element(c.begin(), c.end()) - c.begin());
    return std::array<Corner, 3>{ c[m0], c[(m0 + 1) % 3], c[(m0 + 2) % 3] };
  };
  std::set<std::array<Corner, 3>> output;
  for (std::size_t f = 0; f < r.out.Triangles(); ++f)
  {
    output.insert(corners(r.out, f));
  }
  std::size_t outside = 0;
  for (std::size_t f = 0; f < g.Triangles(); ++f)
  {
    bool selected = false;
    for (int k = 0; k < 3; ++k)
    {
      selected |= g.scalars[g.tris[3 * f + k]] != 0.0f;
    }
    if (!selected)
    {
      ++outside;
      EXPECT_EQ(output.count(corners(g, f)), 1u) << "triangle " << f << " outside the selection";
    }
  }
  EXPECT_GT(outside, g.Triangles() / 3);
}

TEST(AlgorithmsDecimate, NoFlippedFacesOnBumpySphereAndTerrain)
{
  {
    Mesh s = BumpySphere(5); // 20480 triangles
    alg::DecimateOptions o;
    o.targetReduction = 0.9;
    Outcome r = Simplify(MemorySource(s), o);
    ExpectValid(r.out);
    EXPECT_LE(r.out.Triangles(), 2048u);
    EXPECT_GE(r.out.Triangles(), 2000u);
    for (std::size_t f = 0; f < r.out.Triangles(); ++f)
    {
      auto n = FaceNormal(r.out, f);
      auto a = r.out.P(r.out.tris[3 * f]), b = r.out.P(r.out.tris[3 * f + 1]),
           c = r.out.P(r.out.tris[3 * f + 2]);
      double cx = a[0] + b[0] + c[0], cy = a[1] + b[1] + c[1], cz = a[2] + b[2] + c[2];
      double len = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
      double cl = std::sqrt(cx * cx + cy * cy + cz * cz);
      ASSERT_GT(len, 0.0);
      // The bumps tilt the true normal by < 25 degrees from the radial direction.
      EXPECT_GT((n[0] * cx + n[1] * cy + n[2] * cz) / (len * cl), 0.0) << "face " << f;
    }
    for (auto& [e, n] : EdgeUse(r.out))
    {
      EXPECT_EQ(n, 2);
    }
    // Vertices stay near the surface.
    double worst = 0;
    for (std::size_t i = 0; i < r.out.Vertices(); ++i)
    {
      auto p = r.out.P(i);
      double l = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
      worst = std::max(worst, std::abs(l - SphereBump(p[0] / l, p[1] / l, p[2] / l)));
    }
    EXPECT_LT(worst, 0.02);
  }
  {
    Mesh g = Grid(64, Bumps); // 8192 triangles
    alg::DecimateOptions o;
    o.targetReduction = 0.9;
    Outcome r = Simplify(MemorySource(g), o);
    ExpectValid(r.out);
    for (std::size_t f = 0; f < r.out.Triangles(); ++f)
    {
      auto n = FaceNormal(r.out, f);
      EXPECT_GT(n[2], 0.0) << "face " << f;
    }
    for (std::size_t i = 0; i < r.out.Vertices(); ++i)
    {
      auto p = r.out.P(i);
      EXPECT_NEAR(p[2], Bumps(p[0], p[1]), 0.01);
    }
  }
}

Mesh ColoredSphere(int levels)
{
  Mesh s = BumpySphere(levels);
  s.scalarNames = { "x", "quality" };
  for (std::size_t i = 0; i < s.Vertices(); ++i)
  {
    auto p = s.P(i);
    s.scalars.push_back(float(p[0]));
    s.scalars.push_back(float(p[1] * p[2]));
    s.rgba.insert(s.rgba.end(), { std::uint8_t(127.5 + 127 * p[0]), std::uint8_t(127.5 + 127 * p[1]),
                                  std::uint8_t(127.5 + 127 * p[2]), 255 });
    double l = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    s.normals.insert(s.normals.end(), { float(p[0] / l), float(p[1] / l), float(p[2] / l) });
  }
  return s;
}

TEST(AlgorithmsDecimate, InCoreAndOutOfCoreAreIdentical)
{
  Mesh s = ColoredSphere(5);
  alg::DecimateOptions o;
  o.targetTriangles = 1500;
  o.levelsOfDetail = 3;
  Outcome a = Simplify(MemorySource(s), o);
  o.storage.policy = st::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  Outcome b = Simplify(MemorySource(s), o);
  EXPECT_TRUE(b.stats.storage.usedOutOfCore);
  EXPECT_EQ(a.stats.storage.usedOutOfCore, false);
  ASSERT_EQ(a.out.Triangles(), b.out.Triangles());
  ASSERT_EQ(a.out.Vertices(), b.out.Vertices());
  EXPECT_EQ(0, std::memcmp(a.out.xyz.data(), b.out.xyz.data(), a.out.xyz.size() * sizeof(float)));
  EXPECT_TRUE(a.out.tris == b.out.tris);
  EXPECT_EQ(0, std::memcmp(a.out.scalars.data(), b.out.scalars.data(), a.out.scalars.size() * 4));
  EXPECT_EQ(0, std::memcmp(a.out.normals.data(), b.out.normals.data(), a.out.normals.size() * 4));
  EXPECT_TRUE(a.out.rgba == b.out.rgba);
  // Automatic mode with a small budget: starts out of core, ends in core, same result.
  o.storage.policy = st::ModePolicy::Automatic;
  o.storage.memoryBudget = 512 * 1024;
  Outcome c = Simplify(MemorySource(s), o);
  EXPECT_TRUE(c.stats.storage.usedOutOfCore);
  EXPECT_TRUE(c.stats.storage.usedInCore);
  EXPECT_TRUE(a.out.tris == c.out.tris);
  EXPECT_EQ(0, std::memcmp(a.out.xyz.data(), c.out.xyz.data(), a.out.xyz.size() * sizeof(float)));
}

TEST(AlgorithmsDecimate, SweepThreadsDoNotChangeTheResult)
{
  // 40,962 vertices: the candidate sweep of the first passes runs split into ranges (in core),
  // with offers across ranges queued; the outcome must not depend on the split.
  Mesh s = ColoredSphere(6);
  alg::DecimateOptions o;
  o.targetTriangles = 2000;
  o.threads = 1;
  Outcome a = Simplify(MemorySource(s), o);
  for (int threads : { 2, 5 })
  {
    o.threads = threads;
    Outcome b = Simplify(MemorySource(s), o);
    ASSERT_EQ(a.out.Vertices(), b.out.Vertices()) << threads;
    EXPECT_TRUE(a.out.tris == b.out.tris) << threads;
    EXPECT_EQ(0, std::memcmp(a.out.xyz.data(), b.out.xyz.data(), a.out.xyz.size() * sizeof(float)))
      << threads;
    EXPECT_EQ(0, std::memcmp(a.out.scalars.data(), b.out.scalars.data(), a.out.scalars.size() * 4))
      << threads;
  }
}

// Defined below.
Mesh SortedAlongZ(const Mesh& m);

// The reference of the thread tests: s to 4,000 triangles on one thread, in core (o is set up
// for it and kept for the runs compared with it).
Outcome SingleThreadReference(const Mesh& s, alg::DecimateOptions& o)
{
  o.targetTriangles = 4000;
  o.threads = 1;
  Outcome a = Simplify(MemorySource(s), o);
  ExpectValid(a.out);
  EXPECT_EQ(a.out.Triangles(), 4000u);
  return a;
}

TEST(AlgorithmsDecimate, CompactionThreadsDoNotChangeTheResult)
{
  // 163,842 vertices with point data: compaction runs on several threads in the first passes
  // (the degrees and the rings by vertex range, the moves by array), and the outcome must be
  // the one of a single thread.
  Mesh s = SortedAlongZ(ColoredSphere(7));
  ASSERT_GE(s.Vertices(), 65536u);
  alg::DecimateOptions o;
  Outcome a = SingleThreadReference(s, o);
  for (int threads : { 2, 5 })
  {
    o.threads = threads;
    ExpectSameOutput(a, Simplify(MemorySource(s), o), std::to_string(threads) + " threads");
  }
}

// The vertices renumbered along z with their point data (the scanner order the step's chunks
// are made for: neighbours have near indices).
Mesh SortedAlongZ(const Mesh& m)
{
  const std::size_t n = m.Vertices();
  std::vector<std::uint32_t> order(n), rank(n);
  std::iota(order.begin(), order.end(), 0u);
  std::stable_sort(order.begin(), order.end(),
    [&m](std::uint32_t a, std::uint32_t b) { return m.xyz[3 * a + 2] < m.xyz[3 * b + 2]; });
  Mesh r = m;
  const std::size_t ns = m.scalarNames.size();
  for (std::size_t k = 0; k < n; ++k)
  {
    const std::uint32_t i = order[k];
    rank[i] = std::uint32_t(k);
    std::copy_n(&m.xyz[3 * i], 3, &r.xyz[3 * k]);
    if (!m.normals.empty())
    {
      std::copy_n(&m.normals[3 * i], 3, &r.normals[3 * k]);
    }
    if (!m.rgba.empty())
    {
      std::copy_n(&m.rgba[4 * i], 4, &r.rgba[4 * k]);
    }
    if (ns)
    {
      std::copy_n(&m.scalars[ns * i], ns, &r.scalars[ns * k]);
    }
  }
  for (std::uint32_t& v : r.tris)
  {
    v = rank[v];
  }
  return r;
}

// The faces sorted by their lowest vertex (with SortedAlongZ: the scanner order of volumetric
// reconstructions, where the collapse rounds' face split applies).
Mesh FacesByLowestVertex(Mesh m)
{
  const std::size_t nt = m.Triangles();
  std::vector<std::array<std::uint32_t, 3>> t(nt);
  for (std::size_t i = 0; i < nt; ++i)
  {
    t[i] = { m.tris[3 * i], m.tris[3 * i + 1], m.tris[3 * i + 2] };
  }
  std::stable_sort(t.begin(), t.end(), [](const auto& a, const auto& b) {
    return std::min({ a[0], a[1], a[2] }) < std::min({ b[0], b[1], b[2] });
  });
  for (std::size_t i = 0; i < nt; ++i)
  {
    std::copy(t[i].begin(), t[i].end(), &m.tris[3 * i]);
  }
  return m;
}

TEST(AlgorithmsDecimate, OutOfCoreHelperThreadsDoNotChangeTheResult)
{
  // 163,842 vertices with point data in scanner order, at 2 MiB: out of core, the phases run on
  // two threads, the second through forked DMLs (rings, quadrics, candidate sweeps, collapse
  // rounds split at the middle chunk boundary, compaction). The output must be the one in core
  // and the one of a single thread at the same budget.
  Mesh s = FacesByLowestVertex(SortedAlongZ(ColoredSphere(7)));
  ASSERT_GE(s.Vertices(), 65536u);
  alg::DecimateOptions o;
  Outcome a = SingleThreadReference(s, o);
  EXPECT_EQ(a.stats.storage.forks, 0u);
  namespace fs = std::filesystem;
  const fs::path dir =
    fs::temp_directory_path() / ("sipmss_decimate_helpers_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  o.storage.directories = { dir.string() };
  o.storage.memoryBudget = 2 << 20;
  Outcome one = Simplify(MemorySource(s), o);
  EXPECT_TRUE(one.stats.storage.usedOutOfCore);
  EXPECT_EQ(one.stats.storage.forks, 0u);
  ExpectSameOutput(a, one, "out of core, 1 thread");
  EXPECT_EQ(one.stats.achievedError, a.stats.achievedError); // (measured in the lazy sums)
  o.threads = 2;
  Outcome two = Simplify(MemorySource(s), o);
  EXPECT_TRUE(two.stats.storage.usedOutOfCore);
  // At least: rings (4), quadrics, and per pass the sweep, the rounds, compaction (4: the lazy
  // sums, the degrees, the moves, the rings).
  EXPECT_GE(two.stats.storage.forks, 12u);
  EXPECT_LE(two.stats.storage.peakBytes, o.storage.memoryBudget);
  ExpectSameOutput(a, two, "out of core, 2 threads");
  EXPECT_EQ(two.stats.achievedError, a.stats.achievedError);
  // With attributes in the error: the lazy sums also add the extensions, each thread those of
  // its own vertices.
  o.attributes = { { "quality", 2.0 }, { "colors", 0.5 } };
  o.threads = 1;
  o.storage.memoryBudget = 0;
  Outcome aa = Simplify(MemorySource(s), o);
  EXPECT_FALSE(aa.stats.storage.usedOutOfCore);
  o.threads = 2;
  o.storage.memoryBudget = 2 << 20;
  Outcome ab = Simplify(MemorySource(s), o);
  EXPECT_TRUE(ab.stats.storage.usedOutOfCore);
  EXPECT_GE(ab.stats.storage.forks, 12u);
  ExpectSameOutput(aa, ab, "attributes, out of core, 2 threads");
  EXPECT_EQ(ab.stats.achievedError, aa.stats.achievedError);
  EXPECT_FALSE(aa.out.tris == a.out.tris); // (the attributes changed the collapses)
  EXPECT_TRUE(fs::is_empty(dir)); // no file left behind
  fs::remove_all(dir);
}

TEST(AlgorithmsDecimate, AHelperThreadThatThrashesGivesWay)
{
  // At 1 MiB the halves of the budget cannot hold the sweep's and the compaction's pages: two
  // threads would miss 4.5 times as often as one (145K against 32K, measured with the guard
  // off). The forked sweep gives way to one thread when its misses pass ForkRecord::kThrash
  // reads of its files, and a phase that thrashed runs on one thread in the next passes: about
  // twice one thread's misses, and the same output. At 512 KiB the first pass's forked sweep
  // passes its miss limit midway and runs again on one thread from the start: the passes'
  // statistics still count their vertices and edges once, as one thread's run does (they were
  // counted twice).
  Mesh s = FacesByLowestVertex(SortedAlongZ(ColoredSphere(7)));
  alg::DecimateOptions o;
  Outcome a = SingleThreadReference(s, o);
  sipmss::storage::testing::TempDir dir;
  o.storage.directories = { dir.Path() };
  for (const std::uint64_t budget : { 1u << 20, 1u << 19 })
  {
    SCOPED_TRACE(budget);
    o.storage.memoryBudget = budget;
    o.threads = 1;
    Outcome one = Simplify(MemorySource(s), o);
    o.threads = 2;
    Outcome two = Simplify(MemorySource(s), o);
    EXPECT_TRUE(two.stats.storage.usedOutOfCore);
    EXPECT_GT(two.stats.storage.forks, 0u);
    EXPECT_LE(two.stats.storage.misses, 3 * one.stats.storage.misses);
    ExpectSameOutput(a, one, "1 thread");
    ExpectSameOutput(a, two, "2 threads");
    ASSERT_EQ(one.stats.passes.size(), two.stats.passes.size());
    for (std::size_t i = 0; i < one.stats.passes.size(); ++i)
    {
      EXPECT_EQ(one.stats.passes[i].activeVertices, two.stats.passes[i].activeVertices) << i;
      EXPECT_EQ(one.stats.passes[i].edgesPlaced, two.stats.passes[i].edgesPlaced) << i;
    }
  }
  EXPECT_TRUE(sipmss::storage::testing::ListDir(dir.Path()).empty()); // no file left behind
}

// Decimates s with o on one thread; checks that the result has o.targetTriangles triangles, is
// valid, closed and manifold, and that 2 and 5 threads give the same; returns the one-thread run.
Outcome OneThreadRunThatOthersMatch(const Mesh& s, alg::DecimateOptions o)
{
  o.threads = 1;
  Outcome a = Simplify(MemorySource(s), o);
  ExpectValid(a.out);
  EXPECT_EQ(a.out.Triangles(), o.targetTriangles);
  for (auto& [e, n] : EdgeUse(a.out))
  {
    EXPECT_EQ(n, 2); // still closed and manifold
  }
  for (int threads : { 2, 5 })
  {
    o.threads = threads;
    ExpectSameOutput(a, Simplify(MemorySource(s), o), threads == 2 ? "2 threads" : "5 threads");
  }
  return a;
}

TEST(AlgorithmsDecimate, StepChunksDoNotDependOnThreadsOrMode)
{
  // 10,242 vertices along z in chunks of 512: the collapse step of the first passes runs chunk
  // by chunk (in parallel in core), collapses that leave a chunk one at a time afterwards.
  // Threads and the storage mode must not change the result; the chunks do (another order).
  Mesh s = SortedAlongZ(ColoredSphere(5));
  alg::DecimateOptions o;
  o.targetTriangles = 1500;
  o.stepChunkSize = 512;
  Outcome a = OneThreadRunThatOthersMatch(s, o);
  auto same = [&a](const Outcome& b, const char* what) { ExpectSameOutput(a, b, what); };
  o.threads = 2;
  o.storage.policy = st::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  Outcome c = Simplify(MemorySource(s), o);
  EXPECT_TRUE(c.stats.storage.usedOutOfCore);
  same(c, "out of core");
  // One chunk (the step one collapse at a time): a different order, a different result.
  o.storage = {};
  o.stepChunkSize = s.Vertices();
  Outcome d = Simplify(MemorySource(s), o);
  EXPECT_EQ(d.out.Triangles(), 1500u);
  EXPECT_FALSE(a.out.tris == d.out.tris && a.out.xyz == d.out.xyz);
}

TEST(AlgorithmsDecimate, UnannouncedAndInterleavedInputGiveTheSameResult)
{
  Mesh s = ColoredSphere(4);
  alg::DecimateOptions o;
  o.targetTriangles = 500;
  Outcome a = Simplify(MemorySource(s), o);
  Outcome b = Simplify(MemorySource(s, false, false), o);
  Outcome c = Simplify(MemorySource(s, false, true), o);
  EXPECT_TRUE(a.out.tris == b.out.tris);
  EXPECT_TRUE(a.out.tris == c.out.tris);
  EXPECT_TRUE(a.out.xyz == c.out.xyz);
  EXPECT_TRUE(a.out.scalars == c.out.scalars);
  EXPECT_EQ(c.stats.inputTriangles, s.Triangles());
  EXPECT_EQ(c.stats.inputVertices, s.Vertices());
}

TEST(AlgorithmsDecimate, LevelsOfDetailDecrease)
{
  Mesh s = BumpySphere(5); // 20480
  alg::DecimateOptions o;
  o.targetTriangles = 1000;
  o.levelsOfDetail = 5;
  std::vector<int> levelIds;
  std::vector<std::size_t> counts;
  std::vector<Mesh> meshes;
  CollectSink out;
  alg::NullProgress progress;
  alg::Decimate(MemorySource(s), out, o, progress,
    [&](int level, const std::function<void(io::MeshSink&)>& emit) {
      CollectSink sink;
      emit(sink);
      EXPECT_TRUE(sink.ended);
      ExpectValid(sink.mesh);
      levelIds.push_back(level);
      counts.push_back(sink.mesh.Triangles());
      meshes.push_back(sink.mesh);
    });
  ASSERT_EQ(counts.size(), 5u);
  for (int i = 0; i < 5; ++i)
  {
    EXPECT_EQ(levelIds[i], i);
  }
  for (std::size_t i = 1; i < counts.size(); ++i)
  {
    EXPECT_LT(counts[i], counts[i - 1]);
  }
  EXPECT_LT(counts[0], 20480u);
  EXPECT_LE(counts.back(), 1000u);
  EXPECT_GE(counts.back(), 970u);
  // Geometric spacing: 20480 * (1000/20480)^(k/5).
  for (int i = 0; i < 4; ++i)
  {
    double expect = 20480.0 * std::pow(1000.0 / 20480.0, (i + 1) / 5.0);
    EXPECT_NEAR(double(counts[i]), expect, 0.03 * expect + 2);
  }
  EXPECT_TRUE(meshes.back().tris == out.mesh.tris);
  EXPECT_TRUE(meshes.back().xyz == out.mesh.xyz);
}

TEST(AlgorithmsDecimate, FinalCountMeetsTarget)
{
  Mesh g = Grid(50, Bumps); // 5000
  for (std::uint64_t target : { 2500u, 1001u, 333u, 50u })
  {
    alg::DecimateOptions o;
    o.targetTriangles = target;
    Outcome r = Simplify(MemorySource(g), o);
    EXPECT_LE(r.out.Triangles(), target);
    EXPECT_GE(r.out.Triangles() + 2, target);
  }
  alg::DecimateOptions o;
  o.targetReduction = 0.75;
  Outcome r = Simplify(MemorySource(g), o);
  EXPECT_LE(r.out.Triangles(), 1250u);
  EXPECT_GE(r.out.Triangles(), 1248u);
}

TEST(AlgorithmsDecimate, MaximumErrorStopsEarly)
{
  Mesh g = Grid(32, Bumps);
  alg::DecimateOptions o;
  o.targetTriangles = 10;
  o.maximumError = 1e-4;
  Outcome tight = Simplify(MemorySource(g), o);
  o.maximumError = 1e-2;
  Outcome loose = Simplify(MemorySource(g), o);
  EXPECT_GT(tight.out.Triangles(), loose.out.Triangles());
  EXPECT_GT(tight.out.Triangles(), 10u);
  EXPECT_LT(tight.out.Triangles(), g.Triangles());
}

alg::TriangleMesh AsTriangleMesh(const Mesh& m)
{
  return { m.xyz, m.tris };
}

Mesh Scaled(Mesh m, double s)
{
  for (float& x : m.xyz)
  {
    x = float(x * s);
  }
  return m;
}

TEST(AlgorithmsDecimate, FarPassesRunTheirGroupsPartByPartAlikeOnAnyThreadsAndMode)
{
  // 163,842 vertices along z in chunks of 16,384, each four parts of 4,096 (kStepPart): to
  // 1,500 triangles the first passes are far from the target (327,680 faces > 50 x 1,500) and
  // run their cost groups in turn on each part of a chunk. Threads and the storage mode must
  // not change the result: in core on 1, 2 and 5 threads; out of core at 4 MiB, where the step
  // forks (half the budget holds its 1 MiB window), and at 1 MiB, where it does not.
  Mesh s = SortedAlongZ(ColoredSphere(7));
  alg::DecimateOptions o;
  o.targetTriangles = 1500;
  o.stepChunkSize = 16384;
  Outcome a = OneThreadRunThatOthersMatch(s, o);
  auto same = [&a](const Outcome& b, const char* what) { ExpectSameOutput(a, b, what); };
  o.threads = 2;
  sipmss::storage::testing::TempDir dir;
  o.storage.directories = { dir.Path() };
  o.storage.policy = st::ModePolicy::OutOfCore;
  std::uint64_t forks[2] = { 0, 0 };
  for (int i : { 0, 1 })
  {
    o.storage.memoryBudget = i ? 1u << 20 : 4u << 20;
    Outcome c = Simplify(MemorySource(s), o);
    EXPECT_TRUE(c.stats.storage.usedOutOfCore);
    same(c, i ? "1 MiB" : "4 MiB");
    forks[i] = c.stats.storage.forks;
  }
  EXPECT_GT(forks[0], forks[1]); // (the step's forks, at 4 MiB only)
  EXPECT_TRUE(sipmss::storage::testing::ListDir(dir.Path()).empty());
  // Against one chunk (every group in turn over all the vertices): the same quality.
  o.storage = {};
  o.stepChunkSize = s.Vertices();
  Outcome d = Simplify(MemorySource(s), o);
  EXPECT_EQ(d.out.Triangles(), 1500u);
  const double rmsParts = alg::CompareMeshes(AsTriangleMesh(s), AsTriangleMesh(a.out)).rms;
  const double rmsOne = alg::CompareMeshes(AsTriangleMesh(s), AsTriangleMesh(d.out)).rms;
  std::printf("[ parts    ] rms %.4e in parts, %.4e in one chunk\n", rmsParts, rmsOne);
  EXPECT_LT(rmsParts, 1.05 * rmsOne);
}

// The bound is relative to the diagonal, the error reached is reported, and without a target the
// bound is the only stop.
TEST(AlgorithmsDecimate, ErrorBoundIsRelativeToTheDiagonalAndReported)
{
  const Mesh g = BumpySphere(4); // 5120 triangles, diagonal about 2 sqrt(3)
  for (double e : { 1e-3, 4e-3, 1.6e-2 })
  {
    alg::DecimateOptions o;
    o.maximumError = e;
    const Outcome r = Simplify(MemorySource(g), o);
    const double D = r.stats.errorDiagonal;
    EXPECT_GT(D, 3.3);
    EXPECT_LT(D, 3.6);
    // (a float cost against the double bound: within float rounding)
    EXPECT_LE(r.stats.achievedError, e * (1 + 1e-6)) << e;
    EXPECT_GT(r.stats.achievedError, 0.5 * e) << e; // it went as far as the bound allowed
    EXPECT_LT(r.out.Triangles(), g.Triangles());
    // The measured distances: documented in docs/architecture.md, "Error bound".
    const alg::CompareResult c = alg::CompareMeshes(AsTriangleMesh(g), AsTriangleMesh(r.out));
    EXPECT_LE(c.rms, e) << e;
    EXPECT_LE(c.hausdorff, 4 * e) << e;
    std::printf("e %g: %zu triangles, achieved %g, rms %g (%.2f e), hausdorff %g (%.2f e)\n", e,
      r.out.Triangles(), r.stats.achievedError, c.rms, c.rms / e, c.hausdorff, c.hausdorff / e);

    // The same relative bound on the mesh scaled by 8 (exact in floats): the same triangles and
    // error.
    const Outcome big = Simplify(MemorySource(Scaled(g, 8.0)), o);
    EXPECT_EQ(big.out.Triangles(), r.out.Triangles()) << e;
    EXPECT_EQ(big.stats.achievedError, r.stats.achievedError) << e;
    EXPECT_EQ(big.stats.errorDiagonal, 8 * D) << e;
    // An absolute bound of e times the diagonal is the same bound.
    o.absoluteError = true;
    o.maximumError = e * D;
    const Outcome abs = Simplify(MemorySource(g), o);
    EXPECT_EQ(abs.out.Triangles(), r.out.Triangles()) << e;
    EXPECT_EQ(abs.stats.achievedError, r.stats.achievedError) << e;
    // Out of core (the error measured in Compact, with the lazy sums): the same.
    o.storage.policy = st::ModePolicy::OutOfCore;
    o.storage.memoryBudget = 64 * 1024;
    const Outcome paged = Simplify(MemorySource(g), o);
    EXPECT_TRUE(paged.stats.storage.usedOutOfCore);
    EXPECT_EQ(paged.stats.achievedError, r.stats.achievedError) << e;
    ExpectSameOutput(paged, r, "bounded, out of core");
  }
  // A loose bound without a target goes further than the default reduction (0.9) would; with a
  // target the target stops first.
  alg::DecimateOptions o;
  o.maximumError = 0.05;
  const Outcome loose = Simplify(MemorySource(g), o);
  EXPECT_LT(loose.out.Triangles(), g.Triangles() / 10);
  o.targetTriangles = 1000;
  const Outcome both = Simplify(MemorySource(g), o);
  EXPECT_LE(both.out.Triangles(), 1000u);
  EXPECT_GE(both.out.Triangles(), 998u);
  // No bound: the error is still reported.
  alg::DecimateOptions none;
  const Outcome free = Simplify(MemorySource(g), none);
  EXPECT_GT(free.stats.achievedError, 0.0);
  EXPECT_LT(free.stats.achievedError, loose.stats.achievedError);
}

// Levels of detail by the bound alone: level i of K stops where no collapse under
// e / 2^(K-1-i) remains, so it measures within that bound as a single run would, and each level
// is coarser than the one before.
TEST(AlgorithmsDecimate, LevelsOfDetailByTheBoundAlone)
{
  const Mesh g = BumpySphere(4);
  const double e = 1.6e-2;
  const int K = 3;
  alg::DecimateOptions o;
  o.maximumError = e;
  o.levelsOfDetail = K;
  std::vector<Mesh> levels;
  CollectSink sink;
  alg::NullProgress progress;
  const alg::RunStats stats = alg::Decimate(MemorySource(g), sink, o, progress,
    [&](int level, const std::function<void(sipmss::io::MeshSink&)>& emit) {
      EXPECT_EQ(std::size_t(level), levels.size());
      CollectSink one;
      emit(one);
      levels.push_back(std::move(one.mesh));
    });
  ASSERT_EQ(levels.size(), std::size_t(K));
  EXPECT_TRUE(levels.back().tris == sink.mesh.tris);
  EXPECT_LE(stats.achievedError, e * (1 + 1e-6));
  std::size_t before = g.Triangles();
  for (int i = 0; i < K; ++i)
  {
    const double bound = e * alg::LevelBoundFraction(i, K);
    EXPECT_LT(levels[std::size_t(i)].Triangles(), before) << "level " << i;
    before = levels[std::size_t(i)].Triangles();
    // As a single run with that bound: within it (the relation of "Error bound"), and as far.
    const alg::CompareResult c =
      alg::CompareMeshes(AsTriangleMesh(g), AsTriangleMesh(levels[std::size_t(i)]));
    EXPECT_LE(c.rms, bound) << "level " << i;
    EXPECT_LE(c.hausdorff, 4 * bound) << "level " << i;
    alg::DecimateOptions single;
    single.maximumError = bound;
    const Outcome r = Simplify(MemorySource(g), single);
    EXPECT_NEAR(double(levels[std::size_t(i)].Triangles()), double(r.out.Triangles()),
      0.15 * double(r.out.Triangles()))
      << "level " << i;
  }
  EXPECT_EQ(alg::LevelBoundFraction(0, 3), 0.25);
  EXPECT_EQ(alg::LevelBoundFraction(2, 3), 1.0);
}

// Appends a copy of `piece` scaled by s and moved to (x, y, z), with `scalar` as the value of
// every scalar array at its vertices.
void AddPiece(Mesh& m, const Mesh& piece, double s, double x, double y, double z, float scalar = 0)
{
  const std::uint32_t base = std::uint32_t(m.Vertices());
  for (std::size_t i = 0; i < piece.Vertices(); ++i)
  {
    m.xyz.insert(m.xyz.end(), { float(piece.xyz[3 * i] * s + x),
      float(piece.xyz[3 * i + 1] * s + y), float(piece.xyz[3 * i + 2] * s + z) });
    m.scalars.insert(m.scalars.end(), m.scalarNames.size(), scalar);
  }
  for (std::uint32_t v : piece.tris)
  {
    m.tris.push_back(base + v);
  }
}

// Pruning removes exactly the pieces whose bounding box is smaller than the threshold (relative
// to the input's diagonal), and keeps a small piece a lock holds; the same in and out of core.
TEST(AlgorithmsDecimate, PruningRemovesOnlyPiecesUnderTheThreshold)
{
  Mesh g = BumpySphere(3); // 1280 triangles, box side about 2.1
  g.scalarNames = { "lock" };
  g.scalars.assign(g.Vertices(), 0.0f);
  const std::size_t sphere = g.Triangles();
  // Tetrahedra (box diagonal sqrt(3) s) inside the sphere's box: two under 5% of the diagonal,
  // one over it, and one under it with a locked vertex.
  const Mesh tet = Tetrahedron();
  AddPiece(g, tet, 0.05, 0.2, 0.0, 0.0);
  AddPiece(g, tet, 0.08, -0.3, 0.1, 0.0);
  AddPiece(g, tet, 0.12, 0.0, -0.4, 0.2);
  AddPiece(g, tet, 0.05, 0.0, 0.3, -0.3, 1.0f);
  alg::DecimateOptions o;
  o.targetReduction = 0; // (pruning only)
  o.lockArray = "lock";
  const Outcome none = Simplify(MemorySource(g), o);
  EXPECT_EQ(none.out.Triangles(), sphere + 16);
  EXPECT_EQ(none.stats.prunedComponents, 0u);
  o.pruneSize = 0.05;
  const Outcome pruned = Simplify(MemorySource(g), o);
  const double D = pruned.stats.errorDiagonal;
  ASSERT_LT(0.08 * std::sqrt(3.0), 0.05 * D); // (the pieces' sizes against the threshold)
  ASSERT_GT(0.12 * std::sqrt(3.0), 0.05 * D);
  ASSERT_LT(0.12 * std::sqrt(3.0), 0.1 * D);
  EXPECT_EQ(pruned.stats.prunedComponents, 2u);
  EXPECT_EQ(pruned.stats.prunedTriangles, 8u);
  EXPECT_EQ(pruned.out.Triangles(), sphere + 8);
  EXPECT_FALSE(HasVertex(pruned.out, 0.2, 0.0, 0.0));     // pruned
  EXPECT_FALSE(HasVertex(pruned.out, -0.3, 0.1, 0.0));
  EXPECT_TRUE(HasVertex(pruned.out, 0.0, -0.4, 0.2));     // large enough
  EXPECT_TRUE(HasVertex(pruned.out, 0.0, 0.3, -0.3));     // locked
  EXPECT_EQ(pruned.out.Vertices(), none.out.Vertices() - 8);
  // A threshold above the largest piece's size (and below the sphere's) prunes it too.
  o.pruneSize = 0.1;
  EXPECT_EQ(Simplify(MemorySource(g), o).stats.prunedComponents, 3u);
  // With a target, the pruned pieces do not count: the sphere keeps more of its triangles.
  o.pruneSize = 0.05;
  o.targetTriangles = 400;
  o.targetReduction = alg::kDefaultTargetReduction;
  const Outcome small = Simplify(MemorySource(g), o);
  EXPECT_LE(small.out.Triangles(), 400u);
  EXPECT_GE(small.out.Triangles(), 398u);
  o.storage.policy = st::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  const Outcome paged = Simplify(MemorySource(g), o);
  EXPECT_TRUE(paged.stats.storage.usedOutOfCore);
  ExpectSameOutput(small, paged, "pruned, out of core");
  EXPECT_EQ(paged.stats.prunedComponents, 2u);
}

// A selection by a face (cell) scalar: every face outside it is in the output with the same
// corners, and the run is the one of the point selection it stands for (a vertex is selected
// when no face outside the selection has it), byte for byte, in and out of core. A name that is
// neither a point nor a cell array is an error naming both lists.
TEST(AlgorithmsDecimate, CellSelectionKeepsEveryFaceOutsideIt)
{
  Mesh g = Grid(24, Bumps);
  PrependFarVertex(g);
  g.faceName = "region";
  std::vector<bool> outsideVertex(g.Vertices(), false);
  for (std::size_t f = 0; f < g.Triangles(); ++f)
  {
    double cx = 0;
    for (int k = 0; k < 3; ++k)
    {
      cx += g.xyz[3 * g.tris[3 * f + k]] / 3.0;
    }
    const bool in = cx > 0.4;
    g.faceFlags.push_back(in ? 1 : 0);
    for (int k = 0; k < 3 && !in; ++k)
    {
      outsideVertex[g.tris[3 * f + k]] = true;
    }
  }
  Mesh p = g; // the same mesh with the equivalent point selection
  p.faceName.clear();
  p.scalarNames = { "picked" };
  for (std::size_t v = 0; v < p.Vertices(); ++v)
  {
    p.scalars.push_back(outsideVertex[v] ? 0.0f : 1.0f);
  }
  alg::DecimateOptions o;
  o.targetTriangles = 300;
  o.selectionArray = "region";
  const Outcome cells = Simplify(MemorySource(g), o);
  EXPECT_LT(cells.out.Triangles(), g.Triangles() - 200);
  // Every face outside the selection, by its corners' positions.
  std::set<std::array<float, 9>> out;
  for (std::size_t f = 0; f < cells.out.Triangles(); ++f)
  {
    std::array<float, 9> t;
    for (int k = 0; k < 9; ++k)
    {
      t[std::size_t(k)] = cells.out.xyz[3 * cells.out.tris[3 * f + std::size_t(k / 3)] + std::size_t(k % 3)];
    }
    out.insert(t);
  }
  std::size_t kept = 0;
  for (std::size_t f = 0; f < g.Triangles(); ++f)
  {
    if (g.faceFlags[f])
    {
      continue;
    }
    std::array<float, 9> t;
    for (int k = 0; k < 9; ++k)
    {
      t[std::size_t(k)] = g.xyz[3 * g.tris[3 * f + std::size_t(k / 3)] + std::size_t(k % 3)];
    }
    kept += out.count(t);
    EXPECT_EQ(out.count(t), 1u) << "face " << f;
  }
  EXPECT_GT(kept, 100u);
  o.selectionArray = "picked";
  const Outcome points = Simplify(MemorySource(p), o);
  ASSERT_EQ(points.out.Triangles(), cells.out.Triangles());
  EXPECT_EQ(points.out.tris, cells.out.tris);
  EXPECT_EQ(points.out.xyz, cells.out.xyz);
  o.selectionArray = "region";
  o.storage.policy = st::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  const Outcome paged = Simplify(MemorySource(g), o);
  EXPECT_TRUE(paged.stats.storage.usedOutOfCore);
  ExpectSameOutput(cells, paged, "cell selection out of core");
  // A reordered copy does not carry the cell array: an error, not a run without the selection.
  o.layout = alg::LayoutPolicy::Reorder;
  const std::string reordered = RunError(g, o);
  EXPECT_NE(reordered.find("did not come with the faces"), std::string::npos) << reordered;
  o.layout = alg::LayoutPolicy::Automatic;
  o.selectionArray = "nowhere";
  const std::string nowhere = RunError(g, o);
  EXPECT_NE(nowhere.find("'nowhere'"), std::string::npos) << nowhere;
  EXPECT_NE(nowhere.find("cell arrays: other, region"), std::string::npos) << nowhere;
}

TEST(AlgorithmsDecimate, PointDataFollowsThePositions)
{
  // Flat grid: every placement is on its edge, so scalar = x exactly and colors follow x.
  Mesh g = Grid(20);
  g.scalarNames = { "x" };
  for (std::size_t i = 0; i < g.Vertices(); ++i)
  {
    float x = g.xyz[3 * i];
    g.scalars.push_back(x);
    g.rgba.insert(g.rgba.end(), { std::uint8_t(std::lround(200 * x)), 7, 9, 255 });
  }
  alg::DecimateOptions o;
  o.targetTriangles = 60;
  Outcome r = Simplify(MemorySource(g), o);
  ASSERT_EQ(r.out.scalars.size(), r.out.Vertices());
  ASSERT_EQ(r.out.rgba.size(), 4 * r.out.Vertices());
  for (std::size_t i = 0; i < r.out.Vertices(); ++i)
  {
    float x = r.out.xyz[3 * i];
    EXPECT_NEAR(r.out.scalars[i], x, 1e-5);
    EXPECT_NEAR(r.out.rgba[4 * i], 200 * x, 1.01);
    EXPECT_EQ(r.out.rgba[4 * i + 1], 7);
    EXPECT_EQ(r.out.rgba[4 * i + 2], 9);
    EXPECT_EQ(r.out.rgba[4 * i + 3], 255);
  }
  // Bumpy terrain: the optimal placement leaves the edge slightly, scalar = x stays close.
  Mesh t = Grid(40, Bumps);
  t.scalarNames = { "x" };
  for (std::size_t i = 0; i < t.Vertices(); ++i)
  {
    t.scalars.push_back(t.xyz[3 * i]);
  }
  o.targetTriangles = 400;
  r = Simplify(MemorySource(t), o);
  for (std::size_t i = 0; i < r.out.Vertices(); ++i)
  {
    EXPECT_NEAR(r.out.scalars[i], r.out.xyz[3 * i], 0.02);
  }
  // Sphere normals stay unit length.
  Mesh s = ColoredSphere(4);
  o.targetTriangles = 300;
  r = Simplify(MemorySource(s), o);
  ASSERT_EQ(r.out.normals.size(), 3 * r.out.Vertices());
  for (std::size_t i = 0; i < r.out.Vertices(); ++i)
  {
    double l = std::sqrt(r.out.normals[3 * i] * r.out.normals[3 * i] +
      r.out.normals[3 * i + 1] * r.out.normals[3 * i + 1] +
      r.out.normals[3 * i + 2] * r.out.normals[3 * i + 2]);
    EXPECT_NEAR(l, 1.0, 1e-5);
  }
}

TEST(AlgorithmsDecimate, DropsDegenerateAndDuplicateTriangles)
{
  Mesh g = Grid(4); // 32 triangles, vertices 0..24
  // collinear vertices 0, 1, 2 (y = 0): zero area
  g.tris.insert(g.tris.end(), { 0, 1, 2 });
  // repeated index
  g.tris.insert(g.tris.end(), { 5, 5, 6 });
  // exact duplicates (same vertex set) of the first two triangles
  g.tris.insert(g.tris.end(), { g.tris[0], g.tris[1], g.tris[2] });
  g.tris.insert(g.tris.end(), { g.tris[4], g.tris[5], g.tris[3] });
  // an unreferenced vertex
  g.xyz.insert(g.xyz.end(), { 5, 5, 5 });
  alg::DecimateOptions o;
  o.targetTriangles = 1000; // no simplification
  Outcome r = Simplify(MemorySource(g), o);
  EXPECT_EQ(r.stats.inputTriangles, 36u);
  EXPECT_EQ(r.stats.droppedInputFaces, 4u);
  EXPECT_EQ(r.out.Triangles(), 32u);
  EXPECT_EQ(r.out.Vertices(), 25u);
  ExpectValid(r.out);
  // A double-sided pair (the same triangle in both orientations) lying in a surface, where its
  // interior edge has one other face: one face of the pair stays, oriented like its neighbour
  // (cancelling both would open a hole, as in clustered meshes where thin parts fold).
  Mesh d = Grid(4);
  d.tris.insert(d.tris.end(), { d.tris[2], d.tris[1], d.tris[0] });
  r = Simplify(MemorySource(d), o);
  EXPECT_EQ(r.stats.droppedInputFaces, 1u);
  EXPECT_EQ(r.out.Triangles(), 32u);
  ExpectValid(r.out);
  std::multiset<std::array<std::uint32_t, 3>> want, got;
  auto canonical = [](std::uint32_t a, std::uint32_t b, std::uint32_t c) {
    // rotation-invariant, orientation-preserving
    std::array<std::uint32_t, 3> t = { a, b, c };
    while (t[0] != std::min({ a, b, c }))
    {
      t = { t[1], t[2], t[0] };
    }
    return t;
  };
  for (std::size_t i = 0; i + 2 < 3 * 32; i += 3)
  {
    want.insert(canonical(d.tris[i], d.tris[i + 1], d.tris[i + 2]));
  }
  for (std::size_t i = 0; i < r.out.tris.size(); i += 3)
  {
    got.insert(canonical(r.out.tris[i], r.out.tris[i + 1], r.out.tris[i + 2]));
  }
  EXPECT_EQ(got, want); // the grid as it was, orientation included
  // The same pair between two fans that already close its edges (a bipyramid's equator: every
  // edge has a face above and one below): the pair cancels.
  Mesh b;
  b.xyz = { 1, 0, 0, -0.5f, 0.87f, 0, -0.5f, -0.87f, 0, 0, 0, 1, 0, 0, -1 };
  b.tris = { 3, 0, 1, 3, 1, 2, 3, 2, 0, 4, 1, 0, 4, 2, 1, 4, 0, 2, 0, 1, 2, 0, 2, 1 };
  r = Simplify(MemorySource(b), o);
  EXPECT_EQ(r.stats.droppedInputFaces, 2u);
  EXPECT_EQ(r.out.Triangles(), 6u);
  ExpectValid(r.out);
}

TEST(AlgorithmsDecimate, LargeInputCleanupDoesNotDependOnThreads)
{
  // 80,000 triangles: the validation and the search for faces on one vertex set run on all
  // cores. Duplicates, double-sided pairs and zero-area faces spread over the grid must be
  // dropped the same way with 1 and 2 threads; a bad index is reported at the first bad face.
  Mesh g = Grid(200, Bumps);
  const std::size_t n = g.Triangles();
  for (std::size_t f = 7; f < n; f += 997)
  {
    const std::uint32_t a = g.tris[3 * f], b = g.tris[3 * f + 1], c = g.tris[3 * f + 2];
    if (f % 3 == 0)
    {
      g.tris.insert(g.tris.end(), { b, c, a }); // a copy
    }
    else if (f % 3 == 1)
    {
      g.tris.insert(g.tris.end(), { c, b, a }); // the other side
    }
    else
    {
      g.tris.insert(g.tris.end(), { a, a, b }); // zero area
    }
  }
  alg::DecimateOptions o;
  o.targetTriangles = 5000;
  o.threads = 1;
  Outcome a = Simplify(MemorySource(g), o);
  o.threads = 2;
  Outcome b = Simplify(MemorySource(g), o);
  EXPECT_GT(a.stats.droppedInputFaces, 0u);
  EXPECT_EQ(a.stats.droppedInputFaces, b.stats.droppedInputFaces);
  EXPECT_TRUE(a.out.tris == b.out.tris);
  EXPECT_TRUE(a.out.xyz == b.out.xyz);
  ExpectValid(b.out);
  // Two bad faces, far apart: the first one is named.
  Mesh bad = g;
  const std::uint32_t nv = std::uint32_t(bad.Vertices());
  bad.tris[3 * (n - 10) + 1] = nv + 5;
  bad.tris[3 * 1234 + 2] = nv + 7;
  for (int threads : { 1, 2 })
  {
    o.threads = threads;
    try
    {
      Simplify(MemorySource(bad), o);
      ADD_FAILURE() << "no error with " << threads << " threads";
    }
    catch (const std::exception& e)
    {
      EXPECT_NE(std::string(e.what()).find("triangle 1234 has vertex index " + std::to_string(nv + 7)),
        std::string::npos)
        << e.what();
    }
  }
}

TEST(AlgorithmsDecimate, NonManifoldEdgesCollapse)
{
  // Three flat sheets meeting on one spine (a "book", as clustering makes where parts touch):
  // every spine edge has 3 faces. The 10 spine segments alone carry 30 faces, so a target of 12
  // needs collapses of non-manifold edges; each keeps the sheets apart (no duplicate faces).
  const int n = 10;
  Mesh m;
  auto spine = [&](int i) { return std::uint32_t(i); };
  for (int i = 0; i <= n; ++i)
  {
    m.xyz.insert(m.xyz.end(), { float(i) / n, 0.0f, 0.0f });
  }
  const float dirs[3][3] = { { 0, 1, 0 }, { 0, 0, 1 }, { 0, -0.7f, -0.7f } };
  for (const auto& d : dirs)
  {
    const std::uint32_t base = std::uint32_t(m.Vertices());
    for (int r = 1; r <= n; ++r)
    {
      for (int i = 0; i <= n; ++i)
      {
        const float s = float(r) / n;
        m.xyz.insert(m.xyz.end(), { float(i) / n, s * d[1], s * d[2] });
      }
    }
    auto at = [&](int r, int i) {
      return r == 0 ? spine(i) : base + std::uint32_t((r - 1) * (n + 1) + i);
    };
    for (int r = 0; r < n; ++r)
    {
      for (int i = 0; i < n; ++i)
      {
        m.tris.insert(m.tris.end(), { at(r, i), at(r, i + 1), at(r + 1, i + 1) });
        m.tris.insert(m.tris.end(), { at(r, i), at(r + 1, i + 1), at(r + 1, i) });
      }
    }
  }
  alg::DecimateOptions o;
  o.targetTriangles = 12;
  Outcome r = Simplify(MemorySource(m), o);
  ExpectValid(r.out);
  EXPECT_LE(r.out.Triangles(), 14u);
  int nonManifold = 0;
  for (auto& [e, k] : EdgeUse(r.out))
  {
    EXPECT_LE(k, 3);
    nonManifold += k > 2;
  }
  EXPECT_GE(nonManifold, 1); // the sheets still meet on a (shorter) spine
  EXPECT_LT(nonManifold, n);
}

TEST(AlgorithmsDecimate, NonManifoldInputIsHandled)
{
  Mesh g = Grid(10, Bumps);
  // A fin: an extra triangle on the interior edge (5,5)-(6,5) of the grid -> an edge with 3
  // faces, plus a bow-tie vertex: a triangle touching the grid only at corner (10,10).
  std::uint32_t base = std::uint32_t(g.Vertices());
  g.xyz.insert(g.xyz.end(), { 0.55f, 0.5f, 0.5f, 1.2f, 1.0f, 0.0f, 1.0f, 1.2f, 0.0f });
  g.tris.insert(g.tris.end(), { 5 * 11 + 5, 5 * 11 + 6, base });
  std::uint32_t corner = 10 * 11 + 10;
  g.tris.insert(g.tris.end(), { corner, base + 1, base + 2 });
  for (std::uint64_t target : { 150u, 30u })
  {
    alg::DecimateOptions o;
    o.targetTriangles = target;
    Outcome r = Simplify(MemorySource(g), o);
    ExpectValid(r.out);
    EXPECT_LE(r.out.Triangles(), target + 2);
    // Never more non-manifold than the input: the edge with 3 faces is never collapsed (the fin
    // may go as a whole), no new one appears.
    int nonManifold = 0;
    for (auto& [e, n] : EdgeUse(r.out))
    {
      EXPECT_LE(n, 3);
      nonManifold += n > 2;
    }
    EXPECT_LE(nonManifold, 1);
    if (target == 150)
    {
      EXPECT_EQ(nonManifold, 1); // the fin is expensive to remove
    }
    for (std::size_t f = 0; f < r.out.Triangles(); ++f)
    {
      auto n = FaceNormal(r.out, f);
      EXPECT_GT(std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]), 0.0);
    }
  }
}

TEST(AlgorithmsDecimate, WeldJoinsCoincidentVertices)
{
  // Two halves of a grid with duplicated seam vertices.
  Mesh g = Grid(10, Bumps);
  Mesh split;
  split.xyz = g.xyz;
  std::map<std::uint32_t, std::uint32_t> copy;
  for (std::size_t i = 0; i < g.tris.size(); i += 3)
  {
    bool right = g.xyz[3 * g.tris[i]] + g.xyz[3 * g.tris[i + 1]] + g.xyz[3 * g.tris[i + 2]] > 1.5f;
    for (int k = 0; k < 3; ++k)
    {
      std::uint32_t v = g.tris[i + k];
      if (right && g.xyz[3 * v] == 0.5f)
      {
        if (!copy.count(v))
        {
          copy[v] = std::uint32_t(split.xyz.size() / 3);
          split.xyz.insert(split.xyz.end(), { g.xyz[3 * v], g.xyz[3 * v + 1], g.xyz[3 * v + 2] });
        }
        v = copy[v];
      }
      split.tris.push_back(v);
    }
  }
  ASSERT_EQ(BoundaryLoops(split), 2);
  alg::DecimateOptions o;
  o.targetTriangles = 100000;
  o.weldDistance = 0;
  Outcome r = Simplify(MemorySource(split), o);
  EXPECT_EQ(r.out.Vertices(), g.Vertices());
  EXPECT_EQ(BoundaryLoops(r.out), 1);
}

class AbortingProgress final : public alg::Progress
{
public:
  explicit AbortingProgress(int n)
    : n_(n)
  {
    this->SetInterval(0);
  }
  void Report(double, const char* phase) override { this->phase = phase; }
  bool Aborted() override { return ++this->calls > this->n_; }
  int calls = 0;
  std::string phase;

private:
  int n_;
};

TEST(AlgorithmsDecimate, AbortThrowsAndLeavesNoFiles)
{
  Mesh s = ColoredSphere(4);
  namespace fs = std::filesystem;
  fs::path dir = fs::temp_directory_path() / ("sipmss_decimate_abort_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  alg::DecimateOptions o;
  o.targetTriangles = 100;
  o.storage.policy = st::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 64 * 1024;
  o.storage.directories = { dir.string() };
  o.threads = 1; // (only the calling thread ticks: one thread keeps the count of checks fixed)
  // How often a whole run asks whether to abort; then abort at the first few checks and at
  // points spread over the run up to its last check.
  int checks = 0;
  {
    AbortingProgress counting(std::numeric_limits<int>::max());
    CollectSink sink;
    alg::Decimate(MemorySource(s), sink, o, counting);
    checks = counting.calls;
  }
  ASSERT_GT(checks, 20);
  std::set<std::string> phases;
  for (int n : { 0, 1, 2, 3, 5, 8, checks / 4, checks / 2, 3 * checks / 4, checks - 1 })
  {
    AbortingProgress progress(n);
    CollectSink sink;
    EXPECT_THROW(alg::Decimate(MemorySource(s), sink, o, progress), alg::AbortedError) << n;
    phases.insert(progress.phase);
    EXPECT_TRUE(fs::is_empty(dir)) << "after abort at call " << n;
  }
  EXPECT_GE(phases.size(), 3u); // read, rings/quadrics, collapse, ...
  fs::remove_all(dir);
}

TEST(AlgorithmsDecimate, AbortIsQuick)
{
  Mesh g = Grid(300, Bumps); // 180K triangles
  class TimedAbort final : public alg::Progress
  {
  public:
    std::chrono::steady_clock::time_point at;
    void Report(double, const char*) override {}
    bool Aborted() override { return std::chrono::steady_clock::now() >= this->at; }
  } progress;
  for (double after : { 0.02, 0.1, 0.25 })
  {
    alg::DecimateOptions o;
    o.targetTriangles = 100;
    CollectSink sink;
    auto t0 = std::chrono::steady_clock::now();
    progress.at = t0 + std::chrono::duration_cast<std::chrono::steady_clock::duration>(
                         std::chrono::duration<double>(after));
    bool aborted = false;
    try
    {
      alg::Decimate(MemorySource(g), sink, o, progress);
    }
    catch (const alg::AbortedError&)
    {
      aborted = true;
    }
    double late =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - progress.at).count();
    if (aborted)
    {
      // The cores poll every ~0.05 s of work; the bound is loose so that a loaded CI machine
      // does not fail it, yet a loop that never polls (seconds of work) does.
      EXPECT_LT(late, 0.5) << "abort requested at " << after << " s";
    }
  }
}

TEST(AlgorithmsDecimate, StatsAndPhases)
{
  Mesh s = BumpySphere(4);
  alg::DecimateOptions o;
  o.targetTriangles = 500;
  Outcome r = Simplify(MemorySource(s), o);
  EXPECT_EQ(r.stats.inputVertices, s.Vertices());
  EXPECT_EQ(r.stats.inputTriangles, s.Triangles());
  EXPECT_EQ(r.stats.outputTriangles, r.out.Triangles());
  EXPECT_EQ(r.stats.outputVertices, r.out.Vertices());
  std::vector<std::string> names;
  for (auto& p : r.stats.phases)
  {
    names.push_back(p.name);
  }
  EXPECT_EQ(names,
    (std::vector<std::string>{ "read", "rings", "quadrics", "collapse", "fit", "write" }));
  EXPECT_GT(r.stats.storage.peakBytes, 0u);
}

TEST(AlgorithmsDecimate, InitialQuadricIsUsed)
{
  // A huge quadric pinning vertex 0 keeps it in place even when the rest collapses (the
  // quadric's position: without the final fit, which would move it by a little).
  Mesh g = Grid(12, Bumps);
  alg::DecimateOptions o;
  o.fitSurface = false;
  o.targetTriangles = 20;
  const std::uint32_t pinned = 6 * 13 + 6; // the center vertex
  auto p = g.P(pinned);
  o.initialQuadric = [p, pinned](std::uint64_t v, double q[10]) {
    if (v != pinned)
    {
      return false;
    }
    // 1e6 * |x - p|^2
    const double w = 1e6;
    q[0] = w, q[1] = 0, q[2] = 0, q[3] = -w * p[0];
    q[4] = w, q[5] = 0, q[6] = -w * p[1];
    q[7] = w, q[8] = -w * p[2];
    q[9] = w * (p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    return true;
  };
  Outcome r = Simplify(MemorySource(g), o);
  EXPECT_TRUE(HasVertex(r.out, p[0], p[1], p[2]));
}

TEST(AlgorithmsDecimate, RunsOnACallersDML)
{
  Mesh s = ColoredSphere(4);
  alg::DecimateOptions o;
  o.targetTriangles = 400;
  Outcome a = Simplify(MemorySource(s), o);
  st::DML dml;
  st::Profile profile;
  profile.policy = st::ModePolicy::OutOfCore;
  profile.memoryBudget = 256 * 1024;
  dml.Config(profile);
  st::Array<std::uint32_t> other(dml, 1000); // a caller's block that must survive the run
  other.Set(999, 42);
  o.dml = &dml;
  Outcome b = Simplify(MemorySource(s), o);
  EXPECT_TRUE(a.out.tris == b.out.tris);
  EXPECT_TRUE(a.out.xyz == b.out.xyz);
  EXPECT_TRUE(b.stats.storage.usedOutOfCore);
  EXPECT_EQ(other.Get(999), 42u);
}

double RmsDistanceToSphere(const Mesh& m)
{
  double s = 0;
  for (std::size_t i = 0; i < m.Vertices(); ++i)
  {
    auto p = m.P(i);
    double l = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    double d = l - SphereBump(p[0] / l, p[1] / l, p[2] / l);
    s += d * d;
  }
  return std::sqrt(s / double(std::max<std::size_t>(m.Vertices(), 1)));
}

TEST(AlgorithmsDecimate, BunnyTiming)
{
  const std::string path = std::string(SIPMSS_SHARED_DATA_DIR) + "/bunny.ply";
  if (!std::filesystem::exists(path))
  {
    GTEST_SKIP() << "no shared data (" << path << ")";
  }
  alg::DecimateOptions o;
  o.targetTriangles = 5000;
  Outcome a = Simplify(alg::FileSource(path), o);
  EXPECT_LE(a.out.Triangles(), 5000u);
  EXPECT_GE(a.out.Triangles(), 4900u);
  ExpectValid(a.out);
  std::printf("[ bunny    ] in core: %llu -> %llu triangles in %.3f s; %s\n",
    (unsigned long long)a.stats.inputTriangles, (unsigned long long)a.out.Triangles(), a.seconds,
    PhaseSummary(a.stats).c_str());
  o.storage.memoryBudget = 8u << 20;
  Outcome b = Simplify(alg::FileSource(path), o);
  std::printf("[ bunny    ] 8 MB: %llu -> %llu triangles in %.3f s (peak %.1f MB, misses %llu); %s\n",
    (unsigned long long)b.stats.inputTriangles, (unsigned long long)b.out.Triangles(), b.seconds,
    b.stats.storage.peakBytes / 1048576.0, (unsigned long long)b.stats.storage.misses,
    PhaseSummary(b.stats).c_str());
  EXPECT_TRUE(a.out.tris == b.out.tris);
  EXPECT_TRUE(a.out.xyz == b.out.xyz);
  EXPECT_LE(b.stats.storage.peakBytes, 8u << 20);
  // A budget below the bunny's working set: out of core first, same result.
  o.storage.memoryBudget = 2u << 20;
  Outcome c = Simplify(alg::FileSource(path), o);
  std::printf("[ bunny    ] 2 MB: %llu -> %llu triangles in %.3f s (peak %.1f MB, misses %llu, "
              "out of core %d); %s\n",
    (unsigned long long)c.stats.inputTriangles, (unsigned long long)c.out.Triangles(), c.seconds,
    c.stats.storage.peakBytes / 1048576.0, (unsigned long long)c.stats.storage.misses,
    int(c.stats.storage.usedOutOfCore), PhaseSummary(c.stats).c_str());
  EXPECT_TRUE(c.stats.storage.usedOutOfCore);
  EXPECT_TRUE(a.out.tris == c.out.tris);
  EXPECT_TRUE(a.out.xyz == c.out.xyz);
  EXPECT_TRUE(a.out.scalars == c.out.scalars);
  EXPECT_LE(c.stats.storage.peakBytes, 2u << 20);
}

TEST(AlgorithmsDecimate, Generated800KTiming)
{
  // 640 x 640 quads = 819,200 triangles, like the paper's Dragon (871K).
  Mesh g = Grid(640, Bumps);
  alg::DecimateOptions o;
  o.targetTriangles = 10000;
  Outcome a = Simplify(MemorySource(g), o);
  EXPECT_LE(a.out.Triangles(), 10000u);
  EXPECT_GE(a.out.Triangles(), 9900u);
  std::printf("[ 800K     ] in core: %zu -> %zu triangles in %.3f s; %s\n", g.Triangles(),
    a.out.Triangles(), a.seconds, PhaseSummary(a.stats).c_str());
  for (std::size_t i = 0; i < a.out.Vertices(); ++i)
  {
    auto p = a.out.P(i);
    ASSERT_NEAR(p[2], Bumps(p[0], p[1]), 0.01);
  }
  o.storage.memoryBudget = 8u << 20;
  Outcome b = Simplify(MemorySource(g), o);
  std::printf("[ 800K     ] 8 MB: %zu -> %zu triangles in %.3f s (peak %.1f MB, out of core %d); %s\n",
    g.Triangles(), b.out.Triangles(), b.seconds, b.stats.storage.peakBytes / 1048576.0,
    int(b.stats.storage.usedOutOfCore), PhaseSummary(b.stats).c_str());
  EXPECT_TRUE(b.stats.storage.usedOutOfCore);
  EXPECT_LE(b.stats.storage.peakBytes, 8u << 20);
  EXPECT_TRUE(a.out.tris == b.out.tris);
  EXPECT_TRUE(a.out.xyz == b.out.xyz);
}

TEST(AlgorithmsDecimate, SphereQuality)
{
  Mesh s = BumpySphere(6); // 81920
  alg::DecimateOptions o;
  o.targetTriangles = 4000;
  Outcome r = Simplify(MemorySource(s), o);
  double rms = RmsDistanceToSphere(r.out);
  std::printf("[ sphere   ] 81920 -> %zu triangles in %.3f s, rms vertex error %.2e\n",
    r.out.Triangles(), r.seconds, rms);
  EXPECT_LT(rms, 2e-3);
}


// A decimation of s with and without the final fit: both outcomes and their distances to s.
// The fit moves vertices only: the same faces, other positions.
struct FitPair
{
  Outcome plain, fitted;
  alg::CompareResult a, b;
};
FitPair WithAndWithoutFit(const Mesh& s, alg::DecimateOptions o, const char* what)
{
  FitPair r;
  o.fitSurface = false;
  r.plain = Simplify(MemorySource(s), o);
  o.fitSurface = true;
  r.fitted = Simplify(MemorySource(s), o);
  EXPECT_TRUE(r.fitted.out.tris == r.plain.out.tris);
  EXPECT_FALSE(r.fitted.out.xyz == r.plain.out.xyz);
  r.a = alg::CompareMeshes(AsTriangleMesh(s), AsTriangleMesh(r.plain.out));
  r.b = alg::CompareMeshes(AsTriangleMesh(s), AsTriangleMesh(r.fitted.out));
  std::printf("[ fit      ] %s: rms %.3e -> %.3e, hausdorff %.3e -> %.3e\n", what, r.a.rms, r.b.rms,
    r.a.hausdorff, r.b.hausdorff);
  return r;
}

TEST(AlgorithmsDecimate, TheFinalFitLowersTheDistanceAndMovesOnlyMergedVertices)
{
  // The fit moves merged vertices along their normals (the faces stay the same): the distance
  // to the input falls, the achieved error (the largest collapse's) is what it was, and the
  // result is the same in core and at a budget small enough for the fit's own blocks to page.
  Mesh s = BumpySphere(5); // 20,480 triangles
  alg::DecimateOptions o;
  o.targetTriangles = 500;
  const FitPair r = WithAndWithoutFit(s, o, "geometry");
  const Outcome& fitted = r.fitted;
  EXPECT_EQ(fitted.stats.achievedError, r.plain.stats.achievedError);
  EXPECT_LT(r.b.rms, 0.95 * r.a.rms);
  EXPECT_LE(r.b.hausdorff, r.a.hausdorff * 1.05);
  o.storage.policy = sipmss::storage::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 256u << 10;
  const Outcome paged = Simplify(MemorySource(s), o);
  EXPECT_TRUE(paged.stats.storage.usedOutOfCore);
  EXPECT_TRUE(paged.out.xyz == fitted.out.xyz);
  EXPECT_TRUE(paged.out.tris == fitted.out.tris);

  // Nothing collapses: nothing moves (the input's bytes).
  o = alg::DecimateOptions();
  o.targetTriangles = s.Triangles();
  const Outcome same = Simplify(MemorySource(s), o);
  EXPECT_TRUE(same.out.xyz == s.xyz);

  // Locked vertices (a lock array) keep their exact positions while their neighbours fit.
  Mesh locked = BumpySphere(5);
  locked.scalarNames = { "keep" };
  locked.scalars.assign(locked.Vertices(), 0.0f);
  for (std::size_t v = 0; v < locked.Vertices(); v += 7)
  {
    locked.scalars[v] = 1.0f;
  }
  o = alg::DecimateOptions();
  o.targetTriangles = 2000;
  o.lockArray = "keep";
  const Outcome l = Simplify(MemorySource(locked), o);
  std::size_t kept = 0;
  for (std::size_t v = 0; v < locked.Vertices(); v += 7)
  {
    auto p = locked.P(v);
    kept += HasVertex(l.out, p[0], p[1], p[2]);
  }
  EXPECT_EQ(kept, (locked.Vertices() + 6) / 7);
}

TEST(AlgorithmsDecimate, TheFinalFitWithAttributesInTheError)
{
  // A sphere with a sharp color border, decimated with the colors in the error: the fit moves
  // the merged vertices and leaves their colors (the attributes' optimal values) and the faces;
  // the distance falls and the largest distance does not grow (the moves are held to the
  // largest geometric error of a vertex, not to the achieved error, which counts the colors').
  Mesh s = BumpySphere(5);
  for (std::size_t i = 0; i < s.Vertices(); ++i)
  {
    auto p = s.P(i);
    const bool red = p[0] > 0.1 * std::sin(7 * p[1]);
    s.rgba.insert(s.rgba.end(), { std::uint8_t(red ? 230 : 20), std::uint8_t(40),
                                  std::uint8_t(red ? 20 : 220), 255 });
  }
  alg::DecimateOptions o;
  o.targetTriangles = 800;
  o.attributes = { { "colors", 1.0 } };
  const FitPair r = WithAndWithoutFit(s, o, "colors in the error");
  EXPECT_TRUE(r.fitted.out.rgba == r.plain.out.rgba);
  EXPECT_LT(r.b.rms, 0.95 * r.a.rms);
  EXPECT_LE(r.b.hausdorff, r.a.hausdorff * 1.05);
}

TEST(AlgorithmsDecimate, RingsSwitchingOutOfCoreOnTwoThreadsDoNotShareTheDML)
{
  // Regression: the input fits the budget (the run is in core when the rings start), the ring
  // face list does not, so opening it moves every block out of core in the middle of the rings
  // phase. The duplicate face search after it (pass 3) then ran on two threads over the one
  // out-of-core DML, whose page cache serves one thread only: garbage reads, crashes about
  // every other run. It must take the mode again (two threads only through a fork) and give
  // the output of one thread, every time.
  Mesh s = BumpySphere(7); // 163,842 vertices, 327,680 faces, no point data
  ASSERT_GE(s.Triangles(), 65536u); // the rings run on all cores from here in core
  const std::uint64_t nv = s.Vertices(), nf = s.Triangles();
  // Positions (3 doubles), faces (3 indices) and ring offsets fit; the 3 nf ring faces only
  // half: the budget lies halfway between.
  const std::uint64_t input = nv * 3 * sizeof(double) + nf * 3 * sizeof(std::uint32_t) +
    (nv + 1) * sizeof(std::uint32_t);
  alg::DecimateOptions o;
  o.targetTriangles = 4000;
  o.threads = 1;
  o.layout = alg::LayoutPolicy::Keep; // (the path under test is the input's own order)
  namespace fs = std::filesystem;
  const fs::path dir =
    fs::temp_directory_path() / ("sipmss_decimate_rings_switch_" + std::to_string(::getpid()));
  fs::create_directories(dir);
  o.storage.directories = { dir.string() };
  o.storage.memoryBudget = input + nf * 3 * sizeof(std::uint32_t) / 2;
  Outcome one = Simplify(MemorySource(s), o);
  ExpectValid(one.out);
  // The path: the input phase ends in core, the rings out of core.
  auto modeAfter = [](const alg::RunStats& st, const std::string& phase) {
    for (const auto& p : st.phases)
    {
      if (p.name == phase)
      {
        return p.mode;
      }
    }
    ADD_FAILURE() << "no phase " << phase << ": " << PhaseSummary(st);
    return st::Mode::InCore;
  };
  ASSERT_FALSE(one.stats.phases.empty());
  EXPECT_EQ(one.stats.phases.front().mode, st::Mode::InCore) << PhaseSummary(one.stats);
  EXPECT_EQ(modeAfter(one.stats, "rings"), st::Mode::OutOfCore) << PhaseSummary(one.stats);
  o.threads = 2;
  for (int run = 0; run < 10; ++run)
  {
    Outcome two = Simplify(MemorySource(s), o);
    EXPECT_EQ(modeAfter(two.stats, "rings"), st::Mode::OutOfCore) << PhaseSummary(two.stats);
    EXPECT_GT(two.stats.storage.forks, 0u); // the helper thread works through forks
    EXPECT_LE(two.stats.storage.peakBytes, o.storage.memoryBudget);
    ExpectSameOutput(one, two, "2 threads, run " + std::to_string(run));
    if (::testing::Test::HasFailure())
    {
      break;
    }
  }
  EXPECT_TRUE(fs::is_empty(dir)); // no file left behind
  fs::remove_all(dir);
}

} // namespace
