// The one rule for the number of threads of every layer and front end.
#pragma once

#include <thread>

namespace sipmss::storage
{
// A request above 0 is taken as it is; 0 (or less: "automatic") is every core the machine
// reports, at least 1. The output of every algorithm is the same for any value.
inline int ResolveThreads(int requested)
{
  if (requested > 0)
  {
    return requested;
  }
  const unsigned cores = std::thread::hardware_concurrency();
  return cores == 0 ? 1 : static_cast<int>(cores);
}
} // namespace sipmss::storage
