// What the automatic memory budget starts from: the limits on this process's memory.
#include "sipmss/storage/Memory.h"

#include <gtest/gtest.h>

#include <sys/resource.h>
#include <sys/wait.h>
#include <unistd.h>

#include <fstream>
#include <limits>
#include <string>

namespace
{
using namespace sipmss::storage;
constexpr std::uint64_t kNone = std::numeric_limits<std::uint64_t>::max();

TEST(StorageMemory, ParsesMeminfo)
{
  const std::string text = "MemTotal:       24558984 kB\nMemFree:        1000 kB\n"
                           "MemAvailable:   24258392 kB\nBuffers:  12 kB\n";
  EXPECT_EQ(detail::ParseMeminfoKB(text, "MemAvailable"), 24258392ull * 1024);
  EXPECT_EQ(detail::ParseMeminfoKB(text, "MemFree"), 1000ull * 1024);
  EXPECT_EQ(detail::ParseMeminfoKB(text, "Mem"), kNone); // a prefix is not a key
  EXPECT_EQ(detail::ParseMeminfoKB(text, "SwapTotal"), kNone);
  EXPECT_EQ(detail::ParseMeminfoKB("VmSize:\t    3896 kB\n", "VmSize"), 3896ull * 1024);
  EXPECT_EQ(detail::ParseMeminfoKB("VmSize: x kB\n", "VmSize"), kNone);
}

TEST(StorageMemory, ParsesCgroupFiles)
{
  EXPECT_EQ(detail::ParseCgroupNumber("max\n"), kNone);
  EXPECT_EQ(detail::ParseCgroupNumber(""), kNone);
  EXPECT_EQ(detail::ParseCgroupNumber("1073741824\n"), 1073741824ull);
  std::string v2, v1;
  detail::ParseProcCgroup("0::/user.slice/session-1.scope\n", v2, v1);
  EXPECT_EQ(v2, "/user.slice/session-1.scope");
  EXPECT_EQ(v1, "");
  v2.clear();
  detail::ParseProcCgroup("9:name=systemd:/\n4:memory:/process_api/3f1f\n2:cpuacct,cpu:/\n0::/\n",
    v2, v1);
  EXPECT_EQ(v1, "/process_api/3f1f");
  EXPECT_EQ(v2, "/");
  v1.clear();
  detail::ParseProcCgroup("5:cpu,memory:/job/7\n", v2, v1);
  EXPECT_EQ(v1, "/job/7");
}

TEST(StorageMemory, AutomaticBudgetIsHalfOfWhatIsLeft)
{
  EXPECT_EQ(AutomaticBudget({ "MemAvailable", 8ull << 30 }), 4ull << 30);
  EXPECT_EQ(AutomaticBudget({ "RLIMIT_AS", 1ull << 20 }), kMinimumAutomaticBudget);
  EXPECT_EQ(AutomaticBudget({ "", kNone }), 0u); // nothing known: unbounded
}

TEST(StorageMemory, ThisMachineHasAnAnswer)
{
  const MemoryLimit m = AvailableMemory();
  ASSERT_NE(m.bytes, kNone) << "no MemAvailable in /proc/meminfo?";
  EXPECT_FALSE(m.source.empty());
  EXPECT_GT(m.bytes, 0u);
  for (const MemoryLimit& l : MemoryLimits())
  {
    // (MemAvailable is read again here: other processes, e.g. tests running beside this one,
    // may have taken some since)
    const std::uint64_t moved = l.source.find("MemAvailable") != std::string::npos ? (1ull << 30) : 0;
    EXPECT_GE(l.bytes + moved, m.bytes) << l.source;
  }
}

// Under ulimit -v the address space left is the limit: a child process sets RLIMIT_AS to its
// address space in use plus 300 MiB and must see RLIMIT_AS as the lowest limit, about 300 MiB.
TEST(StorageMemory, AddressSpaceLimitIsTheLowestWhenSet)
{
  const pid_t pid = ::fork();
  ASSERT_GE(pid, 0);
  if (pid == 0)
  {
    std::ifstream st("/proc/self/status");
    std::string text((std::istreambuf_iterator<char>(st)), std::istreambuf_iterator<char>());
    const std::uint64_t used = detail::ParseMeminfoKB(text, "VmSize");
    struct rlimit rl{};
    rl.rlim_cur = used + (300ull << 20);
    rl.rlim_max = RLIM_INFINITY;
    if (used == kNone || ::setrlimit(RLIMIT_AS, &rl) != 0)
    {
      ::_exit(3);
    }
    const MemoryLimit m = AvailableMemory();
    const bool named = m.source.find("RLIMIT_AS") != std::string::npos;
    const bool near = m.bytes > (290ull << 20) && m.bytes <= (300ull << 20);
    ::_exit(named && near ? 0 : (named ? 4 : 5));
  }
  int status = 0;
  ASSERT_EQ(::waitpid(pid, &status, 0), pid);
  ASSERT_TRUE(WIFEXITED(status));
  EXPECT_EQ(WEXITSTATUS(status), 0) << "3: cannot set the limit, 4: wrong amount, 5: not lowest";
}

} // namespace
