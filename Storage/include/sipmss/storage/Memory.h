// How much memory this process may use: the basis of the automatic memory budget.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

namespace sipmss::storage
{

// One limit on this process's memory and what is left of it now.
struct MemoryLimit
{
  std::string source;   // "cgroup memory.max", "RLIMIT_AS", "RLIMIT_DATA", "MemAvailable"
  std::uint64_t bytes = 0; // what is left under it now
};

// Every limit found: the cgroup's memory limit (v2 memory.max less memory.current, or v1
// memory.limit_in_bytes less memory.usage_in_bytes, at the process's cgroup and each parent),
// RLIMIT_AS less the address space in use (VmSize), RLIMIT_DATA less the data in use (VmData),
// and /proc/meminfo's MemAvailable. Limits that are not set are not listed.
std::vector<MemoryLimit> MemoryLimits();

// The lowest of them (bytes = UINT64_MAX and source "" when none is known).
MemoryLimit AvailableMemory();

// The automatic budget: kAutomaticBudgetShare of the available memory (the rest is left to the
// work outside the DML: threads' stacks and scratch, the readers' buffers, a caller's own data),
// at least kMinimumAutomaticBudget.
constexpr double kAutomaticBudgetShare = 0.5;
constexpr std::uint64_t kMinimumAutomaticBudget = std::uint64_t(4) << 20;
std::uint64_t AutomaticBudget(const MemoryLimit& available);

namespace detail
{
// Parsers, exposed for the tests. Each returns UINT64_MAX when the value is absent or "max".
std::uint64_t ParseMeminfoKB(const std::string& text, const std::string& key); // bytes
std::uint64_t ParseCgroupNumber(const std::string& text);
// The cgroup paths in /proc/self/cgroup: v2's ("0::/path") and v1's memory controller's.
void ParseProcCgroup(const std::string& text, std::string& v2, std::string& v1memory);
} // namespace detail

} // namespace sipmss::storage
