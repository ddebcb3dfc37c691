// storage::Sort and SortByKey against std::sort: in core and out of core at budgets from 64 KiB up, on random
// and adversarial keys (duplicates, sorted, reversed, organ pipe, all equal, a median-of-three
// killer), with the I/O it does, the memory it holds and an abort in the middle.
#include "StorageTestUtil.h"

#include "sipmss/storage/DML.h"
#include "sipmss/storage/Sort.h"
#include "sipmss/storage/Threads.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <numeric>
#include <random>
#include <stdexcept>
#include <string>
#include <thread>
#include <vector>

namespace
{
using namespace sipmss::storage;
using sipmss::storage::testing::TempDir;

std::vector<std::uint64_t> Keys(const std::string& kind, std::uint64_t n, std::uint64_t seed)
{
  std::mt19937_64 rng(seed);
  std::vector<std::uint64_t> v(n);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    if (kind == "random")
    {
      v[i] = rng();
    }
    else if (kind == "duplicates")
    {
      v[i] = rng() % 7;
    }
    else if (kind == "sorted")
    {
      v[i] = i * 3;
    }
    else if (kind == "reversed")
    {
      v[i] = (n - i) * 3;
    }
    else if (kind == "organpipe")
    {
      v[i] = i < n / 2 ? i : n - i;
    }
    else if (kind == "equal")
    {
      v[i] = 42;
    }
    else if (kind == "sawtooth")
    {
      v[i] = i % 1000;
    }
    else if (kind == "killer")
    {
      v[i] = 0; // below
    }
    else
    {
      throw std::invalid_argument(kind);
    }
  }
  if (kind == "killer")
  {
    // Musser's median-of-three killer sequence for the first/middle/last pivot choice.
    const std::uint64_t k = n / 2;
    for (std::uint64_t i = 1; i <= k; ++i)
    {
      if (i % 2 == 1)
      {
        v[i - 1] = i;
        v[i] = k + i;
      }
      v[k + i - 1] = 2 * i;
    }
  }
  return v;
}

// Keys written to an array of a DML with this budget (automatic mode).
struct KeysInDml
{
  DML dml;
  Array<std::uint64_t> a;
  KeysInDml(const std::vector<std::uint64_t>& in, std::uint64_t budget, const std::string& dir)
  {
    Profile p;
    p.directories = { dir };
    p.memoryBudget = budget;
    this->dml.Config(p);
    this->a = Array<std::uint64_t>(this->dml, in.size());
    this->a.Write(0, in.size(), in.data());
  }
};

// A progress callback that checks its values rise within [0, 1] and throws at its stopAt-th
// call (an abort).
struct StoppingPoll
{
  int stopAt;
  int calls = 0;
  double last = 0;
  bool monotone = true;
  SortPoll Poll()
  {
    return [this](double f) {
      this->monotone = this->monotone && f >= this->last && f <= 1.0;
      this->last = f;
      if (++this->calls == this->stopAt)
      {
        throw std::runtime_error("stop");
      }
    };
  }
};

struct SortRun
{
  std::vector<std::uint64_t> out;
  Stats stats;
  std::uint64_t fileBytesBefore = 0;
  std::uint64_t blockBytes = 0;
};

SortRun SortWithBudget(const std::vector<std::uint64_t>& in, std::uint64_t budget,
  const std::string& dir, ModePolicy policy = ModePolicy::Automatic)
{
  Profile p;
  p.directories = { dir };
  p.memoryBudget = budget;
  p.policy = policy;
  p.structures = { { "keys", sizeof(std::uint64_t), in.size(), 0.0 } };
  DML dml;
  dml.Config(p);
  Array<std::uint64_t> a(dml, in.size());
  a.Write(0, in.size(), in.data());
  SortRun r;
  r.fileBytesBefore = dml.GetStats().fileBytes;
  r.blockBytes = in.size() * sizeof(std::uint64_t);
  const Stats before = dml.GetStats();
  Sort(dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; });
  r.stats = dml.GetStats();
  r.stats.bytesRead -= before.bytesRead;
  r.stats.bytesWritten -= before.bytesWritten;
  r.out.resize(in.size());
  a.Read(0, in.size(), r.out.data());
  return r;
}

TEST(StorageSort, InCoreEqualsStdSort)
{
  TempDir tmp;
  for (const char* kind :
    { "random", "duplicates", "sorted", "reversed", "organpipe", "equal", "sawtooth", "killer" })
  {
    const auto in = Keys(kind, 300000, 1);
    auto expect = in;
    std::sort(expect.begin(), expect.end());
    const SortRun r = SortWithBudget(in, 0, tmp.Path());
    EXPECT_EQ(r.stats.mode, Mode::InCore) << kind;
    EXPECT_TRUE(r.out == expect) << kind;
  }
}

TEST(StorageSort, OutOfCoreEqualsStdSortAtEveryBudget)
{
  TempDir tmp;
  for (std::uint64_t budget : { 64ull << 10, 256ull << 10, 1ull << 20, 8ull << 20 })
  {
    for (const char* kind :
      { "random", "duplicates", "sorted", "reversed", "organpipe", "equal", "sawtooth", "killer" })
    {
      for (std::uint64_t n : { std::uint64_t(2), std::uint64_t(1000), std::uint64_t(250000) })
      {
        const auto in = Keys(kind, n, budget + n);
        auto expect = in;
        std::sort(expect.begin(), expect.end());
        const SortRun r = SortWithBudget(in, budget, tmp.Path(), ModePolicy::OutOfCore);
        const std::string what = std::string(kind) + " n=" + std::to_string(n) +
          " budget=" + std::to_string(budget);
        EXPECT_EQ(r.stats.mode, Mode::OutOfCore) << what;
        EXPECT_TRUE(r.out == expect) << what;
        EXPECT_LE(r.stats.peakBytes, budget) << what;
        // The merge's second block is closed again.
        EXPECT_EQ(r.stats.fileBytes, r.fileBytesBefore) << what;
      }
    }
  }
}

