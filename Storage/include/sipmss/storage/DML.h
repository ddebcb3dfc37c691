// SIPMSS data management layer (DML): the paper's device independent primitives.
//
// An algorithm describes its data structures in a Profile and calls Config(); the DML runs
// in core when the estimated cost C <= budget B, otherwise out of core (each block a file in a
// private per-instance directory, memory a clock page cache). Reconfigure() re-evaluates the
// mode as the data shrinks or grows. Every byte the DML holds is counted against B.
//
// Thread safety: one DML instance is used by one thread at a time. Concurrent *reads* through
// BasePointer() in core mode are safe while no other call runs.
#pragma once

#include <algorithm>
#include <cstddef>
#include <cstdint>
#include <cstring>
#include <memory>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <utility>
#include <vector>

// Element access sits in the innermost loops of the algorithms, whose functions are large enough
// that the compiler's inlining budget runs out before these small bodies: force them inline.
#if defined(__GNUC__) || defined(__clang__)
#define SIPMSS_ALWAYS_INLINE inline __attribute__((always_inline))
#else
#define SIPMSS_ALWAYS_INLINE inline
#endif

namespace sipmss::storage
{

enum class Mode : std::uint8_t
{
  InCore,
  OutOfCore
};
enum class ModePolicy : std::uint8_t
{
  Automatic,
  InCore,
  OutOfCore
};
const char* ToString(Mode m);

// Page allocation between blocks in out-of-core mode.
enum class PagePolicy : std::uint8_t
{
  StaticWeight, // the paper: a block's share of pages follows its weight (size / mean size)
  Adaptive,     // shares follow observed miss rates
  Clock         // no shares: one clock over every cached page (docs/storage.md)
};

struct StructureSpec
{
  std::string name;
  std::size_t elementSize = 0;
  std::uint64_t maxCount = 0;
  double weight = 0.0; // 0: derived from the size, as in the paper
};

struct Profile
{
  std::vector<StructureSpec> structures; // C = sum(elementSize * maxCount) + metadata
  std::vector<std::string> directories;  // empty: $TMPDIR or /tmp
  std::uint64_t memoryBudget = 0;        // B in bytes; 0 = unbounded (always in core)
  ModePolicy policy = ModePolicy::Automatic;
  PagePolicy pagePolicy = PagePolicy::Clock; // measured better than the shares: docs/storage.md
  std::size_t pageSize = 0; // 0: automatic
  // How memoryBudget was chosen, for messages (e.g. "automatic: half of the 2.0 GiB left under
  // RLIMIT_AS"); empty: given by the caller.
  std::string budgetOrigin;
};

// The mode Config(profile) chooses on a DML with no open blocks: out of core when the policy
// says so, or when it is Automatic and the structures' cost C exceeds a bounded budget. For
// decisions made before the DML is configured (an algorithm's layout step).
Mode PlannedMode(const Profile& profile);

struct Stats
{
  Mode mode = Mode::InCore;
  bool usedInCore = false;
  bool usedOutOfCore = false;
  std::uint64_t bytesHeld = 0; // bytes of memory held now (pages, blocks, metadata)
  std::uint64_t peakBytes = 0; // maximum of bytesHeld since Config
  std::uint64_t hits = 0;
  std::uint64_t misses = 0;
  std::uint64_t bytesRead = 0;    // from files
  std::uint64_t bytesWritten = 0; // to files
  std::uint64_t reconfigurations = 0; // mode switches after Config
  std::uint64_t forks = 0;            // forked children joined (their counts are included)
  std::uint64_t fileBytes = 0;        // size of the block files now (temporary disk)
  std::uint64_t peakFileBytes = 0;    // maximum of fileBytes since Config
  std::uint64_t declaredBytes = 0;    // the profile's structures: sum(elementSize * maxCount)
  // What the layer did that the user should hear of: a temporary directory it could not use
  // (read-only, missing, full) and where the block files went instead.
  std::vector<std::string> notes;
};

// One block's I/O since it was opened (DML::GetBlockStats): the page misses of its elements and
// the bytes read from and written to its file; a forked DML's are added when it is joined. The
// Stats totals are their sums over every block the DML has had. In core: zeros.
struct BlockStats
{
  std::uint64_t misses = 0;
  std::uint64_t bytesRead = 0;
  std::uint64_t bytesWritten = 0;
};

// Typed error for every storage failure: the path involved and the OS error (errno) if any.
class StorageError : public std::runtime_error
{
public:
  StorageError(const std::string& message, std::string path, int osError);
  const std::string& Path() const noexcept { return this->path_; }
  int OsError() const noexcept { return this->osError_; }

private:
  std::string path_;
  int osError_;
};

// Raised when an operation cannot be done inside the memory budget (e.g. too many pinned pages).
class BudgetError : public std::runtime_error
{
public:
  using std::runtime_error::runtime_error;
};

// File backend: every file operation of the out-of-core mode goes through it so that tests can
// inject faults. The default backend uses POSIX pread/pwrite with 64-bit offsets.
class FileBackend
{
public:
  virtual ~FileBackend() = default;
  virtual int Create(const std::string& path) = 0; // returns a handle; throws StorageError
  virtual void Close(int handle) = 0;
  virtual void Remove(const std::string& path) = 0;
  virtual void ReadAt(int handle, void* dst, std::size_t bytes, std::uint64_t offset) = 0;
  virtual void WriteAt(int handle, const void* src, std::size_t bytes, std::uint64_t offset) = 0;
  virtual void Truncate(int handle, std::uint64_t bytes) = 0;
  // The bytes of disk the file holds now (a sparse file fills as it is written); 0: unknown.
  virtual std::uint64_t AllocatedBytes(int handle) { (void)handle; return 0; }
  // The bytes an unprivileged user may still write in the file system of `directory`;
  // UINT64_MAX: unknown (no limit is assumed).
  virtual std::uint64_t FreeBytes(const std::string& directory)
  {
    (void)directory;
    return ~std::uint64_t(0);
  }
  static std::unique_ptr<FileBackend> CreatePosix();
};

using BlockId = std::int32_t;

enum class Access : std::uint8_t
{
  Read,
  Write // the page is marked dirty
};

// Out of core: the inline element access (Read, Write, ReadRange, WriteRange, and the accessors
// of Access.h) finds a cached page through a direct-mapped table of the cache's pages, published
// by the DML, at slot (page + FastSalt(block)) mod its size (2 to 4 entries a frame slot). An
// entry is there only while its frame holds the page with the reference bit set, and it allows
// writes (kFastWritable) only while the page is dirty, so a hit needs no bookkeeping: the clock
// hand that clears a reference bit and an eviction take the entry out, a write-back clears
// kFastWritable, and the next access goes through the slow path, which sets the bits and puts
// the entry back. Two pages on one slot take turns through the slow path.
// A tag is page | FastTagBase(block, generation), with kFastWritable while dirty; 0 is empty.
constexpr std::uint64_t kFastWritable = std::uint64_t(1) << 39;
struct FastEntry
{
  std::uint64_t tag = 0;
  unsigned char* data = nullptr;
};
// A block's parameters for the inline access. tagBase == kNoFastTag: never served inline (in
// core, no cache, LRU replacement, one element a page).
constexpr std::uint64_t kNoFastTag = ~std::uint64_t(0);
struct FastBlock
{
  std::uint64_t magic = 0;   // ceil(2^64 / perPage): page = high 64 bits of index * magic
  std::uint64_t perPage = 1; // elements per page
  std::uint64_t count = 0;   // elements of the block
  std::uint64_t tagBase = kNoFastTag; // FastTagBase | kFastWritable
  std::uint64_t salt = 0;    // added to the page for the table slot
  std::uint64_t elementSize = 0;
};
// Block ids served inline: below kFastBlocks. A tag keeps the block id in its top 16 bits, the
// cache's generation (a count of its builds, whose page sizes may differ, modulo 256) in the
// next 8, then kFastWritable, and the page below them: blocks of fewer than 2^39 elements and
// pages of fewer than 2^24. The generation keeps an accessor that missed its Refresh after a
// rebuild off the new table's pages, except after a multiple of 256 rebuilds: Refresh is the
// rule (Access.h).
constexpr std::uint64_t kFastBlocks = 0xFFFE;
inline std::uint64_t FastTagBase(std::int32_t id, std::uint8_t generation)
{
  return (std::uint64_t(id + 1) << 48) | (std::uint64_t(generation) << 40);
}
inline std::uint64_t FastSalt(std::int32_t id)
{
  return (std::uint64_t(id) * 0x9E3779B97F4A7C15ull) >> 40;
}
// floor(a * b / 2^64): with b = ceil(2^64 / d), floor(a / d) for every a below 2^64 / d (the
// rounding adds less than a / 2^64, under 1 / d).
SIPMSS_ALWAYS_INLINE std::uint64_t MulHigh(std::uint64_t a, std::uint64_t b)
{
  return static_cast<std::uint64_t>((static_cast<unsigned __int128>(a) * b) >> 64);
}

// A pinned run of consecutive elements of one block (never crosses a page).
struct Span
{
  void* data = nullptr;
  std::uint64_t first = 0; // element index of data[0]
  std::uint64_t count = 0; // elements valid from data
};

class DML
{
public:
  DML();
  explicit DML(std::unique_ptr<FileBackend> backend);
  ~DML(); // closes every block, removes every file and the private directory
  DML(const DML&) = delete;
  DML& operator=(const DML&) = delete;

