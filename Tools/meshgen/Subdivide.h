// sipmss-meshgen subdivide within a memory budget (Subdivide.cpp).
#pragma once

#include <cstdint>
#include <functional>
#include <string>
#include <vector>

namespace sipmss::meshgen
{
struct SubdivideStats
{
  std::uint64_t vertices = 0, triangles = 0;
  bool outOfCore = false;
  std::uint64_t peakBytes = 0, peakFileBytes = 0; // the blocks' memory and temporary files
};

// Reads `input`, subdivides it `levels` times (midpoint subdivision, the new vertices displaced
// along the normal by `displace` times the edge length, at random) and writes `output`: the
// vertices along the longest axis and the faces by their lowest vertex when scannerOrder, else
// as made (the new vertices after the old ones) unless inMemoryOrder is given: then the mesh is
// copied into memory for it (points, triangles) before it is written. Within memoryBudget bytes
// (0: unbounded) plus buffers of a few MB, temporary block files in `directories`.
SubdivideStats SubdivideFile(const std::string& input, const std::string& output, int levels,
  double displace, bool scannerOrder, std::uint64_t memoryBudget,
  const std::vector<std::string>& directories,
  const std::function<void(std::vector<float>&, std::vector<std::uint32_t>&)>& inMemoryOrder =
    nullptr);
} // namespace sipmss::meshgen
