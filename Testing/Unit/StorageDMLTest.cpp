// Functional tests of the DML: both modes, pins, mode switches, big sparse files, and a
// randomized workload compared against a plain std::vector model under several budgets.
#include "StorageTestUtil.h"

#include "sipmss/storage/DML.h"
#include "sipmss/storage/DMLTesting.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <cstring>
#include <functional>
#include <random>
#include <string>
#include <thread>
#include <utility>
#include <vector>

namespace
{
using namespace sipmss::storage;
using sipmss::storage::testing::ListDir;
using sipmss::storage::testing::TempDir;

Profile MakeProfile(const std::string& dir, std::uint64_t budget, ModePolicy policy,
  PagePolicy pages = PagePolicy::StaticWeight)
{
  Profile p;
  p.directories = { dir };
  p.memoryBudget = budget;
  p.policy = policy;
  p.pagePolicy = pages;
  return p;
}

// An out-of-core DML in a temporary directory with one block `a` of n 8-byte zeros, its page
// cache built (`per` elements a page).
struct PagedZeros
{
  TempDir tmp;
  DML dml;
  Array<std::uint64_t> a;
  std::uint64_t per = 0;
  PagedZeros(std::uint64_t budget, std::uint64_t n)
  {
    this->dml.Config(MakeProfile(this->tmp.Path(), budget, ModePolicy::OutOfCore));
    this->a = Array<std::uint64_t>(this->dml, n);
    EXPECT_EQ(this->a.Get(n - 1), 0u);
    this->per = DMLTestAccess::PageSize(this->dml) / sizeof(std::uint64_t);
  }
};

TEST(StorageDML, InCoreBasics)
{
  DML dml;
  EXPECT_EQ(dml.Config(Profile{}), Mode::InCore);
  Array<int> a(dml, 1000);
  ASSERT_NE(dml.BasePointer(a.Id()), nullptr);
  for (int i = 0; i < 1000; ++i)
  {
    EXPECT_EQ(a.Get(i), 0);
    a.Set(i, i * 3);
  }
  EXPECT_EQ(a.Get(999), 2997);
  // Pin in core: the whole rest of the block, Unpin is a no-op.
  Span s = dml.Pin(a.Id(), 10, Access::Read);
  EXPECT_EQ(s.count, 990u);
  EXPECT_EQ(static_cast<int*>(s.data)[0], 30);
  dml.Unpin(a.Id(), s);
  std::int64_t sum = 0;
  a.ForEachChunk(0, 1000, Access::Read, [&](int* d, std::uint64_t, std::uint64_t n) {
    EXPECT_EQ(n, 1000u); // one chunk in core
    for (std::uint64_t i = 0; i < n; ++i)
    {
      sum += d[i];
    }
  });
  EXPECT_EQ(sum, 3 * 999 * 1000 / 2);
  a.Resize(5000);
  EXPECT_EQ(a.Get(999), 2997);
  EXPECT_EQ(a.Get(4999), 0);
  a.Resize(10);
  a.Resize(20);
  EXPECT_EQ(a.Get(9), 27);
  EXPECT_EQ(a.Get(15), 0); // regrown elements are zero
  EXPECT_EQ(dml.GetStats().mode, Mode::InCore);
  EXPECT_EQ(dml.PrivateDirectory(), "");
  EXPECT_THROW(dml.Read(a.Id(), 8, 0, &sum), std::invalid_argument);
  EXPECT_THROW(dml.Read(a.Id(), 4, 20, &sum), std::out_of_range);
  EXPECT_THROW(dml.CloseBlock(12345), std::invalid_argument);
}

TEST(StorageDML, OutOfCoreBasicsAndCleanup)
{
  TempDir tmp;
  std::string priv;
  {
    DML dml;
    EXPECT_EQ(dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::OutOfCore)),
      Mode::OutOfCore);
    Array<double> a(dml, 100000);
    Array<std::uint32_t> b(dml, 3);
    EXPECT_EQ(dml.BasePointer(a.Id()), nullptr);
    priv = dml.PrivateDirectory();
    EXPECT_EQ(priv.rfind(tmp.Path() + "/sipmss-" + std::to_string(::getpid()) + "-", 0), 0u);
    EXPECT_EQ(ListDir(priv).size(), 2u);
    for (int i = 0; i < 100000; ++i)
    {
      a.Set(i, i * 0.5);
    }
    // 64 KiB budget: small pages, at least ~16 of them.
    EXPECT_LE(DMLTestAccess::PageSize(dml), 4096u);
    EXPECT_GE(DMLTestAccess::FrameSlots(dml), 16u);
    for (int i = 99999; i >= 0; i -= 7)
    {
      ASSERT_EQ(a.Get(i), i * 0.5);
    }
    // ForEachChunk runs page by page out of core.
    std::uint64_t chunks = 0;
    double sum = 0;
    a.ForEachChunk(0, 100000, Access::Read, [&](double* d, std::uint64_t, std::uint64_t n) {
      ++chunks;
      for (std::uint64_t i = 0; i < n; ++i)
      {
        sum += d[i];
      }
    });
    EXPECT_GT(chunks, 100u);
    EXPECT_DOUBLE_EQ(sum, 0.5 * 99999.0 * 100000.0 / 2.0);
    b.Close();
    EXPECT_EQ(ListDir(priv).size(), 1u); // CloseBlock removes the file
    const Stats st = dml.GetStats();
    EXPECT_GT(st.misses, 0u);
    EXPECT_GT(st.hits, 0u);
    EXPECT_GT(st.bytesWritten, 0u);
    EXPECT_LE(st.peakBytes, 64u * 1024u);
    EXPECT_TRUE(st.usedOutOfCore);
  }
  EXPECT_TRUE(ListDir(tmp.Path()).empty()); // the destructor removes the private directory
}

TEST(StorageDML, InlineElementAccessFollowsThePageCache)
{
  // Out of core, Read and Write of one element are served inline from the block's last used
  // page. That page must stop being used when it is evicted (written back if dirty), when the
  // block shrinks inside it, and when the block moves in core.
  TempDir tmp;
  DML dml;
  dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::Automatic));
  Array<std::uint64_t> a(dml, 50000);
  Array<std::uint64_t> b(dml, 50000);
  ASSERT_EQ(dml.GetMode(), Mode::OutOfCore);
  for (std::uint64_t i = 0; i < 50000; ++i)
  {
    a.Set(i, 3 * i);
  }
  const std::uint64_t per = DMLTestAccess::PageSize(dml) / sizeof(std::uint64_t);
  ASSERT_GT(per, 4u);
  // a's page 10 is the last used one; written inline, then evicted by a sweep over b.
  for (std::uint64_t i = 10 * per; i < 11 * per; ++i)
  {
    a.Set(i, a.Get(i) + 1);
  }
  for (std::uint64_t i = 0; i < 50000; ++i)
  {
    b.Set(i, i);
  }
  for (std::uint64_t i = 0; i < 50000; i += 1 + i % 5)
  {
    ASSERT_EQ(a.Get(i), 3 * i + (i >= 10 * per && i < 11 * per)) << i;
  }
  // Shrink inside the last used page: the elements past the new end are gone.
  const std::uint64_t end = 20 * per + per / 2;
  ASSERT_EQ(a.Get(end + 1), 3 * (end + 1));
  a.Resize(end);
  EXPECT_EQ(a.Get(end - 1), 3 * (end - 1)); // its page is the last used one again
  EXPECT_THROW(a.Get(end + 1), std::out_of_range);
  EXPECT_THROW(a.Set(end, 0), std::out_of_range);
  // In core after freeing b: the same values from the block's memory.
  b.Close();
  a.Resize(4000);
  ASSERT_EQ(dml.Reconfigure(), Mode::InCore);
  for (std::uint64_t i = 0; i < 4000; ++i)
  {
    ASSERT_EQ(a.Get(i), 3 * i + (i >= 10 * per && i < 11 * per)) << i;
  }
  const Stats st = dml.GetStats();
  EXPECT_GT(st.hits, 100000u); // inline hits are counted
  EXPECT_GT(st.misses, 0u);
}