  // --- configuration primitives
  Mode Config(const Profile& profile);
  Mode Reconfigure(); // re-evaluate C against B (C = bytes of the blocks open now)
  Mode GetMode() const;
  Stats GetStats() const;
  BlockStats GetBlockStats(BlockId id) const; // (an open block)
  const Profile& GetProfile() const;

  // --- allocation primitives
  BlockId OpenBlock(std::size_t elementSize, std::uint64_t count, double weight = 0.0);
  void CloseBlock(BlockId id);
  void Resize(BlockId id, std::uint64_t count); // grow (new elements are zero) or shrink
  std::uint64_t Count(BlockId id) const;
  std::size_t ElementSize(BlockId id) const;

  // --- read/write primitives (elementSize must equal the block's)
  void Read(BlockId id, std::size_t elementSize, std::uint64_t index, void* dst);
  void Write(BlockId id, std::size_t elementSize, std::uint64_t index, const void* src);
  void ReadRange(BlockId id, std::uint64_t first, std::uint64_t count, void* dst);
  void WriteRange(BlockId id, std::uint64_t first, std::uint64_t count, const void* src);
  // ReadRange for elements read once, whose neighbours are not read soon (a sorter's segments,
  // scattered among other buckets'): out of core, the pages that are not cached are read
  // straight from the file whatever the size, without bringing the whole page into the cache.
  void ReadRangeOnce(BlockId id, std::uint64_t first, std::uint64_t count, void* dst);
  void Fill(BlockId id, const void* element); // every element := *element

