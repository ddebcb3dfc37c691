#include "sipmss/storage/Parallel.h"

#include <algorithm>
#include <chrono>
#include <system_error>
#include <thread>

namespace sipmss::storage
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
    catch (...) // (std::system_error, or std::bad_alloc for the thread's state)
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

namespace
{
// body(t, begin(t), begin(t + 1), stop) on T threads; returns how many started (the caller runs
// the rest). The first exception of any thread (or of poll) is rethrown once all are done.
int RunRanges(int T, const std::function<std::uint64_t(int)>& begin, const RangeBody& body,
  const std::function<void()>& poll, std::atomic<bool>& stop)
{
  std::vector<std::exception_ptr> errors(static_cast<std::size_t>(T));
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
  return started;
}
} // namespace

Workers::Workers(DML& dml, const Phase& phase)
  : dml_(dml)
  , phase_(phase)
{
  this->split_ = phase.helperFirst == Phase::kHalf ? phase.elements / 2
                                                   : std::min(phase.helperFirst, phase.elements);
  if (dml.GetMode() == Mode::InCore)
  {
    if (phase.inCoreThreads && phase.elements >= phase.inCoreMin)
    {
      this->count_ = std::max(1, phase.threads);
    }
    return;
  }
  const std::uint64_t budget = dml.GetProfile().memoryBudget;
  if (!phase.helper || phase.threads < 2 || phase.elements < kHelperMin || budget == 0 ||
    budget / 2 < phase.minBytes)
  {
    return;
  }
  const Stats before = dml.GetStats();
  ForkRecord* record = phase.record;
  if (record && record->declinedAtFileBytes)
  {
    if (2 * before.fileBytes > record->declinedAtFileBytes)
    {
      ++record->declined;
      return;
    }
    record->declinedAtFileBytes = 0; // the blocks have halved since: try the helper again
  }
  const std::uint64_t mid = this->split_;
  std::vector<DML::Range> ranges;
  for (BlockId id : phase.writes)
  {
    ranges.push_back({ id, mid, phase.elements - mid });
  }
  ranges.insert(ranges.end(), phase.helperWrites.begin(), phase.helperWrites.end());
  try
  {
    this->fork_ = dml.Fork(budget / 2, ranges);
  }
  catch (const BudgetError&)
  {
    return; // too little room to share: one thread
  }
  if (this->fork_)
  {
    this->count_ = 2;
    this->forkMisses_ = before.misses;
    this->forkFileBytes_ = before.fileBytes;
    const std::uint64_t page = std::max<std::uint64_t>(dml.PageBytes(), 1);
    this->forkPages_ = std::max<std::uint64_t>((before.fileBytes + page - 1) / page, 1);
  }
}

Workers::~Workers()
{
  try
  {
    this->Join();
  }
  catch (...)
  {
    // (only on an error path: the normal one joins and sees the helper's errors)
  }
}

WriteBounds Workers::Bounds(int t, BlockId id) const
{
  if (this->count_ == 1)
  {
    return {};
  }
  if (std::find(this->phase_.mainWrites.begin(), this->phase_.mainWrites.end(), id) !=
    this->phase_.mainWrites.end())
  {
    return t == 0 ? WriteBounds() : WriteBounds::None();
  }
  const bool own = std::find(this->phase_.writes.begin(), this->phase_.writes.end(), id) !=
    this->phase_.writes.end();
  if (own)
  {
    return { this->Begin(t), this->Begin(t + 1), 0, 0 };
  }
  for (const DML::Range& r : this->phase_.helperWrites)
  {
    if (r.id == id)
    {
      if (!this->fork_)
      {
        return {}; // (in core: the phase's own rule, not checked here)
      }
      if (t == 1)
      {
        return { r.first, r.first + r.count, 0, 0 };
      }
      return { 0, std::numeric_limits<std::uint64_t>::max(), r.first, r.first + r.count };
    }
  }
  return WriteBounds::None();
}

void Workers::Join()
{
  if (this->fork_)
  {
    std::unique_ptr<DML> fork = std::move(this->fork_);
    this->count_ = 1; // (the helper is gone: what is left of the phase runs on one worker)
    this->dml_.Join(*fork);
    const std::uint64_t misses = this->dml_.GetStats().misses - this->forkMisses_;
    if (double(misses) > this->MissLimit(this->phase_.elements))
    {
      this->DeclineHelper();
    }
  }
}

double Workers::MissLimit(std::uint64_t elements) const
{
  return double(ForkRecord::kThrash) * double(this->forkPages_) * double(elements) /
    double(std::max<std::uint64_t>(this->phase_.elements, 1));
}

void Workers::DeclineHelper()
{
  if (this->phase_.record)
  {
    this->phase_.record->declinedAtFileBytes = std::max<std::uint64_t>(this->forkFileBytes_, 1);
  }
}

void Workers::Alone()
{
  this->Join();
  this->count_ = 1; // (the calling thread writes anywhere from now on)
}

void Workers::Run(const RangeBody& body, const std::function<void()>& poll)
{
  std::atomic<bool> stop{ false };
  const int started =
    RunRanges(this->count_, [this](int t) { return this->Begin(t); }, body, poll, stop);
  if (started < this->count_)
  {
    const std::uint64_t from = this->Begin(started);
    this->Alone(); // (the calling thread takes the rest of the range)
    body(0, from, this->phase_.elements, stop);
  }
  this->Join();
}

void Workers::RunTasks(int tasks, const TaskBody& body)
{
  std::atomic<bool> stop{ false };
  int started = 0;
  if (this->count_ >= tasks)
  {
    // (task t is the one-element range [t, t + 1) of worker t)
    started = RunRanges(tasks, [](int t) { return std::uint64_t(t); },
      [&body](int t, std::uint64_t task, std::uint64_t, const std::atomic<bool>& halt) {
        body(t, int(task), halt);
      },
      nullptr, stop);
  }
  if (started < tasks)
  {
    this->Alone();
    for (int k = started; k < tasks && !stop.load(); ++k)
    {
      body(0, k, stop);
    }
  }
  this->Join();
}
} // namespace sipmss::storage
