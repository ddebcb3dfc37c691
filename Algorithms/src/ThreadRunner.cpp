#include "ThreadRunner.h"

#include <atomic>
#include <chrono>
#include <system_error>
#include <thread>

namespace sipmss::algorithms::detail
{
int RunOnThreads(int T, const std::function<void(int)>& work, const std::function<void(int)>& onShort,
  const std::function<void()>& whileWaiting)
{
  std::vector<std::thread> workers;
  std::atomic<int> finished{ 0 };
  int started = 1;
  for (; started < T; ++started)
  {
    try
    {
      workers.emplace_back([&work, &finished](int t) {
        work(t);
        finished.fetch_add(1);
      }, started);
    }
    catch (const std::system_error&)
    {
      if (onShort)
      {
        onShort(started);
      }
      break;
    }
  }
  work(0);
  if (whileWaiting)
  {
    while (finished.load() < int(workers.size()))
    {
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      whileWaiting();
    }
  }
  for (std::thread& w : workers)
  {
    w.join();
  }
  return started;
}

void RethrowFirst(const std::vector<std::exception_ptr>& errors)
{
  for (const std::exception_ptr& e : errors)
  {
    if (e)
    {
      std::rethrow_exception(e);
    }
  }
}

} // namespace sipmss::algorithms::detail