  // --- memory outside the blocks, counted against the budget (the public counted allocator)
  // ChargeMemory counts `bytes` of the caller's heap (and its allocator's overhead) against B:
  // out of core the page cache gives up pages for them; BudgetError when they cannot fit.
  // ReleaseMemory gives the same number back. SpareMemory is what ChargeMemory can take now
  // while the page cache keeps `keepPages` pages and every pinned one (unbounded: 1 << 62).
  void ChargeMemory(std::uint64_t bytes);
  void ReleaseMemory(std::uint64_t bytes) noexcept;
  std::uint64_t SpareMemory(std::uint32_t keepPages = 4);
  // The cache's page size in bytes (out of core; 0 in core).
  std::size_t PageBytes();

  // --- zero-copy access for hot loops
  // In core: the block's memory (valid until the next Config/Reconfigure/Resize/OpenBlock that
  // changes the mode, or CloseBlock of this block). Out of core: nullptr.
  // Note: a Resize of this block may move it even in core (realloc).
  void* BasePointer(BlockId id) const;
  // Pin the page holding `index`; the span runs to the end of that page (or block).
  Span Pin(BlockId id, std::uint64_t index, Access access);
  void Unpin(BlockId id, const Span& span);
  // How many more pages Pin could hold now (out of core: the cache's pages less those pinned
  // and the two kept free; in core: no limit, UINT32_MAX).
  std::uint32_t PinnablePages();

