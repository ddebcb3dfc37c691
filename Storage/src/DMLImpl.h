// Internal state of the DML (not installed). See DML.h for the public contract.
//
// Layout of the implementation:
//   FileBackend.cpp  StorageError, the POSIX backend, private/stale directory handling
//   DML.cpp          public primitives, block descriptors, in-core storage, mode switches
//   PageCache.cpp    out-of-core page cache: frames, WSClock/LRU, quotas, write-back
#pragma once

#include "sipmss/storage/DML.h"
#include "sipmss/storage/DMLTesting.h"

#include <cstddef>
#include <cstdint>
#include <limits>
#include <new>
#include <string>
#include <vector>

namespace sipmss::storage
{
namespace detail
{

// ---------------------------------------------------------------------------------------------
// Memory accounting. Every byte the DML holds is charged here, through HeapCost() so that the
// malloc chunk overhead is included: a small chunk costs its size + 16 bytes; a large one may be
// served by mmap and rounded to whole pages.
constexpr std::uint64_t HeapCost(std::uint64_t n)
{
  return n + 32 <= 120 * 1024 ? n + 16 : ((n + 32 + 4095) & ~std::uint64_t(4095));
}

// Transient allocations that are not worth tracking one by one (a file path string while a
// file is created or removed) are covered by this fixed reserve, charged once per instance.
constexpr std::uint64_t kScratchReserve = 2048;

// Page pool used out of core when the budget is 0 (unbounded) but the mode is forced out of core.
constexpr std::uint64_t kUnboundedPool = 64ull << 20;

struct Accountant
{
  DML::Impl* owner = nullptr; // asked to release cache pages when a charge does not fit
  std::uint64_t budget = 0;   // 0: unbounded
  std::uint64_t held = 0;
  std::uint64_t peak = 0;

  std::uint64_t Room() const
  {
    if (this->budget == 0)
    {
      return std::numeric_limits<std::uint64_t>::max() / 4;
    }
    return this->held >= this->budget ? 0 : this->budget - this->held;
  }
  bool Fits(std::uint64_t n) const { return n <= this->Room(); }
  // Charges n bytes; evicts cache pages if needed; throws BudgetError if it cannot fit.
  void Charge(std::uint64_t n);
  // Charges n bytes only if they fit without evicting anything.
  bool TryCharge(std::uint64_t n) noexcept
  {
    if (!this->Fits(n))
    {
      return false;
    }
    this->Add(n);
    return true;
  }
  void Release(std::uint64_t n) noexcept { this->held -= n < this->held ? n : this->held; }
  void Add(std::uint64_t n) noexcept
  {
    this->held += n;
    if (this->held > this->peak)
    {
      this->peak = this->held;
    }
  }
};

// std allocator that charges the accountant: metadata vectors use it, so metadata that grows
// with the number of blocks or frames is inside the budget (including the transient old+new
// buffers of a vector reallocation).
template <class T>
struct Counted
{
  using value_type = T;
  Accountant* acc = nullptr;

  explicit Counted(Accountant* a) noexcept : acc(a) {}
  template <class U>
  Counted(const Counted<U>& o) noexcept : acc(o.acc) // NOLINT: implicit by the allocator rules
  {
  }
  T* allocate(std::size_t n)
  {
    const std::uint64_t cost = HeapCost(n * sizeof(T));
    this->acc->Charge(cost);
    try
    {
      return static_cast<T*>(::operator new(n * sizeof(T)));
    }
    catch (...)
    {
      this->acc->Release(cost);
      throw;
    }
  }
  void deallocate(T* p, std::size_t n) noexcept
  {
    this->acc->Release(HeapCost(n * sizeof(T)));
    ::operator delete(p);
  }
  template <class U>
  bool operator==(const Counted<U>& o) const noexcept
  {
    return this->acc == o.acc;
  }
  template <class U>
  bool operator!=(const Counted<U>& o) const noexcept
  {
    return this->acc != o.acc;
  }
};

template <class T>
using CVector = std::vector<T, Counted<T>>;
using CString = std::basic_string<char, std::char_traits<char>, Counted<char>>;

// Heap bytes of a copied Profile (strings and vectors), charged as metadata.
std::uint64_t ProfileHeapCost(const Profile& p);

// Directory helpers (FileBackend.cpp).
std::string MakePrivateDirectory(const std::string& parent); // mkdir sipmss-<pid>-<random>
void RemoveTree(const std::string& path) noexcept;            // best effort, no symlink following
std::string ErrnoText(int error);
std::string DefaultDirectory();

// ---------------------------------------------------------------------------------------------
enum class Kind : std::uint8_t
{
  Closed,
  Plain // an element block opened by the user
};

constexpr std::size_t kRecentPages = 4;

struct Block
{
  Kind kind = Kind::Closed;
  std::size_t elementSize = 0;
  std::uint64_t count = 0;
  double weight = 0.0; // 0: derived from the size

