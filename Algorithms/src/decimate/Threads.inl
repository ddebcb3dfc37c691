// Algorithm I: its phases cut into ranges of elements, one per thread.
// (Part of Decimate.cpp's translation unit; the map of the passes: Decimator.h.)
namespace sipmss::algorithms
{
namespace
{
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

} // namespace
} // namespace sipmss::algorithms
