// The memory budget is hard: these tests replace malloc/free (and so operator new/delete) with
// counting versions and check that the heap bytes the DML really holds stay within B.
//
// The hook counts malloc_usable_size() of every live chunk, process-wide. Between the baseline
// and the end of a measurement the test body itself does not allocate (buffers are made before
// the baseline), so the growth of the live bytes is the DML's.
#include "Sanitizers.h"
#include "StorageTestUtil.h"

#include "sipmss/storage/DML.h"
#include "sipmss/storage/DMLTesting.h"
#include "sipmss/storage/Sort.h"

#include <gtest/gtest.h>

#include <atomic>
#include <cstring>
#include <malloc.h>
#include <random>
#include <vector>

// Under AddressSanitizer or ThreadSanitizer the allocator is the sanitizer's, which calls malloc
// before it can resolve __libc_malloc (ThreadSanitizer crashes in its start-up): the hooks are
// left out and the tests skip.
#define SIPMSS_HEAP_HOOK (!SIPMSS_ADDRESS_SANITIZER && !SIPMSS_THREAD_SANITIZER)

#if SIPMSS_HEAP_HOOK
extern "C"
{
  void* __libc_malloc(std::size_t);
  void __libc_free(void*);
  void* __libc_calloc(std::size_t, std::size_t);
  void* __libc_realloc(void*, std::size_t);
  void* __libc_memalign(std::size_t, std::size_t);
}
#endif

#if SIPMSS_HEAP_HOOK
namespace
{
std::atomic<std::int64_t> gLive{ 0 };
std::atomic<std::int64_t> gPeak{ 0 };

void Added(void* p)
{
  if (p)
  {
    const std::int64_t now =
      gLive.fetch_add(static_cast<std::int64_t>(malloc_usable_size(p))) +
      static_cast<std::int64_t>(malloc_usable_size(p));
    std::int64_t peak = gPeak.load(std::memory_order_relaxed);
    while (now > peak && !gPeak.compare_exchange_weak(peak, now))
    {
    }
  }
}
void Removed(void* p)
{
  if (p)
  {
    gLive.fetch_sub(static_cast<std::int64_t>(malloc_usable_size(p)));
  }
}
// The DML's returnable blocks (a sort's runs) are mapped, not taken from malloc: counted too.
void Mapped(std::int64_t bytes)
{
  const std::int64_t now = gLive.fetch_add(bytes) + bytes;
  std::int64_t peak = gPeak.load(std::memory_order_relaxed);
  while (now > peak && !gPeak.compare_exchange_weak(peak, now))
  {
  }
}
const bool gMappedCounted = (sipmss::storage::DMLTestAccess::SetMappedHook(&Mapped), true);
} // namespace
#else
namespace
{
std::atomic<std::int64_t> gLive{ 0 };
std::atomic<std::int64_t> gPeak{ 0 };
} // namespace
#endif

#if SIPMSS_HEAP_HOOK

extern "C"
{
  void* malloc(std::size_t n)
  {
    void* p = __libc_malloc(n);
    Added(p);
    return p;
  }
  void free(void* p)
  {
    Removed(p);
    __libc_free(p);
  }
  void* calloc(std::size_t n, std::size_t s)
  {
    void* p = __libc_calloc(n, s);
    Added(p);
    return p;
  }
  void* realloc(void* p, std::size_t n)
  {
    const std::int64_t old = p ? static_cast<std::int64_t>(malloc_usable_size(p)) : 0;
    void* q = __libc_realloc(p, n);
    if (q || n == 0)
    {
      gLive.fetch_sub(old);
      Added(q);
    }
    return q;
  }
  void* memalign(std::size_t a, std::size_t n)
  {
    void* p = __libc_memalign(a, n);
    Added(p);
    return p;
  }
  void* aligned_alloc(std::size_t a, std::size_t n)
  {
    return memalign(a, n);
  }
  int posix_memalign(void** out, std::size_t a, std::size_t n)
  {
    void* p = memalign(a, n);
    if (!p)
    {
      return ENOMEM;
    }
    *out = p;
    return 0;
  }
}
#endif

