// sipmss-meshgen subdivide within a memory budget (Subdivide.cpp).
#pragma once

#include <cstdint>
#include <functional>
#include <stdexcept>
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

// The order of the output: the scanner order (the vertices along the longest axis, the faces by
// their lowest vertex) or shuffled (both in a random order fixed by a seed).
enum class Order
{
  Scanner,
  Shuffled
};

// Thrown by SubdivideFile when stopRequested returned true (its blocks are gone by then).
struct Interrupted : std::runtime_error
{
  Interrupted()
    : std::runtime_error("interrupted")
  {
  }
};

// Reads `input`, subdivides it `levels` times (midpoint subdivision, the new vertices displaced
// along the normal by `displace` times the edge length, at random) and writes `output` in
// `order`, within memoryBudget bytes (0: unbounded) plus buffers of a few MB, temporary block
// files in `directories`. stopRequested (if set) is asked between chunks of every pass and in
// the sorts: when it returns true the run throws Interrupted.
SubdivideStats SubdivideFile(const std::string& input, const std::string& output, int levels,
  double displace, Order order, std::uint64_t memoryBudget,
  const std::vector<std::string>& directories, const std::function<bool()>& stopRequested = {});
} // namespace sipmss::meshgen
