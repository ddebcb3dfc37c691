// Variable-length records: one list of fixed-size elements per index.
//
// A list block is a descriptor over two internal DML blocks, so lists work in both modes and
// move with Reconfigure like any block:
//   heads: one 16-byte ListHead {offset, size, capacity} per list (never-written heads read as
//          zeros = empty lists);
//   pool:  the elements; a list owns a chunk of `capacity` consecutive elements.
// Capacities are powers of two times minCap (the smallest chunk holding 8 bytes); a full list
// moves to a chunk twice as large and its old chunk goes to the free list of its size class,
// linked through the chunk's first 8 bytes. New chunks are cut from the end of the pool, which
// grows by half its size. The common case (append to a list with room, in core) is two memcpy.
#include "DMLImpl.h"

#include <algorithm>
#include <cstring>

namespace sipmss::storage
{

using detail::Block;
using detail::Kind;
using detail::ListHead;
using detail::ListInfo;

namespace
{
int SizeClass(const ListInfo& L, std::uint32_t cap)
{
  int k = 0;
  while ((std::uint64_t(L.minCap) << k) < cap)
  {
    ++k;
  }
  return k;
}

std::uint32_t CapacityFor(const ListInfo& L, std::uint64_t count)
{
  std::uint64_t cap = L.minCap;
  while (cap < count)
  {
    cap *= 2;
  }
  if (cap > (std::uint64_t(1) << 31))
  {
    throw std::length_error("sipmss::storage: list too long");
  }
  return static_cast<std::uint32_t>(cap);
}
} // namespace

ListHead DML::Impl::ReadHead(ListInfo& L, std::uint64_t list)
{
  ListHead h;
  Block& H = this->blocks[static_cast<std::size_t>(L.heads)];
  this->Transfer(L.heads, H, list * sizeof(ListHead), sizeof(ListHead),
    reinterpret_cast<unsigned char*>(&h), false);
  return h;
}

void DML::Impl::WriteHead(ListInfo& L, std::uint64_t list, const ListHead& h)
{
  Block& H = this->blocks[static_cast<std::size_t>(L.heads)];
  this->Transfer(L.heads, H, list * sizeof(ListHead), sizeof(ListHead),
    reinterpret_cast<unsigned char*>(const_cast<ListHead*>(&h)), true);
}

std::uint64_t DML::Impl::AllocChunk(ListInfo& L, std::uint32_t cap)
{
  const int k = SizeClass(L, cap);
  if (k >= ListInfo::kClasses)
  {
    throw std::length_error("sipmss::storage: list too long");
  }
  Block& P = this->blocks[static_cast<std::size_t>(L.pool)];
  if (L.freeHead[k] != 0)
  {
    const std::uint64_t off = L.freeHead[k] - 1;
    std::uint64_t next = 0;
    this->Transfer(L.pool, P, off * P.elementSize, sizeof(next),
      reinterpret_cast<unsigned char*>(&next), false);
    L.freeHead[k] = next;
    return off;
  }
  const std::uint64_t off = L.poolUsed;
  const std::uint64_t need = off + cap;
  if (need > P.count)
  {
    this->ResizeRaw(L.pool, std::max<std::uint64_t>({ need, P.count + P.count / 2, 64 }));
  }
  L.poolUsed = need;
  return off;
}

void DML::Impl::FreeChunk(ListInfo& L, std::uint64_t offset, std::uint32_t cap)
{
  const int k = SizeClass(L, cap);
  Block& P = this->blocks[static_cast<std::size_t>(L.pool)];
  std::uint64_t link = L.freeHead[k];
  this->Transfer(L.pool, P, offset * P.elementSize, sizeof(link),
    reinterpret_cast<unsigned char*>(&link), true);
  L.freeHead[k] = offset + 1;
}

// Copies n pool elements from `from` to `to` (non-overlapping chunks).
void DML::Impl::CopyPool(ListInfo& L, std::uint64_t from, std::uint64_t to, std::uint64_t n)
{
  Block& P = this->blocks[static_cast<std::size_t>(L.pool)];
  const std::size_t es = P.elementSize;
  if (P.mem)
  {
    std::memcpy(P.mem + to * es, P.mem + from * es, n * es);
    return;
  }
  unsigned char buf[4096]; // bounded: no heap outside the budget
  std::uint64_t bytes = n * es;
  std::uint64_t src = from * es;
  std::uint64_t dst = to * es;
  while (bytes > 0)
  {
    const std::uint64_t c = std::min<std::uint64_t>(bytes, sizeof(buf));
    this->Transfer(L.pool, this->blocks[static_cast<std::size_t>(L.pool)], src, c, buf, false);
    this->Transfer(L.pool, this->blocks[static_cast<std::size_t>(L.pool)], dst, c, buf, true);
    src += c;
    dst += c;
    bytes -= c;
  }
}

void DML::Impl::ResizeList(Block& b, std::uint64_t listCount)
{
  ListInfo& L = this->lists[static_cast<std::size_t>(b.list)];
  // Chunks of dropped lists go back to the free lists.
  for (std::uint64_t i = listCount; i < b.count; ++i)
  {
    const ListHead h = this->ReadHead(L, i);
    if (h.capacity > 0)
    {
      this->FreeChunk(L, h.offset, h.capacity);
    }
  }
  this->ResizeRaw(L.heads, listCount);
  b.count = listCount;
}

// ------------------------------------------------------------------------------------------------
BlockId DML::OpenListBlock(std::size_t elementSize, std::uint64_t listCount, double weight)
{
  Impl& I = *this->impl_;
  detail::BaseSync sync(I);
  if (elementSize == 0)
  {
    throw std::invalid_argument("sipmss::storage: element size must be positive");
  }
  std::size_t li = 0;
  while (li < I.lists.size() && I.lists[li].heads >= 0)
  {
    ++li;
  }
  if (li == I.lists.size())
  {
    I.lists.emplace_back();
  }
  const BlockId heads = I.OpenRaw(Kind::Internal, sizeof(ListHead), listCount, weight);
  BlockId pool = -1;
  try
  {
    pool = I.OpenRaw(Kind::Internal, elementSize, 0, weight);
  }
  catch (...)
  {
    I.CloseRaw(heads);
    throw;
  }
  ListInfo& L = I.lists[li];
  L = ListInfo{};
  L.heads = heads;
  L.pool = pool;
  while (std::uint64_t(L.minCap) * elementSize < 8)
  {
    L.minCap *= 2;
  }
  BlockId id = -1;
  try
  {
    id = I.NewSlot(Kind::List, elementSize, weight);
  }
  catch (...)
  {
    L = ListInfo{};
    I.CloseRaw(heads);
    I.CloseRaw(pool);
    throw;
  }
  Block& b = I.blocks[static_cast<std::size_t>(id)];
  b.count = listCount;
  b.list = static_cast<std::int32_t>(li);
  return id;
}

namespace
{
ListInfo& CheckList(DML::Impl& I, BlockId id, std::uint64_t list)
{
  Block& b = I.Get(id, Kind::List);
  if (list >= b.count)
  {
    throw std::out_of_range("sipmss::storage: list " + std::to_string(list) +
      " out of range of list block " + std::to_string(id));
  }
  return I.lists[static_cast<std::size_t>(b.list)];
}
} // namespace

void DML::Append(BlockId id, std::uint64_t list, const void* element)
{
  Impl& I = *this->impl_;
  ListInfo& L = CheckList(I, id, list);
  const Block& H = I.blocks[static_cast<std::size_t>(L.heads)];
  const Block& P = I.blocks[static_cast<std::size_t>(L.pool)];
  const std::size_t es = P.elementSize;
  if (H.mem && P.mem)
  {
    // Fast path in core: the list has room.
    auto* h = reinterpret_cast<ListHead*>(H.mem) + list;
    if (h->size < h->capacity)
    {
      std::memcpy(P.mem + (h->offset + h->size) * es, element, es);
      ++h->size;
      return;
    }
  }
  detail::BaseSync sync(I); // the pool may grow and move every block out of core
  ListHead h = I.ReadHead(L, list);
  if (h.size == h.capacity)
  {
    if (h.capacity >= (std::uint32_t(1) << 31))
    {
      throw std::length_error("sipmss::storage: list too long");
    }
    const std::uint32_t cap = h.capacity ? h.capacity * 2 : L.minCap;
    const std::uint64_t off = I.AllocChunk(L, cap); // may grow the pool or switch the mode
    I.CopyPool(L, h.offset, off, h.size);
    if (h.capacity > 0)
    {
      I.FreeChunk(L, h.offset, h.capacity);
    }
    h.offset = off;
    h.capacity = cap;
  }
  Block& pool = I.blocks[static_cast<std::size_t>(L.pool)];
  I.Transfer(L.pool, pool, (h.offset + h.size) * es, es,
    static_cast<unsigned char*>(const_cast<void*>(element)), true);
  ++h.size;
  I.WriteHead(L, list, h);
}

std::uint64_t DML::ListSize(BlockId id, std::uint64_t list)
{
  Impl& I = *this->impl_;
  ListInfo& L = CheckList(I, id, list);
  return I.ReadHead(L, list).size;
}

std::uint64_t DML::ReadList(BlockId id, std::uint64_t list, std::vector<unsigned char>& out)
{
  Impl& I = *this->impl_;
  ListInfo& L = CheckList(I, id, list);
  const ListHead h = I.ReadHead(L, list);
  Block& P = I.blocks[static_cast<std::size_t>(L.pool)];
  const std::size_t old = out.size();
  out.resize(old + std::uint64_t(h.size) * P.elementSize);
  I.Transfer(L.pool, P, h.offset * P.elementSize, std::uint64_t(h.size) * P.elementSize,
    out.data() + old, false);
  return h.size;
}

void DML::SetList(BlockId id, std::uint64_t list, const void* elements, std::uint64_t count)
{
  Impl& I = *this->impl_;
  detail::BaseSync sync(I);
  ListInfo& L = CheckList(I, id, list);
  ListHead h = I.ReadHead(L, list);
  if (count > h.capacity)
  {
    const std::uint32_t cap = CapacityFor(L, count);
    const std::uint64_t off = I.AllocChunk(L, cap);
    if (h.capacity > 0)
    {
      I.FreeChunk(L, h.offset, h.capacity);
    }
    h.offset = off;
    h.capacity = cap;
  }
  Block& P = I.blocks[static_cast<std::size_t>(L.pool)];
  I.Transfer(L.pool, P, h.offset * P.elementSize, count * P.elementSize,
    static_cast<unsigned char*>(const_cast<void*>(elements)), true);
  h.size = static_cast<std::uint32_t>(count);
  I.WriteHead(L, list, h);
}

} // namespace sipmss::storage