TEST(StorageDML, CachedPagesAreServedInlineUntilEvicted)
{
  // Out of core, every cached page whose reference bit is set is served inline (the published
  // table of pages), so a loop that moves between several pages (the neighbours of a vertex in
  // a subdivided scan's index ranges) stays off the slow path. Each of them must stop being used
  // when its frame is evicted.
  TempDir tmp;
  DML dml;
  dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::OutOfCore));
  constexpr std::uint64_t n = 50000;
  Array<std::uint64_t> a(dml, n);
  std::vector<std::uint64_t> init(n);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    init[i] = 3 * i;
  }
  dml.WriteRange(a.Id(), 0, n, init.data()); // straight to the file: a holds no frames yet
  const std::uint64_t per = DMLTestAccess::PageSize(dml) / sizeof(std::uint64_t);
  ASSERT_GT(per, 4u);
  constexpr std::size_t kPages = 6;
  ASSERT_GE(DMLTestAccess::FrameSlots(dml), 2 * kPages);
  ASSERT_GT(n / per, 2 + 3 * kPages);
  // Alternate between kPages pages of a (more than the slow path's recent pages): after the
  // first round, every access is inline. The first read of a page and the first write (which
  // marks it dirty) go through the slow path.
  std::uint64_t pages[kPages];
  for (std::size_t k = 0; k < kPages; ++k)
  {
    pages[k] = 2 + 3 * k;
  }
  const std::uint64_t inlineBefore = DMLTestAccess::InlineHits(dml);
  const std::uint64_t missesBefore = dml.GetStats().misses;
  for (std::uint64_t j = 0; j < per; ++j)
  {
    for (std::uint64_t page : pages)
    {
      const std::uint64_t i = page * per + j;
      a.Set(i, a.Get(i) + 1);
    }
  }
  EXPECT_EQ(DMLTestAccess::InlineHits(dml) - inlineBefore, 2 * per * kPages - 2 * kPages);
  EXPECT_EQ(dml.GetStats().misses, missesBefore + kPages);
  // A run inside a cached page is inline too (a vertex's list of faces). Writing a page that
  // was only read so far goes through the slow path once, which marks it dirty (it must be
  // written back below); the next write of it is inline.
  std::vector<bool> plus1000(n, false);
  {
    const std::uint64_t clean = 40;
    ASSERT_EQ(a.Get(clean * per), 3 * clean * per); // a miss
    std::vector<std::uint64_t> run(per / 2);
    const std::uint64_t hits = DMLTestAccess::InlineHits(dml);
    const std::uint64_t first = clean * per + per / 4;
    dml.ReadRange(a.Id(), first, run.size(), run.data());
    for (std::size_t j = 0; j < run.size(); ++j)
    {
      ASSERT_EQ(run[j], 3 * (first + j)) << j;
      run[j] += 1000;
    }
    dml.WriteRange(a.Id(), first, run.size() / 2, run.data());
    dml.WriteRange(a.Id(), first + run.size() / 2, run.size() - run.size() / 2,
      run.data() + run.size() / 2);
    EXPECT_EQ(DMLTestAccess::InlineHits(dml), hits + 2);
    EXPECT_EQ(dml.GetStats().misses, missesBefore + kPages + 1);
    for (std::size_t j = 0; j < run.size(); ++j)
    {
      plus1000[first + j] = true;
    }
  }
  // Those dirty, recent pages are a's only frames. Many other blocks now take their share of
  // the frames, which leaves a one or two: most of its recent pages are evicted (written back).
  // Reads of a must then come from the file, not from frames that now hold other blocks.
  const std::uint32_t slots = DMLTestAccess::FrameSlots(dml);
  ASSERT_GT(slots, 0u);
  std::vector<Array<std::uint64_t>> others;
  for (std::uint32_t k = 0; k < slots; ++k)
  {
    others.emplace_back(dml, 4 * per);
    for (std::uint64_t i = 0; i < 4 * per; ++i)
    {
      others.back().Set(i, 7 * i + k);
    }
  }
  auto expected = [&](std::uint64_t i) {
    const std::uint64_t extra = plus1000[i] ? 1000 : 0;
    for (std::uint64_t page : pages)
    {
      if (i / per == page)
      {
        return 3 * i + 1 + extra;
      }
    }
    return 3 * i + extra;
  };
  for (std::size_t k = kPages; k-- > 0;)
  {
    for (std::uint64_t j = 0; j < per; ++j)
    {
      const std::uint64_t i = pages[k] * per + j;
      ASSERT_EQ(a.Get(i), expected(i)) << "page " << pages[k] << " element " << j;
    }
  }
  for (std::uint64_t i = 0; i < n; i += 1 + i % 7)
  {
    ASSERT_EQ(a.Get(i), expected(i)) << i;
  }
  for (std::uint32_t k = 0; k < slots; ++k)
  {
    for (std::uint64_t i = 0; i < 4 * per; i += 1 + i % 5)
    {
      ASSERT_EQ(others[k].Get(i), 7 * i + k) << k << " " << i;
    }
  }
}

// PagePolicy::Clock (the default) keeps the pages a block keeps using, whatever the other blocks
// do: a small block read over and over keeps its pages while a large one streams past them, so
// that each page misses exactly once. The static shares (by file size) give the small block one
// page, and its pages miss on every round.
TEST(StorageDML, TheClockKeepsTheHotPagesWhileAnotherBlockStreams)
{
  TempDir dir;
  constexpr std::uint64_t kHot = 4, kStream = 400;
  for (const PagePolicy pages : { PagePolicy::Clock, PagePolicy::StaticWeight })
  {
    SCOPED_TRACE(pages == PagePolicy::Clock ? "clock" : "static shares");
    DML dml;
    ASSERT_EQ(dml.Config(MakeProfile(dir.Path(), 256 << 10, ModePolicy::OutOfCore, pages)),
      Mode::OutOfCore);
    const std::uint64_t per = dml.PageBytes() / sizeof(std::uint64_t);
    ASSERT_GT(per, 1u);
    ASSERT_GE(dml.PinnablePages(), kHot + 4) << "the cache must hold the hot pages and more";
    Array<std::uint64_t> hot(dml, kHot * per);
    Array<std::uint64_t> stream(dml, kStream * per);
    const std::uint64_t before = dml.GetStats().misses;
    std::uint64_t sum = 0;
    std::uint64_t x = 0;
    for (std::uint64_t i = 0; i < kStream; ++i)
    {
      dml.Read(stream.Id(), sizeof(x), i * per + i % per, &x);
      sum += x;
      for (std::uint64_t h = 0; h < kHot; ++h)
      {
        dml.Read(hot.Id(), sizeof(x), h * per + i % per, &x);
        sum += x;
      }
    }
    EXPECT_EQ(sum, 0u);
    const std::uint64_t misses = dml.GetStats().misses - before;
    if (pages == PagePolicy::Clock)
    {
      EXPECT_EQ(misses, kHot + kStream);
    }
    else
    {
      EXPECT_GT(misses, kStream * kHot);
    }
  }
  EXPECT_TRUE(ListDir(dir.Path()).empty());
}

