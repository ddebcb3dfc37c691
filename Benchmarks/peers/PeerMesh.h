// The peers' drivers share this: read a mesh with SIPMSS's streaming reader into memory, write the
// used vertices of an index list, and print the JSON line scripts/bench reads.
#pragma once

#include "sipmss/io/MeshIO.h"
#include "sipmss/io/VectorSink.h"

#include <chrono>
#include <cstdint>
#include <cstdio>
#include <string>
#include <vector>

namespace sipmss::bench
{
struct PeerMesh
{
  std::vector<float> p;          // xyz per vertex
  std::vector<std::uint32_t> t;  // three indices per triangle
};

inline PeerMesh ReadPeerMesh(const std::string& path)
{
  PeerMesh m;
  io::VectorSink sink(m.p, m.t);
  io::ReadMesh(path, sink);
  return m;
}

// Writes the vertices `indices` use (renumbered in order of first use) and the triangles.
inline void WriteUsed(const std::string& path, const std::vector<float>& p,
  std::vector<std::uint32_t> indices)
{
  std::vector<std::uint32_t> remap(p.size() / 3, ~0u);
  std::vector<float> pts;
  for (auto& v : indices)
  {
    if (remap[v] == ~0u)
    {
      remap[v] = static_cast<std::uint32_t>(pts.size() / 3);
      pts.insert(pts.end(), &p[3 * v], &p[3 * v + 3]);
    }
    v = remap[v];
  }
  auto w = io::MeshWriter::Create(path);
  w->Begin(pts.size() / 3, indices.size() / 3, io::VertexLayout{});
  io::VertexChunk c;
  c.count = pts.size() / 3;
  c.xyz = pts.data();
  if (c.count)
  {
    w->Vertices(c);
  }
  if (!indices.empty())
  {
    w->Triangles(indices.data(), indices.size() / 3);
  }
  w->End();
}

using Clock = std::chrono::steady_clock;
inline double Seconds(Clock::time_point a, Clock::time_point b)
{
  return std::chrono::duration<double>(b - a).count();
}

inline void PrintResult(double read, double filter, std::size_t triangles, double resultError)
{
  std::printf("{\"read\": %.6f, \"filter\": %.6f, \"triangles\": %zu, \"result_error\": %.6g}\n",
    read, filter, triangles, resultError);
}
} // namespace sipmss::bench
