// Shared by the algorithm tests: a plain mesh, a MeshSource over it, a sink collecting a mesh.
#pragma once

#include "sipmss/algorithms/Common.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <map>
#include <numeric>
#include <random>
#include <set>
#include <string>
#include <vector>

namespace sipmss::testing
{
struct Mesh
{
  std::vector<float> p;
  std::vector<std::uint32_t> t;
  // Optional point scalars: `names` with names.size() values per vertex in `scalar`; without
  // names, a non-empty `scalar` is the one scalar "s".
  std::vector<float> scalar;
  std::vector<std::string> names;
  std::vector<std::string> Names() const
  {
    return !this->names.empty() ? this->names
                                : (this->scalar.empty() ? std::vector<std::string>{}
                                                        : std::vector<std::string>{ "s" });
  }
};

// The triangles of an (n + 1) x (n + 1) grid of vertices numbered row by row: two per quad, the
// same diagonal in each.
inline void GridTriangles(int n, std::vector<std::uint32_t>& t)
{
  auto id = [n](int i, int j) { return std::uint32_t(j * (n + 1) + i); };
  for (int j = 0; j < n; ++j)
  {
    for (int i = 0; i < n; ++i)
    {
      t.insert(t.end(), { id(i, j), id(i + 1, j), id(i + 1, j + 1) });
      t.insert(t.end(), { id(i, j), id(i + 1, j + 1), id(i, j + 1) });
    }
  }
}

// A closed, bumpy UV sphere of radius about 1 around `centre`: n rings of 2n vertices and the
// two poles (4 n^2 triangles), scalar s = z.
inline Mesh BumpyUVSphere(int n, const std::array<double, 3>& centre = { 0, 0, 0 })
{
  Mesh m;
  const double pi = 3.14159265358979323846;
  auto add = [&](double x, double y, double z) {
    const double r = 1.0 + 0.08 * std::sin(5 * x) * std::cos(4 * y) + 0.05 * std::sin(7 * z);
    m.p.insert(m.p.end(), { float(centre[0] + r * x), float(centre[1] + r * y),
      float(centre[2] + r * z) });
    m.scalar.push_back(float(z));
  };
  add(0, 0, 1);
  for (int i = 1; i <= n; ++i)
  {
    const double theta = pi * i / (n + 1);
    for (int j = 0; j < 2 * n; ++j)
    {
      const double phi = pi * j / n;
      add(std::sin(theta) * std::cos(phi), std::sin(theta) * std::sin(phi), std::cos(theta));
    }
  }
  add(0, 0, -1);
  const std::uint32_t south = std::uint32_t(m.p.size() / 3 - 1);
  auto ring = [n](int i, int j) { return std::uint32_t(1 + (i - 1) * 2 * n + (j % (2 * n))); };
  for (int j = 0; j < 2 * n; ++j)
  {
    m.t.insert(m.t.end(), { 0, ring(1, j), ring(1, j + 1) });
    m.t.insert(m.t.end(), { south, ring(n, j + 1), ring(n, j) });
    for (int i = 1; i < n; ++i)
    {
      m.t.insert(m.t.end(), { ring(i, j), ring(i + 1, j), ring(i + 1, j + 1) });
      m.t.insert(m.t.end(), { ring(i, j), ring(i + 1, j + 1), ring(i, j + 1) });
    }
  }
  return m;
}

// The mesh with its vertices and faces in another order and each face's corners rotated (the
// same surface, orientation kept), from a fixed seed.
inline Mesh Shuffled(const Mesh& m, unsigned seed)
{
  std::mt19937 rng(seed);
  const std::size_t nv = m.p.size() / 3, nf = m.t.size() / 3;
  const std::size_t ns = nv ? m.scalar.size() / nv : 0;
  std::vector<std::uint32_t> order(nv), where(nv);
  std::iota(order.begin(), order.end(), 0u);
  std::shuffle(order.begin(), order.end(), rng);
  Mesh s;
  s.names = m.names;
  for (std::size_t i = 0; i < nv; ++i)
  {
    where[order[i]] = std::uint32_t(i);
    s.p.insert(s.p.end(), m.p.begin() + 3 * order[i], m.p.begin() + 3 * order[i] + 3);
    s.scalar.insert(
      s.scalar.end(), m.scalar.begin() + ns * order[i], m.scalar.begin() + ns * (order[i] + 1));
  }
  std::vector<std::size_t> faces(nf);
  std::iota(faces.begin(), faces.end(), std::size_t(0));
  std::shuffle(faces.begin(), faces.end(), rng);
  for (std::size_t f : faces)
  {
    const int r = int(rng() % 3);
    for (int k = 0; k < 3; ++k)
    {
      s.t.push_back(where[m.t[3 * f + (k + r) % 3]]);
    }
  }
  return s;
}

// A mesh's triangles by their corners' coordinates, each rotated to start at its smallest corner
// (orientation kept): two meshes with the same set are the same surface, vertex for vertex.
inline std::multiset<std::array<float, 9>> TrianglesByCoordinates(const Mesh& m)
{
  std::multiset<std::array<float, 9>> out;
  for (std::size_t f = 0; f + 2 < m.t.size(); f += 3)
  {
    std::array<std::array<float, 3>, 3> c;
    for (int k = 0; k < 3; ++k)
    {
      std::copy_n(m.p.begin() + 3 * m.t[f + k], 3, c[k].begin());
    }
    const int first = int(std::min_element(c.begin(), c.end()) - c.begin());
    std::array<float, 9> t;
    for (int k = 0; k < 3; ++k)
    {
      std::copy_n(c[(first + k) % 3].begin(), 3, t.begin() + 3 * k);
    }
    out.insert(t);
  }
  return out;
}

// How the distributed tests cut a mesh into the ranks' pieces.
enum class Cut
{
  Blocks,      // contiguous runs of faces (a file split by byte ranges)
  Slabs,       // by the face's centroid along x (a spatial partition, as RedistributeDataSet)
  Interleaved, // face f to rank f % N (seams everywhere)
  LastEmpty    // blocks over N - 1 ranks; the last rank's piece is empty
};

// Rank r's piece: its faces and the vertices they use, renumbered in order of first use (a vertex
// on a seam is in several pieces, as the pieces of a distributed vtkPolyData are).
inline Mesh Piece(const Mesh& m, int ranks, int r, Cut cut)
{
  const std::size_t nf = m.t.size() / 3;
  const std::size_t ns = m.p.empty() ? 0 : m.scalar.size() / (m.p.size() / 3);
  float lo = 1e30f, hi = -1e30f;
  for (std::size_t i = 0; i < m.p.size(); i += 3)
  {
    lo = std::min(lo, m.p[i]);
    hi = std::max(hi, m.p[i]);
  }
  auto rankOf = [&](std::size_t f) {
    switch (cut)
    {
      case Cut::Blocks:
        return int(f * std::size_t(ranks) / nf);
      case Cut::LastEmpty:
        return ranks == 1 ? 0 : int(f * std::size_t(ranks - 1) / nf);
      case Cut::Interleaved:
        return int(f % std::size_t(ranks));
      default:
      {
        float x = 0;
        for (int k = 0; k < 3; ++k)
        {
          x += m.p[3 * m.t[3 * f + k]] / 3;
        }
        return std::min(ranks - 1, int((x - lo) / (hi - lo) * float(ranks)));
      }
    }
  };
  Mesh piece;
  piece.names = m.names;
  std::map<std::uint32_t, std::uint32_t> renumber;
  for (std::size_t f = 0; f < nf; ++f)
  {
    if (rankOf(f) != r)
    {
      continue;
    }
    for (int k = 0; k < 3; ++k)
    {
      const std::uint32_t v = m.t[3 * f + k];
      auto it = renumber.find(v);
      if (it == renumber.end())
      {
        it = renumber.emplace(v, std::uint32_t(renumber.size())).first;
        piece.p.insert(piece.p.end(), m.p.begin() + 3 * v, m.p.begin() + 3 * v + 3);
        piece.scalar.insert(
          piece.scalar.end(), m.scalar.begin() + ns * v, m.scalar.begin() + ns * (v + 1));
      }
      piece.t.push_back(it->second);
    }
  }
  return piece;
}

inline algorithms::MeshSource MemorySource(const Mesh& m)
{
  return [&m](io::MeshSink& sink, const io::ReadOptions& options) {
    io::MeshHeader h;
    h.vertexCount = m.p.size() / 3;
    h.faceCount = m.t.size() / 3;
    h.layout.scalars = m.Names();
    sink.Begin(h);
    io::VertexChunk c;
    c.count = m.p.size() / 3;
    c.xyz = m.p.data();
    c.scalars = m.scalar.empty() ? nullptr : m.scalar.data();
    sink.Vertices(c);
    io::ReadStats s;
    s.vertices = c.count;
    if (!options.verticesOnly)
    {
      sink.Triangles(m.t.data(), m.t.size() / 3);
      s.triangles = m.t.size() / 3;
      sink.End(s);
    }
    return s;
  };
}

// A progress that reports an abort after `limit` polls (0: at once).
struct AbortLater final : algorithms::Progress
{
  int polls = 0;
  int limit;
  explicit AbortLater(int n)
    : limit(n)
  {
  }
  void Report(double, const char*) override {}
  bool Aborted() override { return ++this->polls > this->limit; }
};

struct Collect final : io::MeshSink
{
  Mesh m;
  io::MeshHeader header;
  void Begin(const io::MeshHeader& h) override
  {
    this->header = h;
    if (h.layout.scalars.size() != 1 || h.layout.scalars[0] != "s")
    {
      this->m.names = h.layout.scalars;
    }
  }
  void Vertices(const io::VertexChunk& c) override
  {
    this->m.p.insert(this->m.p.end(), c.xyz, c.xyz + 3 * c.count);
    if (c.scalars)
    {
      this->m.scalar.insert(this->m.scalar.end(), c.scalars,
        c.scalars + this->header.layout.scalars.size() * c.count);
    }
  }
  void Triangles(const std::uint32_t* i, std::size_t n) override
  {
    this->m.t.insert(this->m.t.end(), i, i + 3 * n);
  }
  void End(const io::ReadStats&) override {}
};

} // namespace sipmss::testing
