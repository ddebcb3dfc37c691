// How much memory this process may use (see Memory.h).
#include "sipmss/storage/Memory.h"

#include <sys/resource.h>

#include <algorithm>
#include <cstdlib>
#include <fstream>
#include <limits>
#include <sstream>

namespace sipmss::storage
{
namespace
{
constexpr std::uint64_t kNone = std::numeric_limits<std::uint64_t>::max();

std::string ReadText(const std::string& path)
{
  std::ifstream in(path);
  if (!in)
  {
    return {};
  }
  std::ostringstream s;
  s << in.rdbuf();
  return s.str();
}

// The limit less the usage at `dir` and each parent up to `root` (the lowest of them).
void CgroupLevels(const std::string& root, std::string path, const char* limitFile,
  const char* usageFile, const char* source, std::vector<MemoryLimit>& out)
{
  std::uint64_t best = kNone;
  for (;;)
  {
    const std::string dir = root + path;
    const std::uint64_t limit = detail::ParseCgroupNumber(ReadText(dir + "/" + limitFile));
    // cgroup v1 writes "no limit" as a huge page-aligned number.
    if (limit != kNone && limit < (std::uint64_t(1) << 60))
    {
      const std::uint64_t usage = detail::ParseCgroupNumber(ReadText(dir + "/" + usageFile));
      const std::uint64_t left = usage == kNone ? limit : (usage >= limit ? 0 : limit - usage);
      best = std::min(best, left);
    }
    if (path.empty() || path == "/")
    {
      break;
    }
    const std::size_t slash = path.find_last_of('/');
    path = slash == std::string::npos ? std::string() : path.substr(0, slash);
  }
  if (best != kNone)
  {
    out.push_back({ source, best });
  }
}
} // namespace

std::uint64_t detail::ParseMeminfoKB(const std::string& text, const std::string& key)
{
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line))
  {
    if (line.compare(0, key.size(), key) == 0 && line.size() > key.size() &&
      line[key.size()] == ':')
    {
      const char* p = line.c_str() + key.size() + 1;
      char* end = nullptr;
      const unsigned long long kb = std::strtoull(p, &end, 10);
      if (end == p)
      {
        return kNone;
      }
      return kb > kNone / 1024 ? kNone : static_cast<std::uint64_t>(kb) * 1024;
    }
  }
  return kNone;
}

std::uint64_t detail::ParseCgroupNumber(const std::string& text)
{
  const std::size_t b = text.find_first_not_of(" \t\n");
  if (b == std::string::npos || text.compare(b, 3, "max") == 0)
  {
    return kNone;
  }
  const char* p = text.c_str() + b;
  char* end = nullptr;
  const unsigned long long v = std::strtoull(p, &end, 10);
  return end == p ? kNone : static_cast<std::uint64_t>(v);
}

void detail::ParseProcCgroup(const std::string& text, std::string& v2, std::string& v1memory)
{
  std::istringstream in(text);
  std::string line;
  while (std::getline(in, line))
  {
    const std::size_t a = line.find(':');
    const std::size_t b = a == std::string::npos ? a : line.find(':', a + 1);
    if (b == std::string::npos)
    {
      continue;
    }
    const std::string controllers = line.substr(a + 1, b - a - 1);
    const std::string path = line.substr(b + 1);
    if (line.compare(0, a, "0") == 0 && controllers.empty())
    {
      v2 = path;
    }
    std::istringstream names(controllers);
    std::string name;
    while (std::getline(names, name, ','))
    {
      if (name == "memory")
      {
        v1memory = path;
      }
    }
  }
}

std::vector<MemoryLimit> MemoryLimits()
{
  std::vector<MemoryLimit> out;
  std::string v2, v1;
  detail::ParseProcCgroup(ReadText("/proc/self/cgroup"), v2, v1);
  if (!v1.empty())
  {
    CgroupLevels("/sys/fs/cgroup/memory", v1 == "/" ? std::string() : v1,
      "memory.limit_in_bytes", "memory.usage_in_bytes", "cgroup memory.limit_in_bytes", out);
  }
  else if (!v2.empty())
  {
    CgroupLevels("/sys/fs/cgroup", v2 == "/" ? std::string() : v2, "memory.max",
      "memory.current", "cgroup memory.max", out);
  }
  const std::string status = ReadText("/proc/self/status");
  struct rlimit rl{};
  if (::getrlimit(RLIMIT_AS, &rl) == 0 && rl.rlim_cur != RLIM_INFINITY)
  {
    const std::uint64_t used = detail::ParseMeminfoKB(status, "VmSize");
    const std::uint64_t lim = rl.rlim_cur;
    out.push_back({ "RLIMIT_AS (ulimit -v)", used == kNone ? lim : (used >= lim ? 0 : lim - used) });
  }
  if (::getrlimit(RLIMIT_DATA, &rl) == 0 && rl.rlim_cur != RLIM_INFINITY)
  {
    const std::uint64_t used = detail::ParseMeminfoKB(status, "VmData");
    const std::uint64_t lim = rl.rlim_cur;
    out.push_back({ "RLIMIT_DATA (ulimit -d)", used == kNone ? lim : (used >= lim ? 0 : lim - used) });
  }
  const std::uint64_t avail = detail::ParseMeminfoKB(ReadText("/proc/meminfo"), "MemAvailable");
  if (avail != kNone)
  {
    out.push_back({ "MemAvailable", avail });
  }
  return out;
}

MemoryLimit AvailableMemory()
{
  MemoryLimit best{ "", kNone };
  for (const MemoryLimit& m : MemoryLimits())
  {
    if (m.bytes < best.bytes)
    {
      best = m;
    }
  }
  return best;
}

std::uint64_t AutomaticBudget(const MemoryLimit& available)
{
  if (available.bytes == kNone)
  {
    return 0; // nothing known: unbounded
  }
  const double share = static_cast<double>(available.bytes) * kAutomaticBudgetShare;
  return std::max<std::uint64_t>(kMinimumAutomaticBudget, static_cast<std::uint64_t>(share));
}

} // namespace sipmss::storage