// sort(N) I/Os: at 64 KiB a 4 MB array needs runs and two merge passes or more; the bytes moved
// are a few times the data, never per element.
TEST(StorageSort, OutOfCoreIOIsAFewPassesOverTheData)
{
  TempDir tmp;
  const std::uint64_t n = 500000; // 4 MB
  const auto in = Keys("random", n, 7);
  auto expect = in;
  std::sort(expect.begin(), expect.end());
  const SortRun r = SortWithBudget(in, 64 << 10, tmp.Path());
  ASSERT_EQ(r.stats.mode, Mode::OutOfCore);
  EXPECT_TRUE(r.out == expect);
  const double written = static_cast<double>(r.stats.bytesWritten) / r.blockBytes;
  const double read = static_cast<double>(r.stats.bytesRead) / r.blockBytes;
  // Runs of about 48 KB: about 85 runs; pages of 4 KB or less: a fan-in of 10 or less, so at
  // least two merge passes besides the runs.
  EXPECT_GE(written, 2.5) << "fewer passes than expected";
  EXPECT_LE(written, 8.0);
  EXPECT_LE(read, 10.0);
}

// A total order gives the same bytes in core and out of core.
struct Face
{
  std::uint32_t a, b, c;
};
bool FaceLess(const Face& x, const Face& y)
{
  if (x.a != y.a)
  {
    return x.a < y.a;
  }
  if (x.b != y.b)
  {
    return x.b < y.b;
  }
  return x.c < y.c;
}

// Faces over `firsts` first vertices, `seconds` second ones and any third (by default 5,000
// and 3: many ties of the first).
std::vector<Face> RandomFaces(
  std::uint64_t n, unsigned seed, std::uint32_t firsts = 5000, std::uint32_t seconds = 3)
{
  std::mt19937 rng(seed);
  std::vector<Face> in(n);
  for (auto& f : in)
  {
    f = { static_cast<std::uint32_t>(rng() % firsts), static_cast<std::uint32_t>(rng() % seconds),
      static_cast<std::uint32_t>(rng()) };
  }
  return in;
}

// A DML with this budget in dir: out of core when bounded, else automatic.
void Configure(DML& dml, std::uint64_t budget, const std::string& dir)
{
  Profile p;
  p.directories = { dir };
  p.memoryBudget = budget;
  p.policy = budget ? ModePolicy::OutOfCore : ModePolicy::Automatic;
  dml.Config(p);
}

TEST(StorageSort, SameBytesInCoreAndOutOfCore)
{
  TempDir tmp;
  const std::uint64_t n = 200000;
  const std::vector<Face> in = RandomFaces(n, 11);
  std::vector<std::vector<Face>> outs;
  for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(96) << 10, std::uint64_t(2) << 20 })
  {
    DML dml;
    Configure(dml, budget, tmp.Path());
    Array<Face> a(dml, n);
    a.Write(0, n, in.data());
    Sort(dml, a, FaceLess);
    std::vector<Face> out(n);
    a.Read(0, n, out.data());
    outs.push_back(std::move(out));
  }
  auto expect = in;
  std::sort(expect.begin(), expect.end(), FaceLess);
  for (const auto& out : outs)
  {
    ASSERT_EQ(out.size(), expect.size());
    EXPECT_EQ(std::memcmp(out.data(), expect.data(), n * sizeof(Face)), 0);
  }
}

// An abort (the poll throws) leaves a permutation, no working memory and no extra block.
TEST(StorageSort, AbortLeavesAPermutationAndNothingHeld)
{
  TempDir tmp;
  for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(128) << 10 })
  {
    for (int stopAt : { 1, 3, 6 })
    {
      const std::uint64_t n = 300000;
      const auto in = Keys("random", n, 3);
      KeysInDml k(in, budget, tmp.Path());
      DML& dml = k.dml;
      Array<std::uint64_t>& a = k.a;
      const Stats before = dml.GetStats();
      const std::uint64_t spareBefore = dml.SpareMemory(4);
      StoppingPoll stop{ stopAt };
      EXPECT_THROW(
        Sort(dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; }, stop.Poll()),
        std::runtime_error);
      EXPECT_TRUE(stop.monotone);
      const Stats after = dml.GetStats();
      EXPECT_EQ(after.fileBytes, before.fileBytes);
          std::vector<std::uint64_t> out(n);
      a.Read(0, n, out.data());
      auto x = in;
      std::sort(x.begin(), x.end());
      std::sort(out.begin(), out.end());
      EXPECT_TRUE(out == x) << "budget " << budget << " stop " << stopAt;
    }
  }
}

TEST(StorageSort, ProgressReachesOne)
{
  TempDir tmp;
  for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(64) << 10 })
  {
    const std::uint64_t n = 400000;
    const auto in = Keys("random", n, 5);
    KeysInDml k(in, budget, tmp.Path());
    DML& dml = k.dml;
    Array<std::uint64_t>& a = k.a;
    double last = 0;
    int calls = 0;
    Sort(dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; }, [&](double f) {
      EXPECT_GE(f, last);
      last = f;
      ++calls;
    });
    EXPECT_GT(calls, 3);
    EXPECT_NEAR(last, 1.0, 1e-9) << budget;
  }
}

