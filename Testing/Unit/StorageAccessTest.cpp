// The accessor (View, CoreAccess, PagedAccess, WithAccess) and the parallel-for (Workers) in both
// storage modes: the same results either way, each worker's declared write ranges enforced
// (this file is built with SIPMSS_CHECK_WRITES), a helper's writes visible after Join.
#define SIPMSS_CHECK_WRITES 1
#include "StorageTestUtil.h"

#include "sipmss/storage/Access.h"
#include "sipmss/storage/Parallel.h"

#include <gtest/gtest.h>

#include <atomic>
#include <memory>
#include <numeric>
#include <random>
#include <string>
#include <vector>

namespace
{
using namespace sipmss::storage;
using sipmss::storage::testing::ListDir;
using sipmss::storage::testing::TempDir;

Profile OutOfCoreProfile(const std::string& dir, std::uint64_t budget)
{
  Profile p;
  p.directories = { dir };
  p.memoryBudget = budget;
  p.policy = ModePolicy::OutOfCore;
  return p;
}

// A DML in core, or out of core with `budget` bytes of pages in dir.
std::unique_ptr<DML> InCoreOrPaged(const TempDir& dir, bool outOfCore, std::uint64_t budget)
{
  auto dml = std::make_unique<DML>();
  if (outOfCore)
  {
    EXPECT_EQ(dml->Config(OutOfCoreProfile(dir.Path(), budget)), Mode::OutOfCore);
  }
  return dml;
}

// The sum of a block's elements times their index, through WithAccess; which kind it got.
template <class T>
std::pair<double, bool> WeightedSum(const View<T>& v, std::uint64_t n)
{
  return WithAccess(
    [n](auto a) {
      double sum = 0;
      for (std::uint64_t i = 0; i < n; ++i)
      {
        sum += double(i) * double(a.Get(i));
      }
      return std::make_pair(sum, decltype(a)::kInCore);
    },
    v);
}

TEST(StorageAccess, WithAccessGivesRawMemoryInCoreAndThePageCacheOutOfCore)
{
  TempDir dir;
  constexpr std::uint64_t n = 50000;
  double expected = 0;
  for (std::uint64_t i = 0; i < n; ++i)
  {
    expected += double(i) * double(i % 977);
  }
  for (const bool outOfCore : { false, true })
  {
    SCOPED_TRACE(outOfCore ? "out of core" : "in core");
    const std::unique_ptr<DML> owned = InCoreOrPaged(dir, outOfCore, 64 << 10);
    DML& dml = *owned;
    Array<std::uint32_t> a(dml, n);
    View<std::uint32_t> v(dml, a);
    EXPECT_EQ(v.InCore(), !outOfCore);
    WithAccess(
      [](auto w) {
        for (std::uint64_t i = 0; i < n; ++i)
        {
          w.Set(i, std::uint32_t(i % 977));
        }
      },
      v);
    const auto [sum, core] = WeightedSum(v, n);
    EXPECT_EQ(sum, expected);
    EXPECT_EQ(core, !outOfCore);
    // Run: in place in core (no copy), copied out of core; the same elements.
    std::vector<std::uint32_t> buffer;
    const std::uint32_t* run = v.Run(1000, 3000, buffer);
    EXPECT_EQ(run == v.Base() + 1000, !outOfCore);
    EXPECT_EQ(buffer.size(), outOfCore ? 3000u : 0u);
    for (std::uint64_t i = 0; i < 3000; ++i)
    {
      ASSERT_EQ(run[i], std::uint32_t((1000 + i) % 977));
    }
    v.Prefetch(n + 5); // (a hint, even past the end: never dereferenced)
  }
  EXPECT_TRUE(ListDir(dir.Path()).empty());
}

// Out of core several views of two blocks read and write at random (runs of nearby elements,
// then a jump; then only read) through a cache of a few pages, so that the pages their inline
// access finds in the DML's table are evicted, written back and replaced under them: every value
// read matches a model, and the blocks hold the model at the end, also after a page was written
// back and kept (Fork) and written again.
TEST(StorageAccess, ViewsFollowEvictionsAndWriteBacks)
{
  TempDir dir;
  {
    DML dml;
    ASSERT_EQ(dml.Config(OutOfCoreProfile(dir.Path(), 48 << 10)), Mode::OutOfCore);
    constexpr std::uint64_t n = 40000;
    Array<std::uint64_t> a(dml, n);
    Array<std::uint32_t> b(dml, n);
    std::vector<std::uint64_t> ma(n, 0);
    std::vector<std::uint32_t> mb(n, 0);
    // (the cache is built on the first access: views made before it take the slow path)
    const std::uint64_t zero = 0;
    dml.Write(a.Id(), sizeof(std::uint64_t), 0, &zero);
    std::vector<View<std::uint64_t>> va;
    std::vector<View<std::uint32_t>> vb;
    for (int k = 0; k < 3; ++k)
    {
      va.emplace_back(dml, a);
      vb.emplace_back(dml, b);
    }
    std::mt19937_64 rng(20261128);
    std::vector<std::uint64_t> at(6, 0);
    std::uint64_t runs = 0;
    for (int op = 0; op < 800000; ++op)
    {
      // (view 0 seldom: the pages it uses go old between its accesses)
      const std::size_t w = rng() % 50 == 0 ? 0 : std::size_t(1 + rng() % 5);
      std::uint64_t& i = at[w];
      i = rng() % 64 == 0 ? rng() % n : (i + rng() % 16) % n; // a run, sometimes a jump
      const bool write = op < 400000 && rng() % 3 == 0; // (then clean pages only are evicted)
      const std::uint64_t len = rng() % 8 == 0 ? 1 + rng() % 40 : 1;
      const std::uint64_t m = std::min(len, n - i);
      if (w < 3)
      {
        View<std::uint64_t>& v = va[w];
        if (write)
        {
          std::vector<std::uint64_t> x(m);
          for (std::uint64_t k = 0; k < m; ++k)
          {
            x[k] = rng();
            ma[i + k] = x[k];
          }
          m == 1 ? v.Set(i, x[0]) : v.SetRange(i, m, x.data());
        }
        else if (m == 1)
        {
          ASSERT_EQ(v.Get(i), ma[i]) << "op " << op << " view " << w << " element " << i;
        }
        else
        {
          std::vector<std::uint64_t> x(m);
          v.GetRange(i, m, x.data());
          ++runs;
          for (std::uint64_t k = 0; k < m; ++k)
          {
            ASSERT_EQ(x[k], ma[i + k]) << "op " << op << " view " << w << " element " << i + k;
          }
        }
      }
      else
      {
        View<std::uint32_t>& v = vb[w - 3];
        if (write)
        {
          const std::uint32_t x = std::uint32_t(rng());
          mb[i] = x;
          v.Set(i, x);
        }
        else
        {
          ASSERT_EQ(v.Get(i), mb[i]) << "op " << op << " view " << w << " element " << i;
        }
      }
    }
    // A page written back and kept (Fork writes this DML's dirty pages back first): a view
    // that wrote it must dirty it again, or its next write is lost when the page goes.
    {
      va[0].Set(7, 1111);
      std::unique_ptr<DML> child = dml.Fork(16 << 10, {});
      dml.Join(*child);
      va[0].Set(7, 2222);
      ma[7] = 2222;
      for (std::uint64_t i = 0; i < n; i += 64)
      {
        ASSERT_EQ(vb[0].Get(i), mb[i]); // (every page of b: a's pages go)
      }
      ASSERT_EQ(va[1].Get(7), 2222u);
    }
    EXPECT_GT(runs, 0u);
    const Stats st = dml.GetStats();
    EXPECT_GT(st.misses, 1000u) << "the pages must be evicted under the views";
    EXPECT_GT(st.hits, 100000u);
    const View<std::uint64_t> ca(dml, a);
    const View<std::uint32_t> cb(dml, b);
    for (std::uint64_t i = 0; i < n; ++i)
    {
      ASSERT_EQ(ca.Get(i), ma[i]) << i;
      ASSERT_EQ(cb.Get(i), mb[i]) << i;
    }
  }
  EXPECT_TRUE(ListDir(dir.Path()).empty());
}

// Peek and Prefetch, the prefetch hints: in core the block's memory; out of core the elements
// whose pages are in the DML's inline table, in place, and nothing for the others (nor past the
// block). A hint never reads or writes a page: the DML's counts do not move.
TEST(StorageAccess, PeekAndPrefetchUseOnlyThePagesAtHand)
{
  TempDir dir;
  constexpr std::uint64_t n = 50000; // 400 KB of elements, through 64 KiB of pages
  for (const bool outOfCore : { false, true })
  {
    SCOPED_TRACE(outOfCore ? "out of core" : "in core");
    const std::unique_ptr<DML> owned = InCoreOrPaged(dir, outOfCore, 64 << 10);
    DML& dml = *owned;
    Array<std::uint64_t> a(dml, n);
    View<std::uint64_t> v(dml, a);
    for (std::uint64_t i = 0; i < n; ++i)
    {
      v.Set(i, i * 7 + 3);
    }
    for (std::uint64_t i = 0; i < n; i += 97)
    {
      ASSERT_EQ(v.Get(i), i * 7 + 3); // (the cache now holds some of the pages)
    }
    v.Refresh();
    const Stats before = dml.GetStats();
    const std::uint64_t atHand = WithAccess(
      [&](auto w) {
        std::uint64_t found = 0;
        for (std::uint64_t i = 0; i < n; ++i)
        {
          if (const std::uint64_t* p = w.Peek(i))
          {
            EXPECT_EQ(*p, i * 7 + 3) << i;
            ++found;
          }
          v.Prefetch(i);
        }
        if constexpr (!decltype(w)::kInCore)
        {
          for (const std::uint64_t past : { n, n + 5, std::uint64_t(0xFFFFFFFFu) })
          {
            EXPECT_EQ(w.Peek(past), nullptr) << past;
            w.Prefetch(past);
            v.Prefetch(past);
          }
        }
        else
        {
          EXPECT_EQ(w.Peek(123), v.Base() + 123);
        }
        return found;
      },
      v);
    const Stats after = dml.GetStats();
    EXPECT_EQ(after.misses, before.misses);
    EXPECT_EQ(after.hits, before.hits);
    EXPECT_EQ(after.bytesRead, before.bytesRead);
    EXPECT_EQ(after.bytesWritten, before.bytesWritten);
    if (outOfCore)
    {
      EXPECT_GT(atHand, 0u) << "the cached pages' elements are at hand";
      EXPECT_LT(atHand, n / 2) << "64 KiB of pages hold less than half of the block";
    }
    else
    {
      EXPECT_EQ(atHand, n);
    }
  }
  EXPECT_TRUE(ListDir(dir.Path()).empty());
}

TEST(StorageAccess, WritesOutsideTheDeclaredBoundsThrow)
{
  DML dml;
  Array<double> a(dml, 100);
  View<double> v(dml, a, WriteBounds{ 10, 50, 20, 30 });
  EXPECT_NO_THROW(v.Set(10, 1.0));
  EXPECT_NO_THROW(v.Set(49, 1.0));
  EXPECT_NO_THROW(v.Set(30, 1.0));
  EXPECT_THROW(v.Set(9, 1.0), WriteOutOfBounds);
  EXPECT_THROW(v.Set(50, 1.0), WriteOutOfBounds);
  EXPECT_THROW(v.Set(25, 1.0), WriteOutOfBounds); // in the hole
  const double three[3] = { 1, 2, 3 };
  EXPECT_NO_THROW(v.SetRange(17, 3, three));
  EXPECT_THROW(v.SetRange(18, 3, three), WriteOutOfBounds); // its last element is in the hole
  EXPECT_THROW(
    WithAccess([](auto w) { w.Set(60, 2.0); }, v), WriteOutOfBounds); // (the kinds check too)
  View<double> none(dml, a, WriteBounds::None());
  EXPECT_THROW(none.Set(0, 1.0), WriteOutOfBounds);
  try
  {
    v.Set(25, 1.0);
  }
  catch (const WriteOutOfBounds& e)
  {
    const std::string what = e.what();
    EXPECT_NE(what.find("[25, 26)"), std::string::npos) << what;
    EXPECT_NE(what.find("[10, 50)"), std::string::npos) << what;
    EXPECT_NE(what.find("without [20, 30)"), std::string::npos) << what;
  }
  EXPECT_EQ(v.Get(25), 0.0); // (a refused write writes nothing)
}

// A phase over [0, n): each worker writes its own range of `owned` (and reads `other`). In core
// on every thread; out of core on two, the helper through a forked DML.
TEST(StorageAccess, WorkersSplitARangeAndEnforceTheirWrites)
{
  TempDir dir;
  constexpr std::uint64_t n = 200000;
  for (const bool outOfCore : { false, true })
  {
    SCOPED_TRACE(outOfCore ? "out of core" : "in core");
    DML dml;
    if (outOfCore)
    {
      ASSERT_EQ(dml.Config(OutOfCoreProfile(dir.Path(), 256 << 10)), Mode::OutOfCore);
    }
    Array<std::uint64_t> owned(dml, n), other(dml, n);
    for (std::uint64_t i = 0; i < n; ++i)
    {
      other.Set(i, 3 * i);
    }
    Phase phase;
    phase.elements = n;
    phase.threads = 3;
    phase.writes = { owned.Id() };
    {
      Workers workers(dml, phase);
      ASSERT_EQ(workers.Count(), outOfCore ? 2 : 3);
      EXPECT_EQ(workers.Forked(), outOfCore);
      EXPECT_EQ(workers.Shared(), !outOfCore);
      EXPECT_EQ(workers.Begin(0), 0u);
      EXPECT_EQ(workers.Begin(workers.Count()), n);
      const int count = workers.Count();
      std::vector<int> seen(std::size_t(count), 0);
      std::atomic<int> refused{ 0 };
      workers.Run([&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>&) {
        EXPECT_EQ(lo, workers.Begin(t));
        EXPECT_EQ(hi, workers.Begin(t + 1));
        View<std::uint64_t> mine = workers.Bind(t, owned);
        View<std::uint64_t> theirs = workers.Bind(t, other);
        WithAccess(
          [&](auto o, auto r) {
            for (std::uint64_t i = lo; i < hi; ++i)
            {
              o.Set(i, r.Get(i) + 1);
            }
          },
          mine, theirs);
        // Outside its range, and in a block it did not declare: refused.
        try
        {
          mine.Set(hi == n ? 0 : n - 1, 7);
        }
        catch (const WriteOutOfBounds&)
        {
          ++refused;
        }
        try
        {
          theirs.Set(lo, 7);
        }
        catch (const WriteOutOfBounds&)
        {
          ++refused;
        }
        seen[std::size_t(t)] = 1;
      });
      EXPECT_EQ(refused.load(), 2 * count);
      EXPECT_EQ(std::accumulate(seen.begin(), seen.end(), 0), count);
      EXPECT_FALSE(workers.Forked()); // (joined by Run: out of core, one worker from then on)
      EXPECT_EQ(workers.Count(), outOfCore ? 1 : 3);
    }
    for (std::uint64_t i = 0; i < n; i += 997)
    {
      ASSERT_EQ(owned.Get(i), 3 * i + 1) << i;
      ASSERT_EQ(other.Get(i), 3 * i) << i;
    }
    ASSERT_EQ(owned.Get(n - 1), 3 * (n - 1) + 1);
  }
}

// One worker for small phases, for one thread, and in core when the phase asks for it; the
// helper's first element and its extra ranges as declared; two tasks over the same elements.
TEST(StorageAccess, WorkersHelperRangesAndTasks)
{
  TempDir dir;
  {
    DML dml;
    Phase small;
    small.elements = 100;
    small.threads = 4;
    small.inCoreMin = 1000;
    EXPECT_EQ(Workers(dml, small).Count(), 1);
    small.inCoreMin = 0;
    small.inCoreThreads = false;
    EXPECT_EQ(Workers(dml, small).Count(), 1);
  }
  DML dml;
  ASSERT_EQ(dml.Config(OutOfCoreProfile(dir.Path(), 256 << 10)), Mode::OutOfCore);
  constexpr std::uint64_t n = 100000;
  Array<std::uint32_t> a(dml, n), b(dml, 2 * n), q(dml, n);
  {
    Phase one;
    one.elements = n;
    one.threads = 1;
    EXPECT_EQ(Workers(dml, one).Count(), 1);
    one.threads = 2;
    one.elements = Workers::kHelperMin - 1;
    EXPECT_EQ(Workers(dml, one).Count(), 1);
  }
  Phase phase;
  phase.elements = n;
  phase.threads = 2;
  phase.helperFirst = 0; // the second task writes every element of a
  phase.writes = { a.Id() };
  phase.helperWrites = { { b.Id(), n, n } }; // and the upper half of b
  phase.mainWrites = { q.Id() };             // the first task all of q
  Workers workers(dml, phase);
  ASSERT_TRUE(workers.Forked());
  EXPECT_EQ(workers.Begin(1), 0u);
  EXPECT_TRUE(workers.Bounds(0, b.Id()).Allows(0, n));
  EXPECT_FALSE(workers.Bounds(0, b.Id()).Allows(n, 1));
  EXPECT_TRUE(workers.Bounds(1, b.Id()).Allows(n, n));
  EXPECT_FALSE(workers.Bounds(1, b.Id()).Allows(n - 1, 1));
  EXPECT_FALSE(workers.Bounds(1, q.Id()).Allows(0, 1));
  EXPECT_FALSE(workers.Bounds(0, a.Id()).Allows(0, 1));
  std::vector<int> ran(2, -1);
  workers.RunTasks(2, [&](int t, int task, const std::atomic<bool>&) {
    ran[std::size_t(task)] = t;
    if (task == 0)
    {
      View<std::uint32_t> qv = workers.Bind(t, q), bv = workers.Bind(t, b);
      for (std::uint64_t i = 0; i < n; ++i)
      {
        qv.Set(i, std::uint32_t(i + 5));
        bv.Set(i, 1);
      }
    }
    else
    {
      View<std::uint32_t> av = workers.Bind(t, a), bv = workers.Bind(t, b);
      for (std::uint64_t i = 0; i < n; ++i)
      {
        av.Set(i, std::uint32_t(2 * i));
        bv.Set(n + i, 2);
      }
      EXPECT_THROW(bv.Set(0, 9), WriteOutOfBounds);
    }
  });
  EXPECT_EQ(ran[0], 0);
  EXPECT_EQ(ran[1], 1);
  EXPECT_FALSE(workers.Forked());
  for (std::uint64_t i = 0; i < n; i += 101)
  {
    ASSERT_EQ(a.Get(i), 2 * i);
    ASSERT_EQ(q.Get(i), i + 5);
    ASSERT_EQ(b.Get(i), 1u);
    ASSERT_EQ(b.Get(n + i), 2u);
  }
}
// A repeated phase whose helper thrashes (each half of the budget too small for the pages it
// reads) runs on one thread from then on, until the blocks' files shrink to half their size;
// one whose reads fit leaves its record alone.
TEST(StorageAccess, WorkersForkOnlyWithTheBytesAPhaseNeeds)
{
  // Phase::minBytes: a helper only when half the budget holds that many bytes of pages.
  TempDir dir;
  DML dml;
  ASSERT_EQ(dml.Config(OutOfCoreProfile(dir.Path(), 1 << 20)), Mode::OutOfCore);
  Array<std::uint32_t> big(dml, std::uint64_t(1) << 20);
  const std::uint64_t half = dml.GetProfile().memoryBudget / 2;
  Phase phase;
  phase.elements = big.Size();
  phase.threads = 2;
  phase.writes = { big.Id() };
  for (const std::uint64_t need : { std::uint64_t(0), half, half + 1 })
  {
    SCOPED_TRACE(need);
    phase.minBytes = need;
    Workers workers(dml, phase);
    EXPECT_EQ(workers.Forked(), need <= half);
    EXPECT_EQ(workers.Count(), need <= half ? 2 : 1);
    // Either way the range is covered once.
    std::vector<std::uint64_t> counts(2, 0);
    workers.Run([&](int t, std::uint64_t begin, std::uint64_t end, const std::atomic<bool>&) {
      View<std::uint32_t> v = workers.Bind(t, big);
      for (std::uint64_t i = begin; i < end; i += 4096)
      {
        v.Set(i, v.Get(i) + 1);
      }
      counts[std::size_t(t)] += end - begin;
    });
    EXPECT_EQ(counts[0] + counts[1], big.Size());
  }
  for (std::uint64_t i = 0; i < big.Size(); i += 4096)
  {
    ASSERT_EQ(big.Get(i), 3u) << i;
  }
}

TEST(StorageAccess, WorkersDeclineAHelperThatThrashed)
{
  TempDir dir;
  DML dml;
  ASSERT_EQ(dml.Config(OutOfCoreProfile(dir.Path(), 256 << 10)), Mode::OutOfCore);
  constexpr std::uint64_t n = std::uint64_t(1) << 20; // 4 MiB: far more pages than frames
  Array<std::uint32_t> big(dml, n), small(dml, Workers::kHelperMin);
  const std::uint64_t pages = dml.GetStats().fileBytes / dml.PageBytes();
  ForkRecord record;
  Phase phase;
  phase.elements = n;
  phase.threads = 2;
  phase.record = &record;
  // Reads of every 64th element's scattered partner: nearly each one a page the frames lost.
  auto scattered = [&](Workers& workers) {
    std::vector<std::uint64_t> sums(2, 0);
    workers.Run([&](int t, std::uint64_t begin, std::uint64_t end, const std::atomic<bool>&) {
      View<std::uint32_t> v = workers.Bind(t, big);
      for (std::uint64_t i = begin; i < end; i += 64)
      {
        sums[std::size_t(t)] += v.Get((i * 2654435761u) % n);
      }
    });
    return sums[0] + sums[1];
  };
  auto sequential = [&](Workers& workers) {
    workers.Run([&](int t, std::uint64_t begin, std::uint64_t end, const std::atomic<bool>&) {
      View<std::uint32_t> v = workers.Bind(t, big);
      std::uint64_t sum = 0;
      for (std::uint64_t i = begin; i < end; ++i)
      {
        sum += v.Get(i);
      }
      EXPECT_EQ(sum, 0u);
    });
  };
  {
    Workers workers(dml, phase);
    ASSERT_TRUE(workers.Forked());
    const std::uint64_t before = dml.GetStats().misses;
    sequential(workers);
    EXPECT_LE(dml.GetStats().misses - before, ForkRecord::kThrash * pages);
    EXPECT_EQ(record.declinedAtFileBytes, 0u);
  }
  {
    Workers workers(dml, phase);
    ASSERT_TRUE(workers.Forked());
    const std::uint64_t before = dml.GetStats().misses;
    EXPECT_EQ(scattered(workers), 0u);
    EXPECT_GT(dml.GetStats().misses - before, ForkRecord::kThrash * pages);
    EXPECT_EQ(record.declinedAtFileBytes, dml.GetStats().fileBytes);
  }
  {
    Workers workers(dml, phase);
    EXPECT_FALSE(workers.Forked());
    EXPECT_EQ(workers.Count(), 1);
    EXPECT_EQ(record.declined, 1u);
    scattered(workers); // (one thread: the record is left as it is)
  }
  EXPECT_NE(record.declinedAtFileBytes, 0u);
  // Without its record a phase forks as before.
  phase.record = nullptr;
  EXPECT_TRUE(Workers(dml, phase).Forked());
  phase.record = &record;
  // The files at a quarter of their bytes then (more than halved: the big block closed): the
  // helper is tried again.
  const std::uint64_t declinedAt = record.declinedAtFileBytes;
  big.Close();
  ASSERT_LE(2 * dml.GetStats().fileBytes, declinedAt);
  phase.elements = Workers::kHelperMin;
  Workers again(dml, phase);
  EXPECT_TRUE(again.Forked());
  EXPECT_EQ(record.declinedAtFileBytes, 0u);
  EXPECT_EQ(record.declined, 1u);
}
} // namespace