TEST(StorageDML, APageWrittenBackIsMarkedDirtyAgainByItsNextWrite)
{
  // A page written inline, then written back without being evicted (a fork writes the parent's
  // dirty pages back), is clean: the next write must go through the slow path and mark it dirty
  // again, or that write would be lost when the page is evicted.
  const std::uint64_t budget = 1 << 20;
  constexpr std::uint64_t n = 1000000; // 8 MB of zeros
  PagedZeros z(budget, n);
  DML& dml = z.dml;
  Array<std::uint64_t>& a = z.a;
  const std::uint64_t per = z.per;
  ASSERT_GT(per, 8u);
  const std::uint64_t i0 = 3 * per + 1;
  auto forkAndJoin = [&](std::uint64_t bytes) {
    std::unique_ptr<DML> child = dml.Fork(bytes, {});
    ASSERT_NE(child, nullptr);
    dml.Join(*child);
  };
  // (a child's page buffers come from this DML, and come back free at Join: a smaller fork
  // later takes those, and page 3 stays cached)
  forkAndJoin(budget / 4);
  a.Set(i0, 1);     // a miss: read, then marked dirty
  std::uint64_t hits = DMLTestAccess::InlineHits(dml);
  a.Set(i0 + 1, 2); // inline
  EXPECT_EQ(DMLTestAccess::InlineHits(dml), hits + 1);
  forkAndJoin(budget / 8); // page 3 is written back, and stays cached
  hits = DMLTestAccess::InlineHits(dml);
  const std::uint64_t cachedMisses = dml.GetStats().misses;
  a.Set(i0 + 2, 3); // the page is cached but clean: the slow path
  EXPECT_EQ(DMLTestAccess::InlineHits(dml), hits);
  EXPECT_EQ(dml.GetStats().misses, cachedMisses);
  a.Set(i0 + 3, 4); // dirty again: inline
  EXPECT_EQ(DMLTestAccess::InlineHits(dml), hits + 1);
  // Every other page of a, twice: page 3 is evicted (and must be written back first).
  const std::uint64_t missesBefore = dml.GetStats().misses;
  for (int round = 0; round < 2; ++round)
  {
    for (std::uint64_t i = 0; i < n; i += per / 2)
    {
      if (i / per != 3) // (a page of a's 8 MB: each is read twice, so every frame turns over)
      {
        ASSERT_EQ(a.Get(i), 0u) << i;
      }
    }
  }
  ASSERT_GT(dml.GetStats().misses, missesBefore + DMLTestAccess::FrameSlots(dml));
  EXPECT_EQ(a.Get(i0), 1u);
  EXPECT_EQ(a.Get(i0 + 1), 2u);
  EXPECT_EQ(a.Get(i0 + 2), 3u);
  EXPECT_EQ(a.Get(i0 + 3), 4u);
  EXPECT_EQ(a.Get(i0 + 4), 0u);
}

TEST(StorageDML, AJoinTakesThisDMLsCopyOfTheChildsElementsOutOfTheInlineTable)
{
  // A page this DML holds clean and serves inline, inside the range a forked child writes: at
  // Join the copy is dropped, and the next read must see the child's elements, not the copy.
  const std::uint64_t budget = 1 << 20;
  PagedZeros z(budget, 1000000); // 8 MB of zeros
  DML& dml = z.dml;
  Array<std::uint64_t>& a = z.a;
  const std::uint64_t per = z.per;
  ASSERT_GT(per, 8u);
  {
    // (buffers to spare: the fork below takes those, not this DML's cached page)
    std::unique_ptr<DML> child = dml.Fork(budget / 4, {});
    ASSERT_NE(child, nullptr);
    dml.Join(*child);
  }
  const std::uint64_t i0 = 5 * per + 3;
  ASSERT_EQ(a.Get(i0), 0u); // a miss: cached, clean
  std::uint64_t hits = DMLTestAccess::InlineHits(dml);
  ASSERT_EQ(a.Get(i0 + 1), 0u);
  ASSERT_EQ(DMLTestAccess::InlineHits(dml), hits + 1); // served inline
  std::unique_ptr<DML> child = dml.Fork(budget / 8, { { a.Id(), 5 * per, per } });
  ASSERT_NE(child, nullptr);
  const std::uint64_t misses = dml.GetStats().misses;
  for (std::uint64_t k = 0; k < 4; ++k)
  {
    const std::uint64_t v = 40 + k;
    child->Write(a.Id(), sizeof(v), i0 + k, &v);
  }
  dml.Join(*child);
  child.reset();
  for (std::uint64_t k = 0; k < 4; ++k)
  {
    EXPECT_EQ(a.Get(i0 + k), 40 + k) << k;
  }
  EXPECT_EQ(a.Get(i0 + 4), 0u);
  EXPECT_GT(dml.GetStats().misses, misses); // (the copy was dropped: read again)
}

TEST(StorageDML, ElementsCutByAShrinkReadZeroAfterAGrowth)
{
  // Out of core, the elements a Resize cuts from a cached, dirty page (served inline) must read
  // zero once the block grows again.
  constexpr std::uint64_t n = 100000;
  PagedZeros z(256 * 1024, n);
  Array<std::uint64_t>& a = z.a;
  const std::uint64_t per = z.per;
  ASSERT_GT(per, 8u);
  ASSERT_GT(n, 4 * per);
  for (std::uint64_t i = n - 2 * per; i < n; ++i)
  {
    a.Set(i, 7);
  }
  const std::uint64_t m = n - per / 2 - 1; // (inside a page)
  a.Resize(m);
  a.Resize(n);
  for (std::uint64_t i = n - 2 * per; i < n; ++i)
  {
    ASSERT_EQ(a.Get(i), i < m ? 7u : 0u) << i;
  }
}

TEST(StorageDML, ElementsLargerThanAPage)
{
  TempDir tmp;
  DML dml;
  dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::OutOfCore));
  Array<int> small(dml, 5000);
  for (int i = 0; i < 5000; ++i)
  {
    small.Set(i, i);
  }
  struct Big
  {
    unsigned char bytes[6000];
  };
  const BlockId big = dml.OpenBlock(sizeof(Big), 20);
  Big v{};
  for (int i = 0; i < 20; ++i)
  {
    std::memset(v.bytes, i + 1, sizeof(v.bytes));
    dml.Write(big, sizeof(Big), i, &v);
  }
  EXPECT_GE(DMLTestAccess::PageSize(dml), sizeof(Big));
  for (int i = 0; i < 20; ++i)
  {
    dml.Read(big, sizeof(Big), i, &v);
    EXPECT_EQ(v.bytes[0], i + 1);
    EXPECT_EQ(v.bytes[5999], i + 1);
  }
  for (int i = 0; i < 5000; ++i)
  {
    ASSERT_EQ(small.Get(i), i);
  }
  EXPECT_LE(dml.GetStats().peakBytes, 64u * 1024u);
}

TEST(StorageDML, PinsAreLimitedByTheBudget)
{
  TempDir tmp;
  DML dml;
  dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::OutOfCore));
  Array<std::uint64_t> a(dml, 200000);
  std::vector<Span> pinned;
  bool refused = false;
  for (std::uint64_t i = 0; i < 200000;)
  {
    try
    {
      Span s = dml.Pin(a.Id(), i, Access::Write);
      static_cast<std::uint64_t*>(s.data)[0] = i + 1;
      pinned.push_back(s);
      i += s.count;
    }
    catch (const BudgetError&)
    {
      refused = true;
      break;
    }
  }
  EXPECT_TRUE(refused);
  EXPECT_GT(pinned.size(), 4u);
  // Plain accesses still work while the rest is pinned.
  a.Set(199999, 7);
  EXPECT_EQ(a.Get(199999), 7u);
  for (const Span& s : pinned)
  {
    dml.Unpin(a.Id(), s);
  }
  for (const Span& s : pinned)
  {
    EXPECT_EQ(a.Get(s.first), s.first + 1);
  }
  EXPECT_LE(dml.GetStats().peakBytes, 64u * 1024u);
}

