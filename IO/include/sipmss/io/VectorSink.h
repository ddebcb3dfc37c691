// A MeshSink that collects positions and triangles into plain vectors (for tools that need the
// whole mesh in memory: `sipmss compare`, sipmss-meshgen, the meshoptimizer bench peer).
#pragma once

#include "sipmss/io/MeshIO.h"

#include <algorithm>
#include <vector>

namespace sipmss::io
{

class VectorSink final : public MeshSink
{
public:
  VectorSink(std::vector<float>& points, std::vector<std::uint32_t>& triangles)
    : points_(points)
    , triangles_(triangles)
  {
  }
  void Begin(const MeshHeader&) override {}
  void Vertices(const VertexChunk& c) override
  {
    this->points_.resize(std::max(this->points_.size(), 3 * (c.first + c.count)));
    std::copy_n(c.xyz, 3 * c.count, this->points_.begin() + 3 * c.first);
  }
  void Triangles(const std::uint32_t* indices, std::size_t count) override
  {
    this->triangles_.insert(this->triangles_.end(), indices, indices + 3 * count);
  }
  void End(const ReadStats&) override {}

private:
  std::vector<float>& points_;
  std::vector<std::uint32_t>& triangles_;
};

} // namespace sipmss::io