namespace
{
using namespace sipmss::storage;
using sipmss::storage::testing::TempDir;

// PinWindow: records modified in place through up to kMaxWays pinned pages (faces reaching
// their vertices in several index ranges) keep every value against a model; each page stays
// pinned while the window uses it (the pages it holds count against what Pin may still take),
// and when the cache shrinks below what the window chose (other pins) it goes on with one
// page instead of failing.
TEST(StorageAccess, PinWindowKeepsSeveralRangesAndGivesWayWhenPagesRunShort)
{
  TempDir tmp;
  DML dml;
  dml.Config(OutOfCoreProfile(tmp.Path(), 4 * 1024 * 1024));
  const std::uint64_t perPage = dml.PageBytes() / sizeof(std::uint64_t);
  const std::uint64_t n = 64 * perPage;
  Array<std::uint64_t> a(dml, n);
  std::vector<std::uint64_t> model(n, 0);
  a.Write(0, n, model.data());
  const std::uint32_t free0 = dml.PinnablePages();
  ASSERT_GE(free0, 4u * PinWindow<std::uint64_t>::kMaxWays) << "the test needs a cache of 32+ pages";
  std::mt19937_64 rng(11);
  {
    PinWindow<std::uint64_t> w(dml, Access::Write, PinWindow<std::uint64_t>::kMaxWays);
    // Seven streams through the block, as the levels of a subdivided scan.
    std::uint64_t at[7];
    for (int s = 0; s < 7; ++s)
    {
      at[s] = std::uint64_t(s) * (n / 7);
    }
    for (int step = 0; step < 20000; ++step)
    {
      const int s = int(rng() % 7);
      const std::uint64_t i = at[s]++ % n;
      w.At(a.Id(), i) += std::uint64_t(step) + 1;
      model[i] += std::uint64_t(step) + 1;
    }
    // The seven streams' pages stay pinned in the window (at most kMaxWays of them).
    EXPECT_LE(free0 - dml.PinnablePages(), PinWindow<std::uint64_t>::kMaxWays);
    EXPECT_GE(free0 - dml.PinnablePages(), 7u);
    // Other pins take all but one of the pages left: the window gives way to one page.
    std::vector<Span> others;
    std::uint64_t page = 0;
    while (dml.PinnablePages() > 0)
    {
      others.push_back(dml.Pin(a.Id(), (page++ % 64) * perPage, Access::Read));
    }
    for (int step = 0; step < 5000; ++step)
    {
      const std::uint64_t i = rng() % n;
      w.At(a.Id(), i) += 3;
      model[i] += 3;
    }
    for (const Span& s : others)
    {
      dml.Unpin(a.Id(), s);
    }
  }
  EXPECT_EQ(dml.PinnablePages(), free0);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    ASSERT_EQ(a.Get(i), model[i]) << i;
  }
}
} // namespace
