// The out-of-core page cache.
//
// Pages: every block is cut into pages of floor(pageSize / elementSize) elements, so an element
// never straddles two pages; element i lives at byte i * elementSize of the block's file. The
// page size is 64 KiB, halved while fewer than 16 pages would fit the budget (down to 512 bytes)
// and raised to the largest element size.
//
// Frames: a fixed table of frame slots sized from the budget left after metadata. A slot gets
// its page buffer lazily, charged to the accountant, so a small working set holds little memory;
// when metadata must grow, ReleaseFrames() gives buffers back (writing dirty pages first).
//
// Replacement by PagePolicy::Clock (the default): no shares. One clock hand goes round every
// frame slot, whatever block holds its page: a referenced page gets its bit cleared, the first
// unreferenced unpinned page goes (a dirty one is written back first; ClockVictim). A block gets
// as many pages as it keeps using, which the shares below did not give (docs/storage.md: a
// block's share, fixed while it was at it, froze the split of a phase's pages).
//
// Shares (PagePolicy::StaticWeight and Adaptive): each block has a quota of frames.
// StaticWeight follows the paper: the quota is proportional to the block's weight (its file size
// relative to the mean, or the weight given at OpenBlock). Adaptive re-weights every epoch by the
// block's recent re-reference misses (misses on pages it evicted recently, detected with a
// direct-mapped table of evicted page tags): a block that would profit from more frames gets
// them, a streaming block does not.
//
// Replacement with shares: a block below its quota takes a frame from the block most above its
// quota; otherwise it replaces one of its own pages. Inside a block the frames form a ring swept
// by a WSClock hand (Carr & Hennessy 1981): a referenced page gets its bit cleared and its time
// stamped; the first unreferenced clean page older than the working-set window tau is evicted.
// Clean unreferenced pages are preferred: old dirty pages are only collected, and written back a
// few together (the write batching of WSClock) when no old clean page turned up first. With no
// old page at all, the least recently stamped unreferenced page goes. The window tau is half the
// block's frame count, in units of the block's own misses (its virtual time).
#include "DMLImpl.h"

