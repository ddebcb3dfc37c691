// A 64-bit finalizer (MurmurHash3's fmix64): spreads keys over hash slots and owner ranks (the
// clustering's tables, the distributed runs) and keys the rounds of sipmss-meshgen's
// permutation. A bijection of the 64-bit numbers.
#pragma once

#include <cstdint>

namespace sipmss::storage
{
inline std::uint64_t Mix(std::uint64_t k)
{
  k ^= k >> 33;
  k *= 0xff51afd7ed558ccdULL;
  k ^= k >> 33;
  k *= 0xc4ceb9fe1a85ec53ULL;
  k ^= k >> 33;
  return k;
}
} // namespace sipmss::storage
