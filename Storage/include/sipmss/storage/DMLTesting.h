// Test and benchmark hooks of the DML. Not for algorithm code.
#pragma once

#include "sipmss/storage/DML.h"

#include <cstddef>
#include <cstdint>
#include <sys/types.h>

namespace sipmss::storage
{

// Page replacement inside a block's share of frames (PagePolicy::StaticWeight and Adaptive; with
// LRU, also under PagePolicy::Clock). WSClock is the DML's policy there; LRU exists only so the
// benchmark can compare against it.
enum class Replacement : std::uint8_t
{
  WSClock,
  Lru
};

struct DMLTestAccess
{
  static void SetReplacement(DML& dml, Replacement r);
  static std::size_t PageSize(const DML& dml);      // 0 until the page cache exists
  static std::uint32_t FrameSlots(const DML& dml);  // frame slots of the page cache
  static std::uint64_t FileBytes(const DML& dml, BlockId id); // st_size of the block's file
  static std::uint64_t InlineHits(const DML& dml); // element accesses served inline (Read/Write)
  // Called with +bytes after AllocateReturnable maps a block and -bytes after FreeReturnable
  // unmaps one (nullptr: none), so that a test counting the heap sees those blocks too.
  static void SetMappedHook(void (*hook)(std::int64_t bytes));
};

namespace detail
{
// Transfers exactly `bytes` with `op` (pread- or pwrite-like), retrying EINTR and partial
// transfers; a zero-length transfer or an error throws StorageError (path left empty, filled in
// by the DML). Exposed so tests can feed it short transfers.
using IoOp = ssize_t (*)(int fd, void* buf, std::size_t n, off_t offset);
void TransferAll(int fd, void* buf, std::size_t bytes, std::uint64_t offset, IoOp op,
  const char* what);
} // namespace detail

} // namespace sipmss::storage