  // --- a second page cache for a helper thread (out of core)
  // Fork lends `bytes` of this DML's budget to a new DML, the child, which serves the element
  // blocks open now (same ids, same files) through a page cache of its own, so that another
  // thread can use them while this one goes on. This DML first writes its dirty pages back (the
  // child reads the files). `childWrites` lists, per block, the one range of elements the child
  // may write (one child at a time). Until Join:
  //   - the child writes no element outside those ranges, this DML none inside them;
  //   - an element the other side writes may be read, but its value is undefined (the use
  //     must not depend on it) until Join;
  //   - neither opens, closes or resizes a block, fills one, or reconfigures.
  // Pages may straddle a range's ends: each side writes back only its own elements of them.
  // Join (on this DML's thread, once the child's thread is done with it) writes the child's
  // dirty elements back, drops this DML's clean copies of the child's ranges and refreshes the
  // child's elements in its dirty pages that straddle them, adds the child's counts to Stats
  // and takes the budget back; the child then holds no block. A child destroyed without Join
  // (on this DML's thread: an error path) loses its unwritten pages and gives the budget back.
  // In core, Fork returns nullptr: BasePointer memory may be shared by threads as is.
  struct Range
  {
    BlockId id = -1;
    std::uint64_t first = 0;
    std::uint64_t count = 0;
  };
  std::unique_ptr<DML> Fork(std::uint64_t bytes, const std::vector<Range>& childWrites);
  void Join(DML& child);

  // Path of this instance's private directory ("" until the first file is made, and again after
  // a switch in core, which removes the files and the directory).
  std::string PrivateDirectory() const;

  // Removes private directories of dead processes under `directory`; returns how many.
  static int CleanStaleDirectories(const std::string& directory);