TEST(StorageSort, TooSmallABudgetIsAClearError)
{
  TempDir tmp;
  Profile p;
  p.directories = { tmp.Path() };
  p.memoryBudget = 16 << 10;
  p.policy = ModePolicy::OutOfCore;
  p.pageSize = 4096;
  DML dml;
  dml.Config(p);
  Array<std::uint64_t> a(dml, 100000);
  try
  {
    Sort(dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; });
    FAIL() << "a 16 KiB budget cannot hold the cache's pages and a sort's windows";
  }
  catch (const BudgetError& e)
  {
    EXPECT_NE(std::string(e.what()).find("too few to sort"), std::string::npos) << e.what();
  }
  EXPECT_EQ(dml.GetStats().fileBytes, 100000u * 8) << "the merge's block is closed again";
}

// SortByKey: the same result as std::sort at every budget and on every kind of keys; by
// distribution where the keys spread, by merges where they crowd.
struct KeyedRun
{
  SortRun run;
  SortMethod method = SortMethod::InMemory;
};

KeyedRun SortByKeyWithBudget(const std::vector<std::uint64_t>& in, std::uint64_t budget,
  const std::string& dir, int keyBits = 64, const SortPoll& poll = {})
{
  DML dml;
  Configure(dml, budget, dir);
  Array<std::uint64_t> a(dml, in.size());
  a.Write(0, in.size(), in.data());
  KeyedRun r;
  r.run.fileBytesBefore = dml.GetStats().fileBytes;
  r.run.blockBytes = in.size() * sizeof(std::uint64_t);
  const Stats before = dml.GetStats();
  r.method = SortByKey(
    dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
    [](std::uint64_t x) { return x; }, keyBits, poll);
  r.run.stats = dml.GetStats();
  r.run.stats.bytesRead -= before.bytesRead;
  r.run.stats.bytesWritten -= before.bytesWritten;
  r.run.out.resize(in.size());
  a.Read(0, in.size(), r.run.out.data());
  return r;
}

TEST(StorageSortByKey, EqualsStdSortAtEveryBudget)
{
  TempDir tmp;
  for (std::uint64_t budget : { 0ull, 64ull << 10, 256ull << 10, 1ull << 20, 8ull << 20 })
  {
    for (const char* kind :
      { "random", "duplicates", "sorted", "reversed", "organpipe", "equal", "sawtooth", "killer" })
    {
      for (std::uint64_t n : { std::uint64_t(2), std::uint64_t(1000), std::uint64_t(250000) })
      {
        const auto in = Keys(kind, n, budget + n + 1);
        auto expect = in;
        std::sort(expect.begin(), expect.end());
        const KeyedRun r = SortByKeyWithBudget(in, budget, tmp.Path());
        const std::string what = std::string(kind) + " n=" + std::to_string(n) +
          " budget=" + std::to_string(budget);
        EXPECT_TRUE(r.run.out == expect) << what;
        EXPECT_EQ(r.run.stats.fileBytes, r.run.fileBytesBefore) << what;
        if (budget)
        {
          EXPECT_EQ(r.run.stats.mode, Mode::OutOfCore) << what;
          EXPECT_LE(r.run.stats.peakBytes, budget) << what;
        }
        else
        {
          EXPECT_EQ(r.method, SortMethod::InMemory) << what;
        }
      }
    }
  }
}

// Keys that spread are distributed: a count, a distribution and the buckets' sorts are three
// reads and two writes of the data; keys all in one range of the count fall back to merging.
TEST(StorageSortByKey, DistributesSpreadKeysAndMergesCrowdedOnes)
{
  TempDir tmp;
  const std::uint64_t n = 500000; // 4 MB
  for (const char* kind : { "random", "sorted", "reversed", "organpipe" })
  {
    const auto in = Keys(kind, n, 9);
    auto expect = in;
    std::sort(expect.begin(), expect.end());
    // (the key's bits: the largest key's)
    int bits = 1;
    while (bits < 64 && (*std::max_element(in.begin(), in.end()) >> bits) != 0)
    {
      ++bits;
    }
    const KeyedRun r = SortByKeyWithBudget(in, 1 << 20, tmp.Path(), bits);
    EXPECT_EQ(r.method, SortMethod::Distribution) << kind;
    EXPECT_TRUE(r.run.out == expect) << kind;
    const double written = double(r.run.stats.bytesWritten) / double(r.run.blockBytes);
    const double read = double(r.run.stats.bytesRead) / double(r.run.blockBytes);
    EXPECT_GE(written, 1.9) << kind;
    EXPECT_LE(written, 2.2) << kind;
    EXPECT_LE(read, 3.3) << kind;
  }
  // (sorted as std::sort does, by this method, within the budget)
  auto check = [&tmp](const std::vector<std::uint64_t>& in, std::uint64_t budget,
                 SortMethod method, const std::string& what) {
    auto expect = in;
    std::sort(expect.begin(), expect.end());
    const KeyedRun r = SortByKeyWithBudget(in, budget, tmp.Path());
    EXPECT_EQ(r.method, method) << what;
    EXPECT_TRUE(r.run.out == expect) << what;
    EXPECT_LE(r.run.stats.peakBytes, budget) << what;
  };
  for (const char* kind : { "equal", "duplicates" })
  {
    check(Keys(kind, n, 9), 1 << 20, SortMethod::Merge, kind);
  }
  // Buckets whose write buffers hold less than a page (partial pages, written straight to the
  // file): still distributed. 16 MB at 256 KiB.
  check(Keys("random", 2000000, 4), 256 << 10, SortMethod::Distribution, "partial pages");
  // 32 MB at 64 KiB: every range of the count holds more than the memory; each is a bucket of
  // its own, distributed again on its lower bits.
  check(Keys("random", 4000000, 3), 64 << 10, SortMethod::Distribution, "every range crowded");
}