  // In core: one contiguous allocation of capacityBytes (>= count * elementSize, >= 1).
  unsigned char* mem = nullptr;
  std::uint64_t capacityBytes = 0;

  // Out of core: a file <private dir>/<fileSeq>.blk holding count * elementSize bytes densely.
  int fd = -1;
  std::int32_t dir = -1; // index into Impl::dirs
  std::uint64_t fileSeq = 0;
  std::uint64_t perPage = 1; // elements per page: floor(pageSize / elementSize)

  // Page-cache state of this block.
  // The last kRecentPages pages the slow path used, most recent first (loops over neighbouring
  // elements move between a few pages): looked up before the hash table.
  std::int32_t recentFrame[kRecentPages] = {}; // -1: none (ClearRecent)
  std::uint64_t recentPage[kRecentPages] = {};
  Block() { this->ClearRecent(); }
  void ClearRecent()
  {
    for (std::int32_t& f : this->recentFrame)
    {
      f = -1;
    }
  }
  std::int32_t hand = -1;      // clock hand / LRU end of this block's frame ring; -1: no frames
  std::uint32_t resident = 0;  // frames held
  std::uint32_t quota = 1;     // target share of frames (StaticWeight or Adaptive)
  std::uint64_t vtime = 0;     // per-block virtual time (its misses), for the WSClock window
  std::uint64_t ghostHits = 0; // misses on recently evicted pages in this epoch (Adaptive)
  double score = 0.0;          // smoothed ghost hits (Adaptive)

  // While forked (DML::Fork): the elements [forkFirst, forkEnd) the child writes. The child
  // writes back only those, the parent only the others.
  std::uint64_t forkFirst = 0, forkEnd = 0;

  // This block's I/O since it was opened (DML::GetBlockStats): its page misses and the bytes
  // read from and written to its file (mutable: counted where a transfer sees a const Block).
  mutable BlockStats io;

  bool InCore() const { return this->mem != nullptr; }
  bool OnFile() const { return this->fd >= 0; }
  std::uint64_t Bytes() const { return this->count * this->elementSize; }
};

// One page frame of the out-of-core cache.
struct Frame
{
  unsigned char* data = nullptr; // HeapCost(pageSize) charged while non-null
  std::uint64_t page = 0;
  std::uint64_t lastUse = 0;  // block virtual time of the last observed reference
  std::int32_t block = -1;    // -1: not holding a page
  std::int32_t next = -1;     // ring of the block, or free list
  std::int32_t prev = -1;
  std::int32_t hashNext = -1; // bucket chain
  std::uint32_t pins = 0;
  bool ref = false;
  bool dirty = false;
};

struct Cache
{
  bool built = false;
  std::size_t pageSize = 0;
  CVector<Frame> frames;          // fixed number of slots, sized from the budget
  CVector<std::int32_t> buckets;  // hash (block, page) -> first frame of the chain
  CVector<std::uint64_t> ghosts;  // Adaptive: direct-mapped tags of recently evicted pages
  CVector<FastEntry> table;       // the inline access's pages (DML.h), 2 to 4 entries a slot
  std::int32_t freeData = -1;     // slots with data but no page
  std::int32_t freeEmpty = -1;    // slots without data
  std::uint32_t withData = 0;
  std::uint32_t pinnedFrames = 0;
  std::uint64_t epochMisses = 0;
  std::uint8_t generation = 0; // builds of the cache (FastTagBase)
  bool quotasDirty = true;
  std::size_t clockHand = 0; // PagePolicy::Clock: the next frame slot the hand looks at

