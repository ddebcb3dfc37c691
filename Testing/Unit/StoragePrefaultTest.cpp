// Fresh memory made present on another thread while its owner writes it (Prefault.h).
#include "sipmss/storage/Prefault.h"

#include <gtest/gtest.h>

#include <sys/mman.h>
#include <unistd.h>

#include <cstdint>
#include <cstring>
#include <vector>

namespace
{
using sipmss::storage::Prefaulter;

// An anonymous mapping of its own (fresh pages, none present yet).
struct Mapping
{
  explicit Mapping(std::size_t n)
    : bytes(n)
    , data(::mmap(nullptr, n, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0))
  {
  }
  ~Mapping()
  {
    if (this->data != MAP_FAILED)
    {
      ::munmap(this->data, this->bytes);
    }
  }
  // Pages of the mapping present now (mincore).
  std::size_t Resident() const
  {
    const std::size_t page = std::size_t(::sysconf(_SC_PAGESIZE));
    std::vector<unsigned char> v((this->bytes + page - 1) / page);
    if (::mincore(this->data, this->bytes, v.data()) != 0)
    {
      return 0;
    }
    std::size_t n = 0;
    for (unsigned char c : v)
    {
      n += c & 1;
    }
    return n * page;
  }
  std::size_t bytes;
  void* data;
};

TEST(StoragePrefault, MakesPagesPresent)
{
  Mapping m(std::size_t(24) << 20);
  ASSERT_NE(m.data, MAP_FAILED);
  ASSERT_EQ(m.Resident(), 0u);
  Prefaulter p;
  ASSERT_TRUE(p.Start({ { m.data, m.bytes } }));
  p.Stop(); // (may stop it early: start again and let it finish below)
  Prefaulter q;
  ASSERT_TRUE(q.Start({ { m.data, m.bytes } }));
  while (q.Populated() < m.bytes && !q.Refused())
  {
    ::usleep(1000);
  }
  q.Stop();
  if (q.Refused())
  {
    GTEST_SKIP() << "this kernel has no MADV_POPULATE_WRITE (Linux 5.14)";
  }
  EXPECT_EQ(q.Populated(), m.bytes);
  EXPECT_EQ(m.Resident(), m.bytes);
  // Present and zero, as fresh memory reads.
  const unsigned char* c = static_cast<const unsigned char*>(m.data);
  EXPECT_TRUE(c[0] == 0 && c[m.bytes / 2] == 0 && c[m.bytes - 1] == 0);
}

// The owner writes while the other thread makes the pages present: every value written stays.
TEST(StoragePrefault, KeepsWhatTheOwnerWrites)
{
  const std::size_t n = std::size_t(64) << 20;
  Mapping m(n);
  ASSERT_NE(m.data, MAP_FAILED);
  auto* w = static_cast<std::uint64_t*>(m.data);
  Prefaulter p;
  ASSERT_TRUE(p.Start({ { m.data, n } }));
  for (std::size_t i = 0; i < n / 8; ++i)
  {
    w[i] = i * 0x9E3779B97F4A7C15ull + 1;
  }
  p.Stop();
  std::size_t wrong = 0;
  for (std::size_t i = 0; i < n / 8; ++i)
  {
    wrong += w[i] != i * 0x9E3779B97F4A7C15ull + 1;
  }
  EXPECT_EQ(wrong, 0u);
}

TEST(StoragePrefault, NothingToDo)
{
  Prefaulter p;
  p.Stop(); // (nothing started)
  EXPECT_FALSE(p.Start({}));
  EXPECT_FALSE(p.Start({ { nullptr, 4096 } }));
  // Partial pages at a range's ends are left alone: one byte is no whole page.
  std::vector<unsigned char> small(16, 7);
  EXPECT_TRUE(Prefaulter::Populate(small.data() + 1, 1));
  EXPECT_EQ(small[1], 7);
  EXPECT_EQ(p.Populated(), 0u);
}
} // namespace