  struct Impl;

private:
  friend struct DMLTestAccess; // test and benchmark hooks (DMLTesting.h)
  std::unique_ptr<Impl> impl_;
  // Base pointers of the in-core element blocks by block id (nullptr otherwise), kept up to
  // date by Impl so that BasePointer() is inline: a compare and two loads, no call.
  void* const* bases_ = nullptr;
  std::size_t baseCount_ = 0;
  // The out-of-core blocks' inline access (kept up to date by Impl: every change of a block's
  // count, mode or the cache re-publishes them): per block its FastBlock, and the cache's table
  // of pages (never null: an empty one-entry table without a cache).
  const FastBlock* fast_ = nullptr;
  std::size_t fastCount_ = 0; // blocks
  const FastEntry* table_ = nullptr;
  std::uint64_t tableMask_ = 0;
  std::uint64_t fastHits_ = 0;
  void ReadElement(BlockId id, std::size_t elementSize, std::uint64_t index, void* dst);
  void WriteElement(BlockId id, std::size_t elementSize, std::uint64_t index, const void* src);
  void ReadRangeSlow(BlockId id, std::uint64_t first, std::uint64_t count, void* dst);
  void WriteRangeSlow(BlockId id, std::uint64_t first, std::uint64_t count, const void* src);
  // Block id's published parameters when its elements are elementSize bytes (0: any), else
  // nullptr.
  const FastBlock* FastBlockOf(BlockId id, std::size_t elementSize) const
  {
    if (static_cast<std::size_t>(id) >= this->fastCount_)
    {
      return nullptr;
    }
    const FastBlock& b = this->fast_[static_cast<std::size_t>(id)];
    return elementSize == 0 || elementSize == b.elementSize ? &b : nullptr;
  }

public:
  // The inline access for callers that keep a block's FastBlock (FastParams: a snapshot valid
  // until the block is resized or closed, none when its elements are not elementSize bytes; the
  // table itself is read on every access, so a mode switch or a cache rebuild only sends
  // accesses to the slow path). FastAt: the cached page holding elements [first, first + count)
  // (count > 0), as its element `first`, or nullptr; Write: only a page already dirty. `size`
  // is the block's element size.
  FastBlock FastParams(BlockId id, std::size_t elementSize) const
  {
    const FastBlock* b = this->FastBlockOf(id, elementSize);
    return b ? *b : FastBlock{};
  }
  template <bool Write>
  SIPMSS_ALWAYS_INLINE unsigned char* FastAt(
    const FastBlock& b, std::size_t size, std::uint64_t first, std::uint64_t count) const
  {
    const std::uint64_t page = MulHigh(first, b.magic);
    const FastEntry& e = this->table_[(page + b.salt) & this->tableMask_];
    if ((Write ? e.tag : e.tag | kFastWritable) != (page | b.tagBase) || first >= b.count ||
      count > b.count - first || (count > 1 && MulHigh(first + count - 1, b.magic) != page))
    {
      return nullptr;
    }
    return e.data + (first - page * b.perPage) * size;
  }
  void CountFastHit() { ++this->fastHits_; }
};

SIPMSS_ALWAYS_INLINE void* DML::BasePointer(BlockId id) const
{
  return static_cast<std::size_t>(id) < this->baseCount_ ? this->bases_[id] : nullptr;
}

// One element: inline when out of core on a cached page (the hot case), else
// ReadElement/WriteElement (in core, pages not in the table, errors).
SIPMSS_ALWAYS_INLINE void DML::Read(BlockId id, std::size_t elementSize, std::uint64_t index, void* dst)
{
  const FastBlock* b = elementSize ? this->FastBlockOf(id, elementSize) : nullptr;
  if (const unsigned char* p = b ? this->FastAt<false>(*b, elementSize, index, 1) : nullptr)
  {
    ++this->fastHits_;
    std::memcpy(dst, p, elementSize);
    return;
  }
  this->ReadElement(id, elementSize, index, dst);
}

SIPMSS_ALWAYS_INLINE void DML::Write(
  BlockId id, std::size_t elementSize, std::uint64_t index, const void* src)
{
  const FastBlock* b = elementSize ? this->FastBlockOf(id, elementSize) : nullptr;
  if (unsigned char* p = b ? this->FastAt<true>(*b, elementSize, index, 1) : nullptr)
  {
    ++this->fastHits_;
    std::memcpy(p, src, elementSize);
    return;
  }
  this->WriteElement(id, elementSize, index, src);
}

// A run of elements: inline when out of core within one cached page (a vertex's list of faces),
// else ReadRangeSlow/WriteRangeSlow.
SIPMSS_ALWAYS_INLINE void DML::ReadRange(
  BlockId id, std::uint64_t first, std::uint64_t count, void* dst)
{
  const FastBlock* b = count > 0 ? this->FastBlockOf(id, 0) : nullptr;
  if (const unsigned char* p = b ? this->FastAt<false>(*b, b->elementSize, first, count) : nullptr)
  {
    ++this->fastHits_;
    std::memcpy(dst, p, count * b->elementSize);
    return;
  }
  this->ReadRangeSlow(id, first, count, dst);
}

SIPMSS_ALWAYS_INLINE void DML::WriteRange(
  BlockId id, std::uint64_t first, std::uint64_t count, const void* src)
{
  const FastBlock* b = count > 0 ? this->FastBlockOf(id, 0) : nullptr;
  if (unsigned char* p = b ? this->FastAt<true>(*b, b->elementSize, first, count) : nullptr)
  {
    ++this->fastHits_;
    std::memcpy(p, src, count * b->elementSize);
    return;
  }
  this->WriteRangeSlow(id, first, count, src);
}

// Typed convenience over one fixed-size block.
template <class T>
class Array
{
public:
  Array() = default;
  Array(DML& dml, std::uint64_t count, double weight = 0.0)
    : dml_(&dml)
    , id_(dml.OpenBlock(sizeof(T), count, weight))
  {
  }
  ~Array() { this->Close(); }
  Array(const Array&) = delete;
  Array& operator=(const Array&) = delete;
  Array(Array&& o) noexcept : dml_(o.dml_), id_(o.id_) { o.dml_ = nullptr; }
  Array& operator=(Array&& o) noexcept
  {
    if (this != &o)
    {
      this->Close();
      this->dml_ = o.dml_;
      this->id_ = o.id_;
      o.dml_ = nullptr;
    }
    return *this;
  }
  void Close()
  {
    if (this->dml_)
    {
      this->dml_->CloseBlock(this->id_);
      this->dml_ = nullptr;
    }
  }
  bool IsOpen() const { return this->dml_ != nullptr; }
  BlockId Id() const { return this->id_; }
  std::uint64_t Size() const { return this->dml_->Count(this->id_); }
  void Resize(std::uint64_t n) { this->dml_->Resize(this->id_, n); }

