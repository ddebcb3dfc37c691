// The thread runner of the algorithm cores (private): decimation's parallel phases and the
// comparison's sampling run their threads through it.
#pragma once

#include <exception>
#include <functional>
#include <vector>

namespace sipmss::algorithms::detail
{
// Runs work(0) on the calling thread and work(1..T-1) on new ones, and joins them. A thread that
// cannot be started ends the list: onShort(started) runs before work(0), so that the caller can
// release those that did start. Returns how many ran. With whileWaiting (which must not throw),
// the calling thread runs it every 2 ms once work(0) is done and others are still running.
int RunOnThreads(int T, const std::function<void(int)>& work,
  const std::function<void(int)>& onShort = nullptr,
  const std::function<void()>& whileWaiting = nullptr);

// Rethrows the first exception of a phase's threads, if any.
void RethrowFirst(const std::vector<std::exception_ptr>& errors);
} // namespace sipmss::algorithms::detail