TEST(StorageDML, AutomaticSwitchAndReconfigure)
{
  TempDir tmp;
  DML dml;
  const std::uint64_t B = 1 << 20;
  EXPECT_EQ(dml.Config(MakeProfile(tmp.Path(), B, ModePolicy::Automatic)), Mode::InCore);
  Array<std::uint32_t> a(dml, 100000); // 400 KB: in core
  for (std::uint32_t i = 0; i < 100000; ++i)
  {
    a.Set(i, i);
  }
  EXPECT_NE(dml.BasePointer(a.Id()), nullptr);
  // Opening 800 KB more would exceed B: the DML moves out of core on its own.
  Array<std::uint32_t> b(dml, 200000);
  EXPECT_EQ(dml.GetMode(), Mode::OutOfCore);
  EXPECT_EQ(dml.GetStats().reconfigurations, 1u);
  EXPECT_EQ(dml.BasePointer(a.Id()), nullptr);
  EXPECT_EQ(a.Get(12345), 12345u);
  b.Set(199999, 5);
  // Still too big: Reconfigure keeps the mode.
  EXPECT_EQ(dml.Reconfigure(), Mode::OutOfCore);
  // Shrink below B: back in core, files and private directory gone, data intact.
  const std::string priv = dml.PrivateDirectory();
  ASSERT_FALSE(priv.empty());
  b.Resize(1000);
  EXPECT_EQ(dml.Reconfigure(), Mode::InCore);
  EXPECT_NE(::access(priv.c_str(), F_OK), 0);
  EXPECT_EQ(dml.PrivateDirectory(), "");
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
  const Stats st = dml.GetStats();
  EXPECT_EQ(st.reconfigurations, 2u);
  EXPECT_TRUE(st.usedInCore && st.usedOutOfCore);
  EXPECT_LE(st.peakBytes, B);
  EXPECT_NE(dml.BasePointer(a.Id()), nullptr);
  for (std::uint32_t i = 0; i < 100000; i += 17)
  {
    ASSERT_EQ(a.Get(i), i);
  }
  // Growth past B in core spills again (in -> out), counted.
  b.Resize(300000);
  EXPECT_EQ(dml.GetMode(), Mode::OutOfCore);
  EXPECT_EQ(dml.GetStats().reconfigurations, 3u);
  EXPECT_EQ(b.Get(299999), 0u);
  EXPECT_EQ(a.Get(99999), 99999u);
  b.Close();
  EXPECT_EQ(dml.Reconfigure(), Mode::InCore);
  EXPECT_EQ(dml.GetStats().reconfigurations, 4u);
  EXPECT_LE(dml.GetStats().peakBytes, B);
}

TEST(StorageDML, ConfigEstimateAndForcedModes)
{
  TempDir tmp;
  {
    DML dml;
    Profile p = MakeProfile(tmp.Path(), 1 << 20, ModePolicy::Automatic);
    p.structures = { { "vertices", 12, 1000000, 0.0 }, { "faces", 12, 2000000, 0.0 } };
    EXPECT_EQ(dml.Config(p), Mode::OutOfCore); // C = 36 MB > B
    Array<float> small(dml, 1000);
    small.Set(3, 1.5f);
    EXPECT_EQ(dml.Reconfigure(), Mode::InCore); // what is open fits
    EXPECT_EQ(small.Get(3), 1.5f);
    EXPECT_EQ(dml.GetStats().reconfigurations, 1u);
  }
  {
    DML dml;
    EXPECT_EQ(dml.Config(MakeProfile(tmp.Path(), 1 << 20, ModePolicy::InCore)), Mode::InCore);
    Array<char> a(dml, 1000);
    EXPECT_THROW(dml.OpenBlock(1, 2 << 20), BudgetError); // hard budget, forced in core
    EXPECT_EQ(dml.GetMode(), Mode::InCore);
  }
  {
    DML dml;
    EXPECT_EQ(dml.Config(MakeProfile(tmp.Path(), 1 << 20, ModePolicy::OutOfCore)),
      Mode::OutOfCore);
    Array<char> a(dml, 10);
    EXPECT_EQ(dml.Reconfigure(), Mode::OutOfCore); // forced
  }
  {
    DML dml; // budget 0: unbounded, in core
    Profile p = MakeProfile(tmp.Path(), 0, ModePolicy::Automatic);
    p.structures = { { "huge", 8, std::uint64_t(1) << 40, 0.0 } };
    EXPECT_EQ(dml.Config(p), Mode::InCore);
  }
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
}

// PlannedMode is Config's choice on a fresh DML, also right at the budget's edge.
TEST(StorageDML, PlannedModeIsConfigsChoice)
{
  TempDir tmp;
  int outOfCore = 0, inCore = 0; // (Automatic, bounded)
  for (ModePolicy policy : { ModePolicy::Automatic, ModePolicy::InCore, ModePolicy::OutOfCore })
  {
    for (std::uint64_t budget : { std::uint64_t(0), std::uint64_t(1) << 20 })
    {
      // C = 3.5 n bytes and the DML's metadata, around the budget of 1 MiB
      for (std::uint64_t n = 280000; n <= 320000; n += 97)
      {
        Profile p = MakeProfile(tmp.Path(), budget, policy);
        p.structures = { { "a", 3, n, 0.0 }, { "b", 1, n / 2, 0.0 } };
        DML dml;
        const Mode planned = PlannedMode(p);
        ASSERT_EQ(int(planned), int(dml.Config(p))) << int(policy) << " " << budget << " " << n;
        if (policy == ModePolicy::Automatic && budget)
        {
          (planned == Mode::OutOfCore ? outOfCore : inCore)++;
        }
      }
    }
  }
  EXPECT_GT(outOfCore, 10);
  EXPECT_GT(inCore, 10);
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
}

// An in-core block that grows past the huge-page size moves to fresh memory: its elements stay,
// the new ones are zero.
TEST(StorageDML, InCoreGrowthKeepsTheElements)
{
  DML dml;
  Array<std::uint64_t> a(dml, 1000);
  for (std::uint64_t i = 0; i < a.Size(); ++i)
  {
    a.Set(i, i * 7 + 1);
  }
  std::uint64_t filled = a.Size();
  while (a.Size() < (std::uint64_t(24) << 20) / sizeof(std::uint64_t))
  {
    a.Resize(a.Size() * 2 + 3);
    for (std::uint64_t i = 0; i < a.Size(); i += 997)
    {
      ASSERT_EQ(a.Get(i), i < filled ? i * 7 + 1 : 0u) << i << " of " << a.Size();
    }
    for (std::uint64_t i = filled; i < a.Size(); ++i)
    {
      a.Set(i, i * 7 + 1);
    }
    filled = a.Size();
    EXPECT_EQ(dml.GetMode(), Mode::InCore);
  }
  EXPECT_EQ(a.Get(filled - 1), (filled - 1) * 7 + 1);
}

TEST(StorageDML, ConfigWithOpenBlocksMovesThem)
{
  TempDir tmp;
  DML dml;
  dml.Config(MakeProfile(tmp.Path(), 256 * 1024, ModePolicy::OutOfCore));
  Array<std::uint64_t> a(dml, 100000);
  for (std::uint64_t i = 0; i < 100000; ++i)
  {
    a.Set(i, i * i);
  }
  const auto check = [&] {
    for (std::uint64_t i = 0; i < 100000; i += 37)
    {
      ASSERT_EQ(a.Get(i), i * i);
    }
  };
  EXPECT_EQ(dml.Config(MakeProfile(tmp.Path(), 0, ModePolicy::Automatic)), Mode::InCore);
  EXPECT_NE(dml.BasePointer(a.Id()), nullptr);
  check();
  EXPECT_EQ(dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::Automatic)),
    Mode::OutOfCore);
  EXPECT_EQ(dml.BasePointer(a.Id()), nullptr);
  check();
  EXPECT_LE(dml.GetStats().peakBytes, 64u * 1024u);
}

TEST(StorageDML, BlocksSpreadOverDirectories)
{
  TempDir d1;
  TempDir d2;
  {
    DML dml;
    Profile p = MakeProfile(d1.Path(), 128 * 1024, ModePolicy::OutOfCore);
    p.directories.push_back(d2.Path());
    dml.Config(p);
    std::vector<Array<int>> arrays;
    for (int i = 0; i < 4; ++i)
    {
      arrays.emplace_back(dml, 10000);
      arrays.back().Set(9999, i);
    }
    ASSERT_EQ(ListDir(d1.Path()).size(), 1u);
    ASSERT_EQ(ListDir(d2.Path()).size(), 1u);
    EXPECT_EQ(ListDir(d1.Path() + "/" + ListDir(d1.Path())[0]).size(), 2u);
    EXPECT_EQ(ListDir(d2.Path() + "/" + ListDir(d2.Path())[0]).size(), 2u);
    for (int i = 0; i < 4; ++i)
    {
      EXPECT_EQ(arrays[i].Get(9999), i);
    }
  }
  EXPECT_TRUE(ListDir(d1.Path()).empty());
  EXPECT_TRUE(ListDir(d2.Path()).empty());
}