// Keys that crowd into a few ranges of the count with their lower bits spread (spatial keys: a
// surface fills few cells of the top levels of a Morton order) are distributed, the crowded ranges
// again on their lower bits: the result is std::sort's, within the budget, in a bounded number of
// passes; an abort inside a crowded range's sort leaves the array as it was and holds nothing.
TEST(StorageSortByKey, CrowdedRangesAreDistributedOnTheirLowerBits)
{
  TempDir tmp;
  const std::uint64_t n = 600000; // 4.8 MB
  std::mt19937_64 rng(21);
  std::vector<std::uint64_t> in(n);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    // (90% in three ranges of the top 12 bits, the rest anywhere)
    static const std::uint64_t tops[3] = { 0x123, 0x7ff, 0xa00 };
    const std::uint64_t low = rng() & ((std::uint64_t(1) << 52) - 1);
    in[i] = rng() % 10 < 9 ? (tops[rng() % 3] << 52 | low) : rng();
  }
  auto expect = in;
  std::sort(expect.begin(), expect.end());
  for (std::uint64_t budget : { std::uint64_t(256) << 10, std::uint64_t(1) << 20 })
  {
    const std::string what = "budget " + std::to_string(budget);
    const KeyedRun r = SortByKeyWithBudget(in, budget, tmp.Path());
    EXPECT_EQ(r.method, SortMethod::Distribution) << what;
    EXPECT_TRUE(r.run.out == expect) << what;
    EXPECT_LE(r.run.stats.peakBytes, budget) << what;
    EXPECT_EQ(r.run.stats.fileBytes, r.run.fileBytesBefore) << what;
    // (top: a count, a distribution; a crowded range: its count, distribution and buckets; the
    // rest: their buckets. At most about 5 reads and 3 writes; a merge needs more at this size)
    const double read = double(r.run.stats.bytesRead) / double(r.run.blockBytes);
    const double written = double(r.run.stats.bytesWritten) / double(r.run.blockBytes);
    EXPECT_LE(read, 5.5) << what;
    EXPECT_LE(written, 3.5) << what;
    EXPECT_GE(read, 3.5) << what << ": the crowded ranges were distributed again";
  }
  // An abort at every tenth of the progress calls, inside the crowded ranges' sorts too.
  int total = 0;
  {
    KeysInDml k(in, 1 << 20, tmp.Path());
    SortByKey(
      k.dml, k.a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
      [](std::uint64_t x) { return x; }, 64, [&](double) { ++total; });
  }
  ASSERT_GT(total, 10);
  for (int stopAt = total / 10; stopAt < total; stopAt += total / 10)
  {
    KeysInDml k(in, 1 << 20, tmp.Path());
    const Stats before = k.dml.GetStats();
    const std::uint64_t spareBefore = k.dml.SpareMemory(4);
    StoppingPoll stop{ stopAt };
    EXPECT_THROW(SortByKey(
                   k.dml, k.a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
                   [](std::uint64_t x) { return x; }, 64, stop.Poll()),
      std::runtime_error);
    EXPECT_TRUE(stop.monotone) << stopAt;
    EXPECT_EQ(k.dml.GetStats().fileBytes, before.fileBytes) << stopAt;
    EXPECT_EQ(k.dml.SpareMemory(4), spareBefore) << stopAt;
    std::vector<std::uint64_t> out(n);
    k.a.Read(0, n, out.data());
    EXPECT_TRUE(out == in) << "the array changed: stop at " << stopAt << " of " << total;
  }
}

// A key that is a prefix of the order (faces by their first vertex): the same bytes as std::sort
// in core and out of core.
TEST(StorageSortByKey, SameBytesAsSortWithAPrefixKey)
{
  TempDir tmp;
  const std::uint64_t n = 200000;
  const std::vector<Face> in = RandomFaces(n, 13);
  auto expect = in;
  std::sort(expect.begin(), expect.end(), FaceLess);
  // (at 96 KiB every range of the count is crowded: each distributed again on its lower bits)
  for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(96) << 10, std::uint64_t(2) << 20 })
  {
    DML dml;
    Configure(dml, budget, tmp.Path());
    Array<Face> a(dml, n);
    a.Write(0, n, in.data());
    const SortMethod m = SortByKey(dml, a, FaceLess, [](const Face& f) { return f.a; }, 13);
    EXPECT_EQ(m,
      budget == 0 ? SortMethod::InMemory
                  : SortMethod::Distribution)
      << budget;
    std::vector<Face> out(n);
    a.Read(0, n, out.data());
    EXPECT_EQ(std::memcmp(out.data(), expect.data(), n * sizeof(Face)), 0) << budget;
  }
}

