// Shared by the algorithm tests: a plain mesh, a MeshSource over it, a sink collecting a mesh.
#pragma once

#include "sipmss/algorithms/Common.h"

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
