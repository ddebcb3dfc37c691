// The one way an algorithm reads and writes a block: a typed accessor.
//
//   View<T>         an accessor of one block through one DML (the algorithm's, or a forked one a
//                   helper thread uses), chosen at run time: the block's memory in core, the
//                   DML's page cache out of core. Refresh() after anything that may change the
//                   mode, move or resize the block (OpenBlock, Resize, Reconfigure).
//   CoreAccess<T>   the same interface, resolved at compile time: raw memory (in core).
//   PagedAccess<T>  the same interface, resolved at compile time: the page cache (out of core).
//   PinWindow<T>    in-place access by reference (T& At(block, i)) through a few pinned pages.
//   WithAccess(f, views...)
//                   calls f once with every view as CoreAccess when they are all in core, else
//                   with every view as PagedAccess: a phase written once as a generic lambda (or a
//                   template over the access kind) runs on raw pointers in core and through the
//                   DML out of core. `kInCore` tells a body which it got, for what only memory
//                   has (prefetch hints need addresses).
//
// Each accessor carries the range of elements it may write (WriteBounds: every element unless a
// parallel phase restricts it, see Parallel.h). Builds with SIPMSS_CHECK_WRITES (the default
// when NDEBUG is not defined; the storage tests turn it on) check every Set and SetRange against
// it and throw WriteOutOfBounds: the rules of a parallel phase (each thread writes only its own
// elements) are then enforced, not only written down.
#pragma once

#include "sipmss/storage/DML.h"

#include <algorithm>
#include <cstring>
#include <limits>
#include <stdexcept>
#include <string>
#include <vector>

#ifndef SIPMSS_CHECK_WRITES
#ifdef NDEBUG
#define SIPMSS_CHECK_WRITES 0
#else
#define SIPMSS_CHECK_WRITES 1
#endif
#endif

// The accessors' definitions depend on SIPMSS_CHECK_WRITES: they live in an inline namespace
// named after it, so that a checked and an unchecked translation unit never share (and the
// linker never picks between) two different bodies of one function.
#if SIPMSS_CHECK_WRITES
#define SIPMSS_ACCESS_NAMESPACE checked_writes
#else
#define SIPMSS_ACCESS_NAMESPACE unchecked_writes
#endif

namespace sipmss::storage
{
// The elements an accessor may write: [first, end) without [holeFirst, holeEnd).
struct WriteBounds
{
  std::uint64_t first = 0;
  std::uint64_t end = std::numeric_limits<std::uint64_t>::max();
  std::uint64_t holeFirst = 0;
  std::uint64_t holeEnd = 0;