// An abort leaves the array as it was (out of core) or a permutation (in core), with no working
// memory and no extra block held; progress is monotone and reaches 1, also when it merges.
TEST(StorageSortByKey, AbortAndProgress)
{
  TempDir tmp;
  for (const char* kind : { "random", "equal" })
  {
    for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(1) << 20 })
    {
      const std::uint64_t n = 300000;
      const auto in = Keys(kind, n, 5);
      for (int stopAt : { 1000000, 1, 2, 4 })
      {
        KeysInDml k(in, budget, tmp.Path());
        const Stats before = k.dml.GetStats();
        const std::uint64_t spareBefore = k.dml.SpareMemory(4);
        StoppingPoll stop{ stopAt };
        bool stopped = false;
        SortMethod method = SortMethod::InMemory;
        try
        {
          method = SortByKey(
            k.dml, k.a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
            [](std::uint64_t x) { return x; }, 64, stop.Poll());
        }
        catch (const std::runtime_error&)
        {
          stopped = true;
        }
        const std::string what = std::string(kind) + " budget " + std::to_string(budget) +
          " stop " + std::to_string(stopAt);
        EXPECT_TRUE(stop.monotone) << what;
        EXPECT_EQ(k.dml.GetStats().fileBytes, before.fileBytes) << what;
        EXPECT_EQ(k.dml.SpareMemory(4), spareBefore) << what;
        std::vector<std::uint64_t> out(n);
        k.a.Read(0, n, out.data());
        auto sorted = in;
        std::sort(sorted.begin(), sorted.end());
        if (!stopped)
        {
          EXPECT_EQ(method,
            budget == 0 ? SortMethod::InMemory
                        : (std::string(kind) == "random" ? SortMethod::Distribution
                                                         : SortMethod::Merge))
            << what;
          EXPECT_NEAR(stop.last, 1.0, 1e-9) << what;
          EXPECT_TRUE(out == sorted) << what;
          continue;
        }
        if (budget && std::string(kind) == "random")
        {
          EXPECT_TRUE(out == in) << "the array changed: " << what;
        }
        std::sort(out.begin(), out.end());
        EXPECT_TRUE(out == sorted) << what;
      }
    }
  }
}

// The in-memory radix sort on one and two threads: every kind of keys, the full 64-bit range, keys
// near the top, and ties of the key ordered by less; an abort on two threads leaves a permutation.
TEST(StorageSortByKey, RadixSortInMemoryEqualsStdSort)
{
  const std::uint64_t n = (std::uint64_t(1) << 21) + 3;
  auto less = [](std::uint64_t x, std::uint64_t y) { return x < y; };
  auto id = [](std::uint64_t x) { return x; };
  for (const char* kind :
    { "random", "duplicates", "sorted", "reversed", "organpipe", "equal", "sawtooth", "killer" })
  {
    auto in = Keys(kind, n, 21);
    if (std::string(kind) == "sawtooth")
    {
      for (auto& k : in)
      {
        k = ~std::uint64_t(0) - k; // (near the top of the range)
      }
    }
    auto expect = in;
    std::sort(expect.begin(), expect.end());
    for (int threads : { 1, 2 })
    {
      auto out = in;
      double last = 0;
      detail::RadixSortByKey(out.data(), n, id, less, [&](double f) { last = f; }, threads);
      EXPECT_TRUE(out == expect) << kind << " threads " << threads;
      EXPECT_NEAR(last, 1.0, 1e-9) << kind;
    }
  }
  // Faces by their first vertex (many ties, ordered by the rest).
  std::mt19937 rng(17);
  std::vector<Face> faces(n);
  for (auto& f : faces)
  {
    f = { static_cast<std::uint32_t>(rng() % 100000), static_cast<std::uint32_t>(rng() % 3),
      static_cast<std::uint32_t>(rng()) };
  }
  auto expect = faces;
  std::sort(expect.begin(), expect.end(), FaceLess);
  auto first = [](const Face& f) { return std::uint64_t(f.a); };
  for (int threads : { 1, 2 })
  {
    auto out = faces;
    detail::RadixSortByKey(out.data(), n, first, FaceLess, {}, threads);
    EXPECT_EQ(std::memcmp(out.data(), expect.data(), n * sizeof(Face)), 0) << threads;
  }
  // An abort in the middle of the two threads' ranges.
  auto in = Keys("random", n, 23);
  auto out = in;
  int calls = 0;
  EXPECT_THROW(detail::RadixSortByKey(out.data(), n, id, less,
                 [&](double) {
                   if (++calls == 20)
                   {
                     throw std::runtime_error("stop");
                   }
                 },
                 2),
    std::runtime_error);
  std::sort(in.begin(), in.end());
  std::sort(out.begin(), out.end());
  EXPECT_TRUE(out == in);
}