  T Get(std::uint64_t i) const
  {
    if (void* base = this->dml_->BasePointer(this->id_))
    {
      return static_cast<const T*>(base)[i];
    }
    T v;
    this->dml_->Read(this->id_, sizeof(T), i, &v);
    return v;
  }
  void Set(std::uint64_t i, const T& v)
  {
    if (void* base = this->dml_->BasePointer(this->id_))
    {
      static_cast<T*>(base)[i] = v;
      return;
    }
    this->dml_->Write(this->id_, sizeof(T), i, &v);
  }
  void Read(std::uint64_t first, std::uint64_t n, T* dst) const
  {
    this->dml_->ReadRange(this->id_, first, n, dst);
  }
  // Read for elements read once (DML::ReadRangeOnce).
  void ReadOnce(std::uint64_t first, std::uint64_t n, T* dst) const
  {
    this->dml_->ReadRangeOnce(this->id_, first, n, dst);
  }
  void Write(std::uint64_t first, std::uint64_t n, const T* src)
  {
    this->dml_->WriteRange(this->id_, first, n, src);
  }

  // Calls f(T* data, uint64_t first, uint64_t count) over [first, first+n) page by page.
  template <class F>
  void ForEachChunk(std::uint64_t first, std::uint64_t n, Access access, F&& f)
  {
    const std::uint64_t end = first + n;
    while (first < end)
    {
      Span s = this->dml_->Pin(this->id_, first, access);
      std::uint64_t c = s.count < end - first ? s.count : end - first;
      try
      {
        f(static_cast<T*>(s.data), first, c);
      }
      catch (...)
      {
        this->dml_->Unpin(this->id_, s);
        throw;
      }
      this->dml_->Unpin(this->id_, s);
      first += c;
    }
  }

  // Exchanges the blocks of two arrays of the same DML.
  void Swap(Array& o) noexcept
  {
    std::swap(this->dml_, o.dml_);
    std::swap(this->id_, o.id_);
  }

private:
  DML* dml_ = nullptr;
  BlockId id_ = -1;
};

// Working memory that leaves the process as soon as it is freed, whichever thread allocated or
// frees it. glibc serves a freed block below its mmap threshold again from the same arena, and
// that threshold rises to the size of every mapped block freed (up to 32 MiB): buffers of a few
// MiB allocated and freed in turn (a sort's runs, the layout step's slices) would stay resident
// in the heap beside the next one, and a thread's own arena keeps what it freed from the others.
// Blocks of at least kReturnableMapBytes are mapped (mmap) and unmapped when freed; smaller ones
// come from operator new. AllocateReturnable throws std::bad_alloc; FreeReturnable takes the
// size that was allocated.
constexpr std::size_t kReturnableMapBytes = std::size_t(64) << 10;
void* AllocateReturnable(std::size_t bytes);
void FreeReturnable(void* p, std::size_t bytes) noexcept;

// A buffer of n elements counted against a DML's budget (ChargeMemory) for its lifetime: the
// working memory of a phase that is not a block (a sort's runs, a merge's heads). Its memory is
// returnable (AllocateReturnable): freed, it leaves the process at once. Its elements are not
// initialized.
template <class T>
class CountedBuffer
{
  static_assert(std::is_trivially_default_constructible_v<T> && std::is_trivially_destructible_v<T>,
    "CountedBuffer holds plain records");

public:
  CountedBuffer(DML& dml, std::size_t n)
    : dml_(&dml)
    , bytes_(static_cast<std::uint64_t>(n) * sizeof(T))
  {
    dml.ChargeMemory(this->bytes_);
    try
    {
      this->data_ = static_cast<T*>(AllocateReturnable(std::max<std::size_t>(n, 1) * sizeof(T)));
    }
    catch (...)
    {
      dml.ReleaseMemory(this->bytes_);
      throw;
    }
    this->size_ = n;
  }
  ~CountedBuffer()
  {
    FreeReturnable(this->data_, std::max<std::size_t>(this->size_, 1) * sizeof(T));
    this->dml_->ReleaseMemory(this->bytes_);
  }
  CountedBuffer(const CountedBuffer&) = delete;
  CountedBuffer& operator=(const CountedBuffer&) = delete;
  T* Data() { return this->data_; }
  std::size_t Size() const { return this->size_; }
  T& operator[](std::size_t i) { return this->data_[i]; }

private:
  DML* dml_;
  std::uint64_t bytes_;
  T* data_ = nullptr;
  std::size_t size_ = 0;
};

} // namespace sipmss::storage
