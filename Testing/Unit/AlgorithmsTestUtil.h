// Shared by the algorithm tests: a plain mesh, a MeshSource over it, a sink collecting a mesh.
#pragma once

#include "sipmss/algorithms/Common.h"

#include <vector>

namespace sipmss::testing
{
struct Mesh
{
  std::vector<float> p;
  std::vector<std::uint32_t> t;
  std::vector<float> scalar; // optional point scalar "s"
};

inline algorithms::MeshSource MemorySource(const Mesh& m)
{
  return [&m](io::MeshSink& sink, const io::ReadOptions& options) {
    io::MeshHeader h;
    h.vertexCount = m.p.size() / 3;
    h.faceCount = m.t.size() / 3;
    if (!m.scalar.empty())
    {
      h.layout.scalars = { "s" };
    }
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
  void Begin(const io::MeshHeader& h) override { this->header = h; }
  void Vertices(const io::VertexChunk& c) override
  {
    this->m.p.insert(this->m.p.end(), c.xyz, c.xyz + 3 * c.count);
    if (c.scalars)
    {
      this->m.scalar.insert(this->m.scalar.end(), c.scalars, c.scalars + c.count);
    }
  }
  void Triangles(const std::uint32_t* i, std::size_t n) override
  {
    this->m.t.insert(this->m.t.end(), i, i + 3 * n);
  }
  void End(const io::ReadStats&) override {}
};

} // namespace sipmss::testing