// BucketSorter: elements added one by one come out sorted as std::sort sorts them, at budgets
// from 64 KiB (one bucket, sorted out of core at the end) to 8 MiB (many buckets), with spread
// keys and with keys crowded into one bucket (that bucket sorted out of core on its own).
std::vector<Face> SortByBuckets(const std::vector<Face>& in, std::uint64_t keyEnd,
  std::uint64_t budget, const std::string& dir, std::size_t* buckets = nullptr,
  bool* oneBucket = nullptr, int threads = 1, std::size_t pageSize = 0,
  std::uint64_t* addedReads = nullptr, std::size_t* bufferElements = nullptr)
{
  Profile p;
  p.directories = { dir };
  p.memoryBudget = budget;
  p.policy = ModePolicy::OutOfCore;
  p.pageSize = pageSize;
  DML dml;
  dml.Config(p);
  Array<Face> out(dml, in.size());
  const std::uint64_t fileBytes = dml.GetStats().fileBytes;
  {
    auto first = [](const Face& f) { return std::uint64_t(f.a); };
    BucketSorter<Face, decltype(first), decltype(&FaceLess)> sorter(
      dml, in.size(), keyEnd, first, &FaceLess);
    const std::uint64_t readBefore = dml.GetStats().bytesRead;
    for (const Face& f : in)
    {
      sorter.Add(f);
    }
    if (addedReads)
    {
      *addedReads = dml.GetStats().bytesRead - readBefore;
    }
    if (buckets)
    {
      *buckets = sorter.Buckets();
    }
    if (bufferElements)
    {
      *bufferElements = sorter.BufferElements();
    }
    if (oneBucket)
    {
      *oneBucket = sorter.OneBucket();
    }
    double last = 0;
    bool monotone = true;
    sorter.Finish(out, [&](double f) {
      monotone = monotone && f >= last && f <= 1.0 + 1e-12;
      last = f;
    }, threads);
    EXPECT_TRUE(monotone);
    EXPECT_NEAR(last, 1.0, 1e-9);
  }
  EXPECT_EQ(dml.GetStats().fileBytes, fileBytes) << "a temporary block is left";
  EXPECT_LE(dml.GetStats().peakBytes, budget);
  std::vector<Face> r(in.size());
  out.Read(0, in.size(), r.data());
  return r;
}

TEST(StorageBucketSorter, EqualsStdSortSpreadAndCrowded)
{
  TempDir tmp;
  std::mt19937 rng(29);
  const std::uint64_t n = 300000;
  for (const char* kind : { "spread", "crowded", "fan", "sorted" })
  {
    std::vector<Face> in(n);
    for (std::uint64_t i = 0; i < n; ++i)
    {
      const std::string k = kind;
      const std::uint32_t a = k == "spread" ? static_cast<std::uint32_t>(rng() % 100000)
        : k == "crowded"                    ? static_cast<std::uint32_t>(50000 + rng() % 5)
        : k == "fan"                        ? (i % 3 ? 0u : static_cast<std::uint32_t>(rng() % 100000))
                                            : static_cast<std::uint32_t>(i / 3);
      in[i] = { a, static_cast<std::uint32_t>(rng() % 7), static_cast<std::uint32_t>(rng()) };
    }
    auto expect = in;
    std::sort(expect.begin(), expect.end(), FaceLess);
    for (std::uint64_t budget : { 64ull << 10, 1ull << 20, 8ull << 20 })
    {
      std::size_t buckets = 0;
      bool one = false;
      const auto out = SortByBuckets(in, 100000, budget, tmp.Path(), &buckets, &one);
      EXPECT_EQ(std::memcmp(out.data(), expect.data(), n * sizeof(Face)), 0)
        << kind << " budget " << budget << " buckets " << buckets;
      if (budget == (8u << 20))
      {
        // (a bucket of 2^17 elements or more sorts in memory on two threads: the same order)
        const auto two = SortByBuckets(in, 100000, budget, tmp.Path(), nullptr, nullptr, 2);
        EXPECT_EQ(std::memcmp(two.data(), expect.data(), n * sizeof(Face)), 0)
          << kind << " on two threads";
      }
      if (budget == (1u << 20))
      {
        EXPECT_GT(buckets, 1u) << "3.6 MB in 1 MiB: several buckets";
        EXPECT_FALSE(one);
      }
      if (budget == (64u << 10))
      {
        EXPECT_TRUE(one) << "64 KiB: fewer than 64 elements of write buffer per bucket";
      }
    }
  }
}

// SortByKeyInto: the sink gets std::sort's order, in order, in contiguous chunks, at every
// budget and for spread, crowded (distributed again, or merged) and equal keys; out of core the
// distributed buckets are not written back: one write of the data and three reads (SortByKey and
// a scan: two writes and four reads).
struct IntoRun
{
  std::vector<std::uint64_t> out;
  bool contiguous = true;
  SortMethod method = SortMethod::InMemory;
  Stats stats;
  std::uint64_t fileBytesBefore = 0;
};

IntoRun SortByKeyIntoWithBudget(
  const std::vector<std::uint64_t>& in, std::uint64_t budget, const std::string& dir, int keyBits = 64)
{
  DML dml;
  Configure(dml, budget, dir);
  Array<std::uint64_t> a(dml, in.size());
  a.Write(0, in.size(), in.data());
  IntoRun r;
  r.fileBytesBefore = dml.GetStats().fileBytes;
  const Stats before = dml.GetStats();
  r.method = SortByKeyInto(
    dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
    [](std::uint64_t x) { return x; }, keyBits,
    SortSink<std::uint64_t>([&r](const std::uint64_t* d, std::uint64_t first, std::uint64_t n) {
      r.contiguous = r.contiguous && first == r.out.size() && n > 0;
      r.out.insert(r.out.end(), d, d + n);
    }));
  r.stats = dml.GetStats();
  r.stats.bytesRead -= before.bytesRead;
  r.stats.bytesWritten -= before.bytesWritten;
  return r;
}

