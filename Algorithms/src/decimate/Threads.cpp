// Algorithm I: the thread runner of its parallel phases (what each does: Decimator.h).
#include "Decimator.h"

namespace sipmss::algorithms::decimate
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

void ForRanges(int T, std::uint64_t n, const RangeBody& body,
  const std::function<void()>& beforeFallback, const std::function<void()>& poll)
{
  auto begin = [n, T](int t) { return n * std::uint64_t(t) / std::uint64_t(T); };
  std::vector<std::exception_ptr> errors(static_cast<std::size_t>(T));
  std::atomic<bool> stop{ false };
  const int started = RunOnThreads(
    T,
    [&](int t) {
      try
      {
        body(t, begin(t), begin(t + 1), stop);
      }
      catch (...)
      {
        errors[std::size_t(t)] = std::current_exception();
        stop = true;
      }
    },
    nullptr,
    poll ? std::function<void()>([&]() {
      if (stop.load())
      {
        return;
      }
      try
      {
        poll();
      }
      catch (...)
      {
        errors[0] = std::current_exception();
        stop = true;
      }
    })
         : std::function<void()>());
  RethrowFirst(errors);
  if (started < T)
  {
    if (beforeFallback)
    {
      beforeFallback();
    }
    body(0, begin(started), n, stop);
  }
}

} // namespace sipmss::algorithms::decimate