TEST(StorageDML, SparseFileBeyond4GiB)
{
  TempDir tmp;
  DML dml;
  dml.Config(MakeProfile(tmp.Path(), 1 << 20, ModePolicy::Automatic));
  const std::uint64_t count = 625000000; // 5e9 bytes of 8-byte elements
  const BlockId id = dml.OpenBlock(8, count);
  EXPECT_EQ(dml.GetMode(), Mode::OutOfCore);
  EXPECT_EQ(DMLTestAccess::FileBytes(dml, id), 5000000000ull);
  const std::uint64_t at4G = (std::uint64_t(1) << 32) / 8;
  const std::uint64_t idx[] = { 0, at4G - 1, at4G, at4G + 1, 600000000, count - 1 };
  for (const std::uint64_t i : idx)
  {
    const std::uint64_t v = i * 2654435761u + 1;
    dml.Write(id, 8, i, &v);
  }
  std::vector<std::uint64_t> range(1000);
  for (std::uint64_t i = 0; i < range.size(); ++i)
  {
    range[i] = i ^ 0xABCDEFull;
  }
  dml.WriteRange(id, at4G + 100000, range.size(), range.data()); // direct I/O past 4 GiB
  // Force everything out of the cache with unrelated traffic.
  for (std::uint64_t i = 0; i < 2000; ++i)
  {
    std::uint64_t x = 0;
    dml.Read(id, 8, 100000000 + i * 1000, &x);
    ASSERT_EQ(x, 0u); // never written: zeros
  }
  for (const std::uint64_t i : idx)
  {
    std::uint64_t v = 0;
    dml.Read(id, 8, i, &v);
    EXPECT_EQ(v, i * 2654435761u + 1) << i;
  }
  std::vector<std::uint64_t> back(range.size());
  dml.ReadRange(id, at4G + 100000, back.size(), back.data());
  EXPECT_EQ(back, range);
  dml.Resize(id, count + 1000); // grow past 5 GB: new elements read as zeros
  std::uint64_t z = 1;
  dml.Read(id, 8, count + 999, &z);
  EXPECT_EQ(z, 0u);
  EXPECT_LE(dml.GetStats().peakBytes, 1u << 20);
}

TEST(StorageDML, FillAndRanges)
{
  TempDir tmp;
  for (const ModePolicy policy : { ModePolicy::InCore, ModePolicy::OutOfCore })
  {
    DML dml;
    dml.Config(MakeProfile(tmp.Path(), policy == ModePolicy::InCore ? 0 : 64 * 1024, policy));
    Array<std::uint16_t> a(dml, 30001);
    const std::uint16_t seven = 7;
    dml.Fill(a.Id(), &seven);
    EXPECT_EQ(a.Get(0), 7);
    EXPECT_EQ(a.Get(30000), 7);
    a.Set(5, 1);
    const std::uint16_t zero = 0;
    dml.Fill(a.Id(), &zero);
    EXPECT_EQ(a.Get(5), 0);
    EXPECT_EQ(a.Get(30000), 0);
    std::vector<std::uint16_t> v(30001);
    for (std::size_t i = 0; i < v.size(); ++i)
    {
      v[i] = static_cast<std::uint16_t>(i * 31);
    }
    a.Write(0, v.size(), v.data());
    std::vector<std::uint16_t> w(v.size());
    a.Read(0, w.size(), w.data());
    EXPECT_EQ(v, w);
    EXPECT_THROW(a.Read(30000, 2, w.data()), std::out_of_range);
  }
}

// A DML out of core at 256 KiB for the transfer tests: its page in 4-byte words, and a way to
// push every page of a block out of the cache (another block's pages take it over, element by
// element).
struct PagedWords
{
  TempDir tmp;
  DML dml;
  std::size_t page = 0;
  PagedWords()
  {
    this->dml.Config(MakeProfile(this->tmp.Path(), 256 * 1024, ModePolicy::OutOfCore));
    this->page = this->dml.PageBytes() / sizeof(std::uint32_t);
  }
  void Evict(Array<std::uint32_t>& other, std::uint64_t n) const
  {
    for (std::uint64_t i = 0; i < n; i += this->page / 2)
    {
      other.Set(i, std::uint32_t(i));
    }
  }
  // The bytes f() reads from and writes to the files.
  template <class F>
  std::pair<std::uint64_t, std::uint64_t> Moved(F&& f)
  {
    const Stats before = this->dml.GetStats();
    f();
    const Stats after = this->dml.GetStats();
    return { after.bytesRead - before.bytesRead, after.bytesWritten - before.bytesWritten };
  }
};

TEST(StorageDML, BulkRangesOfPagesNotCachedGoStraightToTheFile)
{
  // Out of core, a range read or written in bulk (a sixteenth of a page or more) moves only its
  // own bytes for the pages that are not cached, also where it starts or ends inside a page: no
  // page is read to be written in part, or read whole for a part of it. Pages that are cached
  // (dirty ones above all) are used as they are, and every element keeps its value.
  PagedWords w;
  DML& dml = w.dml;
  const std::size_t page = w.page;
  ASSERT_GE(page, 64u);
  const std::uint64_t n = 40 * page;
  Array<std::uint32_t> a(dml, n);
  std::vector<std::uint32_t> model(n, 0);
  std::mt19937 rng(3);
  // Odd ranges of a quarter to three pages, written then read, at offsets inside pages.
  for (int round = 0; round < 200; ++round)
  {
    const std::uint64_t len = page / 4 + rng() % (3 * page);
    const std::uint64_t first = rng() % (n - len);
    if (round % 3 == 2)
    {
      // (an element written through the cache first: its page is cached and dirty)
      const std::uint64_t i = first + rng() % len;
      a.Set(i, 0xABCD0000u + std::uint32_t(round));
      model[i] = 0xABCD0000u + std::uint32_t(round);
    }
    std::vector<std::uint32_t> v(len);
    if (round % 2 == 0)
    {
      for (std::uint64_t k = 0; k < len; ++k)
      {
        v[k] = std::uint32_t(rng());
        model[first + k] = v[k];
      }
      a.Write(first, len, v.data());
    }
    else
    {
      a.Read(first, len, v.data());
      for (std::uint64_t k = 0; k < len; ++k)
      {
        ASSERT_EQ(v[k], model[first + k]) << round << " " << k;
      }
    }
  }
  for (std::uint64_t i = 0; i < n; i += 7)
  {
    ASSERT_EQ(a.Get(i), model[i]) << i;
  }
  // A part of a page not cached: read, only its bytes; written, no read at all. (Every page
  // of `a` leaves the cache when another block's pages take it over, element by element.)
  Array<std::uint32_t> other(dml, n);
  auto evict = [&] { w.Evict(other, n); };
  evict();
  const std::uint64_t len = page / 2, first = 10 * page + page / 3;
  std::vector<std::uint32_t> part(len);
  EXPECT_EQ(w.Moved([&] { a.Read(first, len, part.data()); }).first, len * sizeof(std::uint32_t));
  for (std::uint64_t k = 0; k < len; ++k)
  {
    ASSERT_EQ(part[k], model[first + k]);
  }
  evict();
  const auto written = w.Moved([&] { a.Write(first + page, len, part.data()); });
  EXPECT_EQ(written.first, 0u);
  EXPECT_EQ(written.second, len * sizeof(std::uint32_t));
  EXPECT_EQ(a.Get(first + page + len - 1), part[len - 1]);
  EXPECT_EQ(a.Get(first + page + len), model[first + page + len]);
}