TEST(StorageSortByKeyInto, HandsStdSortsOrderToTheSinkAtEveryBudget)
{
  TempDir tmp;
  for (std::uint64_t budget : { 0ull, 64ull << 10, 1ull << 20, 8ull << 20 })
  {
    for (const char* kind : { "random", "duplicates", "sorted", "reversed", "equal", "killer" })
    {
      for (std::uint64_t n : { std::uint64_t(1), std::uint64_t(1000), std::uint64_t(600000) })
      {
        const auto in = Keys(kind, n, 11);
        auto expect = in;
        std::sort(expect.begin(), expect.end());
        const IntoRun r = SortByKeyIntoWithBudget(in, budget, tmp.Path());
        const std::string what = std::string(kind) + " n=" + std::to_string(n) +
          " budget=" + std::to_string(budget);
        EXPECT_TRUE(r.out == expect) << what;
        EXPECT_TRUE(r.contiguous) << what;
        EXPECT_EQ(r.stats.fileBytes, r.fileBytesBefore) << what;
        if (budget)
        {
          EXPECT_LE(r.stats.peakBytes, budget) << what;
        }
      }
    }
  }
  // Spread keys out of core: distributed, the data written once and read three times.
  const auto in = Keys("random", 500000, 9);
  auto expect = in;
  std::sort(expect.begin(), expect.end());
  const IntoRun r = SortByKeyIntoWithBudget(in, 1 << 20, tmp.Path());
  EXPECT_EQ(r.method, SortMethod::Distribution);
  EXPECT_TRUE(r.out == expect);
  const double bytes = 500000.0 * sizeof(std::uint64_t);
  EXPECT_LE(double(r.stats.bytesWritten) / bytes, 1.2);
  EXPECT_LE(double(r.stats.bytesRead) / bytes, 3.3);
  // Every range crowded (distributed again on the lower bits), and crowded ranges that must be
  // merged: the sink still gets the sorted order.
  for (const bool merged : { false, true })
  {
    std::mt19937_64 rng(merged ? 23 : 3);
    std::vector<std::uint64_t> keys(merged ? 600000 : 4000000);
    for (std::uint64_t& k : keys)
    {
      k = merged && rng() % 10 < 9
        ? (std::uint64_t(0x123) << 52 | std::uint64_t(0x9e3779b9) << 20 | (rng() & 0xfffff))
        : rng();
    }
    auto sorted = keys;
    std::sort(sorted.begin(), sorted.end());
    const IntoRun c = SortByKeyIntoWithBudget(keys, merged ? 1 << 20 : 64 << 10, tmp.Path());
    EXPECT_EQ(c.method, SortMethod::Distribution) << merged;
    EXPECT_TRUE(c.out == sorted) << merged;
    EXPECT_TRUE(c.contiguous) << merged;
    EXPECT_EQ(c.stats.fileBytes, c.fileBytesBefore) << merged;
  }
}

// A sink that throws (an abort) stops SortByKeyInto: the exception comes out, the array holds
// its elements as they were, and no temporary block is left.
TEST(StorageSortByKeyInto, AnAbortFromTheSinkLeavesTheArrayAndNoBlock)
{
  TempDir tmp;
  for (const bool crowded : { false, true })
  {
    auto in = Keys("random", 500000, 13);
    if (crowded)
    {
      for (std::uint64_t& k : in)
      {
        k = (k & 0xffff) | std::uint64_t(0xabc) << 40; // (every key in one range of the count)
      }
    }
    DML dml;
    Configure(dml, 1 << 20, tmp.Path());
    Array<std::uint64_t> a(dml, in.size());
    a.Write(0, in.size(), in.data());
    const std::uint64_t fileBytes = dml.GetStats().fileBytes;
    int calls = 0;
    EXPECT_THROW(SortByKeyInto(
                   dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
                   [](std::uint64_t x) { return x; }, 64,
                   SortSink<std::uint64_t>([&calls](const std::uint64_t*, std::uint64_t, std::uint64_t) {
                     if (++calls == 2)
                     {
                       throw std::runtime_error("stop");
                     }
                   })),
      std::runtime_error)
      << crowded;
    EXPECT_EQ(calls, 2) << crowded;
    EXPECT_EQ(dml.GetStats().fileBytes, fileBytes) << crowded;
    std::vector<std::uint64_t> now(in.size());
    a.Read(0, in.size(), now.data());
    if (crowded)
    {
      // (merged first: the array is sorted, then read back for the sink)
      std::sort(in.begin(), in.end());
    }
    EXPECT_TRUE(now == in) << crowded;
  }
}

// A crowded range whose keys also fall in one range of its own count (32 constant bits below the
// top ones) is merged in a block of its own: the result is still std::sort's within the budget,
// nothing is left behind, and the progress goes on from the count it had reported.
TEST(StorageSortByKey, ACrowdedRangeThatCannotBeDistributedAgainIsMerged)
{
  TempDir tmp;
  const std::uint64_t n = 600000;
  std::mt19937_64 rng(23);
  std::vector<std::uint64_t> in(n);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    const std::uint64_t crowded = std::uint64_t(0x123) << 52 | std::uint64_t(0x9e3779b9) << 20 |
      (rng() & 0xfffff);
    in[i] = rng() % 10 < 9 ? crowded : rng();
  }
  auto expect = in;
  std::sort(expect.begin(), expect.end());
  double last = 0;
  bool monotone = true;
  int calls = 0;
  const KeyedRun r = SortByKeyWithBudget(in, 1 << 20, tmp.Path(), 64, [&](double f) {
    monotone = monotone && f >= last && f <= 1.0 + 1e-12;
    last = f;
    ++calls;
  });
  EXPECT_EQ(r.method, SortMethod::Distribution);
  EXPECT_TRUE(r.run.out == expect);
  EXPECT_LE(r.run.stats.peakBytes, std::uint64_t(1) << 20);
  EXPECT_EQ(r.run.stats.fileBytes, r.run.fileBytesBefore);
  EXPECT_TRUE(monotone);
  EXPECT_NEAR(last, 1.0, 1e-9);
  EXPECT_GT(calls, 3);
}

