#include "sipmss/storage/Prefault.h"

#include <algorithm>
#include <cstdint>
#include <system_error>

#include <sys/mman.h>
#include <unistd.h>

#ifndef MADV_POPULATE_WRITE
#define MADV_POPULATE_WRITE 23 // (Linux 5.14; older headers lack the name)
#endif

namespace sipmss::storage
{
namespace
{
constexpr std::size_t kStep = std::size_t(2) << 20;

// The whole pages inside [data, data + bytes): madvise takes page-aligned starts, and a partial
// page at either end may share its page with memory the range does not own (it is left alone).
bool PageSpan(void* data, std::size_t bytes, std::uintptr_t& first, std::uintptr_t& last)
{
  const long ps = ::sysconf(_SC_PAGESIZE);
  const std::uintptr_t page = ps > 0 ? std::uintptr_t(ps) : 4096;
  const std::uintptr_t a = reinterpret_cast<std::uintptr_t>(data);
  first = (a + page - 1) & ~(page - 1);
  last = (a + bytes) & ~(page - 1);
  return data && last > first;
}
} // namespace

bool Prefaulter::Populate(void* data, std::size_t bytes)
{
  std::uintptr_t first = 0, last = 0;
  if (!PageSpan(data, bytes, first, last))
  {
    return true;
  }
  return ::madvise(reinterpret_cast<void*>(first), last - first, MADV_POPULATE_WRITE) == 0;
}

bool Prefaulter::Start(std::vector<Range> ranges)
{
  this->Stop();
  ranges.erase(std::remove_if(ranges.begin(), ranges.end(),
                 [](const Range& r) { return !r.data || r.bytes == 0; }),
    ranges.end());
  if (ranges.empty())
  {
    return false;
  }
  this->stop_ = false;
  this->refused_ = false;
  this->populated_ = 0;
  try
  {
    this->thread_ = std::thread([this, ranges = std::move(ranges)] {
      for (const Range& r : ranges)
      {
        std::uintptr_t first = 0, last = 0;
        if (!PageSpan(r.data, r.bytes, first, last))
        {
          continue;
        }
        for (std::uintptr_t a = first; a < last; a += kStep)
        {
          if (this->stop_.load(std::memory_order_relaxed))
          {
            return;
          }
          const std::size_t n = std::size_t(std::min<std::uintptr_t>(kStep, last - a));
          if (!Populate(reinterpret_cast<void*>(a), n))
          {
            // EINVAL: a kernel without it; anything else (no memory: ENOMEM): the caller's
            // own first touches will meet the same, with the error handling they have.
            this->refused_ = true;
            return;
          }
          this->populated_.fetch_add(n, std::memory_order_relaxed);
        }
      }
    });
  }
  catch (const std::system_error&)
  {
    return false; // (no thread: the caller's first touches do the work, as without)
  }
  return true;
}

void Prefaulter::Stop() noexcept
{
  if (this->thread_.joinable())
  {
    this->stop_ = true;
    this->thread_.join();
  }
}
} // namespace sipmss::storage