TEST(StorageDML, EachBlocksIoIsCountedAndTheBlocksAddUpToTheTotals)
{
  // GetBlockStats: a block's misses and bytes read and written since it was opened, a forked
  // child's included once joined; summed over the blocks they are the Stats totals.
  PagedWords w;
  DML& dml = w.dml;
  const std::uint64_t page = w.page, pages = 40, n = pages * page;
  Array<std::uint32_t> a(dml, n), b(dml, n);
  auto io = [&](const Array<std::uint32_t>& x) { return dml.GetBlockStats(x.Id()); };
  EXPECT_EQ(io(a).misses + io(a).bytesRead + io(a).bytesWritten, 0u);
  auto addsUp = [&](const char* when) {
    const Stats t = dml.GetStats();
    EXPECT_EQ(io(a).misses + io(b).misses, t.misses) << when;
    EXPECT_EQ(io(a).bytesRead + io(b).bytesRead, t.bytesRead) << when;
    EXPECT_EQ(io(a).bytesWritten + io(b).bytesWritten, t.bytesWritten) << when;
  };
  for (std::uint64_t i = 0; i < n; ++i)
  {
    a.Set(i, std::uint32_t(i));
  }
  w.Evict(b, n); // most of a's pages go, written back whole
  const std::uint64_t pageBytes = page * sizeof(std::uint32_t);
  EXPECT_GT(io(a).bytesWritten, 0u);
  EXPECT_LE(io(a).bytesWritten, n * sizeof(std::uint32_t));
  EXPECT_EQ(io(a).bytesWritten % pageBytes, 0u);
  EXPECT_GE(io(a).misses, pages);
  addsUp("after the writes");
  // A sweep over a, which the cache cannot hold: most of its pages miss, each miss reads its
  // page whole; b is not read.
  const BlockStats a0 = io(a), b0 = io(b);
  std::uint64_t sum = 0;
  for (std::uint64_t i = 0; i < n; ++i)
  {
    sum += a.Get(i);
  }
  EXPECT_EQ(sum, n * (n - 1) / 2);
  const std::uint64_t missed = io(a).misses - a0.misses;
  EXPECT_LE(missed, pages);
  EXPECT_GE(missed, pages / 2);
  EXPECT_EQ(io(a).bytesRead - a0.bytesRead, missed * pageBytes);
  EXPECT_EQ(io(b).misses, b0.misses);
  EXPECT_EQ(io(b).bytesRead, b0.bytesRead);
  addsUp("after the sweep");
  // A forked child sweeps the upper half of b: its misses are b's after the join.
  const BlockStats b1 = io(b);
  std::unique_ptr<DML> child = dml.Fork(dml.GetProfile().memoryBudget / 2, {});
  ASSERT_NE(child, nullptr);
  for (std::uint64_t i = n / 2; i < n; ++i)
  {
    std::uint32_t x = 0;
    child->Read(b.Id(), sizeof x, i, &x);
  }
  EXPECT_EQ(child->GetBlockStats(b.Id()).misses, pages / 2);
  dml.Join(*child);
  EXPECT_EQ(io(b).misses - b1.misses, pages / 2);
  addsUp("after the join");
  // A block opened in a closed one's slot starts from nothing; in core nothing is counted.
  const BlockId old = a.Id();
  a = Array<std::uint32_t>();
  Array<std::uint32_t> again(dml, n);
  EXPECT_EQ(again.Id(), old);
  EXPECT_EQ(dml.GetBlockStats(again.Id()).misses + dml.GetBlockStats(again.Id()).bytesRead, 0u);
  DML inCore;
  inCore.Config(Profile{});
  Array<std::uint32_t> x(inCore, 1000);
  for (std::uint64_t i = 0; i < 1000; ++i)
  {
    x.Set(i, std::uint32_t(i));
  }
  EXPECT_EQ(inCore.GetBlockStats(x.Id()).misses + inCore.GetBlockStats(x.Id()).bytesRead +
      inCore.GetBlockStats(x.Id()).bytesWritten, 0u);
  EXPECT_THROW(dml.GetBlockStats(BlockId(1000)), std::invalid_argument);
}

TEST(StorageDML, ReadOnceMovesOnlyItsBytesWhateverTheSize)
{
  // ReadOnce (a sorter's segments): a range of a few elements of a page not cached is read
  // straight from the file, only its own bytes, where Read brings the whole page in; a cached
  // page (a dirty one) is used as it is. Every element read has its value.
  PagedWords w;
  DML& dml = w.dml;
  const std::size_t page = w.page;
  ASSERT_GE(page, 256u);
  const std::uint64_t n = 40 * page;
  Array<std::uint32_t> a(dml, n), other(dml, n);
  std::vector<std::uint32_t> model(n);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    model[i] = std::uint32_t(i * 2654435761u);
  }
  a.Write(0, n, model.data());
  auto evict = [&] { w.Evict(other, n); };
  const std::uint64_t len = page / 64, first = 7 * page + 5; // (under a sixteenth of a page)
  std::vector<std::uint32_t> v(len);
  evict();
  EXPECT_EQ(w.Moved([&] { a.ReadOnce(first, len, v.data()); }).first, len * sizeof(std::uint32_t));
  for (std::uint64_t k = 0; k < len; ++k)
  {
    ASSERT_EQ(v[k], model[first + k]) << k;
  }
  // Read of the same size reads the whole page into the cache.
  evict();
  EXPECT_EQ(w.Moved([&] { a.Read(first, len, v.data()); }).first, dml.PageBytes());
  // A dirty cached page: ReadOnce sees the element written through the cache.
  evict();
  a.Set(first + 3, 12345u);
  model[first + 3] = 12345u;
  EXPECT_EQ(w.Moved([&] { a.ReadOnce(first, len, v.data()); }).first, 0u);
  for (std::uint64_t k = 0; k < len; ++k)
  {
    ASSERT_EQ(v[k], model[first + k]) << k;
  }
  // Ranges across pages, some cached and some not.
  std::mt19937 rng(5);
  for (int round = 0; round < 100; ++round)
  {
    const std::uint64_t m = 1 + rng() % (2 * page);
    const std::uint64_t at = rng() % (n - m);
    if (round % 4 == 0)
    {
      evict();
    }
    std::vector<std::uint32_t> w(m);
    a.ReadOnce(at, m, w.data());
    for (std::uint64_t k = 0; k < m; ++k)
    {
      ASSERT_EQ(w[k], model[at + k]) << round << " " << k;
    }
  }
}

// ------------------------------------------------------------------------------------------------
// Randomized equivalence against a std::vector model.
class Workload
{
public:
  struct Model
  {
    std::size_t es = 0;
    BlockId id = -1;
    std::vector<unsigned char> data;
  };

  Workload(DML& dml, std::uint64_t seed)
    : dml_(dml)
    , rng_(seed)
  {
    const std::size_t sizes[] = { 4, 12, 80, 3, 2500 };
    const std::uint64_t counts[] = { 100000, 30000, 5000, 50000, 100 };
    for (int i = 0; i < 5; ++i)
    {
      Model m;
      m.es = sizes[i];
      m.id = dml.OpenBlock(m.es, counts[i]);
      m.data.assign(m.es * counts[i], 0);
      this->blocks_.push_back(std::move(m));
    }
  }

