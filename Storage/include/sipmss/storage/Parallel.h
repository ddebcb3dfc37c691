// The one way an algorithm runs a phase on several threads: a parallel-for over element ranges
// with declared write ranges.
//
// A phase over the elements [0, n) declares the blocks it writes, each worker only within its
// own range of elements (and, out of core, any further ranges its helper writes). Workers then
// decides how the phase runs, so that no algorithm tests the storage mode:
//   - in core: on up to `threads` threads sharing the blocks' memory (from `inCoreMin` elements);
//   - out of core: on two threads when the budget can be shared: the upper half of the range on a
//     helper thread through a DML forked from the algorithm's (DML::Fork lends it half of the
//     budget and its declared ranges), joined when the phase ends; not while the phase's
//     ForkRecord says that its last forked run thrashed;
//   - else on the calling thread alone.
// Worker t reads and writes through Dml(t) with views made by Bind (restricted to its write
// ranges: checked in builds with SIPMSS_CHECK_WRITES, Access.h). The output of a phase must not
// depend on how many workers ran it.
#pragma once

#include "sipmss/storage/Access.h"
#include "sipmss/storage/DML.h"

#include <atomic>
#include <cstdint>
#include <exception>
#include <functional>
#include <memory>
#include <vector>

namespace sipmss::storage
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

// A worker's body: its index t, its elements [begin, end), and the phase's stop flag (set when
// another worker threw, e.g. an abort: return early). The bodies must be independent of each
// other (each writes only its own ranges).
using RangeBody =
  std::function<void(int t, std::uint64_t begin, std::uint64_t end, const std::atomic<bool>& stop)>;

// What a phase that runs again and again (each pass of an algorithm) learns of its helper out
// of core. A forked phase that misses more than kThrash times the pages of the block files
// (each half budget too small for its window of pages: the two threads evict each other's
// pages, where one thread with the whole budget would not) runs on one thread from then on,
// until the blocks' files shrink to half the bytes they had then; it is then tried forked
// again. Its output does not depend on it (a phase's never depends on its workers).
struct ForkRecord
{
  static constexpr std::uint64_t kThrash = 16;
  std::uint64_t declinedAtFileBytes = 0; // 0: the helper is welcome
  std::uint64_t declined = 0;            // phases run on one thread because of it
};

// What a phase over [0, elements) needs to know to run in parallel.
struct Phase
{
  static constexpr std::uint64_t kHalf = ~std::uint64_t(0);
  std::uint64_t elements = 0;
  int threads = 1;              // at most this many workers (ResolveThreads first)
  bool inCoreThreads = true;    // in core: on `threads` threads (false: on one)
  std::uint64_t inCoreMin = 0;  // in core: fewer elements run on one thread
  bool helper = true;           // out of core: a helper thread may take the upper part
  // The second worker's first element when there are two (default: elements / 2); with more
  // (in core), the range is cut evenly. A phase of two parts asks for two threads.
  std::uint64_t helperFirst = kHalf;
  std::vector<BlockId> writes;  // blocks written, each worker within its own element range
  std::vector<DML::Range> helperWrites; // out of core: more ranges the helper writes
  std::vector<BlockId> mainWrites; // blocks only worker 0 writes (all of them), never the others
  ForkRecord* record = nullptr;     // out of core: where a repeated phase keeps what it learned
  // Out of core: the bytes of cached pages a worker needs at once (its window over the blocks
  // it reads); with less in half the budget the phase runs on one thread, which has it all.
  std::uint64_t minBytes = 0;
};

class Workers
{
public:
  // Out of core, below this many elements a phase runs on one thread (its sweep is short).
  static constexpr std::uint64_t kHelperMin = 65536;

  Workers(DML& dml, const Phase& phase);
  ~Workers(); // joins a helper still forked (its errors are dropped: see Join)
  Workers(const Workers&) = delete;
  Workers& operator=(const Workers&) = delete;

  int Count() const { return this->count_; }
  // Out of core on two threads: worker 1 goes through a forked DML.
  bool Forked() const { return this->fork_ != nullptr; }
  // In core on several threads: the workers share the blocks' memory.
  bool Shared() const { return this->count_ > 1 && !this->fork_; }
  DML& Dml(int t) const { return (t == 1 && this->fork_) ? *this->fork_ : this->dml_; }
  // Worker t's elements: [Begin(t), Begin(t + 1)) (the helper's from Phase::helperFirst).
  std::uint64_t Begin(int t) const
  {
    if (this->count_ == 2 && t == 1)
    {
      return this->split_;
    }
    return this->phase_.elements * std::uint64_t(t) / std::uint64_t(this->count_);
  }
  // The elements worker t may write in block id.
  WriteBounds Bounds(int t, BlockId id) const;
  // A view of `a` for worker t: through Dml(t), restricted to Bounds(t, a's block).
  template <class T>
  View<T> Bind(int t, const Array<T>& a) const
  {
    return View<T>(this->Dml(t), a, this->Bounds(t, a.Id()));
  }
  // Ends the helper: its writes become visible to the algorithm's DML (DML::Join), and a forked
  // phase has one worker from then on. Call once the workers are done, before the algorithm's
  // DML is used for anything else; errors throw.
  void Join();
  // Out of core with a helper (the phase's ForkRecord): how many misses `elements` of the
  // phase's elements may cost before the forked run counts as thrashing (kThrash reads of their
  // share of the block files; any worker may ask), and DeclineHelper, which records a thrash so
  // that the phase runs on one thread next time (Join records one by itself from the misses of
  // the whole phase).
  double MissLimit(std::uint64_t elements) const;
  void DeclineHelper();
  // body(t, Begin(t), Begin(t + 1), stop) on each worker (0: the calling thread); the range of
  // a worker that cannot be started runs on the calling thread afterwards (after the helper is
  // joined, through the algorithm's DML, with every write allowed). With poll (e.g. a progress
  // check), the calling thread polls every 2 ms while it waits for the others, so that one
  // costly element on another worker does not hold an abort back. Joins at the end.
  void Run(const RangeBody& body, const std::function<void()>& poll = nullptr);
  // A phase of `tasks` different jobs over the same elements (e.g. one moves the quadrics, the
  // other the rest; their write ranges as declared for workers 0 and 1): task k on worker k
  // when there are that many workers, else every task on the calling thread in order. The
  // tasks of workers that cannot be started run on the calling thread afterwards (after the
  // helper is joined). body(t, task, stop): t is the worker whose views the task uses.
  using TaskBody = std::function<void(int t, int task, const std::atomic<bool>& stop)>;
  void RunTasks(int tasks, const TaskBody& body);

private:
  DML& dml_;
  Phase phase_;
  int count_ = 1;
  std::uint64_t split_ = 0; // the helper's first element
  // Joins the helper and leaves one worker, the calling thread, which then writes anywhere (a
  // worker could not be started: its part runs there).
  void Alone();
  std::unique_ptr<DML> fork_;
  // Out of core with a helper: the misses, the files' bytes and pages when it was forked
  // (ForkRecord; MissLimit reads no DML, so any worker may call it).
  std::uint64_t forkMisses_ = 0, forkFileBytes_ = 0, forkPages_ = 1;
};
} // namespace sipmss::storage