  bool Allows(std::uint64_t first, std::uint64_t count) const
  {
    const std::uint64_t last = first + count; // (exclusive)
    return count == 0 ||
      (first >= this->first && last <= this->end &&
        (last <= this->holeFirst || first >= this->holeEnd));
  }
  static WriteBounds None() { return { 0, 0, 0, 0 }; }
};

// A write outside an accessor's WriteBounds (a parallel phase broke its declared ranges).
class WriteOutOfBounds : public std::logic_error
{
public:
  WriteOutOfBounds(BlockId id, std::uint64_t first, std::uint64_t count, const WriteBounds& b)
    : std::logic_error("sipmss::storage: write of elements [" + std::to_string(first) + ", " +
        std::to_string(first + count) + ") of block " + std::to_string(id) +
        " outside its declared range [" + std::to_string(b.first) + ", " +
        (b.end == std::numeric_limits<std::uint64_t>::max() ? std::string("end")
                                                             : std::to_string(b.end)) +
        ")" +
        (b.holeEnd > b.holeFirst ? " without [" + std::to_string(b.holeFirst) + ", " +
              std::to_string(b.holeEnd) + ")"
                                 : std::string()))
  {
  }
};

// A hint that the element at p is read soon: fetches its cache lines, its first and its last
// byte (an 80-byte record spans two; a smaller one may straddle two). p is never dereferenced:
// any address will do. Always inlined: GCC takes a function whose only effect is a prefetch
// for one without effects, and drops its calls.
template <class T>
SIPMSS_ALWAYS_INLINE void PrefetchElement(const T* p)
{
#if defined(__GNUC__)
  __builtin_prefetch(static_cast<const void*>(p));
  if constexpr (sizeof(T) > 8)
  {
    __builtin_prefetch(reinterpret_cast<const char*>(p) + sizeof(T) - 1);
  }
#else
  (void)p;
#endif
}

inline namespace SIPMSS_ACCESS_NAMESPACE
{
namespace detail
{
SIPMSS_ALWAYS_INLINE void CheckWrite(
  [[maybe_unused]] BlockId id, [[maybe_unused]] const WriteBounds& b,
  [[maybe_unused]] std::uint64_t first, [[maybe_unused]] std::uint64_t count)
{
#if SIPMSS_CHECK_WRITES
  if (!b.Allows(first, count))
  {
    throw WriteOutOfBounds(id, first, count, b);
  }
#endif
}
// The accessors' inline access out of core: elements [first, first + n) on a page in the DML's
// table copied out (FastRead) or in (FastWrite: a dirty page), else false (the DML's own path).
template <class T>
SIPMSS_ALWAYS_INLINE bool FastRead(
  DML& dml, const FastBlock& b, std::uint64_t first, std::uint64_t n, T* dst)
{
  if (const unsigned char* p = dml.template FastAt<false>(b, sizeof(T), first, n))
  {
    dml.CountFastHit();
    std::memcpy(dst, p, n * sizeof(T));
    return true;
  }
  return false;
}
// For hints: element `first` in place on a page in the DML's table, else nullptr (also for a
// block not served inline, tagBase kNoFastTag, whose accessor may have no DML).
template <class T>
SIPMSS_ALWAYS_INLINE const T* FastPeek(const DML* dml, const FastBlock& b, std::uint64_t first)
{
  return b.tagBase == kNoFastTag
    ? nullptr
    : reinterpret_cast<const T*>(dml->template FastAt<false>(b, sizeof(T), first, 1));
}
template <class T>
SIPMSS_ALWAYS_INLINE bool FastWrite(
  DML& dml, const FastBlock& b, std::uint64_t first, std::uint64_t n, const T* src)
{
  if (unsigned char* p = dml.template FastAt<true>(b, sizeof(T), first, n))
  {
    dml.CountFastHit();
    std::memcpy(p, src, n * sizeof(T));
    return true;
  }
  return false;
}
} // namespace detail

template <class T>
class View
{
public:
  View() = default;
  View(DML& dml, const Array<T>& a, const WriteBounds& bounds = {})
    : dml_(&dml)
    , id_(a.Id())
    , bounds_(bounds)
  {
    this->Refresh();
  }
  void Refresh()
  {
    this->base_ = static_cast<T*>(this->dml_->BasePointer(this->id_));
    this->fast_ = this->base_ ? FastBlock{} : this->dml_->FastParams(this->id_, sizeof(T));
  }
  bool IsBound() const { return this->dml_ != nullptr; }
  // Whether the block is in this DML's memory (then CoreAccess serves it).
  bool InCore() const { return this->base_ != nullptr; }
  DML& Dml() const { return *this->dml_; }
  BlockId Id() const { return this->id_; }
  T* Base() const { return this->base_; }
  const WriteBounds& Bounds() const { return this->bounds_; }
  void Restrict(const WriteBounds& bounds) { this->bounds_ = bounds; }

  SIPMSS_ALWAYS_INLINE T Get(std::uint64_t i) const
  {
    if (this->base_)
    {
      return this->base_[i];
    }
    T v;
    if (!detail::FastRead(*this->dml_, this->fast_, i, 1, &v))
    {
      this->dml_->Read(this->id_, sizeof(T), i, &v);
    }
    return v;
  }
  SIPMSS_ALWAYS_INLINE void Set(std::uint64_t i, const T& v)
  {
    detail::CheckWrite(this->id_, this->bounds_, i, 1);
    if (this->base_)
    {
      this->base_[i] = v;
      return;
    }
    if (!detail::FastWrite(*this->dml_, this->fast_, i, 1, &v))
    {
      this->dml_->Write(this->id_, sizeof(T), i, &v);
    }
  }
  void GetRange(std::uint64_t first, std::uint64_t n, T* dst) const
  {
    if (n == 0)
    {
      return;
    }
    if (this->base_)
    {
      std::memcpy(dst, this->base_ + first, n * sizeof(T));
      return;
    }
    if (!detail::FastRead(*this->dml_, this->fast_, first, n, dst))
    {
      this->dml_->ReadRange(this->id_, first, n, dst);
    }
  }
  void SetRange(std::uint64_t first, std::uint64_t n, const T* src)
  {
    if (n == 0)
    {
      return;
    }
    detail::CheckWrite(this->id_, this->bounds_, first, n);
    if (this->base_)
    {
      std::memcpy(this->base_ + first, src, n * sizeof(T));
      return;
    }
    if (!detail::FastWrite(*this->dml_, this->fast_, first, n, src))
    {
      this->dml_->WriteRange(this->id_, first, n, src);
    }
  }
  // The elements [first, first + n) to read: in place in core, else copied into `buffer`.
  const T* Run(std::uint64_t first, std::uint64_t n, std::vector<T>& buffer) const
  {
    if (this->base_)
    {
      return this->base_ + first;
    }
    buffer.resize(n);
    this->GetRange(first, n, buffer.data());
    return buffer.data();
  }
  // A hint that element i is read soon: fetches its cache lines (its first and last byte: a
  // 80-byte record spans two). In core from the block's memory; out of core from its page when
  // the page is in the DML's inline table (a lookup, no read: a page not cached stays so).
  SIPMSS_ALWAYS_INLINE void Prefetch(std::uint64_t i) const
  {
    if (this->base_)
    {
      // (as an integer: i may be past the block, e.g. a dead face's corner; never dereferenced)
      PrefetchElement(reinterpret_cast<const T*>(
        reinterpret_cast<std::uintptr_t>(this->base_) + std::uintptr_t(i) * sizeof(T)));
    }
    else if (const T* p = detail::FastPeek<T>(this->dml_, this->fast_, i)) // (none past the end)
    {
      PrefetchElement(p);
    }
  }

private:
  DML* dml_ = nullptr;
  BlockId id_ = -1;
  T* base_ = nullptr;
  WriteBounds bounds_;
  FastBlock fast_; // out of core: the block's inline access, as of Refresh()
};

// In core: the block's memory, no test per element.
template <class T>
class CoreAccess
{
public:
  static constexpr bool kInCore = true;
  explicit CoreAccess(const View<T>& v)
    : base_(v.Base())
    , id_(v.Id())
    , bounds_(v.Bounds())
  {
  }
  SIPMSS_ALWAYS_INLINE T Get(std::uint64_t i) const { return this->base_[i]; }
  SIPMSS_ALWAYS_INLINE void Set(std::uint64_t i, const T& v)
  {
    detail::CheckWrite(this->id_, this->bounds_, i, 1);
    this->base_[i] = v;
  }
  void GetRange(std::uint64_t first, std::uint64_t n, T* dst) const
  {
    if (n)
    {
      std::memcpy(dst, this->base_ + first, n * sizeof(T));
    }
  }
  void SetRange(std::uint64_t first, std::uint64_t n, const T* src)
  {
    if (n)
    {
      detail::CheckWrite(this->id_, this->bounds_, first, n);
      std::memcpy(this->base_ + first, src, n * sizeof(T));
    }
  }
  // The elements' memory, for reading in place and for prefetch hints.
  SIPMSS_ALWAYS_INLINE const T* Data() const { return this->base_; }
  // As PagedAccess::Peek: element i in the block's memory (i within the block).
  SIPMSS_ALWAYS_INLINE const T* Peek(std::uint64_t i) const { return this->base_ + i; }
  // As View::Run: in place (`buffer` unused).
  const T* Run(std::uint64_t first, std::uint64_t, std::vector<T>&) const
  {
    return this->base_ + first;
  }

private:
  T* base_;
  BlockId id_;
  WriteBounds bounds_;
};

// Out of core: the DML's page cache, through its inline table of cached pages with the block's
// parameters kept here (the accessor lives for one phase body, in which no block is resized).
template <class T>
class PagedAccess
{
public:
  static constexpr bool kInCore = false;
  explicit PagedAccess(const View<T>& v)
    : dml_(v.IsBound() ? &v.Dml() : nullptr)
    , id_(v.Id())
    , bounds_(v.Bounds())
  {
    if (this->dml_)
    {
      this->fast_ = this->dml_->FastParams(this->id_, sizeof(T));
    }
  }
  SIPMSS_ALWAYS_INLINE T Get(std::uint64_t i) const
  {
    T v;
    if (!detail::FastRead(*this->dml_, this->fast_, i, 1, &v))
    {
      this->dml_->Read(this->id_, sizeof(T), i, &v);
    }
    return v;
  }
  SIPMSS_ALWAYS_INLINE void Set(std::uint64_t i, const T& v)
  {
    detail::CheckWrite(this->id_, this->bounds_, i, 1);
    if (!detail::FastWrite(*this->dml_, this->fast_, i, 1, &v))
    {
      this->dml_->Write(this->id_, sizeof(T), i, &v);
    }
  }
  void GetRange(std::uint64_t first, std::uint64_t n, T* dst) const
  {
    if (n == 0)
    {
      return;
    }
    if (!detail::FastRead(*this->dml_, this->fast_, first, n, dst))
    {
      this->dml_->ReadRange(this->id_, first, n, dst);
    }
  }
  void SetRange(std::uint64_t first, std::uint64_t n, const T* src)
  {
    if (n == 0)
    {
      return;
    }
    detail::CheckWrite(this->id_, this->bounds_, first, n);
    if (!detail::FastWrite(*this->dml_, this->fast_, first, n, src))
    {
      this->dml_->WriteRange(this->id_, first, n, src);
    }
  }
  // For prefetch hints: element i in place when its page is in the DML's inline table, else
  // nullptr (never a read: a page not cached stays so; i past the block gives nullptr). The
  // pointer is valid until the next access through this DML that may miss.
  SIPMSS_ALWAYS_INLINE const T* Peek(std::uint64_t i) const
  {
    return detail::FastPeek<T>(this->dml_, this->fast_, i);
  }
  // A hint that element i is read soon: its cache lines when its page is cached (Peek).
  SIPMSS_ALWAYS_INLINE void Prefetch(std::uint64_t i) const
  {
    if (const T* p = this->Peek(i))
    {
      PrefetchElement(p);
    }
  }
  // As View::Run: copied into `buffer` (one table lookup per page, not per element).
  const T* Run(std::uint64_t first, std::uint64_t n, std::vector<T>& buffer) const
  {
    buffer.resize(n);
    this->GetRange(first, n, buffer.data());
    return buffer.data();
  }

private:
  DML* dml_;
  BlockId id_;
  WriteBounds bounds_;
  FastBlock fast_;
};

} // inline namespace SIPMSS_ACCESS_NAMESPACE

// In-place access by reference (read-modify-write of records): a few pinned pages of one block
// kept across element accesses (out of core), so that runs of nearby accesses cost one page
// lookup instead of one per element; in core the block's memory. Not write-checked (a
// single-threaded accessor). Release() before anything that may move or resize the block.
// `maxWays` pages at most (up to kMaxWays), fewer when the cache has few pages: a quarter of
// what may be pinned when the block is first used (DML::PinnablePages), at least two. The
// faces of a subdivided scan reach their vertices in as many index ranges as it has levels
// (the 397M-triangle file: 7), which two pages kept missing. A page is replaced in clock order
// (one used since the hand last passed stays).
template <class T>
class PinWindow
{
public:
  static constexpr std::size_t kMaxWays = 8;
  PinWindow(DML& dml, Access access, std::size_t maxWays = 2)
    : dml_(dml)
    , access_(access)
    , maxWays_(std::clamp<std::size_t>(maxWays, 1, kMaxWays))
  {
  }
  ~PinWindow() { this->Release(); }
  PinWindow(const PinWindow&) = delete;
  PinWindow& operator=(const PinWindow&) = delete;