namespace
{
using namespace sipmss::storage;
using sipmss::storage::testing::TempDir;

#define SKIP_WITHOUT_HEAP_HOOK()                                                                  \
  if (!SIPMSS_HEAP_HOOK)                                                                           \
  {                                                                                                \
    GTEST_SKIP() << "the heap hook is off under a sanitizer";                                      \
  }

// Live heap growth since the baseline, with its peak.
struct HeapMeter
{
  std::int64_t base = 0;
  void Start()
  {
    this->base = gLive.load();
    gPeak.store(this->base);
  }
  std::int64_t Now() const { return gLive.load() - this->base; }
  std::int64_t Peak() const { return gPeak.load() - this->base; }
};

TEST(StorageBudget, HookWorks)
{
  SKIP_WITHOUT_HEAP_HOOK();
  HeapMeter m;
  m.Start();
  void* p = std::malloc(100000);
  EXPECT_GE(m.Now(), 100000);
  std::free(p);
  EXPECT_GE(m.Peak(), 100000);
  EXPECT_LT(m.Now(), 1000);
  // A returnable block is mapped (not from malloc) and counted by the mapped hook.
  m.Start();
  void* q = AllocateReturnable(200000);
  EXPECT_GE(m.Now(), 200000);
  FreeReturnable(q, 200000);
  EXPECT_GE(m.Peak(), 200000);
  EXPECT_LT(m.Now(), 1000);
}

// 8 blocks of 4 MiB with B = 256 KiB: the real heap of the DML never exceeds B.
TEST(StorageBudget, ManyLargeBlocksStayWithinBudget)
{
  SKIP_WITHOUT_HEAP_HOOK();
  TempDir tmp;
  const std::uint64_t B = 256 * 1024;
  Profile profile;
  profile.directories = { tmp.Path() };
  profile.memoryBudget = B;
  profile.structures = { { "blocks", 8, 8 * 512 * 1024, 0.0 } };
  std::vector<std::uint64_t> buf(20000);   // made before the baseline
  std::int64_t worstOverAccounted = 0; // real - accounted after each call
  HeapMeter m;
  m.Start();
  {
    DML dml;
    ASSERT_EQ(dml.Config(profile), Mode::OutOfCore);
    auto check = [&] {
      worstOverAccounted = std::max<std::int64_t>(
        worstOverAccounted, m.Now() - static_cast<std::int64_t>(dml.GetStats().bytesHeld));
    };
    BlockId ids[8];
    for (int b = 0; b < 8; ++b)
    {
      ids[b] = dml.OpenBlock(8, 512 * 1024, b == 0 ? 4.0 : 0.0); // 4 MiB each
      check();
    }
    std::mt19937_64 rng(3);
    for (int round = 0; round < 3; ++round)
    {
      for (int b = 0; b < 8; ++b)
      {
        for (std::uint64_t i = 0; i < 512 * 1024; i += 97)
        {
          const std::uint64_t v = i * 8 + b + round;
          dml.Write(ids[b], 8, i, &v);
        }
        check();
      }
      for (int k = 0; k < 20000; ++k)
      {
        const int b = static_cast<int>(rng() % 8);
        const std::uint64_t i = (rng() % (512 * 1024 / 97)) * 97;
        std::uint64_t v = 0;
        dml.Read(ids[b], 8, i, &v);
        ASSERT_EQ(v, i * 8 + b + round);
      }
      check();
      dml.ReadRange(ids[round], 1000, buf.size(), buf.data());
      dml.WriteRange(ids[round + 1], 5000, buf.size(), buf.data());
      Span s = dml.Pin(ids[7], 12345, Access::Write);
      static_cast<std::uint64_t*>(s.data)[0] = 1;
      dml.Unpin(ids[7], s);
      check();
    }
    dml.Resize(ids[0], 4 * 1024 * 1024); // grow to 32 MiB (sparse)
    dml.Resize(ids[1], 10);
    check();
    for (int b = 2; b < 8; ++b)
    {
      dml.CloseBlock(ids[b]);
    }
    dml.Reconfigure();
    check();
    const Stats st = dml.GetStats();
    EXPECT_LE(st.peakBytes, B);
    EXPECT_LE(st.bytesHeld, B);
    EXPECT_GT(st.misses, 1000u);
    EXPECT_EQ(st.mode, Mode::OutOfCore);
  }
  EXPECT_LE(m.Peak(), static_cast<std::int64_t>(B)) << "real DML heap exceeded the budget";
  EXPECT_LE(worstOverAccounted, 0) << "real heap above the accounted bytes";
  EXPECT_LE(m.Now(), 0) << "leak";
}

// An external sort's runs, merge windows and run table are charged: the real heap of a 4 MB sort
// at B = 128 KiB stays within B.
TEST(StorageBudget, ExternalSortStaysWithinBudget)
{
  SKIP_WITHOUT_HEAP_HOOK();
  TempDir tmp;
  const std::uint64_t B = 128 * 1024;
  const std::uint64_t n = 500000;
  Profile profile;
  profile.directories = { tmp.Path() };
  profile.memoryBudget = B;
  profile.structures = { { "keys", 8, n, 0.0 } };
  std::vector<std::uint64_t> data(n); // made before the baseline
  std::mt19937_64 rng(5);
  for (auto& v : data)
  {
    v = rng();
  }
  std::vector<std::uint64_t> expect = data;
  std::sort(expect.begin(), expect.end());
  HeapMeter m;
  m.Start();
  {
    DML dml;
    ASSERT_EQ(dml.Config(profile), Mode::OutOfCore);
    Array<std::uint64_t> a(dml, n);
    a.Write(0, n, data.data());
    Sort(dml, a, [](std::uint64_t x, std::uint64_t y) { return x < y; });
    a.Read(0, n, data.data());
    EXPECT_LE(dml.GetStats().peakBytes, B);
  }
  EXPECT_LE(m.Peak(), static_cast<std::int64_t>(B)) << "real heap of the sort exceeded the budget";
  EXPECT_LE(m.Now(), 0) << "leak";
  EXPECT_TRUE(data == expect);
}

// In core the budget is hard too: an OpenBlock that would exceed it moves everything out.
TEST(StorageBudget, InCoreGrowthSwitchesInsteadOfExceeding)
{
  SKIP_WITHOUT_HEAP_HOOK();
  TempDir tmp;
  const std::uint64_t B = 1 << 20;
  Profile profile;
  profile.directories = { tmp.Path() };
  profile.memoryBudget = B;
  HeapMeter m;
  m.Start();
  {
    DML dml;
    ASSERT_EQ(dml.Config(profile), Mode::InCore);
    const BlockId a = dml.OpenBlock(4, 100000);
    const BlockId g = dml.OpenBlock(4, 0);
    for (std::uint32_t k = 0; k < 200000; k += 1000) // both grow until they must spill
    {
      dml.Resize(g, k + 1000);
      for (std::uint32_t i = k; i < k + 1000; ++i)
      {
        dml.Write(g, 4, i, &i);
      }
      dml.Resize(a, dml.Count(a) + 1000);
    }
    EXPECT_EQ(dml.GetMode(), Mode::OutOfCore);
    EXPECT_GE(dml.GetStats().reconfigurations, 1u);
    EXPECT_LE(dml.GetStats().peakBytes, B);
    std::uint32_t v = 0;
    dml.Read(g, 4, 123457, &v);
    EXPECT_EQ(v, 123457u);
  }
  EXPECT_LE(m.Peak(), static_cast<std::int64_t>(B));
}

// Metadata that grows with the number of blocks is inside the budget as well.
TEST(StorageBudget, BlockMetadataIsCounted)
{
  SKIP_WITHOUT_HEAP_HOOK();
  TempDir tmp;
  const std::uint64_t B = 128 * 1024;
  Profile profile;
  profile.directories = { tmp.Path() };
  profile.memoryBudget = B;
  profile.policy = ModePolicy::OutOfCore;
  std::vector<BlockId> ids;
  ids.reserve(5000);
  HeapMeter m;
  m.Start();
  bool refused = false;
  {
    DML dml;
    dml.Config(profile);
    try
    {
      for (int i = 0; i < 5000; ++i)
      {
        ids.push_back(dml.OpenBlock(8, 1000));
        const std::uint64_t v = static_cast<std::uint64_t>(i);
        dml.Write(ids.back(), 8, 999, &v);
      }
    }
    catch (const BudgetError&)
    {
      refused = true; // the descriptors alone would exceed B
    }
    EXPECT_GT(ids.size(), 100u);
    for (std::size_t i = 0; i < ids.size(); i += 13)
    {
      std::uint64_t v = 0;
      dml.Read(ids[i], 8, 999, &v);
      ASSERT_EQ(v, i);
    }
    EXPECT_LE(dml.GetStats().peakBytes, B);
  }
  EXPECT_TRUE(refused);
  EXPECT_LE(m.Peak(), static_cast<std::int64_t>(B));
}

} // namespace