  void Step(int step)
  {
    const int op = static_cast<int>(this->rng_() % 100);
    Model& m = this->blocks_[this->rng_() % this->blocks_.size()];
    const std::uint64_t n = m.data.size() / m.es;
    if (op < 28 && n > 0) // write one
    {
      const std::uint64_t i = this->rng_() % n;
      std::vector<unsigned char> e = this->Bytes(m.es);
      this->dml_.Write(m.id, m.es, i, e.data());
      std::memcpy(m.data.data() + i * m.es, e.data(), m.es);
    }
    else if (op < 50 && n > 0) // read one
    {
      const std::uint64_t i = this->rng_() % n;
      std::vector<unsigned char> e(m.es);
      this->dml_.Read(m.id, m.es, i, e.data());
      ASSERT_EQ(0, std::memcmp(e.data(), m.data.data() + i * m.es, m.es))
        << "step " << step << " block " << m.id << " index " << i;
    }
    else if (op < 57 && n > 0) // write a range (up to ~100 KB, crossing pages)
    {
      const std::uint64_t first = this->rng_() % n;
      const std::uint64_t c = std::min<std::uint64_t>(n - first, 1 + this->rng_() % (100000 / m.es));
      std::vector<unsigned char> e = this->Bytes(c * m.es);
      this->dml_.WriteRange(m.id, first, c, e.data());
      std::memcpy(m.data.data() + first * m.es, e.data(), e.size());
    }
    else if (op < 64 && n > 0) // read a range
    {
      const std::uint64_t first = this->rng_() % n;
      const std::uint64_t c = std::min<std::uint64_t>(n - first, 1 + this->rng_() % (100000 / m.es));
      std::vector<unsigned char> e(c * m.es);
      this->dml_.ReadRange(m.id, first, c, e.data());
      ASSERT_EQ(0, std::memcmp(e.data(), m.data.data() + first * m.es, e.size()))
        << "step " << step << " range " << first << "+" << c;
    }
    else if (op < 67) // resize: shrink or grow, bounded
    {
      std::uint64_t target = n / 2 + this->rng_() % (n + n / 4 + 200); // drifts upwards
      target = std::min<std::uint64_t>(target, 400000 / m.es + 10);
      this->Resize(m, target);
    }
    else if (op < 68 && n > 0) // pin and modify a page
    {
      const std::uint64_t i = this->rng_() % n;
      Span s = this->dml_.Pin(m.id, i, Access::Write);
      const std::uint64_t c = std::min<std::uint64_t>(s.count, 5);
      std::vector<unsigned char> e = this->Bytes(c * m.es);
      std::memcpy(s.data, e.data(), e.size());
      this->dml_.Unpin(m.id, s);
      std::memcpy(m.data.data() + i * m.es, e.data(), e.size());
    }
    else if (op < 69) // fill
    {
      std::vector<unsigned char> e = this->Bytes(m.es);
      if (this->rng_() % 2)
      {
        std::fill(e.begin(), e.end(), 0);
      }
      this->dml_.Fill(m.id, e.data());
      for (std::uint64_t i = 0; i < n; ++i)
      {
        std::memcpy(m.data.data() + i * m.es, e.data(), m.es);
      }
    }
    else if (n > 0) // read a range back
    {
      const std::uint64_t first = this->rng_() % n;
      const std::uint64_t count = std::min<std::uint64_t>(n - first, 1 + this->rng_() % 64);
      std::vector<unsigned char> e(count * m.es);
      this->dml_.ReadRange(m.id, first, count, e.data());
      ASSERT_TRUE(std::memcmp(e.data(), m.data.data() + first * m.es, e.size()) == 0)
        << "step " << step << " block " << m.id;
    }
  }

  void Resize(Model& m, std::uint64_t count)
  {
    this->dml_.Resize(m.id, count);
    m.data.resize(count * m.es, 0);
  }

  void ShrinkAll(std::uint64_t bytes)
  {
    for (auto& m : this->blocks_)
    {
      this->Resize(m, std::min<std::uint64_t>(m.data.size(), bytes) / m.es);
    }
  }

  void CheckAll()
  {
    for (const auto& m : this->blocks_)
    {
      const std::uint64_t n = m.data.size() / m.es;
      ASSERT_EQ(this->dml_.Count(m.id), n);
      std::vector<unsigned char> e(m.data.size());
      this->dml_.ReadRange(m.id, 0, n, e.data());
      ASSERT_TRUE(e == m.data) << "block " << m.id;
    }
  }

private:
  std::vector<unsigned char> Bytes(std::size_t n)
  {
    std::vector<unsigned char> e(n);
    for (auto& c : e)
    {
      c = static_cast<unsigned char>(this->rng_());
    }
    return e;
  }

  DML& dml_;
  std::mt19937_64 rng_;
  std::vector<Model> blocks_;
};

struct RandomCase
{
  const char* name;
  std::uint64_t budget;
  ModePolicy policy;
  PagePolicy pages;
};

class StorageDMLRandom : public ::testing::TestWithParam<RandomCase>
{
};

TEST_P(StorageDMLRandom, MatchesVectorModel)
{
  const RandomCase c = GetParam();
  TempDir tmp;
  {
    DML dml;
    Profile p = MakeProfile(tmp.Path(), c.budget, c.policy, c.pages);
    p.structures = { { "data", 1, 1600000, 0.0 } };
    const Mode mode = dml.Config(p);
    EXPECT_EQ(mode, c.budget == 0 ? Mode::InCore : Mode::OutOfCore);
    Workload w(dml, 20240607);
    for (int step = 0; step < 15000; ++step)
    {
      w.Step(step);
      if (::testing::Test::HasFatalFailure())
      {
        return;
      }
    }
    w.CheckAll();
    const Stats st = dml.GetStats();
    if (c.budget != 0)
    {
      EXPECT_LE(st.peakBytes, c.budget);
      EXPECT_EQ(st.mode, Mode::OutOfCore);
      EXPECT_GT(st.misses, 0u);
    }
  }
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
}

INSTANTIATE_TEST_SUITE_P(Budgets, StorageDMLRandom,
  ::testing::Values(RandomCase{ "InCore", 0, ModePolicy::Automatic, PagePolicy::StaticWeight },
    RandomCase{ "OutOfCore64K", 64 * 1024, ModePolicy::Automatic, PagePolicy::StaticWeight },
    RandomCase{ "OutOfCore256K", 256 * 1024, ModePolicy::Automatic, PagePolicy::StaticWeight },
    RandomCase{ "OutOfCore1M", 1024 * 1024, ModePolicy::Automatic, PagePolicy::StaticWeight },
    RandomCase{ "Adaptive256K", 256 * 1024, ModePolicy::Automatic, PagePolicy::Adaptive },
    RandomCase{ "Clock256K", 256 * 1024, ModePolicy::Automatic, PagePolicy::Clock }),
  [](const ::testing::TestParamInfo<RandomCase>& i) { return std::string(i.param.name); });

TEST(StorageDML, RandomizedWithReconfiguration)
{
  TempDir tmp;
  DML dml;
  const std::uint64_t B = 1 << 20;
  Profile p = MakeProfile(tmp.Path(), B, ModePolicy::Automatic);
  p.structures = { { "data", 1, 1600000, 0.0 } };
  ASSERT_EQ(dml.Config(p), Mode::OutOfCore);
  Workload w(dml, 77);
  bool sawIn = false;
  bool sawOut = false;
  for (int step = 0; step < 20000; ++step)
  {
    w.Step(step);
    ASSERT_FALSE(::testing::Test::HasFatalFailure());
    if (step % 2500 == 1249)
    {
      w.ShrinkAll(60000); // small enough to fit B
      ASSERT_EQ(dml.Reconfigure(), Mode::InCore) << "step " << step; // out -> in
      sawIn = true;
    }
    if (dml.GetMode() == Mode::OutOfCore && sawIn)
    {
      sawOut = true; // the workload grew past B: in -> out happened on its own
    }
    if (step % 2500 == 2000)
    {
      dml.Reconfigure(); // whatever it decides, contents must stay identical
    }
  }
  w.CheckAll();
  const Stats st = dml.GetStats();
  EXPECT_TRUE(sawIn);
  EXPECT_TRUE(sawOut);
  EXPECT_GE(st.reconfigurations, 4u);
  EXPECT_TRUE(st.usedInCore && st.usedOutOfCore);
  EXPECT_LE(st.peakBytes, B);
}