  T& At(BlockId id, std::uint64_t i)
  {
    if (void* base = this->dml_.BasePointer(id))
    {
      return static_cast<T*>(base)[i];
    }
    if (id != this->id_)
    {
      this->Release();
      this->id_ = id;
      this->ways_ = std::min<std::size_t>(
        this->maxWays_, std::max<std::size_t>(2, this->dml_.PinnablePages() / 4));
    }
    for (std::size_t k = 0; k < this->used_; ++k)
    {
      const Span& s = this->spans_[k];
      if (i - s.first < s.count)
      {
        this->used_recently_[k] = true;
        return static_cast<T*>(s.data)[i - s.first];
      }
    }
    std::size_t k = 0;
    if (this->used_ < this->ways_)
    {
      k = this->used_++;
    }
    else
    {
      while (this->used_recently_[this->hand_])
      {
        this->used_recently_[this->hand_] = false;
        this->hand_ = (this->hand_ + 1) % this->ways_;
      }
      k = this->hand_;
      this->hand_ = (this->hand_ + 1) % this->ways_;
      this->dml_.Unpin(this->id_, this->spans_[k]);
      this->spans_[k] = Span{};
    }
    Span s;
    try
    {
      s = this->dml_.Pin(id, i, this->access_);
    }
    catch (const BudgetError&)
    {
      bool others = false;
      for (std::size_t j = 0; j < this->used_; ++j)
      {
        others = others || this->spans_[j].data != nullptr;
      }
      if (!others)
      {
        throw;
      }
      // (the cache has fewer pages than when the ways were chosen: start again with one)
      this->Release();
      this->ways_ = 1;
      k = this->used_++;
      s = this->dml_.Pin(id, i, this->access_);
    }
    this->spans_[k] = s;
    this->used_recently_[k] = true;
    return static_cast<T*>(s.data)[i - s.first];
  }
  void Release()
  {
    for (std::size_t k = 0; k < this->used_; ++k)
    {
      if (this->spans_[k].data)
      {
        this->dml_.Unpin(this->id_, this->spans_[k]);
      }
      this->spans_[k] = Span{};
      this->used_recently_[k] = false;
    }
    this->used_ = 0;
    this->hand_ = 0;
  }

private:
  DML& dml_;
  Access access_;
  std::size_t maxWays_;
  std::size_t ways_ = 2;
  BlockId id_ = -1;
  Span spans_[kMaxWays];
  bool used_recently_[kMaxWays] = {};
  std::size_t used_ = 0, hand_ = 0;
};

inline namespace SIPMSS_ACCESS_NAMESPACE
{
// f(CoreAccess<T>...) when every view is in core, else f(PagedAccess<T>...). A view that is not
// bound (a block the phase does not have) counts as in core and must not be used.
template <class F, class... T>
decltype(auto) WithAccess(F&& f, const View<T>&... views)
{
  if (((views.InCore() || !views.IsBound()) && ...))
  {
    return f(CoreAccess<T>(views)...);
  }
  return f(PagedAccess<T>(views)...);
}
} // inline namespace SIPMSS_ACCESS_NAMESPACE
} // namespace sipmss::storage