#include <algorithm>
#include <cstdlib>
#include <cstring>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace sipmss::storage
{

using detail::Block;
using detail::Frame;
using detail::HeapCost;
using detail::Kind;

namespace
{
// PagePolicy::Clock: the reference bits the hand clears at most on one fault (ClockVictim).
constexpr std::size_t kClockScan = 8;

std::uint64_t Pow2AtLeast(std::uint64_t n)
{
  std::uint64_t p = 1;
  while (p < n)
  {
    p <<= 1;
  }
  return p;
}

std::uint64_t Mix(std::uint64_t a, std::uint64_t b)
{
  std::uint64_t h = a * 0x9E3779B97F4A7C15ull ^ (b + 0x632BE59BD9B4E019ull) * 0xC2B2AE3D27D4EB4Full;
  return h ^ (h >> 29);
}

constexpr int kMaxWritesPerSweep = 4;
constexpr std::uint64_t kMinPage = 512;
constexpr std::uint64_t kMaxPage = std::uint64_t(64) * 1024;
constexpr std::uint64_t kTargetPages = 16;
// Per-slot metadata besides the page buffer: the Frame, <= 2 bucket entries, <= 4 ghost tags,
// <= 4 entries of the inline access's table.
constexpr std::uint64_t kSlotMeta = sizeof(Frame) + 2 * sizeof(std::int32_t) +
  4 * sizeof(std::uint64_t) + 4 * sizeof(FastEntry);
} // namespace

std::size_t DML::Impl::ChoosePageSize() const
{
  std::size_t maxElement = 1;
  for (const auto& b : this->blocks)
  {
    if (b.kind == Kind::Plain)
    {
      maxElement = std::max(maxElement, b.elementSize);
    }
  }
  for (const auto& s : this->profile.structures)
  {
    maxElement = std::max(maxElement, s.elementSize);
  }
  if (this->profile.pageSize != 0)
  {
    return std::max(this->profile.pageSize, maxElement);
  }
  const std::uint64_t avail = this->acc.budget ? this->acc.Room() : detail::kUnboundedPool;
  std::uint64_t ps = kMaxPage;
  while (ps > kMinPage && avail / (HeapCost(ps) + kSlotMeta) < kTargetPages)
  {
    ps /= 2;
  }
  return std::max<std::size_t>(static_cast<std::size_t>(ps), maxElement);
}

void DML::Impl::EnsureCache()
{
  detail::Cache& C = this->cache;
  if (C.built)
  {
    return;
  }
  C.pageSize = this->ChoosePageSize();
  const std::uint64_t avail = this->acc.budget ? this->acc.Room() : detail::kUnboundedPool;
  const std::uint64_t tables = 4 * HeapCost(0) + 64; // allocation overheads of the four tables
  const std::uint64_t slots =
    avail > tables ? (avail - tables) / (HeapCost(C.pageSize) + kSlotMeta) : 0;
  if (slots < 2)
  {
    throw BudgetError("sipmss::storage: memory budget too small for the out-of-core mode (" +
      std::to_string(avail) + " bytes left for pages of " + std::to_string(C.pageSize) + ")");
  }
  try
  {
    C.frames.assign(slots, Frame{});
    C.buckets.assign(Pow2AtLeast(slots), -1);
    C.table.assign(Pow2AtLeast(2 * slots), FastEntry{});
    if (this->profile.pagePolicy == PagePolicy::Adaptive)
    {
      C.ghosts.assign(Pow2AtLeast(2 * slots), 0);
    }
  }
  catch (...)
  {
    detail::CVector<Frame>(detail::Counted<Frame>(&this->acc)).swap(C.frames);
    detail::CVector<std::int32_t>(detail::Counted<std::int32_t>(&this->acc)).swap(C.buckets);
    detail::CVector<FastEntry>(detail::Counted<FastEntry>(&this->acc)).swap(C.table);
    throw;
  }
  for (std::size_t i = 0; i < slots; ++i)
  {
    C.frames[i].next = i + 1 < slots ? static_cast<std::int32_t>(i + 1) : -1;
  }
  C.freeEmpty = 0;
  C.freeData = -1;
  C.withData = 0;
  C.pinnedFrames = 0;
  C.epochMisses = 0;
  C.clockHand = 0;
  for (auto& b : this->blocks)
  {
    b.perPage = std::max<std::uint64_t>(1, C.pageSize / std::max<std::size_t>(b.elementSize, 1));
    b.ClearRecent();
    b.hand = -1;
    b.resident = 0;
  }
  C.built = true;
  C.quotasDirty = true;
  ++C.generation;
  this->SyncAllFast();
}

void DML::Impl::DestroyCache(bool writeBack)
{
  detail::Cache& C = this->cache;
  if (!C.built)
  {
    return;
  }
  if (writeBack)
  {
    for (std::size_t i = 0; i < C.frames.size(); ++i)
    {
      if (C.frames[i].block >= 0 && C.frames[i].dirty)
      {
        this->WriteBack(static_cast<std::int32_t>(i)); // a failure leaves the cache intact
      }
    }
  }
  for (auto& f : C.frames)
  {
    if (f.data)
    {
      std::free(f.data);
      this->acc.Release(HeapCost(C.pageSize));
    }
  }
  for (auto& b : this->blocks)
  {
    b.ClearRecent();
    b.hand = -1;
    b.resident = 0;
  }
  detail::CVector<Frame>(detail::Counted<Frame>(&this->acc)).swap(C.frames);
  detail::CVector<std::int32_t>(detail::Counted<std::int32_t>(&this->acc)).swap(C.buckets);
  detail::CVector<std::uint64_t>(detail::Counted<std::uint64_t>(&this->acc)).swap(C.ghosts);
  detail::CVector<FastEntry>(detail::Counted<FastEntry>(&this->acc)).swap(C.table);
  C.freeData = C.freeEmpty = -1;
  C.withData = C.pinnedFrames = 0;
  C.built = false;
  this->SyncAllFast();
}

std::uint64_t DML::Impl::CacheCost() const
{
  const detail::Cache& C = this->cache;
  std::uint64_t c = C.withData * HeapCost(C.pageSize);
  c += C.frames.capacity() ? HeapCost(C.frames.capacity() * sizeof(Frame)) : 0;
  c += C.buckets.capacity() ? HeapCost(C.buckets.capacity() * sizeof(std::int32_t)) : 0;
  c += C.ghosts.capacity() ? HeapCost(C.ghosts.capacity() * sizeof(std::uint64_t)) : 0;
  c += C.table.capacity() ? HeapCost(C.table.capacity() * sizeof(FastEntry)) : 0;
  return c;
}

// Frames that can hold pages now: those with buffers plus those the budget still allows.
std::uint32_t DML::Impl::FrameCapacity() const
{
  const detail::Cache& C = this->cache;
  const std::uint64_t empty = C.frames.size() - C.withData;
  const std::uint64_t affordable = this->acc.Room() / HeapCost(C.pageSize);
  return static_cast<std::uint32_t>(C.withData + std::min(empty, affordable));
}

std::int32_t DML::Impl::Lookup(BlockId id, std::uint64_t page) const
{
  const detail::Cache& C = this->cache;
  std::int32_t fi =
    C.buckets[Mix(static_cast<std::uint64_t>(id), page) & (C.buckets.size() - 1)];
  while (fi >= 0)
  {
    const Frame& f = C.frames[static_cast<std::size_t>(fi)];
    if (f.page == page && f.block == id)
    {
      return fi;
    }
    fi = f.hashNext;
  }
  return -1;
}

void DML::Impl::RingInsert(Block& b, std::int32_t fi)
{
  auto& F = this->cache.frames;
  Frame& f = F[static_cast<std::size_t>(fi)];
  if (b.hand < 0)
  {
    f.next = f.prev = fi;
    b.hand = fi;
    return;
  }
  // Just behind the hand: swept last (WSClock), most recently used end (LRU).
  const std::int32_t h = b.hand;
  const std::int32_t p = F[static_cast<std::size_t>(h)].prev;
  f.next = h;
  f.prev = p;
  F[static_cast<std::size_t>(p)].next = fi;
  F[static_cast<std::size_t>(h)].prev = fi;
}

void DML::Impl::RingRemove(Block& b, std::int32_t fi)
{
  auto& F = this->cache.frames;
  Frame& f = F[static_cast<std::size_t>(fi)];
  if (f.next == fi)
  {
    b.hand = -1;
  }
  else
  {
    F[static_cast<std::size_t>(f.prev)].next = f.next;
    F[static_cast<std::size_t>(f.next)].prev = f.prev;
    if (b.hand == fi)
    {
      b.hand = f.next;
    }
  }
  f.next = f.prev = -1;
}

bool DML::Impl::FastServed(BlockId id, const Block& b) const
{
  return b.kind == Kind::Plain && !b.mem && this->cache.built && !this->cache.table.empty() &&
    this->replacement != Replacement::Lru && // (LRU moves the frame on every access)
    id >= 0 && static_cast<std::uint64_t>(id) < kFastBlocks && b.perPage > 1 &&
    b.perPage < (std::uint64_t(1) << 24) && // (MulHigh exact: count * perPage < 2^64)
    b.count < (std::uint64_t(1) << 39);
}

void DML::Impl::FastInstall(BlockId id, const Block& b, std::int32_t fi)
{
  if (!this->FastServed(id, b))
  {
    return;
  }
  const Frame& f = this->cache.frames[static_cast<std::size_t>(fi)];
  auto& T = this->cache.table;
  FastEntry& e = T[(f.page + FastSalt(id)) & (T.size() - 1)];
  e.tag = f.page | FastTagBase(id, this->cache.generation) | (f.dirty ? kFastWritable : 0);
  e.data = f.data;
}

// The table's entry of frame fi's page when it names that frame (nullptr otherwise).
FastEntry* DML::Impl::FastEntryOf(std::int32_t fi)
{
  auto& T = this->cache.table;
  const Frame& f = this->cache.frames[static_cast<std::size_t>(fi)];
  if (T.empty() || f.block < 0)
  {
    return nullptr;
  }
  FastEntry& e = T[(f.page + FastSalt(f.block)) & (T.size() - 1)];
  const bool ours = (e.tag | kFastWritable) ==
    (f.page | FastTagBase(f.block, this->cache.generation) | kFastWritable);
  return ours ? &e : nullptr;
}

void DML::Impl::FastRemove(std::int32_t fi)
{
  if (FastEntry* e = this->FastEntryOf(fi))
  {
    *e = FastEntry{};
  }
}

void DML::Impl::FastClearWrite(std::int32_t fi)
{
  if (FastEntry* e = this->FastEntryOf(fi))
  {
    e->tag &= ~kFastWritable;
  }
}

unsigned char* DML::Impl::PageFor(BlockId id, Block& b, std::uint64_t page, bool write, bool fetch)
{
  std::int32_t fi = -1;
  if (b.recentFrame[0] >= 0 && b.recentPage[0] == page)
  {
    fi = b.recentFrame[0];
    ++this->stats.hits;
  }
  else
  {
    // One of the other recent pages, else the hash table, else a fault (which may evict some of
    // the recent pages: Evict clears their entries). The page becomes the most recent.
    std::size_t k = 1;
    while (k < detail::kRecentPages && !(b.recentFrame[k] >= 0 && b.recentPage[k] == page))
    {
      ++k;
    }
    if (k < detail::kRecentPages)
    {
      fi = b.recentFrame[k];
      ++this->stats.hits;
    }
    else
    {
      k = detail::kRecentPages - 1; // the oldest entry goes
      fi = this->Lookup(id, page);
      if (fi >= 0)
      {
        ++this->stats.hits;
      }
      else
      {
        fi = this->Fault(id, b, page, fetch);
        ++this->stats.misses;
        ++b.io.misses;
      }
    }
    for (; k > 0; --k)
    {
      b.recentFrame[k] = b.recentFrame[k - 1];
      b.recentPage[k] = b.recentPage[k - 1];
    }
    b.recentFrame[0] = fi;
    b.recentPage[0] = page;
  }
  Frame& f = this->cache.frames[static_cast<std::size_t>(fi)];
  f.ref = true;
  f.dirty = f.dirty || write;
  this->FastInstall(id, b, fi);
  if (this->replacement == Replacement::Lru && b.hand >= 0)
  {
    // Move to the most recently used end (just behind the hand, which marks the LRU end).
    if (b.hand == fi)
    {
      b.hand = f.next;
    }
    else if (this->cache.frames[static_cast<std::size_t>(b.hand)].prev != fi)
    {
      this->RingRemove(b, fi);
      this->RingInsert(b, fi);
    }
  }
  return f.data;
}

std::int32_t DML::Impl::Fault(BlockId id, Block& b, std::uint64_t page, bool fetch)
{
  detail::Cache& C = this->cache;
  const std::int32_t fi = this->AcquireFrame(id);
  Frame& f = C.frames[static_cast<std::size_t>(fi)];
  const std::uint64_t pb = this->PageBytes(b);
  const std::uint64_t first = page * pb;
  const std::uint64_t valid = std::min(pb, b.Bytes() - first);
  if (fetch)
  {
    try
    {
      this->BackendRead(b, f.data, valid, first);
    }
    catch (...)
    {
      f.next = C.freeData;
      C.freeData = fi;
      throw;
    }
  }
  if (valid < pb)
  {
    std::memset(f.data + valid, 0, pb - valid); // bytes past the end stay zero
  }
  f.block = id;
  f.page = page;
  f.ref = true;
  f.dirty = false;
  f.pins = 0;
  f.lastUse = b.vtime++;
  const std::size_t bucket = Mix(static_cast<std::uint64_t>(id), page) & (C.buckets.size() - 1);
  f.hashNext = C.buckets[bucket];
  C.buckets[bucket] = fi;
  this->RingInsert(b, fi);
  ++b.resident;

  if (!C.ghosts.empty())
  {
    // Adaptive: a miss on a page this block evicted recently means more frames would help.
    const std::uint64_t tag = Mix(b.fileSeq + 1, page) | 1;
    std::uint64_t& g = C.ghosts[tag & (C.ghosts.size() - 1)];
    if (g == tag)
    {
      ++b.ghostHits;
      g = 0;
    }
    if (++C.epochMisses >= std::max<std::uint64_t>(64, C.frames.size()))
    {
      C.epochMisses = 0;
      for (auto& blk : this->blocks)
      {
        blk.score = 0.5 * blk.score + static_cast<double>(blk.ghostHits);
        blk.ghostHits = 0;
      }
      C.quotasDirty = true;
    }
  }
  return fi;
}

std::int32_t DML::Impl::AcquireFrame(BlockId requester)
{
  detail::Cache& C = this->cache;
  if (C.freeData < 0 && C.freeEmpty >= 0 && this->acc.TryCharge(HeapCost(C.pageSize)))
  {
    void* data = std::malloc(C.pageSize);
    if (data)
    {
      const std::int32_t fi = C.freeEmpty;
      Frame& f = C.frames[static_cast<std::size_t>(fi)];
      C.freeEmpty = f.next;
      f.data = static_cast<unsigned char*>(data);
      f.next = C.freeData;
      C.freeData = fi;
      ++C.withData;
    }
    else
    {
      this->acc.Release(HeapCost(C.pageSize));
    }
  }
  if (C.freeData < 0)
  {
    const std::int32_t victim = this->FindVictim(requester);
    if (victim < 0)
    {
      throw BudgetError("sipmss::storage: every cache page is pinned; the memory budget allows " +
        std::to_string(this->FrameCapacity()) + " pages");
    }
    this->Evict(victim, true); // puts it on freeData
  }
  const std::int32_t fi = C.freeData;
  C.freeData = C.frames[static_cast<std::size_t>(fi)].next;
  C.frames[static_cast<std::size_t>(fi)].next = -1;
  return fi;
}

void DML::Impl::RecomputeQuotas()
{
  detail::Cache& C = this->cache;
  C.quotasDirty = false;
  const double capacity = this->FrameCapacity();
  double sumBytes = 0.0;
  double n = 0.0;
  for (const auto& b : this->blocks)
  {
    if (b.fd >= 0 && b.count > 0)
    {
      sumBytes += static_cast<double>(b.Bytes());
      n += 1.0;
    }
  }
  if (n == 0.0)
  {
    return;
  }
  const double mean = sumBytes / n;
  double sumW = 0.0;
  double sumScore = 0.0;
  for (const auto& b : this->blocks)
  {
    if (b.fd >= 0 && b.count > 0)
    {
      sumW += b.weight > 0.0 ? b.weight : static_cast<double>(b.Bytes()) / mean;
      sumScore += b.score;
    }
  }
  const bool adaptive = !C.ghosts.empty() && sumScore > 0.0;
  // Adaptive: the static weight keeps a small share (10% of the evidence) for idle blocks.
  const double bias = std::max(1.0, 0.1 * sumScore);
  const double total = adaptive ? sumScore + bias : sumW;
  for (auto& b : this->blocks)
  {
    if (b.fd < 0 || b.count == 0)
    {
      continue;
    }
    const double w = (b.weight > 0.0 ? b.weight : static_cast<double>(b.Bytes()) / mean) / sumW;
    const double raw = adaptive ? b.score + bias * w : w * sumW;
    b.quota = static_cast<std::uint32_t>(std::max(1.0, capacity * raw / total));
  }
}

// PagePolicy::Clock: one hand over every frame slot, whatever block holds its page: a
// referenced page gets its bit cleared (and its inline entry taken out, so that its next use
// sets the bit again), the first unreferenced unpinned page goes (a dirty one is written back
// by Evict). At most kClockScan bits are cleared a fault: past them the first page whose bit it
// cleared goes (the oldest it looked at). Each cleared bit costs its page one access through the
// slow path, and when a phase uses nearly every cached page (two threads' halves of a small
// budget) an unbounded hand cleared most of them on every fault: Lucy-size's decimation at
// 8 MB took 1.015 times as long as with the shares, with 12% fewer misses; bounded, 0.958
// (docs/benchmarks.md). -1 when every page is pinned.
std::int32_t DML::Impl::ClockVictim()
{
  auto& F = this->cache.frames;
  const std::size_t n = F.size();
  std::int32_t firstCleared = -1;
  std::size_t cleared = 0;
  for (std::size_t s = 0; s < 2 * n + 1; ++s)
  {
    const std::size_t fi = this->cache.clockHand < n ? this->cache.clockHand : 0;
    this->cache.clockHand = fi + 1 < n ? fi + 1 : 0;
    Frame& f = F[fi];
    if (f.block < 0 || f.pins > 0)
    {
      continue;
    }
    if (f.ref)
    {
      if (cleared == kClockScan)
      {
        return firstCleared;
      }
      f.ref = false;
      this->FastRemove(static_cast<std::int32_t>(fi));
      if (firstCleared < 0)
      {
        firstCleared = static_cast<std::int32_t>(fi);
      }
      ++cleared;
      continue;
    }
    return static_cast<std::int32_t>(fi);
  }
  return -1;
}

std::int32_t DML::Impl::FindVictim(BlockId requester)
{
  if (this->profile.pagePolicy == PagePolicy::Clock && this->replacement != Replacement::Lru)
  {
    return this->ClockVictim();
  }
  if (this->cache.quotasDirty)
  {
    this->RecomputeQuotas();
  }
  std::int32_t target = -1;
  const Block* r = requester >= 0 ? &this->blocks[static_cast<std::size_t>(requester)] : nullptr;
  if (r && r->resident >= r->quota)
  {
    target = requester; // at its share: replace locally
  }
  else
  {
    // Below its share (or no requester): take from the block most above its share, else from
    // the block holding the most frames.
    std::int64_t bestOver = 0;
    std::uint32_t most = 0;
    std::int32_t largest = -1;
    for (std::size_t i = 0; i < this->blocks.size(); ++i)
    {
      const Block& b = this->blocks[i];
      if (b.resident == 0)
      {
        continue;
      }
      const std::int64_t over = std::int64_t(b.resident) - std::int64_t(b.quota);
      if (over > bestOver)
      {
        bestOver = over;
        target = static_cast<std::int32_t>(i);
      }
      if (b.resident > most)
      {
        most = b.resident;
        largest = static_cast<std::int32_t>(i);
      }
    }
    if (target < 0)
    {
      target = r && r->resident > 0 ? requester : largest;
    }
  }
  if (target >= 0)
  {
    const std::int32_t fi = this->SweepVictim(this->blocks[static_cast<std::size_t>(target)]);
    if (fi >= 0)
    {
      return fi;
    }
  }
  for (auto& b : this->blocks) // everything of the target is pinned: any unpinned frame
  {
    if (b.resident > 0)
    {
      const std::int32_t fi = this->SweepVictim(b);
      if (fi >= 0)
      {
        return fi;
      }
    }
  }
  return -1;
}

std::int32_t DML::Impl::SweepVictim(Block& v)
{
  auto& F = this->cache.frames;
  if (v.hand < 0)
  {
    return -1;
  }
  if (this->replacement == Replacement::Lru)
  {
    std::int32_t fi = v.hand; // least recently used end
    for (std::uint32_t i = 0; i < v.resident; ++i, fi = F[static_cast<std::size_t>(fi)].next)
    {
      if (F[static_cast<std::size_t>(fi)].pins == 0)
      {
        return fi;
      }
    }
    return -1;
  }
  // At most one revolution: clear and stamp referenced pages; take the first old clean page.
  // Old dirty pages are collected; once a batch is full (or the revolution ends without an old
  // clean page) the batch is written back together, the first is the victim and the hand is left
  // on the second, so the next fault finds a clean old page at once. With no old page at all,
  // the least recently stamped unreferenced page is taken (clean on ties).
  const std::uint64_t tau = std::max<std::uint32_t>(1, v.resident / 2);
  std::int32_t dirtyOld[kMaxWritesPerSweep];
  int nDirty = 0;
  std::int32_t oldest = -1;
  std::int32_t anyUnpinned = -1;
  for (std::uint32_t s = 0, n = v.resident; s < n && nDirty < kMaxWritesPerSweep; ++s)
  {
    const std::int32_t fi = v.hand;
    Frame& f = F[static_cast<std::size_t>(fi)];
    v.hand = f.next;
    if (f.pins > 0)
    {
      continue;
    }
    if (anyUnpinned < 0)
    {
      anyUnpinned = fi;
    }
    if (f.ref)
    {
      f.ref = false;
      this->FastRemove(fi);
      f.lastUse = v.vtime;
      continue;
    }
    if (v.vtime - f.lastUse > tau)
    {
      if (!f.dirty)
      {
        return fi;
      }
      dirtyOld[nDirty++] = fi;
      continue;
    }
    if (oldest < 0)
    {
      oldest = fi;
      continue;
    }
    const Frame& o = F[static_cast<std::size_t>(oldest)];
    if (f.lastUse < o.lastUse || (f.lastUse == o.lastUse && o.dirty && !f.dirty))
    {
      oldest = fi;
    }
  }
  if (nDirty > 0)
  {
    for (int i = 0; i < nDirty; ++i)
    {
      this->WriteBack(dirtyOld[i]);
    }
    if (nDirty > 1)
    {
      v.hand = dirtyOld[1];
    }
    return dirtyOld[0];
  }
  return oldest >= 0 ? oldest : anyUnpinned; // a dirty victim is written back on eviction
}

void DML::Impl::WriteBack(std::int32_t fi)
{
  Frame& f = this->cache.frames[static_cast<std::size_t>(fi)];
  const Block& b = this->blocks[static_cast<std::size_t>(f.block)];
  const std::uint64_t pb = this->PageBytes(b);
  const std::uint64_t first = f.page * pb;
  const std::uint64_t end = std::min(first + pb, b.Bytes());
  if (first < end)
  {
    // [lo, hi): the page's bytes a forked child writes (empty unless the block is forked); the
    // child writes back only those, a parent only the others.
    std::uint64_t lo = std::max(first, b.forkFirst * b.elementSize);
    std::uint64_t hi = std::min(end, b.forkEnd * b.elementSize);
    if (lo >= hi)
    {
      lo = hi = end;
    }
    if (this->forkParent)
    {
      if (lo < hi)
      {
        this->BackendWrite(b, f.data + (lo - first), hi - lo, lo);
      }
    }
    else
    {
      if (first < lo)
      {
        this->BackendWrite(b, f.data, lo - first, first);
      }
      if (hi < end)
      {
        this->BackendWrite(b, f.data + (hi - first), end - hi, hi);
      }
    }
  }
  f.dirty = false;
  this->FastClearWrite(fi);
}

void DML::Impl::Evict(std::int32_t fi, bool writeBack)
{
  detail::Cache& C = this->cache;
  Frame& f = C.frames[static_cast<std::size_t>(fi)];
  if (writeBack && f.dirty)
  {
    this->WriteBack(fi); // throws with the page still cached and dirty
  }
  Block& b = this->blocks[static_cast<std::size_t>(f.block)];
  std::int32_t* link = &C.buckets[Mix(static_cast<std::uint64_t>(f.block), f.page) &
    (C.buckets.size() - 1)];
  while (*link != fi)
  {
    link = &C.frames[static_cast<std::size_t>(*link)].hashNext;
  }
  *link = f.hashNext;
  f.hashNext = -1;
  this->RingRemove(b, fi);
  --b.resident;
  for (std::int32_t& r : b.recentFrame)
  {
    if (r == fi)
    {
      r = -1;
    }
  }
  this->FastRemove(fi);
  if (f.pins > 0)
  {
    --C.pinnedFrames;
  }
  if (!C.ghosts.empty())
  {
    const std::uint64_t tag = Mix(b.fileSeq + 1, f.page) | 1;
    C.ghosts[tag & (C.ghosts.size() - 1)] = tag;
  }
  f.block = -1;
  f.pins = 0;
  f.ref = f.dirty = false;
  f.next = C.freeData;
  C.freeData = fi;
}

void DML::Impl::DropBlockPages(BlockId id, std::uint64_t fromPage)
{
  if (!this->cache.built)
  {
    return;
  }
  // Walk the block's own ring (not the whole table); `next` is taken before an eviction.
  Block& b = this->blocks[static_cast<std::size_t>(id)];
  auto& F = this->cache.frames;
  std::int32_t fi = b.hand;
  for (std::uint32_t n = b.resident; n > 0; --n)
  {
    const std::int32_t next = F[static_cast<std::size_t>(fi)].next;
    if (F[static_cast<std::size_t>(fi)].page >= fromPage)
    {
      this->Evict(fi, false);
    }
    fi = next;
  }
  b.ClearRecent();
  this->SyncFast(id);
  this->cache.quotasDirty = true;
}

void DML::Impl::MergeChildRange(BlockId id)
{
  Block& b = this->blocks[static_cast<std::size_t>(id)];
  if (!this->cache.built || b.forkFirst >= b.forkEnd)
  {
    return;
  }
  const std::uint64_t pb = this->PageBytes(b);
  const std::uint64_t lo = b.forkFirst * b.elementSize, hi = b.forkEnd * b.elementSize;
  auto& F = this->cache.frames;
  std::int32_t fi = b.hand;
  for (std::uint32_t n = b.resident; n > 0; --n)
  {
    const std::int32_t next = F[static_cast<std::size_t>(fi)].next;
    Frame& f = F[static_cast<std::size_t>(fi)];
    const std::uint64_t first = f.page * pb;
    const std::uint64_t a = std::max(first, lo), e = std::min({ first + pb, hi, b.Bytes() });
    if (a < e)
    {
      if (f.dirty || f.pins > 0)
      {
        this->BackendRead(b, f.data + (a - first), e - a, a); // (a pinned span stays valid)
      }
      else
      {
        this->Evict(fi, false);
      }
    }
    fi = next;
  }
  b.ClearRecent();
  this->SyncFast(id);
  this->cache.quotasDirty = true;
}

// Accountant callback: free page buffers until `bytes` fit (cached pages go first to the
// blocks most above their share; dirty ones are written back).
void DML::Impl::ReleaseFrames(std::uint64_t bytes)
{
  std::uint64_t freed = 0;
  while (!this->acc.Fits(bytes))
  {
    unsigned char* data = this->TakeBuffer();
    if (!data)
    {
      break;
    }
    std::free(data);
    freed += this->cache.pageSize;
  }
#if defined(__GLIBC__)
  // Page buffers are below glibc's mmap threshold: freed, they stay in the heap's arena, and the
  // large buffer they make room for (a sort's runs) would come on top of them in the process's
  // resident memory. Give the freed pages back to the system when there are many.
  if (freed >= (std::uint64_t(1) << 20))
  {
    ::malloc_trim(0);
  }
#endif
}

unsigned char* DML::Impl::TakeBuffer()
{
  detail::Cache& C = this->cache;
  if (!C.built)
  {
    return nullptr;
  }
  if (C.freeData < 0)
  {
    const std::int32_t victim = this->FindVictim(-1);
    if (victim < 0)
    {
      return nullptr;
    }
    this->Evict(victim, true);
  }
  const std::int32_t fi = C.freeData;
  Frame& f = C.frames[static_cast<std::size_t>(fi)];
  C.freeData = f.next;
  unsigned char* data = f.data;
  f.data = nullptr;
  f.next = C.freeEmpty;
  C.freeEmpty = fi;
  --C.withData;
  this->acc.Release(HeapCost(C.pageSize));
  C.quotasDirty = true;
  return data;
}

bool DML::Impl::GiveBuffer(unsigned char* data)
{
  detail::Cache& C = this->cache;
  if (!C.built || C.freeEmpty < 0 || !this->acc.TryCharge(HeapCost(C.pageSize)))
  {
    return false;
  }
  const std::int32_t fi = C.freeEmpty;
  Frame& f = C.frames[static_cast<std::size_t>(fi)];
  C.freeEmpty = f.next;
  f.data = data;
  f.next = C.freeData;
  C.freeData = fi;
  ++C.withData;
  C.quotasDirty = true;
  return true;
}

std::int32_t DML::Impl::PinPage(BlockId id, Block& b, std::uint64_t page, bool write)
{
  detail::Cache& C = this->cache;
  std::int32_t fi = this->Lookup(id, page);
  if (fi < 0 || C.frames[static_cast<std::size_t>(fi)].pins == 0)
  {
    // Keep at least one unpinned frame so plain reads and writes can always proceed.
    if (C.pinnedFrames + 2 > this->FrameCapacity())
    {
      throw BudgetError("sipmss::storage: too many pinned pages for the memory budget (" +
        std::to_string(C.pinnedFrames) + " pinned)");
    }
  }
  fi = static_cast<std::int32_t>(this->PageFor(id, b, page, write, true) ? b.recentFrame[0] : -1);
  Frame& f = C.frames[static_cast<std::size_t>(fi)];
  if (f.pins++ == 0)
  {
    ++C.pinnedFrames;
  }
  return fi;
}

void DML::Impl::UnpinPage(BlockId id, std::uint64_t page)
{
  const std::int32_t fi = this->Lookup(id, page);
  if (fi < 0)
  {
    return;
  }
  Frame& f = this->cache.frames[static_cast<std::size_t>(fi)];
  if (f.pins > 0 && --f.pins == 0)
  {
    --this->cache.pinnedFrames;
  }
}

} // namespace sipmss::storage