  explicit Cache(Accountant* a) : frames(Counted<Frame>(a)), buckets(Counted<std::int32_t>(a)),
    ghosts(Counted<std::uint64_t>(a)), table(Counted<FastEntry>(a))
  {
  }
};

struct PrivateDir
{
  CString parent;
  CString path;   // empty until created
  CString reason; // not empty: unusable (why, e.g. a read-only file system)
  int osError = 0;          // with reason: the errno
  bool noted = false;       // the user was told that block files went elsewhere
  std::uint64_t device = 0; // st_dev of the parent: block files on one file system share its room
  explicit PrivateDir(Accountant* a)
    : parent(Counted<char>(a))
    , path(Counted<char>(a))
    , reason(Counted<char>(a))
  {
  }
};

} // namespace detail

struct DML::Impl
{
  // The accountant is declared first: every counted container below refers to it.
  detail::Accountant acc;
  std::unique_ptr<FileBackend> backend;
  Profile profile;
  std::uint64_t profileCost = 0;
  Mode mode = Mode::InCore;
  Stats stats;
  Replacement replacement = Replacement::WSClock;

  detail::CVector<detail::Block> blocks;
  detail::CVector<detail::PrivateDir> dirs;
  // Mirror of the in-core base pointers read by the inline DML::BasePointer(); its capacity
  // follows blocks' capacity so SyncBases() never allocates.
  detail::CVector<void*> bases;
  // Mirror of the out-of-core blocks' parameters read by the inline DML::Read/Write (same
  // capacity rule as bases).
  detail::CVector<FastBlock> fast;
  DML* owner = nullptr;
  std::uint64_t nextFileSeq = 0;
  std::uint64_t nextDir = 0; // round robin over profile.directories
  detail::Cache cache;
  // Fork: a child serves its parent's files (it never creates, closes or removes one) and has
  // `lent` bytes of the parent's budget; a parent counts its children.
  Impl* forkParent = nullptr;
  bool attached = false; // a child between Fork and Join (or its destruction)
  std::uint64_t lent = 0;
  std::uint32_t children = 0;
  void CheckUnforked(const char* what) const; // no structural change while forked

  explicit Impl(std::unique_ptr<FileBackend> b);
  ~Impl();
  Impl(const Impl&) = delete;
  Impl& operator=(const Impl&) = delete;

