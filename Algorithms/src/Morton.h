// Morton (Z-order) codes: the layout step's vertex order (StoredMesh::Reorder) and the
// comparison's triangle order (Compare.cpp).
#pragma once

#include <cstdint>

namespace sipmss::algorithms::detail
{
// The low 21 bits of x spread to every third bit (bit i to bit 3i): three coordinates spread and
// shifted by 0, 1 and 2 interleave into a 63-bit Morton code (z y x from the top).
inline std::uint64_t Spread21(std::uint64_t x)
{
  x &= 0x1fffff;
  x = (x | x << 32) & 0x1f00000000ffffULL;
  x = (x | x << 16) & 0x1f0000ff0000ffULL;
  x = (x | x << 8) & 0x100f00f00f00f00fULL;
  x = (x | x << 4) & 0x10c30c30c30c30c3ULL;
  x = (x | x << 2) & 0x1249249249249249ULL;
  return x;
}
} // namespace sipmss::algorithms::detail
