// The peers' drivers share this: read a mesh with SIPMSS's streaming reader into memory, write the
// used vertices of an index list, and print the JSON line scripts/bench reads.
#pragma once

#include "sipmss/io/MeshIO.h"
#include "sipmss/io/VectorSink.h"

#include <algorithm>
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
  // With ReadPeerMesh(path, true), the input's vertex normals and colors when it has them.
  std::vector<float> n;          // 3 per vertex, or empty
  std::vector<std::uint8_t> rgba; // 4 per vertex, or empty
};

// Collects positions and triangles (VectorSink), and normals and colors when asked.
class PeerSink final : public io::MeshSink
{
public:
  PeerSink(PeerMesh& m, bool attributes)
    : m_(m)
    , positions_(m.p, m.t)
    , attributes_(attributes)
  {
  }
  void Begin(const io::MeshHeader& h) override { this->positions_.Begin(h); }
  void Vertices(const io::VertexChunk& c) override
  {
    this->positions_.Vertices(c);
    if (this->attributes_ && c.normals)
    {
      this->m_.n.resize(3 * (c.first + c.count));
      std::copy_n(c.normals, 3 * c.count, this->m_.n.begin() + 3 * c.first);
    }
    if (this->attributes_ && c.rgba)
    {
      this->m_.rgba.resize(4 * (c.first + c.count));
      std::copy_n(c.rgba, 4 * c.count, this->m_.rgba.begin() + 4 * c.first);
    }
  }
  void Triangles(const std::uint32_t* indices, std::size_t count) override
  {
    this->positions_.Triangles(indices, count);
  }
  void End(const io::ReadStats& s) override { this->positions_.End(s); }

private:
  PeerMesh& m_;
  io::VectorSink positions_;
  bool attributes_;
};

inline PeerMesh ReadPeerMesh(const std::string& path, bool attributes = false)
{
  PeerMesh m;
  PeerSink sink(m, attributes);
  io::ReadMesh(path, sink);
  return m;
}

// Writes the vertices `indices` use (renumbered in order of first use) and the triangles, with
// the normals and colors of `attributes` (its p and t are not used) when given.
inline void WriteUsed(const std::string& path, const std::vector<float>& p,
  std::vector<std::uint32_t> indices, const PeerMesh* attributes = nullptr)
{
  const bool normals = attributes && !attributes->n.empty();
  const bool colors = attributes && !attributes->rgba.empty();
  std::vector<std::uint32_t> remap(p.size() / 3, ~0u);
  std::vector<float> pts, nrm;
  std::vector<std::uint8_t> rgba;
  for (auto& v : indices)
  {
    if (remap[v] == ~0u)
    {
      remap[v] = static_cast<std::uint32_t>(pts.size() / 3);
      pts.insert(pts.end(), &p[3 * v], &p[3 * v + 3]);
      if (normals)
      {
        nrm.insert(nrm.end(), &attributes->n[3 * v], &attributes->n[3 * v + 3]);
      }
      if (colors)
      {
        rgba.insert(rgba.end(), &attributes->rgba[4 * v], &attributes->rgba[4 * v + 4]);
      }
    }
    v = remap[v];
  }
  auto w = io::MeshWriter::Create(path);
  io::VertexLayout layout;
  layout.normals = normals;
  layout.colors = colors;
  w->Begin(pts.size() / 3, indices.size() / 3, layout);
  io::VertexChunk c;
  c.count = pts.size() / 3;
  c.xyz = pts.data();
  c.normals = normals ? nrm.data() : nullptr;
  c.rgba = colors ? rgba.data() : nullptr;
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
