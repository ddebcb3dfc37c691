// The DML primitives: configuration, block allocation, element access and mode switches.
//
// Each block is either in core (one contiguous allocation) or on a file (served by the page
// cache, PageCache.cpp). Normally all blocks share the mode of the DML; after an operation failed
// half way through a mode switch some blocks may still be in the other mode, which every
// primitive handles (they dispatch per block), so the DML stays usable and destructible.
#include "DMLImpl.h"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <exception>
#include <limits>
#include <new>
#include <stdexcept>
#include <string_view>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

namespace sipmss::storage
{

using detail::Block;
using detail::HeapCost;
using detail::Kind;

namespace
{
// Blocks from this size on get huge pages (two of 2 MiB at least).
constexpr std::uint64_t kHugeBlockBytes = std::uint64_t(4) << 20;
constexpr std::size_t kHugePageBytes = std::size_t(2) << 20;

// In-core blocks are accessed at random (rings, quadrics, candidates): on large blocks 2 MiB
// pages save most TLB misses (the kernel's "madvise" THP mode leaves them off otherwise).
void AdviseHugePages(void* p, std::uint64_t bytes)
{
#ifdef MADV_HUGEPAGE
  if (!p || bytes < kHugeBlockBytes)
  {
    return;
  }
  const std::uintptr_t a = reinterpret_cast<std::uintptr_t>(p);
  const std::uintptr_t first = (a + kHugePageBytes - 1) & ~std::uintptr_t(kHugePageBytes - 1);
  const std::uintptr_t last = (a + bytes) & ~std::uintptr_t(kHugePageBytes - 1);
  if (last > first)
  {
    ::madvise(reinterpret_cast<void*>(first), last - first, MADV_HUGEPAGE); // advice only
  }
#else
  (void)p;
  (void)bytes;
#endif
}

bool AllZero(const unsigned char* p, std::size_t n)
{
  return n == 0 || (p[0] == 0 && std::memcmp(p, p + 1, n - 1) == 0);
}

std::uint64_t CheckedBytes(std::uint64_t count, std::size_t elementSize)
{
  if (elementSize == 0)
  {
    throw std::invalid_argument("sipmss::storage: element size must be positive");
  }
  if (count > (std::uint64_t(1) << 62) / elementSize)
  {
    throw std::invalid_argument("sipmss::storage: block size overflows");
  }
  return count * elementSize;
}
} // namespace

void detail::Accountant::Charge(std::uint64_t n)
{
  if (!this->Fits(n) && this->owner)
  {
    this->owner->ReleaseFrames(n);
  }
  if (!this->Fits(n))
  {
    throw BudgetError("sipmss::storage: memory budget exceeded (need " + std::to_string(n) +
      " bytes, holding " + std::to_string(this->held) + " of " + std::to_string(this->budget) +
      ")");
  }
  this->Add(n);
}

// ------------------------------------------------------------------------------------------------
DML::Impl::Impl(std::unique_ptr<FileBackend> b)
  : backend(std::move(b))
  , blocks(detail::Counted<Block>(&this->acc))
  , dirs(detail::Counted<detail::PrivateDir>(&this->acc))
  , bases(detail::Counted<void*>(&this->acc))
  , fast(detail::Counted<FastBlock>(&this->acc))
  , cache(&this->acc)
{
  this->acc.owner = this;
  // The instance itself, the backend object and the scratch reserve (see kScratchReserve).
  this->acc.Add(HeapCost(sizeof(Impl)) + HeapCost(64) + detail::kScratchReserve);
}

DML::Impl::~Impl()
{
  this->Shutdown();
}

void DML::Impl::Shutdown() noexcept
{
  // Pages are discarded: the files are removed anyway.
  for (auto& f : this->cache.frames)
  {
    std::free(f.data);
    f.data = nullptr;
  }
  if (this->forkParent)
  {
    // A child: the files are the parent's. Destroyed without Join (an error path): its unwritten
    // pages are lost, and the parent takes its budget back and may change its blocks again.
    for (auto& b : this->blocks)
    {
      b.fd = -1;
    }
    if (this->attached)
    {
      Impl& P = *this->forkParent;
      P.acc.Release(this->lent);
      this->lent = 0;
      --P.children;
      for (auto& b : P.blocks)
      {
        b.forkFirst = b.forkEnd = 0;
      }
      this->attached = false;
    }
  }
  for (auto& b : this->blocks)
  {
    std::free(b.mem);
    b.mem = nullptr;
    if (b.fd >= 0)
    {
      try
      {
        this->backend->Close(b.fd);
      }
      catch (...)
      {
      }
      b.fd = -1;
      try
      {
        const std::string path = this->FilePath(b);
        try
        {
          this->backend->Remove(path);
        }
        catch (...)
        {
          ::unlink(path.c_str());
        }
      }
      catch (...)
      {
      }
    }
  }
  for (const auto& d : this->dirs)
  {
    if (!d.path.empty())
    {
      const std::string p(d.path.data(), d.path.size());
      if (::rmdir(p.c_str()) != 0 && errno != ENOENT)
      {
        // Files the backend failed to remove: everything in the private directory is ours.
        detail::RemoveTree(p);
      }
    }
  }
}

void DML::Impl::SyncBases() noexcept
{
  // Within capacity (reserved in NewSlot): resize does not allocate.
  this->bases.resize(std::min(this->blocks.size(), this->bases.capacity()));
  for (std::size_t i = 0; i < this->bases.size(); ++i)
  {
    const Block& b = this->blocks[i];
    this->bases[i] = b.kind == Kind::Plain ? b.mem : nullptr;
  }
  this->owner->bases_ = this->bases.data();
  this->owner->baseCount_ = this->bases.size();
  this->SyncAllFast();
}

void DML::Impl::SyncFast(BlockId id) noexcept
{
  if (id < 0 || static_cast<std::size_t>(id) >= this->fast.size())
  {
    return;
  }
  FastBlock& p = this->fast[static_cast<std::size_t>(id)];
  p = FastBlock{};
  const Block& b = this->blocks[static_cast<std::size_t>(id)];
  if (!this->FastServed(id, b))
  {
    return;
  }
  p.magic = ~std::uint64_t(0) / b.perPage + 1; // ceil(2^64 / perPage): perPage is at least 2
  p.perPage = b.perPage;
  p.count = b.count;
  p.tagBase = FastTagBase(id, this->cache.generation) | kFastWritable;
  p.salt = FastSalt(id);
  p.elementSize = b.elementSize;
}

void DML::Impl::SyncAllFast() noexcept
{
  // Within capacity (reserved in NewSlot, like bases): resize does not allocate.
  const std::size_t n = std::min(this->blocks.size(), this->fast.capacity());
  this->fast.resize(n);
  for (std::size_t i = 0; i < n; ++i)
  {
    this->SyncFast(static_cast<BlockId>(i));
  }
  static const FastEntry kEmptyTable[1] = {};
  this->owner->fast_ = this->fast.data();
  this->owner->fastCount_ = n;
  const bool table = this->cache.built && !this->cache.table.empty();
  this->owner->table_ = table ? this->cache.table.data() : kEmptyTable;
  this->owner->tableMask_ = table ? this->cache.table.size() - 1 : 0;
}

Block& DML::Impl::Get(BlockId id, Kind kind)
{
  if (id < 0 || static_cast<std::size_t>(id) >= this->blocks.size() ||
    this->blocks[static_cast<std::size_t>(id)].kind != kind)
  {
    throw std::invalid_argument("sipmss::storage: invalid block id " + std::to_string(id));
  }
  return this->blocks[static_cast<std::size_t>(id)];
}

const Block& DML::Impl::Get(BlockId id, Kind kind) const
{
  return const_cast<Impl*>(this)->Get(id, kind);
}

BlockId DML::Impl::NewSlot(Kind kind, std::size_t elementSize, double weight)
{
  std::size_t i = 0;
  while (i < this->blocks.size() && this->blocks[i].kind != Kind::Closed)
  {
    ++i;
  }
  if (i == this->blocks.size())
  {
    if (i >= static_cast<std::size_t>(std::numeric_limits<BlockId>::max()))
    {
      throw std::length_error("sipmss::storage: too many blocks");
    }
    // Grow explicitly so the cache releases pages before (not during) the reallocation.
    if (this->blocks.size() == this->blocks.capacity())
    {
      const std::size_t cap = std::max<std::size_t>(8, this->blocks.capacity() * 2);
      this->ReleaseFrames(HeapCost(cap * sizeof(Block)) + HeapCost(cap * sizeof(void*)) +
        HeapCost(cap * sizeof(FastBlock)));
      this->bases.reserve(cap);
      this->fast.reserve(cap);
      this->blocks.reserve(cap);
    }
    this->blocks.emplace_back();
  }
  Block& b = this->blocks[i];
  b = Block{};
  b.kind = kind;
  b.elementSize = elementSize;
  b.weight = weight > 0.0 ? weight : 0.0;
  return static_cast<BlockId>(i);
}

bool DML::Impl::NeedsSpill(std::uint64_t extraBytes) const
{
  return this->acc.budget != 0 && !this->acc.Fits(extraBytes);
}

void DML::Impl::CheckUnforked(const char* what) const
{
  if (this->forkParent || this->children > 0)
  {
    throw std::logic_error(std::string("sipmss::storage: ") + what +
      (this->forkParent ? " on a forked child DML" : " while a forked child DML is not joined"));
  }
}

BlockId DML::Impl::OpenRaw(Kind kind, std::size_t elementSize, std::uint64_t count, double weight)
{
  this->CheckUnforked("OpenBlock");
  const std::uint64_t bytes = CheckedBytes(count, elementSize);
  const BlockId id = this->NewSlot(kind, elementSize, weight);
  try
  {
    if (this->mode == Mode::InCore && this->NeedsSpill(HeapCost(std::max<std::uint64_t>(bytes, 1))))
    {
      // The budget is hard: opening this block in core would exceed it.
      if (this->profile.policy == ModePolicy::InCore)
      {
        throw BudgetError("sipmss::storage: block of " + std::to_string(bytes) +
          " bytes exceeds the memory budget and the mode is forced in core");
      }
      this->SwitchTo(Mode::OutOfCore);
      ++this->stats.reconfigurations;
    }
    Block& b = this->blocks[static_cast<std::size_t>(id)];
    if (this->mode == Mode::InCore)
    {
      const std::uint64_t cap = std::max<std::uint64_t>(bytes, 1);
      this->acc.Charge(HeapCost(cap));
      b.mem = static_cast<unsigned char*>(std::calloc(cap, 1));
      if (!b.mem)
      {
        this->acc.Release(HeapCost(cap));
        throw std::bad_alloc();
      }
      AdviseHugePages(b.mem, cap);
      b.capacityBytes = cap;
      b.count = count;
    }
    else
    {
      b.count = count;
      this->CreateFile(id);
    }
  }
  catch (...)
  {
    this->blocks[static_cast<std::size_t>(id)] = Block{};
    throw;
  }
  return id;
}

std::string DML::Impl::FilePath(const Block& b) const
{
  if (this->forkParent)
  {
    return this->forkParent->FilePath(b); // (the parent's directories do not change meanwhile)
  }
  const auto& d = this->dirs[static_cast<std::size_t>(b.dir)].path;
  std::string p(d.data(), d.size());
  p += '/';
  p += std::to_string(b.fileSeq);
  p += ".blk";
  return p;
}

void DML::Impl::Rethrow(const StorageError& e, const Block& b) const
{
  if (!e.Path().empty())
  {
    throw e;
  }
  // The backend does not know paths: add the block's file and keep the backend's message.
  std::string message = e.what();
  if (e.OsError() != 0)
  {
    const std::string suffix = ": " + detail::ErrnoText(e.OsError());
    if (message.size() >= suffix.size() &&
      message.compare(message.size() - suffix.size(), suffix.size(), suffix) == 0)
    {
      message.resize(message.size() - suffix.size());
    }
  }
  throw StorageError("block file " + message, this->FilePath(b), e.OsError());
}

void DML::Impl::BackendRead(const Block& b, void* dst, std::uint64_t n, std::uint64_t off)
{
  try
  {
    this->backend->ReadAt(b.fd, dst, n, off);
  }
  catch (const StorageError& e)
  {
    this->Rethrow(e, b);
  }
  this->stats.bytesRead += n;
  b.io.bytesRead += n;
}

void DML::Impl::BackendWrite(const Block& b, const void* src, std::uint64_t n, std::uint64_t off)
{
  try
  {
    this->backend->WriteAt(b.fd, src, n, off);
  }
  catch (const StorageError& e)
  {
    // A full file system (another process took the room): the file moves to a directory that
    // has room for all of it, and the write is made there.
    const std::string why = detail::ErrnoText(e.OsError());
    if ((e.OsError() != ENOSPC && e.OsError() != EDQUOT) ||
      !this->Relocate(const_cast<Block&>(b), b.Bytes(), why))
    {
      this->Rethrow(e, b);
    }
    try
    {
      this->backend->WriteAt(b.fd, src, n, off);
    }
    catch (const StorageError& again)
    {
      this->Rethrow(again, b);
    }
  }
  this->stats.bytesWritten += n;
  b.io.bytesWritten += n;
}

// Moves b's file to another directory with room for `bytes` (b's data is copied; the holes of
// a sparse file stay holes); false when there is none, or while forked (a child reads the
// file through the same handle).
bool DML::Impl::Relocate(Block& b, std::uint64_t bytes, const std::string& why)
{
  if (this->forkParent || this->children > 0 || b.fd < 0 || b.dir < 0)
  {
    return false;
  }
  const std::vector<std::string> candidates = this->Directories();
  const std::size_t from = std::size_t(b.dir);
  const std::string fromParent(this->dirs[from].parent.data(), this->dirs[from].parent.size());
  for (const std::string& parent : candidates)
  {
    const std::size_t di = this->DirIndex(parent);
    if (di == from || !this->EnsureDirectory(di) ||
      (this->dirs[di].device == this->dirs[from].device) || !this->HasRoom(di, bytes, nullptr))
    {
      continue;
    }
    Block moved = b; // (a copy of the bookkeeping: the old file stays b's until the copy is done)
    moved.dir = static_cast<std::int32_t>(di);
    moved.fileSeq = this->nextFileSeq++;
    const std::string path = this->FilePath(moved);
    int fd = -1;
    try
    {
      fd = this->backend->Create(path);
      this->backend->Truncate(fd, b.Bytes());
      std::vector<unsigned char> buf(1 << 16);
      for (std::uint64_t off = 0; off < b.Bytes(); off += buf.size())
      {
        const std::size_t n = std::size_t(std::min<std::uint64_t>(buf.size(), b.Bytes() - off));
        this->backend->ReadAt(b.fd, buf.data(), n, off);
        if (!AllZero(buf.data(), n))
        {
          this->backend->WriteAt(fd, buf.data(), n, off);
        }
      }
    }
    catch (const StorageError&)
    {
      if (fd >= 0)
      {
        this->backend->Close(fd);
        try
        {
          this->backend->Remove(path);
        }
        catch (const StorageError&)
        {
        }
      }
      continue;
    }
    this->backend->Close(b.fd);
    try
    {
      this->backend->Remove(this->FilePath(b));
    }
    catch (const StorageError&)
    {
    }
    b.fd = fd;
    b.dir = moved.dir;
    b.fileSeq = moved.fileSeq;
    this->Note("temporary directory " + fromParent + ": " + why + ": block files go to " + parent);
    return true;
  }
  return false;
}

void DML::Impl::BackendTruncate(const Block& b, std::uint64_t n)
{
  try
  {
    this->backend->Truncate(b.fd, n);
  }
  catch (const StorageError& e)
  {
    this->Rethrow(e, b);
  }
}

namespace
{
std::string MiB(std::uint64_t bytes)
{
  char text[32];
  std::snprintf(text, sizeof(text), "%.1f MiB", double(bytes) / (1024.0 * 1024.0));
  return text;
}
} // namespace

void DML::Impl::Note(const std::string& text)
{
  auto& notes = this->stats.notes;
  if (std::find(notes.begin(), notes.end(), text) == notes.end() && notes.size() < 64)
  {
    notes.push_back(text);
  }
}

void DML::Impl::NoteFileBytes(std::uint64_t removed, std::uint64_t added)
{
  this->stats.fileBytes = this->stats.fileBytes - std::min(removed, this->stats.fileBytes) + added;
  this->stats.peakFileBytes = std::max(this->stats.peakFileBytes, this->stats.fileBytes);
}

// The profile's temporary directories, or the default one.
std::vector<std::string> DML::Impl::Directories() const
{
  return this->profile.directories.empty() ? std::vector<std::string>{ detail::DefaultDirectory() }
                                           : this->profile.directories;
}

std::size_t DML::Impl::DirIndex(const std::string& parent)
{
  std::size_t di = 0;
  while (di < this->dirs.size() &&
    std::string_view(this->dirs[di].parent.data(), this->dirs[di].parent.size()) != parent)
  {
    ++di;
  }
  if (di == this->dirs.size())
  {
    this->dirs.emplace_back(&this->acc);
    try
    {
      this->dirs.back().parent.assign(parent.data(), parent.size());
    }
    catch (...)
    {
      this->dirs.pop_back();
      throw;
    }
  }
  return di;
}

// Makes the private directory under dirs[di] if needed; false (and the reason kept) when the
// directory cannot be used.
bool DML::Impl::EnsureDirectory(std::size_t di)
{
  detail::PrivateDir& d = this->dirs[di];
  if (!d.reason.empty())
  {
    return false;
  }
  if (!d.path.empty())
  {
    return true;
  }
  const std::string parent(d.parent.data(), d.parent.size());
  std::string path;
  try
  {
    path = detail::MakePrivateDirectory(parent);
  }
  catch (const StorageError& e)
  {
    const std::string why = e.OsError() ? detail::ErrnoText(e.OsError()) : std::string(e.what());
    d.reason.assign(why.data(), why.size());
    d.osError = e.OsError();
    return false;
  }
  try
  {
    d.path.assign(path.data(), path.size());
    struct stat st;
    d.device = ::stat(path.c_str(), &st) == 0 ? std::uint64_t(st.st_dev) : 0;
  }
  catch (...)
  {
    ::rmdir(path.c_str());
    throw;
  }
  return true;
}

// The bytes the block files on dirs[di]'s file system may still take there: their sizes less
// what they hold (sparse files fill as pages are written back).
std::uint64_t DML::Impl::PendingBytes(std::size_t di) const
{
  std::uint64_t pending = 0;
  for (const Block& b : this->blocks)
  {
    if (b.fd >= 0 && b.dir >= 0 &&
      this->dirs[static_cast<std::size_t>(b.dir)].device == this->dirs[di].device)
    {
      const std::uint64_t size = b.Bytes(), held = this->backend->AllocatedBytes(b.fd);
      pending += size > held ? size - held : 0;
    }
  }
  return pending;
}

// Whether `bytes` more of block files fit on dirs[di]'s file system (with what its block files
// may still take); else why not, in `why`.
bool DML::Impl::HasRoom(std::size_t di, std::uint64_t bytes, std::string* why) const
{
  const detail::PrivateDir& d = this->dirs[di];
  const std::uint64_t free = this->backend->FreeBytes(std::string(d.path.data(), d.path.size()));
  if (free == ~std::uint64_t(0))
  {
    return true;
  }
  const std::uint64_t pending = this->PendingBytes(di);
  if (free >= pending && free - pending >= bytes)
  {
    return true;
  }
  if (why)
  {
    *why = MiB(free) + " free" + (pending ? " (" + MiB(pending) + " of it promised to block files)" : "") +
      ", " + MiB(bytes) + " needed";
  }
  return false;
}

// Creates the block's file (size count * elementSize, sparse) in the next directory that can
// be used and has room for it; the others are skipped, and the user is told (notes).
void DML::Impl::CreateFile(BlockId id)
{
  const std::vector<std::string> candidates = this->Directories();
  const std::size_t start = std::size_t(this->nextDir++ % candidates.size());
  Block& b = this->blocks[static_cast<std::size_t>(id)];
  std::string problems;
  int osError = 0; // the first problem's
  bool tell = false; // a directory the user was not told about yet was skipped
  int fd = -1;
  for (std::size_t k = 0; k < candidates.size() && fd < 0; ++k)
  {
    const std::string& parent = candidates[(start + k) % candidates.size()];
    const std::size_t di = this->DirIndex(parent);
    std::string why;
    int error = ENOSPC;
    if (!this->EnsureDirectory(di))
    {
      why = std::string(this->dirs[di].reason.data(), this->dirs[di].reason.size());
      error = this->dirs[di].osError;
    }
    else if (this->HasRoom(di, b.Bytes(), &why))
    {
      b.dir = static_cast<std::int32_t>(di);
      b.fileSeq = this->nextFileSeq++;
      const std::string path = this->FilePath(b);
      try
      {
        fd = this->backend->Create(path);
      }
      catch (const StorageError& e)
      {
        why = e.OsError() ? detail::ErrnoText(e.OsError()) : std::string(e.what());
        error = e.OsError();
        if (e.OsError() != ENOSPC && e.OsError() != EDQUOT)
        {
          this->dirs[di].reason.assign(why.data(), why.size());
          this->dirs[di].osError = e.OsError();
        }
        b.dir = -1;
      }
    }
    if (fd < 0)
    {
      problems += (problems.empty() ? "" : "; ") + parent + ": " + why;
      osError = osError ? osError : error;
      tell |= !this->dirs[di].noted;
      this->dirs[di].noted = true;
    }
    else if (tell)
    {
      this->Note("temporary directory " + problems + ": block files go to " + parent);
    }
  }
  if (fd < 0)
  {
    throw StorageError("no temporary directory can take a block file of " + MiB(b.Bytes()) +
        " (" + problems + "); free some space or give a directory on a larger disk (--tmpdir)",
      candidates[start], osError);
  }
  b.fd = fd;
  this->NoteFileBytes(0, b.Bytes());
  try
  {
    this->BackendTruncate(b, b.Bytes());
    if (this->cache.built)
    {
      if (b.elementSize > this->cache.pageSize)
      {
        // Elements larger than the page: rebuild the cache with larger pages.
        if (this->cache.pinnedFrames > 0)
        {
          throw BudgetError("sipmss::storage: cannot enlarge pages while pages are pinned");
        }
        this->DestroyCache(true);
      }
      else
      {
        b.perPage = this->cache.pageSize / b.elementSize;
      }
    }
  }
  catch (...)
  {
    this->RemoveFile(b);
    throw;
  }
  this->cache.quotasDirty = true;
}

// Closes and removes the block's file (the block keeps its other state).
void DML::Impl::RemoveFile(Block& b)
{
  if (b.fd < 0)
  {
    return;
  }
  this->backend->Close(b.fd);
  b.fd = -1;
  this->NoteFileBytes(b.Bytes(), 0);
  const std::string path = this->FilePath(b);
  this->backend->Remove(path);
}

void DML::Impl::CloseRaw(BlockId id)
{
  this->CheckUnforked("CloseBlock");
  Block& b = this->blocks[static_cast<std::size_t>(id)];
  if (b.mem)
  {
    std::free(b.mem);
    b.mem = nullptr;
    this->acc.Release(HeapCost(b.capacityBytes));
  }
  if (b.fd >= 0)
  {
    this->DropBlockPages(id, 0);
    Block copy = b; // the slot is closed first so a failing Remove leaves a consistent DML
    b = Block{};
    this->cache.quotasDirty = true;
    this->RemoveFile(copy); // leftovers are removed with the private directory
    return;
  }
  b = Block{};
}

// In core: grows by realloc (the old and new buffers are both charged while realloc may copy).
// Returns false when the new size does not fit the budget.
void DML::Impl::ResizeInCore(Block& b, std::uint64_t count)
{
  const std::uint64_t newBytes = CheckedBytes(count, b.elementSize);
  const std::uint64_t oldBytes = b.Bytes();
  if (newBytes <= b.capacityBytes)
  {
    if (newBytes > oldBytes)
    {
      std::memset(b.mem + oldBytes, 0, newBytes - oldBytes);
    }
    else if (b.capacityBytes > 4096 && newBytes < b.capacityBytes / 4)
    {
      const std::uint64_t cap = std::max<std::uint64_t>(newBytes, 1);
      if (void* p = std::realloc(b.mem, cap)) // shrinking realloc does not copy
      {
        this->acc.Release(HeapCost(b.capacityBytes));
        this->acc.Add(HeapCost(cap));
        b.mem = static_cast<unsigned char*>(p);
        b.capacityBytes = cap;
      }
    }
    b.count = count;
    return;
  }
  std::uint64_t cap = std::max(newBytes, b.capacityBytes + b.capacityBytes / 2);
  if (!this->acc.Fits(HeapCost(cap)))
  {
    cap = newBytes;
  }
  this->acc.Charge(HeapCost(cap)); // throws BudgetError when it does not fit
  // A block of huge-page size moves to fresh memory advised for huge pages (realloc would move
  // its small pages as they are): the cell records of a clustering grow this way, and are then
  // accessed at random (in a shuffled input a TLB miss each on small pages; Lucy-size
  // clustering 1.4 s faster, docs/benchmarks.md). It starts on a huge page, so records of a
  // power-of-two size start on a cache line (cluster records: a face's update in two lines).
  void* p = nullptr;
  if (cap >= kHugeBlockBytes)
  {
    if (::posix_memalign(&p, kHugePageBytes, cap) != 0)
    {
      p = nullptr;
    }
    if (p)
    {
      AdviseHugePages(p, cap);
      std::memcpy(p, b.mem, oldBytes);
      std::free(b.mem);
    }
  }
  else
  {
    p = std::realloc(b.mem, cap);
  }
  if (!p)
  {
    this->acc.Release(HeapCost(cap));
    throw std::bad_alloc();
  }
  this->acc.Release(HeapCost(b.capacityBytes));
  b.mem = static_cast<unsigned char*>(p);
  b.capacityBytes = cap;
  AdviseHugePages(b.mem, cap);
  std::memset(b.mem + oldBytes, 0, newBytes - oldBytes);
  b.count = count;
}

void DML::Impl::ResizeRaw(BlockId id, std::uint64_t count)
{
  this->CheckUnforked("Resize");
  Block* b = &this->blocks[static_cast<std::size_t>(id)];
  const std::uint64_t newBytes = CheckedBytes(count, b->elementSize);
  if (b->mem)
  {
    const std::uint64_t grow = newBytes > b->capacityBytes ? HeapCost(newBytes) : 0;
    if (!this->NeedsSpill(grow))
    {
      this->ResizeInCore(*b, count);
      return;
    }
    if (this->profile.policy == ModePolicy::InCore)
    {
      throw BudgetError("sipmss::storage: growing the block to " + std::to_string(newBytes) +
        " bytes exceeds the memory budget and the mode is forced in core");
    }
    if (this->mode == Mode::InCore)
    {
      this->SwitchTo(Mode::OutOfCore);
      ++this->stats.reconfigurations;
    }
    else
    {
      this->SpillBlock(id);
    }
    b = &this->blocks[static_cast<std::size_t>(id)];
  }
  // On file: room first (else the file moves to a directory that has it), truncate (a failure
  // changes nothing), then drop or clear cached pages beyond the new end so regrown elements
  // read as zeros.
  const std::uint64_t oldBytes = b->Bytes();
  std::string why;
  if (newBytes > oldBytes && b->dir >= 0 &&
    !this->HasRoom(std::size_t(b->dir), newBytes - oldBytes, &why) &&
    !this->Relocate(*b, newBytes, why))
  {
    throw StorageError("temporary directory " +
        std::string(this->dirs[std::size_t(b->dir)].parent.data(),
          this->dirs[std::size_t(b->dir)].parent.size()) +
        ": no room to grow a block file to " + MiB(newBytes) + " (" + why +
        ") and no other directory has it; free some space or give a directory on a larger disk "
        "(--tmpdir)",
      this->FilePath(*b), ENOSPC);
  }
  this->BackendTruncate(*b, newBytes);
  this->NoteFileBytes(oldBytes, newBytes);
  if (count < b->count && this->cache.built)
  {
    const std::uint64_t per = b->perPage;
    this->DropBlockPages(id, (count + per - 1) / per);
    if (count % per != 0)
    {
      const std::int32_t fi = this->Lookup(id, count / per);
      if (fi >= 0)
      {
        const std::uint64_t keep = (count % per) * b->elementSize;
        std::memset(this->cache.frames[static_cast<std::size_t>(fi)].data + keep, 0,
          this->PageBytes(*b) - keep);
      }
    }
  }
  b->count = count;
  this->cache.quotasDirty = true;
}

// Moves an in-core block to a new file. All-zero runs are not written: the file stays sparse.
void DML::Impl::SpillBlock(BlockId id)
{
  this->CreateFile(id);
  Block& b = this->blocks[static_cast<std::size_t>(id)];
  try
  {
    constexpr std::uint64_t kChunk = 1 << 16;
    const std::uint64_t bytes = b.Bytes();
    for (std::uint64_t off = 0; off < bytes; off += kChunk)
    {
      const std::uint64_t n = std::min(kChunk, bytes - off);
      if (!AllZero(b.mem + off, n))
      {
        this->BackendWrite(b, b.mem + off, n, off);
      }
    }
  }
  catch (...)
  {
    try
    {
      this->RemoveFile(b);
    }
    catch (...)
    {
    }
    throw;
  }
  std::free(b.mem);
  b.mem = nullptr;
  this->acc.Release(HeapCost(b.capacityBytes));
  b.capacityBytes = 0;
}

// Reads a file-backed block (whose pages are not cached) into memory and removes its file.
void DML::Impl::LoadBlock(BlockId id)
{
  Block& b = this->blocks[static_cast<std::size_t>(id)];
  const std::uint64_t cap = std::max<std::uint64_t>(b.Bytes(), 1);
  this->acc.Charge(HeapCost(cap));
  auto* mem = static_cast<unsigned char*>(std::malloc(cap));
  if (!mem)
  {
    this->acc.Release(HeapCost(cap));
    throw std::bad_alloc();
  }
  AdviseHugePages(mem, cap);
  try
  {
    this->BackendRead(b, mem, b.Bytes(), 0);
  }
  catch (...)
  {
    std::free(mem);
    this->acc.Release(HeapCost(cap));
    throw;
  }
  b.mem = mem;
  b.capacityBytes = cap;
  b.ClearRecent();
  this->RemoveFile(b);
}

// Cost of holding every open block in core now: metadata plus the blocks' bytes.
std::uint64_t DML::Impl::CostInCore() const
{
  std::uint64_t c = this->acc.held - this->CacheCost();
  for (const auto& b : this->blocks)
  {
    if (b.kind == Kind::Plain)
    {
      c += HeapCost(std::max<std::uint64_t>(b.Bytes(), 1));
      if (b.mem)
      {
        c -= HeapCost(b.capacityBytes);
      }
    }
  }
  return c;
}

void DML::Impl::SwitchTo(Mode target)
{
  if (target == Mode::OutOfCore)
  {
    this->mode = Mode::OutOfCore; // new blocks go to files even if a spill below fails
    this->stats.usedOutOfCore = true;
    for (std::size_t i = 0; i < this->blocks.size(); ++i)
    {
      if (this->blocks[i].mem && this->blocks[i].kind == Kind::Plain)
      {
        this->SpillBlock(static_cast<BlockId>(i));
      }
    }
    return;
  }
  this->DestroyCache(true); // writes dirty pages back, frees every frame
  for (std::size_t i = 0; i < this->blocks.size(); ++i)
  {
    if (this->blocks[i].fd >= 0)
    {
      this->LoadBlock(static_cast<BlockId>(i));
    }
  }
  // No file is left: remove the private directories too (made again by the next spill), so an
  // in-core phase leaves nothing on disk even if the process is killed.
  for (auto& d : this->dirs)
  {
    if (!d.path.empty())
    {
      const std::string p(d.path.data(), d.path.size());
      if (::rmdir(p.c_str()) == 0 || errno == ENOENT)
      {
        d.path.clear();
      }
    }
  }
  this->mode = Mode::InCore;
  this->stats.usedInCore = true;
}

void DML::Impl::Transfer(BlockId id, Block& b, std::uint64_t off, std::uint64_t n,
  unsigned char* buf, bool write, bool once)
{
  if (n == 0)
  {
    return; // buf may be null (an empty vector's data())
  }
  if (b.mem)
  {
    if (write)
    {
      std::memcpy(b.mem + off, buf, n);
    }
    else
    {
      std::memcpy(buf, b.mem + off, n);
    }
    return;
  }
  this->EnsureCache();
  const std::uint64_t pb = this->PageBytes(b);
  const std::uint64_t end = off + n;
  // A bulk transfer (a sixteenth of a page or more) reads and writes the pages that are not
  // cached straight from and to the file, whole or in part (the file is authoritative for
  // them): streaming does not flush the cache, and a range that starts or ends inside a page (a
  // bucket's buffer, a sorter's segment) would otherwise read that whole page into the cache,
  // to write back part of it, or to read it again for the neighbouring range (the shuffled
  // Lucy-size layout step read 1.6 times its bytes). A transfer of data read once (`once`) is
  // bulk whatever its size: a sorter's segments, each in a page of other buckets' segments.
  const bool bulk = once || n >= pb / 16;
  while (off < end)
  {
    const std::uint64_t page = off / pb;
    const std::uint64_t pageEnd = (page + 1) * pb;
    if (bulk && this->Lookup(id, page) < 0)
    {
      std::uint64_t stop = std::min(end, pageEnd), last = page + 1;
      while (stop < end && this->Lookup(id, last) < 0)
      {
        stop = std::min(end, (last + 1) * pb);
        ++last;
      }
      if (write)
      {
        this->BackendWrite(b, buf, stop - off, off);
      }
      else
      {
        this->BackendRead(b, buf, stop - off, off);
      }
      this->stats.misses += last - page;
      b.io.misses += last - page;
      buf += stop - off;
      off = stop;
      continue;
    }
    // (a cached page; or a small transfer, whose page is cached for the accesses around it)
    const std::uint64_t chunk = std::min(end, pageEnd) - off;
    const bool full = off == page * pb && end >= pageEnd;
    unsigned char* data = this->PageFor(id, b, page, write, !(write && full)) + (off - page * pb);
    if (write)
    {
      std::memcpy(data, buf, chunk);
    }
    else
    {
      std::memcpy(buf, data, chunk);
    }
    off += chunk;
    buf += chunk;
  }
}

// ------------------------------------------------------------------------------------------------
DML::DML()
  : DML(FileBackend::CreatePosix())
{
}

DML::DML(std::unique_ptr<FileBackend> backend)
  : impl_(std::make_unique<Impl>(backend ? std::move(backend) : FileBackend::CreatePosix()))
{
  this->impl_->owner = this; // DML is neither copyable nor movable: the pointer stays valid
}

DML::~DML() = default;

namespace
{
// The cost of a profile's structures (C without the DML's metadata and open blocks), and the
// mode C decides under the profile's policy and budget: Config's rule, shared with PlannedMode.
std::uint64_t StructuresCost(const Profile& profile)
{
  std::uint64_t c = HeapCost(sizeof(Block) * (profile.structures.size() + 1));
  for (const auto& s : profile.structures)
  {
    c += HeapCost(CheckedBytes(s.maxCount, std::max<std::size_t>(s.elementSize, 1)));
  }
  return c;
}

Mode ModeFor(const Profile& profile, std::uint64_t c)
{
  const std::uint64_t B = profile.memoryBudget;
  return profile.policy == ModePolicy::OutOfCore ||
      (profile.policy == ModePolicy::Automatic && B != 0 && c > B)
    ? Mode::OutOfCore
    : Mode::InCore;
}
} // namespace

Mode PlannedMode(const Profile& profile)
{
  // (Config's C on a DML that holds nothing but this profile)
  return ModeFor(profile, detail::ProfileHeapCost(profile) + StructuresCost(profile));
}

Mode DML::Config(const Profile& profile)
{
  Impl& I = *this->impl_;
  I.CheckUnforked("Config");
  detail::BaseSync sync(I);
  if (I.cache.pinnedFrames > 0)
  {
    throw std::logic_error("sipmss::storage: Config while pages are pinned");
  }
  // Replace the stored profile (its heap bytes are metadata).
  const std::uint64_t estimate = detail::ProfileHeapCost(profile);
  I.acc.Charge(estimate);
  try
  {
    I.profile = profile;
  }
  catch (...)
  {
    I.acc.Release(estimate);
    throw;
  }
  I.acc.Release(I.profileCost + estimate);
  I.profileCost = detail::ProfileHeapCost(I.profile);
  I.acc.Add(I.profileCost);

  // C = sum(elementSize * maxCount) + metadata; never less than what is open now.
  std::uint64_t c = I.acc.held - I.CacheCost() + StructuresCost(profile);
  for (const auto& b : I.blocks)
  {
    if (b.mem)
    {
      c -= HeapCost(b.capacityBytes);
    }
  }
  I.stats.declaredBytes = 0;
  for (const auto& s : profile.structures)
  {
    I.stats.declaredBytes += CheckedBytes(s.maxCount, s.elementSize);
  }
  c = std::max(c, I.CostInCore());
  const std::uint64_t B = profile.memoryBudget;
  const Mode target = ModeFor(profile, c);

  // Drop the cache (its size and page size follow the budget and policy), move the blocks
  // without a limit (moving out frees memory), then apply the new budget, also on failure.
  I.DestroyCache(true);
  struct ApplyBudget
  {
    detail::Accountant& acc;
    std::uint64_t budget;
    ~ApplyBudget() { this->acc.budget = this->budget; }
  } apply{ I.acc, B };
  I.acc.budget = 0;
  if (target == Mode::OutOfCore)
  {
    I.SwitchTo(Mode::OutOfCore);
  }
  else if (B == 0 || I.CostInCore() <= B)
  {
    I.SwitchTo(Mode::InCore);
  }
  else
  {
    throw BudgetError("sipmss::storage: the open blocks exceed the budget and the mode is "
                      "forced in core");
  }
  I.acc.budget = B;
  if (B != 0 && I.acc.held > B)
  {
    throw BudgetError("sipmss::storage: memory budget " + std::to_string(B) +
      " is below the DML's metadata (" + std::to_string(I.acc.held) + " bytes)");
  }
  I.acc.peak = I.acc.held;
  I.stats.reconfigurations = 0;
  I.stats.usedInCore = I.mode == Mode::InCore;
  I.stats.usedOutOfCore = I.mode == Mode::OutOfCore;
  return I.mode;
}

Mode DML::Reconfigure()
{
  Impl& I = *this->impl_;
  I.CheckUnforked("Reconfigure");
  detail::BaseSync sync(I);
  if (I.cache.pinnedFrames > 0)
  {
    return I.mode; // pinned pages cannot move
  }
  const std::uint64_t B = I.acc.budget;
  const std::uint64_t c = I.CostInCore();
  const ModePolicy policy = I.profile.policy;
  const Mode before = I.mode;
  if (policy != ModePolicy::OutOfCore && (B == 0 || c <= B))
  {
    bool anyOnFile = false;
    for (const auto& b : I.blocks)
    {
      anyOnFile = anyOnFile || b.fd >= 0;
    }
    if (before == Mode::OutOfCore || anyOnFile)
    {
      I.SwitchTo(Mode::InCore);
    }
  }
  else if (policy != ModePolicy::InCore && B != 0 && c > B)
  {
    I.SwitchTo(Mode::OutOfCore);
  }
  if (I.mode != before)
  {
    ++I.stats.reconfigurations;
  }
  return I.mode;
}

Mode DML::GetMode() const
{
  return this->impl_->mode;
}

Stats DML::GetStats() const
{
  Stats s = this->impl_->stats;
  s.hits += this->fastHits_;
  s.mode = this->impl_->mode;
  s.bytesHeld = this->impl_->acc.held;
  s.peakBytes = this->impl_->acc.peak;
  return s;
}

namespace
{
std::atomic<void (*)(std::int64_t)> gMappedHook{ nullptr }; // DMLTestAccess::SetMappedHook
} // namespace

void* AllocateReturnable(std::size_t bytes)
{
  if (bytes < kReturnableMapBytes)
  {
    return ::operator new(bytes);
  }
  void* p = ::mmap(nullptr, bytes, PROT_READ | PROT_WRITE, MAP_PRIVATE | MAP_ANONYMOUS, -1, 0);
  if (p == MAP_FAILED)
  {
    throw std::bad_alloc();
  }
  if (auto hook = gMappedHook.load(std::memory_order_relaxed))
  {
    hook(static_cast<std::int64_t>(bytes));
  }
  return p;
}

void FreeReturnable(void* p, std::size_t bytes) noexcept
{
  if (!p)
  {
    return;
  }
  if (bytes < kReturnableMapBytes)
  {
    ::operator delete(p);
  }
  else
  {
    ::munmap(p, bytes);
    if (auto hook = gMappedHook.load(std::memory_order_relaxed))
    {
      hook(-static_cast<std::int64_t>(bytes));
    }
  }
}

void DML::ChargeMemory(std::uint64_t bytes)
{
  Impl& I = *this->impl_;
  if (I.mode == Mode::OutOfCore)
  {
    I.EnsureCache(); // sized before the charge: the frames' table keeps its slots afterwards
  }
  I.acc.Charge(HeapCost(bytes));
}

void DML::ReleaseMemory(std::uint64_t bytes) noexcept
{
  this->impl_->acc.Release(HeapCost(bytes));
}

std::uint64_t DML::SpareMemory(std::uint32_t keepPages)
{
  Impl& I = *this->impl_;
  if (I.acc.budget == 0)
  {
    // Unbounded: in core anything; forced out of core, the unbounded page pool's size.
    return I.mode == Mode::OutOfCore ? detail::kUnboundedPool : std::uint64_t(1) << 62;
  }
  std::uint64_t spare = I.acc.Room();
  if (I.mode == Mode::OutOfCore)
  {
    I.EnsureCache();
    const detail::Cache& C = I.cache;
    const std::uint64_t keep = std::uint64_t(keepPages) + C.pinnedFrames;
    if (C.withData > keep)
    {
      spare += (C.withData - keep) * HeapCost(C.pageSize);
    }
    else
    {
      const std::uint64_t missing = (keep - C.withData) * HeapCost(C.pageSize);
      spare = spare > missing ? spare - missing : 0;
    }
  }
  // What ChargeMemory adds to a request (the allocator's overhead) stays out of the answer.
  return spare > 4096 + 32 ? spare - 4096 - 32 : 0;
}

std::size_t DML::PageBytes()
{
  Impl& I = *this->impl_;
  if (I.mode != Mode::OutOfCore)
  {
    return 0;
  }
  I.EnsureCache();
  return I.cache.pageSize;
}

const Profile& DML::GetProfile() const
{
  return this->impl_->profile;
}

BlockId DML::OpenBlock(std::size_t elementSize, std::uint64_t count, double weight)
{
  detail::BaseSync sync(*this->impl_);
  return this->impl_->OpenRaw(Kind::Plain, elementSize, count, weight);
}

void DML::CloseBlock(BlockId id)
{
  Impl& I = *this->impl_;
  detail::BaseSync sync(I);
  if (id < 0 || static_cast<std::size_t>(id) >= I.blocks.size() ||
    I.blocks[static_cast<std::size_t>(id)].kind != Kind::Plain)
  {
    throw std::invalid_argument("sipmss::storage: invalid block id " + std::to_string(id));
  }
  I.CloseRaw(id);
}

void DML::Resize(BlockId id, std::uint64_t count)
{
  Impl& I = *this->impl_;
  detail::BaseSync sync(I);
  I.Get(id, Kind::Plain);
  I.ResizeRaw(id, count);
}

std::uint64_t DML::Count(BlockId id) const
{
  const Impl& I = *this->impl_;
  return I.Get(id, Kind::Plain).count;
}

BlockStats DML::GetBlockStats(BlockId id) const
{
  return this->impl_->Get(id, Kind::Plain).io;
}

std::size_t DML::ElementSize(BlockId id) const
{
  const Impl& I = *this->impl_;
  return I.Get(id, Kind::Plain).elementSize;
}

namespace
{
[[noreturn]] __attribute__((noinline, cold)) void ThrowElement(
  const Block* b, BlockId id, std::size_t elementSize, std::uint64_t index)
{
  if (!b)
  {
    throw std::invalid_argument("sipmss::storage: invalid block id " + std::to_string(id));
  }
  if (elementSize != b->elementSize)
  {
    throw std::invalid_argument("sipmss::storage: element size " + std::to_string(elementSize) +
      " does not match block " + std::to_string(id) + " (" + std::to_string(b->elementSize) + ")");
  }
  throw std::out_of_range("sipmss::storage: index " + std::to_string(index) +
    " out of range of block " + std::to_string(id));
}

// The checks of every element access, inline (the throws are out of line).
inline Block& CheckElement(DML::Impl& I, BlockId id, std::size_t elementSize, std::uint64_t index)
{
  if (static_cast<std::size_t>(id) >= I.blocks.size() ||
    I.blocks[static_cast<std::size_t>(id)].kind != Kind::Plain)
  {
    ThrowElement(nullptr, id, elementSize, index);
  }
  Block& b = I.blocks[static_cast<std::size_t>(id)];
  if (elementSize != b.elementSize || index >= b.count)
  {
    ThrowElement(&b, id, elementSize, index);
  }
  return b;
}

Block& CheckRange(DML::Impl& I, BlockId id, std::uint64_t first, std::uint64_t count)
{
  Block& b = I.Get(id, Kind::Plain);
  if (first > b.count || count > b.count - first)
  {
    throw std::out_of_range("sipmss::storage: range out of bounds of block " + std::to_string(id));
  }
  return b;
}
} // namespace

// The slow paths of the inline Read/Write (DML.h), which serve the pages in the published table:
// here in core, checks, and any other page (PageFor keeps its own recent pages too).
void DML::ReadElement(BlockId id, std::size_t elementSize, std::uint64_t index, void* dst)
{
  Impl& I = *this->impl_;
  Block& b = CheckElement(I, id, elementSize, index);
  if (b.mem)
  {
    std::memcpy(dst, b.mem + index * elementSize, elementSize);
    return;
  }
  I.EnsureCache();
  const std::uint64_t page = index / b.perPage;
  const unsigned char* data = I.PageFor(id, b, page, false, true);
  std::memcpy(dst, data + (index - page * b.perPage) * elementSize, elementSize);
}

void DML::WriteElement(BlockId id, std::size_t elementSize, std::uint64_t index, const void* src)
{
  Impl& I = *this->impl_;
  Block& b = CheckElement(I, id, elementSize, index);
  if (b.mem)
  {
    std::memcpy(b.mem + index * elementSize, src, elementSize);
    return;
  }
  I.EnsureCache();
  const std::uint64_t page = index / b.perPage;
  unsigned char* data = I.PageFor(id, b, page, true, true);
  std::memcpy(data + (index - page * b.perPage) * elementSize, src, elementSize);
}

void DML::ReadRangeSlow(BlockId id, std::uint64_t first, std::uint64_t count, void* dst)
{
  Impl& I = *this->impl_;
  Block& b = CheckRange(I, id, first, count);
  I.Transfer(id, b, first * b.elementSize, count * b.elementSize, static_cast<unsigned char*>(dst),
    false);
}

void DML::ReadRangeOnce(BlockId id, std::uint64_t first, std::uint64_t count, void* dst)
{
  Impl& I = *this->impl_;
  Block& b = CheckRange(I, id, first, count);
  I.Transfer(id, b, first * b.elementSize, count * b.elementSize, static_cast<unsigned char*>(dst),
    false, true);
}

void DML::WriteRangeSlow(BlockId id, std::uint64_t first, std::uint64_t count, const void* src)
{
  Impl& I = *this->impl_;
  Block& b = CheckRange(I, id, first, count);
  I.Transfer(id, b, first * b.elementSize, count * b.elementSize,
    static_cast<unsigned char*>(const_cast<void*>(src)), true);
}

void DML::Fill(BlockId id, const void* element)
{
  Impl& I = *this->impl_;
  I.CheckUnforked("Fill");
  Block& b = I.Get(id, Kind::Plain);
  const std::size_t es = b.elementSize;
  const auto* e = static_cast<const unsigned char*>(element);
  const bool zero = AllZero(e, es);
  const auto fillPattern = [&](unsigned char* dst, std::uint64_t elements)
  {
    if (zero || elements == 0)
    {
      std::memset(dst, 0, elements * es);
      return;
    }
    std::memcpy(dst, e, es);
    for (std::uint64_t done = 1; done < elements;) // doubling copies
    {
      const std::uint64_t n = std::min(done, elements - done);
      std::memcpy(dst + done * es, dst, n * es);
      done += n;
    }
  };
  if (b.mem)
  {
    fillPattern(b.mem, b.count);
    return;
  }
  if (b.count == 0)
  {
    return;
  }
  if (zero)
  {
    // Zero fill of a file: drop its pages and punch everything out by truncation.
    I.DropBlockPages(id, 0);
    I.BackendTruncate(b, 0);
    I.BackendTruncate(b, b.Bytes());
    return;
  }
  I.EnsureCache();
  const std::uint64_t per = b.perPage;
  const std::uint64_t pages = (b.count + per - 1) / per;
  const auto valid = [&](std::uint64_t page) { return std::min(per, b.count - page * per); };
  // Fill resident pages in place (page 0 is made resident and becomes the pattern), then write
  // the pattern page directly to every page that is not cached.
  const std::int32_t pattern = I.PinPage(id, b, 0, true);
  try
  {
    for (auto& f : I.cache.frames)
    {
      if (f.block == id)
      {
        fillPattern(f.data, valid(f.page));
        f.dirty = true;
      }
    }
    const unsigned char* src = I.cache.frames[static_cast<std::size_t>(pattern)].data;
    for (std::uint64_t p = 1; p < pages; ++p)
    {
      if (I.Lookup(id, p) < 0)
      {
        I.BackendWrite(b, src, valid(p) * es, p * per * es);
      }
    }
  }
  catch (...)
  {
    I.UnpinPage(id, 0);
    throw;
  }
  I.UnpinPage(id, 0);
}

namespace
{
// A child's view of its parent's backend: reads and writes only (the POSIX backend's are
// thread-safe: pread/pwrite on a descriptor).
class BorrowedBackend final : public FileBackend
{
public:
  explicit BorrowedBackend(FileBackend& b)
    : b_(b)
  {
  }
  int Create(const std::string&) override { throw std::logic_error("sipmss::storage: Create on a child DML"); }
  void Close(int) override {}
  void Remove(const std::string&) override { throw std::logic_error("sipmss::storage: Remove on a child DML"); }
  void ReadAt(int handle, void* dst, std::size_t bytes, std::uint64_t offset) override
  {
    this->b_.ReadAt(handle, dst, bytes, offset);
  }
  void WriteAt(int handle, const void* src, std::size_t bytes, std::uint64_t offset) override
  {
    this->b_.WriteAt(handle, src, bytes, offset);
  }
  void Truncate(int, std::uint64_t) override { throw std::logic_error("sipmss::storage: Truncate on a child DML"); }
  std::uint64_t AllocatedBytes(int handle) override { return this->b_.AllocatedBytes(handle); }
  std::uint64_t FreeBytes(const std::string& directory) override
  {
    return this->b_.FreeBytes(directory);
  }

private:
  FileBackend& b_;
};
} // namespace

std::unique_ptr<DML> DML::Fork(std::uint64_t bytes, const std::vector<Range>& childWrites)
{
  Impl& I = *this->impl_;
  I.CheckUnforked("Fork"); // (one child at a time, and no grandchildren)
  if (I.mode != Mode::OutOfCore)
  {
    return nullptr;
  }
  for (const Range& r : childWrites)
  {
    const Block& b = I.Get(r.id, Kind::Plain);
    if (r.first > b.count || r.count > b.count - r.first)
    {
      throw std::out_of_range("sipmss::storage: Fork range out of bounds of block " +
        std::to_string(r.id));
    }
    for (const Range& o : childWrites)
    {
      if (&o != &r && o.id == r.id)
      {
        throw std::invalid_argument("sipmss::storage: Fork takes one range per block");
      }
    }
  }
  detail::BaseSync sync(I);
  I.EnsureCache();
  // The child reads the files: write every dirty page back (the pages stay cached, clean).
  for (std::size_t i = 0; i < I.cache.frames.size(); ++i)
  {
    if (I.cache.frames[i].block >= 0 && I.cache.frames[i].dirty)
    {
      I.WriteBack(static_cast<std::int32_t>(i));
    }
  }
  std::unique_ptr<DML> child;
  bool charged = false;
  try
  {
    child = std::make_unique<DML>(std::make_unique<BorrowedBackend>(*I.backend));
    Impl& K = *child->impl_;
    K.forkParent = &I; // first: from here on the child never closes or removes a file
    K.lent = bytes;
    K.replacement = I.replacement;
    K.profile.policy = ModePolicy::OutOfCore;
    K.profile.memoryBudget = bytes;
    K.profile.pagePolicy = I.profile.pagePolicy;
    K.profile.pageSize = I.cache.pageSize;
    K.mode = Mode::OutOfCore;
    K.stats.usedOutOfCore = true;
    const std::size_t n = I.blocks.size();
    K.blocks.reserve(std::max<std::size_t>(n, 1));
    K.bases.reserve(std::max<std::size_t>(n, 1));
    K.fast.reserve(std::max<std::size_t>(n, 1));
    for (std::size_t i = 0; i < n; ++i)
    {
      const Block& src = I.blocks[i];
      Block b;
      if (src.kind == Kind::Plain && src.fd >= 0)
      {
        b.kind = Kind::Plain;
        b.elementSize = src.elementSize;
        b.count = src.count;
        b.weight = src.weight;
        b.fd = src.fd;
        b.dir = src.dir;
        b.fileSeq = src.fileSeq;
      }
      K.blocks.push_back(b);
    }
    K.acc.budget = bytes;
    if (K.acc.held > bytes)
    {
      throw BudgetError("sipmss::storage: " + std::to_string(bytes) +
        " bytes are too few for a forked DML's metadata (" + std::to_string(K.acc.held) + ")");
    }
    K.EnsureCache();
    for (std::size_t i = 0; i < n; ++i)
    {
      Block& b = K.blocks[i];
      if (b.kind == Kind::Plain)
      {
        b.perPage = I.blocks[i].perPage; // the same pages (the unit of Fork's contract)
        if (I.PageBytes(I.blocks[i]) > K.cache.pageSize)
        {
          throw std::logic_error("sipmss::storage: forked pages do not fit the child's frames");
        }
      }
    }
    // The child's page buffers are this DML's (moved, not freed and allocated again), and what
    // this DML lacks is allocated here, on this thread: a buffer the child's thread allocated
    // would come from that thread's malloc arena, where it stays resident once freed beside
    // what this thread's arena holds (about half the budget more peak RSS).
    if (K.cache.pageSize == I.cache.pageSize)
    {
      while (K.cache.freeEmpty >= 0 && K.acc.Fits(HeapCost(K.cache.pageSize)))
      {
        unsigned char* data = I.TakeBuffer();
        if (!data)
        {
          data = static_cast<unsigned char*>(std::malloc(K.cache.pageSize));
        }
        if (!data)
        {
          break;
        }
        if (!K.GiveBuffer(data))
        {
          if (!I.GiveBuffer(data))
          {
            std::free(data);
          }
          break;
        }
      }
    }
    K.SyncBases();
    I.acc.Charge(bytes); // evicts (and frees) more pages of this DML if needed
    charged = true;
    for (const Range& r : childWrites)
    {
      for (Block* b : { &I.blocks[static_cast<std::size_t>(r.id)],
             &K.blocks[static_cast<std::size_t>(r.id)] })
      {
        b->forkFirst = r.first;
        b->forkEnd = r.first + r.count;
      }
    }
  }
  catch (...)
  {
    child.reset();
    if (charged)
    {
      I.acc.Release(bytes);
    }
    throw;
  }
  ++I.children;
  child->impl_->attached = true;
  return child;
}

void DML::Join(DML& child)
{
  Impl& I = *this->impl_;
  Impl& K = *child.impl_;
  if (K.forkParent != &I)
  {
    throw std::logic_error("sipmss::storage: Join of a DML that is not a child of this one");
  }
  detail::BaseSync sync(I);
  std::exception_ptr error;
  for (std::size_t i = 0; i < K.cache.frames.size() && !error; ++i)
  {
    if (K.cache.frames[i].block >= 0 && K.cache.frames[i].dirty)
    {
      try
      {
        K.WriteBack(static_cast<std::int32_t>(i));
      }
      catch (...)
      {
        error = std::current_exception();
      }
    }
  }
  I.acc.Release(K.lent);
  K.lent = 0;
  --I.children;
  K.attached = false;
  // The page buffers go back to this DML.
  if (K.cache.pageSize == I.cache.pageSize)
  {
    for (auto& f : K.cache.frames)
    {
      if (f.data && I.GiveBuffer(f.data))
      {
        f.data = nullptr;
        K.acc.Release(HeapCost(K.cache.pageSize));
      }
    }
  }
  K.DestroyCache(false);
  // This DML's copies of the child's elements may be stale: clean pages go, dirty ones (its own
  // elements beside the child's) read the child's part again.
  for (std::size_t i = 0; i < I.blocks.size(); ++i)
  {
    Block& b = I.blocks[i];
    if (b.forkFirst < b.forkEnd)
    {
      try
      {
        I.MergeChildRange(static_cast<BlockId>(i));
      }
      catch (...)
      {
        error = std::current_exception();
      }
      b.forkFirst = b.forkEnd = 0;
    }
  }
  I.stats.hits += K.stats.hits + child.fastHits_;
  I.stats.misses += K.stats.misses;
  I.stats.bytesRead += K.stats.bytesRead;
  I.stats.bytesWritten += K.stats.bytesWritten;
  ++I.stats.forks;
  for (std::size_t i = 0; i < K.blocks.size() && i < I.blocks.size(); ++i)
  {
    // (the child's blocks are the parent's, by the same ids)
    BlockStats& to = I.blocks[i].io;
    const BlockStats& from = K.blocks[i].io;
    to.misses += from.misses;
    to.bytesRead += from.bytesRead;
    to.bytesWritten += from.bytesWritten;
  }
  for (Block& b : K.blocks)
  {
    b = Block{};
  }
  K.SyncBases();
  K.forkParent = nullptr;
  child.fastHits_ = 0;
  if (error)
  {
    std::rethrow_exception(error);
  }
}

Span DML::Pin(BlockId id, std::uint64_t index, Access access)
{
  Impl& I = *this->impl_;
  Block& b = I.Get(id, Kind::Plain);
  if (index >= b.count)
  {
    throw std::out_of_range("sipmss::storage: pin index out of range of block " + std::to_string(id));
  }
  if (b.mem)
  {
    return Span{ b.mem + index * b.elementSize, index, b.count - index };
  }
  I.EnsureCache();
  const std::uint64_t page = index / b.perPage;
  const std::int32_t fi = I.PinPage(id, b, page, access == Access::Write);
  const std::uint64_t end = std::min((page + 1) * b.perPage, b.count);
  return Span{ I.cache.frames[static_cast<std::size_t>(fi)].data +
      (index - page * b.perPage) * b.elementSize,
    index, end - index };
}

void DML::Unpin(BlockId id, const Span& span)
{
  Impl& I = *this->impl_;
  Block& b = I.Get(id, Kind::Plain);
  if (b.mem || !I.cache.built || span.data == nullptr)
  {
    return; // in core pins are free
  }
  I.UnpinPage(id, span.first / b.perPage);
}

std::uint32_t DML::PinnablePages()
{
  Impl& I = *this->impl_;
  if (I.mode != Mode::OutOfCore)
  {
    return std::numeric_limits<std::uint32_t>::max();
  }
  I.EnsureCache();
  const std::uint64_t capacity = I.FrameCapacity(), held = std::uint64_t(I.cache.pinnedFrames) + 2;
  return capacity > held ? static_cast<std::uint32_t>(capacity - held) : 0;
}

std::string DML::PrivateDirectory() const
{
  for (const auto& d : this->impl_->dirs)
  {
    if (!d.path.empty())
    {
      return std::string(d.path.data(), d.path.size());
    }
  }
  return std::string();
}

// ------------------------------------------------------------------------------------------------
void DMLTestAccess::SetReplacement(DML& dml, Replacement r)
{
  dml.impl_->replacement = r;
}

std::size_t DMLTestAccess::PageSize(const DML& dml)
{
  return dml.impl_->cache.built ? dml.impl_->cache.pageSize : 0;
}

std::uint32_t DMLTestAccess::FrameSlots(const DML& dml)
{
  return static_cast<std::uint32_t>(dml.impl_->cache.frames.size());
}

std::uint64_t DMLTestAccess::FileBytes(const DML& dml, BlockId id)
{
  const Block& b = dml.impl_->Get(id, Kind::Plain);
  struct stat st{};
  if (b.fd < 0 || ::fstat(b.fd, &st) != 0)
  {
    return 0;
  }
  return static_cast<std::uint64_t>(st.st_size);
}

std::uint64_t DMLTestAccess::InlineHits(const DML& dml)
{
  return dml.fastHits_;
}

void DMLTestAccess::SetMappedHook(void (*hook)(std::int64_t bytes))
{
  gMappedHook.store(hook);
}

} // namespace sipmss::storage