TEST(StorageDML, InstancesInThreadsDoNotShareFiles)
{
  TempDir tmp;
  std::vector<std::string> dirs(4);
  std::vector<int> ok(4, 0);
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t)
  {
    threads.emplace_back([&, t] {
      DML dml;
      dml.Config(MakeProfile(tmp.Path(), 64 * 1024, ModePolicy::OutOfCore));
      Array<int> a(dml, 50000);
      for (int i = 0; i < 50000; ++i)
      {
        a.Set(i, i * (t + 1));
      }
      dirs[t] = dml.PrivateDirectory();
      int good = 1;
      for (int i = 0; i < 50000; ++i)
      {
        good &= a.Get(i) == i * (t + 1);
      }
      ok[t] = good;
    });
  }
  for (auto& th : threads)
  {
    th.join();
  }
  std::sort(dirs.begin(), dirs.end());
  EXPECT_EQ(std::unique(dirs.begin(), dirs.end()), dirs.end());
  for (int t = 0; t < 4; ++t)
  {
    EXPECT_EQ(ok[t], 1);
  }
  EXPECT_TRUE(ListDir(tmp.Path()).empty());
}

} // namespace

// Fork: a child DML on another thread writes its range of a block while the parent writes the
// rest; pages straddle the boundary (it is not page aligned). In block a both sides write the
// boundary page back while forked (each only its own elements); in block c both end there, so
// at Join the parent's dirty copy takes the child's elements. The parent then sees both sides
// and has its budget back.
TEST(StorageDML, ForkedChildWritesItsRangeAndJoinMergesTheBoundaryPage)
{
  TempDir dir;
  DML dml;
  const std::uint64_t budget = 256 << 10;
  ASSERT_EQ(dml.Config(MakeProfile(dir.Path(), budget, ModePolicy::OutOfCore)), Mode::OutOfCore);
  constexpr std::uint64_t n = 100000, mid = 12345;
  Array<std::uint32_t> a(dml, n), c(dml, n);
  Array<double> b(dml, n / 2);
  for (std::uint64_t i = 0; i < n; ++i)
  {
    a.Set(i, std::uint32_t(i));
    c.Set(i, std::uint32_t(i));
  }
  for (std::uint64_t i = 0; i < n / 2; ++i)
  {
    b.Set(i, 0.5 * double(i));
  }
  const std::uint64_t missesBefore = dml.GetStats().misses;
  std::unique_ptr<DML> child =
    dml.Fork(budget / 2, { { a.Id(), mid, n - mid }, { c.Id(), mid, n - mid } });
  ASSERT_NE(child, nullptr);
  // Structural changes wait for Join, on both sides.
  EXPECT_THROW(dml.Resize(a.Id(), n + 1), std::logic_error);
  EXPECT_THROW((Array<int>(dml, 10)), std::logic_error);
  EXPECT_THROW(dml.Reconfigure(), std::logic_error);
  EXPECT_THROW(child->Resize(a.Id(), n + 1), std::logic_error);
  EXPECT_THROW(child->Config(Profile{}), std::logic_error);
  EXPECT_THROW(child->Fork(1 << 16, {}), std::logic_error);
  EXPECT_THROW(dml.Fork(1 << 16, {}), std::logic_error); // one child at a time
  bool childRead = true, childReadB = true;
  auto update = [&](const Array<std::uint32_t>& blk, std::uint64_t i) {
    std::uint32_t x = 0;
    child->Read(blk.Id(), sizeof x, i, &x);
    childRead = childRead && x == i;
    x = std::uint32_t(i + 1000000);
    child->Write(blk.Id(), sizeof x, i, &x);
  };
  // a: the parent caches the boundary page (reading its own element), the child updates its
  // range (its copy of that page is written back as it moves on), then the parent updates its
  // range; its copy, written back while it reads b, must not bring back the child's old
  // elements.
  EXPECT_EQ(a.Get(mid - 1), mid - 1);
  std::thread first([&]() {
    for (std::uint64_t i = mid; i < n; ++i)
    {
      update(a, i);
    }
  });
  first.join();
  bool parentReadB = true;
  for (std::uint64_t i = mid; i-- > 0;)
  {
    a.Set(i, std::uint32_t(i + 2000000));
  }
  for (std::uint64_t i = 0; i < n / 2; ++i)
  {
    parentReadB = parentReadB && b.Get(i) == 0.5 * double(i);
  }
  // c: both at the same time, ending on the boundary page.
  std::thread helper([&]() {
    for (std::uint64_t i = n; i-- > mid;)
    {
      update(c, i);
    }
    for (std::uint64_t i = 0; i < n / 2; i += 7)
    {
      double y = 0;
      child->Read(b.Id(), sizeof y, i, &y);
      childReadB = childReadB && y == 0.5 * double(i);
    }
  });
  for (std::uint64_t i = 0; i < mid; ++i)
  {
    c.Set(i, std::uint32_t(i + 2000000));
  }
  helper.join();
  EXPECT_TRUE(childRead);
  EXPECT_TRUE(childReadB);
  EXPECT_TRUE(parentReadB);
  const std::uint64_t childMisses = child->GetStats().misses;
  EXPECT_GT(childMisses, 0u);
  dml.Join(*child);
  for (const Array<std::uint32_t>* blk : { &a, &c })
  {
    for (std::uint64_t i = 0; i < n; ++i)
    {
      ASSERT_EQ(blk->Get(i), i < mid ? i + 2000000 : i + 1000000) << "element " << i;
    }
  }
  const Stats st = dml.GetStats();
  EXPECT_EQ(st.forks, 1u);
  EXPECT_GE(st.misses, missesBefore + childMisses);
  EXPECT_LE(st.peakBytes, budget);
  EXPECT_LE(st.bytesHeld, budget);
  // The budget is back and the structure may change again.
  a.Resize(n + 1);
  EXPECT_EQ(a.Get(n), 0u);
  std::unique_ptr<DML> again = dml.Fork(budget / 2, {});
  ASSERT_NE(again, nullptr);
  dml.Join(*again);
}

TEST(StorageDML, ForkInCoreReturnsNullAndTooLittleRoomIsABudgetError)
{
  DML inCore;
  inCore.Config(Profile{});
  Array<int> x(inCore, 100);
  EXPECT_EQ(inCore.Fork(1 << 20, { { x.Id(), 0, 100 } }), nullptr);

  TempDir dir;
  DML dml;
  dml.Config(MakeProfile(dir.Path(), 128 << 10, ModePolicy::OutOfCore));
  Array<std::uint64_t> a(dml, 50000);
  for (std::uint64_t i = 0; i < 50000; ++i)
  {
    a.Set(i, i * i);
  }
  EXPECT_THROW(dml.Fork(64, {}), BudgetError);                  // not even the child's metadata
  EXPECT_THROW(dml.Fork(1 << 20, {}), BudgetError);             // more than the budget
  EXPECT_THROW(dml.Fork(1 << 16, { { a.Id(), 10, 50000 } }), std::out_of_range);
  EXPECT_THROW(dml.Fork(1 << 16, { { a.Id(), 0, 1 }, { a.Id(), 5, 1 } }), std::invalid_argument);
  // Nothing was lost and nothing stays lent.
  for (std::uint64_t i = 0; i < 50000; ++i)
  {
    ASSERT_EQ(a.Get(i), i * i);
  }
  // A child destroyed without Join (an error path) gives the budget back and unblocks the
  // parent; what it had not written back is lost.
  {
    std::unique_ptr<DML> lost = dml.Fork(64 << 10, { { a.Id(), 0, 10 } });
    ASSERT_NE(lost, nullptr);
    EXPECT_THROW(a.Resize(10), std::logic_error);
  }
  EXPECT_EQ(dml.GetStats().forks, 0u);
  a.Resize(10);
  std::unique_ptr<DML> child = dml.Fork(64 << 10, { { a.Id(), 5, 5 } });
  ASSERT_NE(child, nullptr);
  const std::uint64_t v = 7;
  child->Write(a.Id(), sizeof v, 9, &v);
  dml.Join(*child);
  EXPECT_EQ(a.Get(9), 7u);
  EXPECT_EQ(a.Get(4), 16u);
}