  // --- DML.cpp
  detail::Block& Get(BlockId id, detail::Kind kind);
  const detail::Block& Get(BlockId id, detail::Kind kind) const;
  BlockId NewSlot(detail::Kind kind, std::size_t elementSize, double weight);
  BlockId OpenRaw(detail::Kind kind, std::size_t elementSize, std::uint64_t count, double weight);
  void CloseRaw(BlockId id);
  void ResizeRaw(BlockId id, std::uint64_t count);
  void ResizeInCore(detail::Block& b, std::uint64_t count);
  void CreateFile(BlockId id);
  void RemoveFile(detail::Block& b);
  void SpillBlock(BlockId id);
  void LoadBlock(BlockId id);
  void SwitchTo(Mode target);
  bool NeedsSpill(std::uint64_t extraBytes) const;
  std::uint64_t CostInCore() const;
  std::string FilePath(const detail::Block& b) const;
  [[noreturn]] void Rethrow(const StorageError& e, const detail::Block& b) const;
  void BackendRead(const detail::Block& b, void* dst, std::uint64_t n, std::uint64_t off);
  void BackendWrite(const detail::Block& b, const void* src, std::uint64_t n, std::uint64_t off);
  void BackendTruncate(const detail::Block& b, std::uint64_t n);
  // Temporary directories: where a block file of `bytes` can go (fallback over the profile's
  // directories when one is unusable or has no room), and moving a block's file elsewhere.
  std::vector<std::string> Directories() const;
  std::size_t DirIndex(const std::string& parent);
  bool EnsureDirectory(std::size_t di);
  std::uint64_t PendingBytes(std::size_t di) const;
  bool HasRoom(std::size_t di, std::uint64_t bytes, std::string* why) const;
  bool Relocate(detail::Block& b, std::uint64_t bytes, const std::string& why);
  void NoteFileBytes(std::uint64_t removed, std::uint64_t added);
  void Note(const std::string& text);
  // Copies bytes [off, off + n) of a block from/to buf in either mode. `once`: a bulk transfer
  // whatever its size (the data is not read again soon: ReadRangeOnce).
  void Transfer(BlockId id, detail::Block& b, std::uint64_t off, std::uint64_t n,
    unsigned char* buf, bool write, bool once = false);
  void Shutdown() noexcept;
  void SyncBases() noexcept; // also SyncAllFast
  void SyncFast(BlockId id) noexcept;
  void SyncAllFast() noexcept;
  // The inline access's table (DML.h): a frame's entry goes in when the slow path has set its
  // reference bit (with the write tag when dirty); it goes out when the reference bit is
  // cleared or the frame evicted, and the write tag when the page is written back.
  bool FastServed(BlockId id, const detail::Block& b) const;
  void FastInstall(BlockId id, const detail::Block& b, std::int32_t fi);
  FastEntry* FastEntryOf(std::int32_t fi);
  void FastRemove(std::int32_t fi);
  void FastClearWrite(std::int32_t fi);

  // --- PageCache.cpp
  void EnsureCache();
  void DestroyCache(bool writeBack);
  std::size_t ChoosePageSize() const;
  std::uint64_t CacheCost() const; // bytes held by the cache (frames and tables)
  std::uint32_t FrameCapacity() const;
  unsigned char* PageFor(BlockId id, detail::Block& b, std::uint64_t page, bool write, bool fetch);
  std::int32_t Lookup(BlockId id, std::uint64_t page) const;
  std::int32_t Fault(BlockId id, detail::Block& b, std::uint64_t page, bool fetch);
  std::int32_t AcquireFrame(BlockId requester);
  std::int32_t FindVictim(BlockId requester);
  std::int32_t ClockVictim();
  std::int32_t SweepVictim(detail::Block& v);
  void WriteBack(std::int32_t fi);
  void Evict(std::int32_t fi, bool writeBack);
  void DropBlockPages(BlockId id, std::uint64_t fromPage); // discard pages >= fromPage
  // Join: the block's clean pages overlapping the child's range are dropped; in its dirty ones
  // the child's elements are read again from the file.
  void MergeChildRange(BlockId id);
  void ReleaseFrames(std::uint64_t bytes); // Accountant callback
  // A page buffer out of the cache (a victim's, written back first; nullptr: none left) and
  // into it (false: no free slot or no room). Fork and Join move buffers between two caches of
  // the same page size instead of freeing and allocating: freed heap memory stays resident.
  unsigned char* TakeBuffer();
  bool GiveBuffer(unsigned char* data);
  void RecomputeQuotas();
  void RingInsert(detail::Block& b, std::int32_t fi);
  void RingRemove(detail::Block& b, std::int32_t fi);
  std::uint64_t PageBytes(const detail::Block& b) const { return b.perPage * b.elementSize; }
  std::int32_t PinPage(BlockId id, detail::Block& b, std::uint64_t page, bool write);
  void UnpinPage(BlockId id, std::uint64_t page);
};

namespace detail
{
// Refreshes the BasePointer() mirror when a public call that may move block memory ends,
// normally or by an exception.
struct BaseSync
{
  DML::Impl& impl;
  explicit BaseSync(DML::Impl& i) : impl(i) {}
  ~BaseSync() { this->impl.SyncBases(); }
  BaseSync(const BaseSync&) = delete;
  BaseSync& operator=(const BaseSync&) = delete;
};
} // namespace detail

} // namespace sipmss::storage