// Many elements for the memory (36 MB at 512 KiB): the segments' records go to a block and are
// sorted by bucket, so the key's range is still cut into 123 buckets (with a table of them in
// memory it could not be: one bucket); the result is std::sort's, within the budget.
TEST(StorageBucketSorter, ManySegmentsForTheMemoryStillCutTheKeyRange)
{
  TempDir tmp;
  const std::uint64_t n = 3000000;
  const std::vector<Face> in = RandomFaces(n, 31, 1000000, 7);
  auto expect = in;
  std::sort(expect.begin(), expect.end(), FaceLess);
  std::size_t buckets = 0;
  bool one = true;
  const auto out = SortByBuckets(in, 1000000, 512 << 10, tmp.Path(), &buckets, &one);
  EXPECT_FALSE(one);
  EXPECT_GT(buckets, 100u);
  EXPECT_EQ(std::memcmp(out.data(), expect.data(), n * sizeof(Face)), 0);
}

// Write buffers under a sixteenth of a page (125 buckets of about 120 faces in 512 KiB, pages of
// 32 KiB) are gathered in a page and written whole: adding the elements reads none of the
// segments' pages from the files (written one by one, each buffer would read its page first; the
// segments' records, 24 bytes each, still do), and the result is still std::sort's.
TEST(StorageBucketSorter, SmallSegmentsAreWrittenInWholePagesWithoutReading)
{
  TempDir tmp;
  const std::uint64_t n = 3000000;
  const std::vector<Face> in = RandomFaces(n, 37, 1000000, 7);
  auto expect = in;
  std::sort(expect.begin(), expect.end(), FaceLess);
  std::size_t buckets = 0;
  std::uint64_t reads = 1;
  std::size_t per = 0;
  const auto out = SortByBuckets(
    in, 1000000, 512 << 10, tmp.Path(), &buckets, nullptr, 1, 32 << 10, &reads, &per);
  EXPECT_GT(buckets, 100u);
  EXPECT_LT(per * sizeof(Face) * 16, std::size_t(32) << 10)
    << "the buffers are under a sixteenth of a page";
  EXPECT_LT(reads, n * sizeof(Face) / 16) << "the segments' pages were read";
  EXPECT_EQ(std::memcmp(out.data(), expect.data(), n * sizeof(Face)), 0);
}

TEST(StorageBucketSorter, WrongCountsAndKeysAreErrors)
{
  TempDir tmp;
  DML dml;
  Configure(dml, 1 << 20, tmp.Path());
  auto first = [](const Face& f) { return std::uint64_t(f.a); };
  using Sorter = BucketSorter<Face, decltype(first), decltype(&FaceLess)>;
  Array<Face> out(dml, 10);
  {
    Sorter sorter(dml, 10, 100, first, &FaceLess);
    sorter.Add({ 1, 2, 3 });
    EXPECT_THROW(sorter.Finish(out), std::logic_error) << "fewer elements than announced";
  }
  {
    Sorter sorter(dml, 10, 1000000, first, &FaceLess);
    for (std::uint32_t i = 0; i < 10; ++i)
    {
      sorter.Add({ i, 0, 0 });
    }
    EXPECT_THROW(sorter.Add({ 3, 0, 0 }), std::logic_error) << "more elements than announced";
  }
  {
    Sorter sorter(dml, 300000, 1000000, first, &FaceLess);
    ASSERT_GT(sorter.Buckets(), 1u);
    EXPECT_THROW(sorter.Add({ 2000000000u, 0, 0 }), std::logic_error) << "a key beyond the range";
  }
  EXPECT_EQ(dml.GetStats().fileBytes, 10 * sizeof(Face)) << "the sorters' blocks are closed";
}

TEST(StorageSortByKey, AKeyAboveItsBitsIsAnError)
{
  TempDir tmp;
  const auto in = Keys("random", 100000, 2);
  KeysInDml k(in, 256 << 10, tmp.Path());
  const std::uint64_t fileBytes = k.dml.GetStats().fileBytes;
  EXPECT_THROW(SortByKey(
                 k.dml, k.a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
                 [](std::uint64_t x) { return x; }, 20),
    std::logic_error);
  EXPECT_EQ(k.dml.GetStats().fileBytes, fileBytes);
  std::vector<std::uint64_t> out(in.size());
  k.a.Read(0, in.size(), out.data());
  EXPECT_TRUE(out == in);
  EXPECT_THROW(SortByKey(
                 k.dml, k.a, [](std::uint64_t x, std::uint64_t y) { return x < y; },
                 [](std::uint64_t x) { return x; }, 0),
    std::invalid_argument);
}

} // namespace

TEST(StorageThreads, OneRuleForTheThreadCount)
{
  EXPECT_EQ(sipmss::storage::ResolveThreads(3), 3);
  EXPECT_EQ(sipmss::storage::ResolveThreads(1), 1);
  const int cores = static_cast<int>(std::thread::hardware_concurrency());
  EXPECT_EQ(sipmss::storage::ResolveThreads(0), cores > 0 ? cores : 1);
  EXPECT_EQ(sipmss::storage::ResolveThreads(-5), sipmss::storage::ResolveThreads(0));
}
