// Sorting a DML block within the memory budget, in whichever mode the DML is.
//
// In core the block is plain memory and is sorted in place (an introsort whose top levels poll,
// no extra memory; on two threads from 2^20 elements). Out of core it is an external merge sort in sort(N) I/Os: runs as large as
// the budget's spare memory are read, sorted in memory and written back in place; then passes of
// a k-way merge (k as large as the spare memory allows one page of input per run) go between the
// block and a second block of the same size, and the arrays are exchanged if the result ends in
// the second one. Every byte of working memory is charged to the DML (CountedBuffer), so the run
// stays inside the budget; the second block is a temporary file of the block's size.
//
// The result is identical in both modes when `less` is a total order of the elements that differ
// (e.g. a key and then an index): elements neither less than the other may come out in another
// order in each mode. `poll(fraction)` is called between steps (about every 2^16 elements
// in core, every run and merge buffer out of core); it may throw to abort, which leaves the
// array a permutation of its elements and every temporary block closed.
#pragma once

#include "sipmss/storage/DML.h"
#include "sipmss/storage/Threads.h"

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <functional>
#include <optional>
#include <stdexcept>
#include <string>
#include <thread>
#include <utility>

namespace sipmss::storage
{

using SortPoll = std::function<void(double fraction)>;

namespace detail
{
// Partitions [first, last) around the median of its first, middle and last elements: returns
// the ends of the run equal to the pivot ([first, lo) less, [lo, hi) equal, [hi, last) greater).
template <class T, class Less>
std::pair<T*, T*> PartitionByMedian(T* first, T* last, Less& less)
{
  T* a = first;
  T* b = first + (last - first) / 2;
  T* c = last - 1;
  T* m = less(*a, *b) ? (less(*b, *c) ? b : (less(*a, *c) ? c : a))
                      : (less(*a, *c) ? a : (less(*b, *c) ? c : b));
  const T pivot = *m; // (a copy: the partition moves the elements)
  T* lo = std::partition(first, last, [&](const T& x) { return less(x, pivot); });
  T* hi = std::partition(lo, last, [&](const T& x) { return !less(pivot, x); });
  return { lo, hi };
}

// Introsort over [first, last) that polls between partitions of large ranges: median-of-three
// partitions down to ranges of kLeaf elements, which std::sort finishes; a range that recurses
// deeper than 2 log2(n) levels is finished by a heap sort (no quadratic input).
template <class T, class Less>
void SortInMemory(T* data, std::uint64_t n, Less& less, const SortPoll& poll, double from,
  double span)
{
  if (n == 0)
  {
    // (e.g. SortInMemoryParallel's sides when every element equals the pivot)
    if (poll)
    {
      poll(from + span);
    }
    return;
  }
  constexpr std::uint64_t kLeaf = std::uint64_t(1) << 16;
  struct Part
  {
    std::uint64_t first, last;
    int depth;
  };
  int maxDepth = 0;
  for (std::uint64_t m = n; m > 1; m >>= 1)
  {
    maxDepth += 2;
  }
  // The larger part is pushed and the smaller taken, so the parts pushed halve: at most
  // log2(n) <= 64 entries, on the stack (no heap memory outside the budget).
  Part stack[66];
  int top = 0;
  stack[top++] = { 0, n, 0 };
  std::uint64_t done = 0;
  while (top > 0)
  {
    Part p = stack[--top];
    while (p.last - p.first > kLeaf)
    {
      if (p.depth >= maxDepth)
      {
        std::make_heap(data + p.first, data + p.last, less);
        std::sort_heap(data + p.first, data + p.last, less);
        break;
      }
      const auto [lo, hi] = PartitionByMedian(data + p.first, data + p.last, less);
      const std::uint64_t mid1 = static_cast<std::uint64_t>(lo - data);
      const std::uint64_t mid2 = static_cast<std::uint64_t>(hi - data);
      done += mid2 - mid1; // the pivot's equals are in place
      Part left{ p.first, mid1, p.depth + 1 };
      Part right{ mid2, p.last, p.depth + 1 };
      if (left.last - left.first > right.last - right.first)
      {
        std::swap(left, right);
      }
      stack[top++] = right;
      p = left;
      if (poll)
      {
        poll(from + span * static_cast<double>(done) / static_cast<double>(n));
      }
    }
    if (p.last - p.first <= kLeaf)
    {
      std::sort(data + p.first, data + p.last, less);
    }
    done += p.last - p.first;
    if (poll)
    {
      poll(from + span * static_cast<double>(done) / static_cast<double>(n));
    }
  }
}
// In memory on two threads when there are at least two cores and 2^20 elements: one
// median-of-three partition, the smaller side sorted on a helper thread (it stops at its next
// partition once the calling thread's poll has thrown), the larger on the calling thread with the
// polls. The same result as on one thread (the partition is the same; each side is sorted).
template <class T, class Less>
void SortInMemoryParallel(T* data, std::uint64_t n, Less& less, const SortPoll& poll, int threads)
{
  if (n < (std::uint64_t(1) << 20) || ResolveThreads(threads) < 2)
  {
    SortInMemory(data, n, less, poll, 0.0, 1.0);
    return;
  }
  const auto [lo, hi] = PartitionByMedian(data, data + n, less);
  const std::uint64_t left = static_cast<std::uint64_t>(lo - data);
  const std::uint64_t right = static_cast<std::uint64_t>(data + n - hi);
  struct Stopped
  {
  };
  std::atomic<bool> stop{ false };
  const SortPoll helperPoll = [&stop](double) {
    if (stop.load(std::memory_order_relaxed))
    {
      throw Stopped{};
    }
  };
  T* smallFirst = left <= right ? data : hi;
  const std::uint64_t small = left <= right ? left : right;
  T* bigFirst = left <= right ? hi : data;
  const std::uint64_t big = left <= right ? right : left;
  std::thread helper([&] {
    try
    {
      SortInMemory(smallFirst, small, less, helperPoll, 0.0, 0.0);
    }
    catch (const Stopped&)
    {
    }
  });
  try
  {
    SortInMemory(bigFirst, big, less, poll, 0.0, 1.0);
  }
  catch (...)
  {
    stop = true;
    helper.join();
    throw;
  }
  helper.join();
}
} // namespace detail

// threads: 1 = the calling thread only; 0 = two when the machine has two cores (in core; `less`
// is then called from two threads at once).
template <class T, class Less>
void Sort(DML& dml, Array<T>& array, Less less, const SortPoll& poll = {}, int threads = 0)
{
  const std::uint64_t n = array.Size();
  if (n < 2)
  {
    return;
  }
  if (T* base = static_cast<T*>(dml.BasePointer(array.Id())))
  {
    detail::SortInMemoryParallel(base, n, less, poll, threads);
    return;
  }

  // Out of core. The working memory: what the budget spares beside a few cache pages (the reads
  // and writes below go through the cache one page at a time), at most the data's size; 1/8 of
  // it is kept for the merge's table of runs (36 bytes per run of at least 64 elements).
  const std::uint64_t pageElements =
    std::max<std::uint64_t>(1, dml.PageBytes() / sizeof(T));
  auto spareElements = [&] { return dml.SpareMemory(4) / 8 * 7 / sizeof(T); };
  std::uint64_t spare = spareElements();
  Array<T> other; // the merge's second block, opened before the memory is taken
  if (spare < n)
  {
    other = Array<T>(dml, n);
    spare = spareElements();
  }
  if (spare < 3 * 64)
  {
    throw BudgetError("sipmss::storage: the memory budget leaves " +
      std::to_string(dml.SpareMemory(4)) + " bytes beside the page cache, too few to sort " +
      std::to_string(n) + " elements of " + std::to_string(sizeof(T)) + " bytes");
  }
  spare = std::min<std::uint64_t>(spare, n);
  CountedBuffer<T> buffer(dml, static_cast<std::size_t>(spare));
  T* buf = buffer.Data();
  // The merge's windows: one page of input per run (at least 64 elements), and one of output.
  const std::uint64_t per = std::min(pageElements, std::max<std::uint64_t>(64, spare / 3));
  const std::uint64_t fanIn = std::max<std::uint64_t>(2, spare / per - 1);

  // Run formation, in place.
  const std::uint64_t runLength = spare;
  const std::uint64_t runs = (n + runLength - 1) / runLength;
  // Merge passes: each step's share of the whole (one read and write of the data per pass).
  std::uint64_t passes = 0;
  for (std::uint64_t r = runs; r > 1; r = (r + fanIn - 1) / fanIn)
  {
    ++passes;
  }
  const double share = 1.0 / static_cast<double>(passes + 1);
  for (std::uint64_t r = 0; r < runs; ++r)
  {
    const std::uint64_t first = r * runLength;
    const std::uint64_t count = std::min(runLength, n - first);
    array.Read(first, count, buf);
    detail::SortInMemory(buf, count, less, SortPoll(), 0.0, 0.0);
    array.Write(first, count, buf);
    if (poll)
    {
      poll(share * static_cast<double>(r + 1) / static_cast<double>(runs));
    }
  }
  if (runs == 1)
  {
    return;
  }

  // k-way merges. Each input run has a window of `per` elements in buf; the output one more.
  const std::uint64_t maxK = std::min(fanIn, runs);
  CountedBuffer<std::uint64_t> table(dml, static_cast<std::size_t>(4 * maxK));
  CountedBuffer<std::uint32_t> heap(dml, static_cast<std::size_t>(maxK)); // runs by head
  Array<T>* src = &array;
  Array<T>* dst = &other;
  std::uint64_t length = runLength; // of the runs in src (the last may be shorter)
  std::uint64_t pass = 0;
  while (length < n)
  {
    const std::uint64_t merged = length >= (n + fanIn - 1) / fanIn ? n : length * fanIn;
    for (std::uint64_t group = 0; group < n; group += merged)
    {
      const std::uint64_t groupEnd = std::min(n, group + merged);
      const std::uint64_t k = (groupEnd - group + length - 1) / length;
      // Per run j: next element to read from src, end of the run, position and fill of its
      // window in buf (windows at j * per; the output window after the last).
      std::uint64_t* next = table.Data();
      std::uint64_t* end = next + k;
      std::uint64_t* pos = end + k;
      std::uint64_t* fill = pos + k;
      std::uint32_t* heapFirst = heap.Data();
      std::uint32_t* heapLast = heapFirst;
      auto refill = [&](std::uint64_t j) {
        const std::uint64_t c = std::min(per, end[j] - next[j]);
        src->Read(next[j], c, buf + j * per);
        next[j] += c;
        pos[j] = 0;
        fill[j] = c;
      };
      // The heap's order: the smaller head first, the lower run on ties (a stable merge).
      auto later = [&](std::uint32_t x, std::uint32_t y) {
        const T& a = buf[x * per + pos[x]];
        const T& b = buf[y * per + pos[y]];
        return less(b, a) || (!less(a, b) && x > y);
      };
      for (std::uint64_t j = 0; j < k; ++j)
      {
        next[j] = group + j * length;
        end[j] = std::min(groupEnd, next[j] + length);
        refill(j);
        *heapLast++ = static_cast<std::uint32_t>(j);
      }
      // A min-heap of the runs by head (heapFirst[0] the least): the least run's next head
      // replaces it at the top and sinks once (one sift per element, not a pop and a push).
      auto sink = [&]() {
        const std::size_t size = static_cast<std::size_t>(heapLast - heapFirst);
        std::size_t at = 0;
        const std::uint32_t top = heapFirst[0];
        for (;;)
        {
          std::size_t child = 2 * at + 1;
          if (child >= size)
          {
            break;
          }
          if (child + 1 < size && later(heapFirst[child], heapFirst[child + 1]))
          {
            ++child;
          }
          if (!later(top, heapFirst[child]))
          {
            break;
          }
          heapFirst[at] = heapFirst[child];
          at = child;
        }
        heapFirst[at] = top;
      };
      std::make_heap(heapFirst, heapLast, later); // (a max-heap under `later`: the least on top)
      T* out = buf + k * per;
      std::uint64_t outFill = 0;
      std::uint64_t written = group;
      while (heapLast != heapFirst)
      {
        const std::uint32_t j = heapFirst[0];
        out[outFill++] = buf[j * per + pos[j]];
        if (outFill == per)
        {
          dst->Write(written, outFill, out);
          written += outFill;
          outFill = 0;
          if (poll)
          {
            poll(share * (static_cast<double>(pass + 1) +
                           static_cast<double>(written) / static_cast<double>(n)));
          }
        }
        if (++pos[j] == fill[j])
        {
          if (next[j] < end[j])
          {
            refill(j);
          }
          else
          {
            heapFirst[0] = *--heapLast; // the run is done: the last leaf takes its place
            if (heapLast == heapFirst)
            {
              continue;
            }
          }
        }
        sink();
      }
      if (outFill > 0)
      {
        dst->Write(written, outFill, out);
        written += outFill;
      }
      if (poll)
      {
        poll(share * (static_cast<double>(pass + 1) +
                       static_cast<double>(written) / static_cast<double>(n)));
      }
    }
    std::swap(src, dst);
    length = merged;
    ++pass;
  }
  if (src != &array)
  {
    array.Swap(other); // the sorted data is in `other`'s block; the old one closes with it
  }
}


// A consumer of sorted elements (SortByKeyInto): sink(data, first, n) gets the elements
// [first, first + n) of the sorted order, called in order.
template <class T>
using SortSink = std::function<void(const T*, std::uint64_t, std::uint64_t)>;

// How SortByKey sorted: in memory, by distribution to key ranges, or by Sort's merges.
enum class SortMethod
{
  InMemory,
  Distribution,
  Merge
};

namespace detail
{
// Sorting [data, data + n) by key and then by less (key never decreasing along less: the order
// is less's): an in-place most-significant-digit radix sort on the key above its least value,
// eight bits a level (American flag sort: a count, then each element swapped into its digit's
// place); ranges of at most 64 elements and ranges of one key are finished by std::sort. At most
// eight levels of recursion, 4 KiB each; no heap memory.
//
// One level: the elements ordered by their digit ((key - lo) >> shift) & 255; ends[d] is the end
// of digit d's range (ends[-1] = 0).
template <class T, class Key>
void RadixPartition(T* data, std::size_t n, Key& key, std::uint64_t lo, int shift,
  std::size_t (&ends)[256])
{
  auto digit = [&](const T& x) { return static_cast<std::size_t>(((key(x) - lo) >> shift) & 255); };
  std::size_t head[256] = {};
  for (std::size_t i = 0; i < n; ++i)
  {
    ++head[digit(data[i])];
  }
  std::size_t at = 0;
  for (std::size_t d = 0; d < 256; ++d)
  {
    const std::size_t c = head[d];
    head[d] = at;
    at += c;
    ends[d] = at;
  }
  for (std::size_t d = 0; d < 256; ++d)
  {
    while (head[d] < ends[d])
    {
      T x = data[head[d]];
      std::size_t e = digit(x);
      while (e != d)
      {
        std::swap(x, data[head[e]++]);
        e = digit(x);
      }
      data[head[d]++] = x;
    }
  }
}

template <class T, class Key, class Less>
void RadixSortLevel(T* data, std::size_t n, Key& key, Less& less, std::uint64_t lo, int shift);

// Finishes one digit's range of a level at `shift`: at shift 0 its elements have one key and
// less orders them; else the next level (the last takes the lowest eight bits, those above them
// being equal in the range).
template <class T, class Key, class Less>
void RadixSortDigit(T* data, std::size_t n, Key& key, Less& less, std::uint64_t lo, int shift)
{
  if (n < 2)
  {
    return;
  }
  if (shift == 0)
  {
    std::sort(data, data + n, less);
  }
  else
  {
    RadixSortLevel(data, n, key, less, lo, std::max(0, shift - 8));
  }
}

template <class T, class Key, class Less>
void RadixSortLevel(T* data, std::size_t n, Key& key, Less& less, std::uint64_t lo, int shift)
{
  if (n <= 64)
  {
    std::sort(data, data + n, less);
    return;
  }
  std::size_t ends[256];
  RadixPartition(data, n, key, lo, shift, ends);
  std::size_t begin = 0;
  for (std::size_t d = 0; d < 256; begin = ends[d++])
  {
    RadixSortDigit(data + begin, ends[d] - begin, key, less, lo, shift);
  }
}

// The whole sort. From 2^16 elements the first level's 256 ranges are sorted one by one with a
// poll after each; from 2^17 (kRadixTwoThreadsFrom) with two threads (ResolveThreads) by both
// threads, each taking the next range, the calling thread polling between its ranges (a throw
// stops the helper at its next range; the data stay a permutation). (2^17 elements take
// milliseconds, a thread's start tens of microseconds: the out-of-core sorts' buckets, a few
// hundred thousand elements at 8 MB, sort on both cores.)
constexpr std::uint64_t kRadixTwoThreadsFrom = std::uint64_t(1) << 17;
template <class T, class Key, class Less>
void RadixSortByKey(
  T* data, std::uint64_t n, Key& key, Less& less, const SortPoll& poll = {}, int threads = 1)
{
  if (n < 2)
  {
    return;
  }
  std::uint64_t lo = key(data[0]), hi = lo;
  for (std::uint64_t i = 1; i < n; ++i)
  {
    const std::uint64_t k = key(data[i]);
    lo = std::min(lo, k);
    hi = std::max(hi, k);
  }
  int bits = 0;
  while (bits < 64 && ((hi - lo) >> bits) != 0)
  {
    ++bits;
  }
  if (bits == 0)
  {
    SortInMemoryParallel(data, n, less, poll, threads); // (one key)
    return;
  }
  const int shift = std::max(0, bits - 8); // (the top digit: the key's top eight bits)
  if (n < (std::uint64_t(1) << 16))
  {
    RadixSortLevel(data, static_cast<std::size_t>(n), key, less, lo, shift);
    if (poll)
    {
      poll(1.0);
    }
    return;
  }
  // (larger: the first level here, then its ranges with a poll after each, on two threads from
  // kRadixTwoThreadsFrom elements)
  const bool two = n >= kRadixTwoThreadsFrom && ResolveThreads(threads) >= 2;
  std::size_t ends[256];
  RadixPartition(data, static_cast<std::size_t>(n), key, lo, shift, ends);
  std::atomic<std::size_t> next{ 0 };
  std::atomic<std::uint64_t> done{ 0 };
  std::atomic<bool> stop{ false };
  auto work = [&](bool polls) {
    for (std::size_t d; !stop.load(std::memory_order_relaxed) && (d = next++) < 256;)
    {
      const std::size_t begin = d ? ends[d - 1] : 0, c = ends[d] - begin;
      RadixSortDigit(data + begin, c, key, less, lo, shift);
      const std::uint64_t now = done += c;
      if (polls && poll)
      {
        poll(double(now) / double(n));
      }
    }
  };
  if (!two)
  {
    work(true);
    return;
  }
  std::thread helper([&] { work(false); });
  try
  {
    work(true);
  }
  catch (...)
  {
    stop = true;
    helper.join();
    throw;
  }
  helper.join();
  if (poll)
  {
    poll(1.0);
  }
}

// SortByKey's distribution (out of core) of src[srcFirst, srcFirst + n); false, with nothing
// changed and nothing held, when all the keys fall in one range of the count, or the data are too
// large for one distribution within the working memory.
// - At the top (`out` null, the whole array): the buckets are sorted in place in a second block,
//   which then becomes the array (an abort leaves the array as it was); with a `sink`, each
//   bucket sorted in memory goes to the sink instead of being written back, the second block is
//   dropped and the array stays as it was.
// - A range that holds more than the working memory (crowded keys: a range of the count is a
//   range of the key, and spatial keys crowd) is a bucket of its own, sorted by the same
//   distribution on the key's lower bits (`keyBits` = the range's shift; `masked`: the keys are
//   taken below those bits) from its place in the second block into the same place (`out`,
//   `outFirst`): no copy (the sink passed down). Where that cannot distribute either, the
//   bucket is merged (Sort) in a block of its own (and read back for the sink). Every level
//   holds its table (1/16 of the memory) and gives its buffer back while a bucket below it
//   sorts.
template <class T, class Less, class Key>
bool DistributeRange(DML& dml, Array<T>& src, std::uint64_t srcFirst, std::uint64_t n,
  Array<T>* out, std::uint64_t outFirst, Less& less, Key& key, int keyBits, bool masked,
  const SortPoll& poll, int threads, double& told, const SortSink<T>* sink = nullptr);

// Hands array[first, first + n) to the sink in chunks read through `buf`.
template <class T>
void ScanRange(Array<T>& array, std::uint64_t first, std::uint64_t n, T* buf, std::uint64_t bufSize,
  const SortSink<T>& sink)
{
  for (std::uint64_t i = 0; i < n; i += bufSize)
  {
    const std::uint64_t c = std::min(bufSize, n - i);
    array.Read(first + i, c, buf);
    sink(buf, first + i, c);
  }
}

// Copies from[fromFirst, fromFirst + n) to to[toFirst, toFirst + n) through `buf`.
template <class T>
void CopyRange(Array<T>& from, std::uint64_t fromFirst, Array<T>& to, std::uint64_t toFirst,
  std::uint64_t n, CountedBuffer<T>& buf)
{
  for (std::uint64_t i = 0; i < n; i += buf.Size())
  {
    const std::uint64_t c = std::min<std::uint64_t>(buf.Size(), n - i);
    from.Read(fromFirst + i, c, buf.Data());
    to.Write(toFirst + i, c, buf.Data());
  }
}

// Sorts src[srcFirst, srcFirst + n) into out[outFirst, outFirst + n) by merging (Sort) in a block
// of its own: the crowded bucket that the distribution cannot split.
template <class T, class Less>
void MergeRange(DML& dml, Array<T>& src, std::uint64_t srcFirst, std::uint64_t n, Array<T>& out,
  std::uint64_t outFirst, Less& less, const SortPoll& poll, int threads)
{
  Array<T> part(dml, n);
  const auto chunk = static_cast<std::size_t>(
    std::max<std::uint64_t>(1, std::min<std::uint64_t>(n, dml.PageBytes() / sizeof(T))));
  {
    CountedBuffer<T> buf(dml, chunk);
    CopyRange(src, srcFirst, part, 0, n, buf);
  }
  Sort(dml, part, less, poll, threads);
  CountedBuffer<T> buf(dml, chunk);
  CopyRange(part, 0, out, outFirst, n, buf);
}

template <class T, class Less, class Key>
bool DistributeRange(DML& dml, Array<T>& src, std::uint64_t srcFirst, std::uint64_t n,
  Array<T>* out, std::uint64_t outFirst, Less& less, Key& key, int keyBits, bool masked,
  const SortPoll& poll, int threads, double& told, const SortSink<T>* sink)
{
  const std::uint64_t pageElements = std::max<std::uint64_t>(1, dml.PageBytes() / sizeof(T));
  Array<T> other(dml, n); // (opened before the memory is taken, as Sort's)
  // The table: 2^binBits counts of equal ranges of the key (then each range's bucket) and three
  // numbers per bucket, within 1/16 of the working memory. A bucket is a run of ranges, closed
  // when the next range would overflow the buffer: two consecutive buckets hold more than the
  // buffer, so there are at most 2 n / buffer + 1 of them (the buffer is more than half the
  // working memory), and at most one per range. (Three numbers per range instead left a 63-bit
  // Morton key 13 bits of ranges at 8 MB, 4 bits an axis: a scan's vertices crowded into ranges
  // larger than the buffer, distributed a second time.)
  const std::uint64_t workBytes = dml.SpareMemory(4) / 8 * 7;
  const std::uint64_t halfBuffer = std::max<std::uint64_t>(1, workBytes / 2 / sizeof(T));
  const std::uint64_t bucketsAtMost = 2 * (n / halfBuffer) + 3;
  auto tableWords = [bucketsAtMost](int bits) {
    const std::uint64_t ranges = std::uint64_t(1) << bits;
    return ranges + 3 * std::min(ranges, bucketsAtMost) + 1;
  };
  int binBits = std::min(keyBits, 16);
  while (binBits > 4 && tableWords(binBits) * sizeof(std::uint64_t) > workBytes / 16)
  {
    --binBits;
  }
  const int shift = keyBits - binBits;
  const std::size_t bins = std::size_t(1) << binBits;
  const std::size_t maxBuckets = static_cast<std::size_t>(std::min<std::uint64_t>(bins, bucketsAtMost));
  const std::uint64_t mask = masked && keyBits < 64 ? (std::uint64_t(1) << keyBits) - 1 : ~std::uint64_t(0);
  CountedBuffer<std::uint64_t> table(dml, static_cast<std::size_t>(tableWords(binBits)));
  std::uint64_t* count = table.Data(); // per range; later its bucket
  std::uint64_t* start = count + bins; // per bucket (and the end)
  std::uint64_t* at = start + maxBuckets + 1;
  std::uint64_t* fill = at + maxBuckets;
  const std::uint64_t spare = std::min<std::uint64_t>(n, dml.SpareMemory(4) / 8 * 7 / sizeof(T));
  if (spare < 2 * pageElements)
  {
    return false;
  }
  std::optional<CountedBuffer<T>> buffer(std::in_place, dml, static_cast<std::size_t>(spare));
  T* buf = buffer->Data();
  // (shift < 64: binBits >= 1)
  auto rangeOf = [&](const T& x) { return static_cast<std::size_t>((key(x) & mask) >> shift); };
  // Progress: the count is one read, the distribution a read and a write, the buckets a read, a
  // sort and a write.
  auto tell = [&poll, &told](double f) {
    told = f;
    if (poll)
    {
      poll(f);
    }
  };

  // 1. The count of each key range.
  std::fill(count, count + bins, 0);
  for (std::uint64_t first = 0; first < n; first += spare)
  {
    const std::uint64_t c = std::min(spare, n - first);
    src.Read(srcFirst + first, c, buf);
    for (std::uint64_t i = 0; i < c; ++i)
    {
      // (every key is checked here, once, at the top)
      const std::uint64_t k = key(buf[i]) & mask;
      if (!masked && keyBits < 64 && (k >> keyBits) != 0)
      {
        throw std::logic_error("sipmss::storage::SortByKey: a key of more than " +
          std::to_string(keyBits) + " bits");
      }
      ++count[static_cast<std::size_t>(k >> shift)]; // (rangeOf)
    }
    tell(0.15 * double(first + c) / double(n));
  }
  // 2. Buckets: runs of consecutive ranges that fit the buffer, each range in one bucket; a
  //    range larger than the buffer is a bucket of its own (unless it is all of them).
  std::size_t buckets = 0; // (closed so far)
  start[0] = 0;
  std::uint64_t held = 0; // (in the open bucket)
  for (std::size_t r = 0; r < bins; ++r)
  {
    if (count[r] == n && n > spare)
    {
      return false; // (one range: nothing to distribute)
    }
    if (held > 0 && held + count[r] > spare)
    {
      if (buckets + 1 == maxBuckets)
      {
        return false; // (the buffer smaller than the bound assumed: not expected)
      }
      start[buckets + 1] = start[buckets] + held;
      ++buckets;
      held = 0;
    }
    held += count[r];
    count[r] = buckets; // (the range's bucket)
  }
  start[buckets + 1] = start[buckets] + held;
  ++buckets;
  const std::uint64_t readElements = std::min(spare / 4, 2 * pageElements);
  const std::uint64_t per = (spare - readElements) / buckets;
  // A bucket's buffer of a page or more writes whole pages; down to 1/16 of a page (in bytes,
  // the DML's rule) it writes the whole buffer each time, straight to the file (a bulk
  // transfer, docs/storage.md), which still costs less than merging; below that a second level
  // of buckets would be needed, and merging is as good.
  if (per < 64 || per * sizeof(T) < pageElements * sizeof(T) / 16)
  {
    return false;
  }

  // 3. Distribution into `other`: each bucket's elements in their order in the range.
  T* in = buf + buckets * per;
  for (std::size_t b = 0; b < buckets; ++b)
  {
    at[b] = start[b];
    fill[b] = 0;
  }
  // Writes bucket b's buffer up to the last page boundary it reaches (else all of it, and all of
  // it when `all`): with a buffer of a page or more, a bucket writes whole pages after its first
  // write. A smaller buffer writes all of it: cut at a page boundary, its remainder before the
  // boundary could be under a sixteenth of a page, a transfer that reads the page into the cache
  // first (the 397M-triangle layout step's Morton sort read 27 GB for 14 GB of reads).
  auto flush = [&](std::size_t b, bool all) {
    std::uint64_t c = fill[b];
    if (!all && per >= pageElements)
    {
      const std::uint64_t aligned = (at[b] + fill[b]) / pageElements * pageElements;
      c = aligned > at[b] ? aligned - at[b] : fill[b];
    }
    if (c == 0)
    {
      return;
    }
    T* region = buf + b * per;
    other.Write(at[b], c, region);
    at[b] += c;
    fill[b] -= c;
    std::copy(region + c, region + c + fill[b], region);
  };
  for (std::uint64_t first = 0; first < n; first += readElements)
  {
    const std::uint64_t c = std::min(readElements, n - first);
    src.Read(srcFirst + first, c, in);
    for (std::uint64_t i = 0; i < c; ++i)
    {
      const std::size_t b = static_cast<std::size_t>(count[rangeOf(in[i])]);
      buf[b * per + fill[b]++] = in[i];
      if (fill[b] == per)
      {
        flush(b, false);
      }
    }
    tell(0.15 + 0.35 * double(first + c) / double(n));
  }
  for (std::size_t b = 0; b < buckets; ++b)
  {
    flush(b, true);
  }

  // 4. Each bucket sorted: in memory, in place in `other` at the top, else into `out`; a
  //    crowded one by the distribution below this range's bits (the buffer given back meanwhile).
  Array<T>& dst = out ? *out : other;
  const std::uint64_t dstFirst = out ? outFirst : 0;
  for (std::size_t b = 0; b < buckets; ++b)
  {
    const std::uint64_t c = start[b + 1] - start[b];
    const double from = 0.5 + 0.5 * double(start[b]) / double(n);
    const double to = 0.5 + 0.5 * double(start[b + 1]) / double(n);
    if (c > spare)
    {
      buffer.reset();
      SortPoll inner;
      if (poll)
      {
        inner = [&poll, from, to](double f) { poll(from + (to - from) * f); };
      }
      double innerTold = 0;
      if (shift == 0 ||
        !DistributeRange(dml, other, start[b], c, &dst, dstFirst + start[b], less, key, shift, true,
          inner, threads, innerTold, sink))
      {
        // (progress on from where the distribution's count left it)
        SortPoll rest;
        if (inner)
        {
          rest = [&inner, innerTold](double f) { inner(innerTold + (1.0 - innerTold) * f); };
        }
        MergeRange(dml, other, start[b], c, dst, dstFirst + start[b], less, rest, threads);
        buffer.emplace(dml, static_cast<std::size_t>(spare));
        buf = buffer->Data();
        if (sink)
        {
          ScanRange(dst, dstFirst + start[b], c, buf, spare, *sink);
        }
      }
      else
      {
        buffer.emplace(dml, static_cast<std::size_t>(spare));
        buf = buffer->Data();
      }
    }
    else if (c > 0)
    {
      other.Read(start[b], c, buf);
      RadixSortByKey(buf, c, key, less, SortPoll(), threads);
      if (sink)
      {
        (*sink)(buf, dstFirst + start[b], c); // (not written: the sink takes it from here)
      }
      else
      {
        dst.Write(dstFirst + start[b], c, buf);
      }
    }
    tell(to);
  }
  if (!out && !sink)
  {
    src.Swap(other); // (the old order closes with `other`)
  }
  return true;
}

template <class T, class Less, class Key>
bool SortByDistribution(DML& dml, Array<T>& array, Less& less, Key& key, int keyBits,
  const SortPoll& poll, int threads, double& told, const SortSink<T>* sink = nullptr)
{
  return DistributeRange(dml, array, 0, array.Size(), static_cast<Array<T>*>(nullptr), 0, less,
    key, keyBits, false, poll, threads, told, sink);
}
} // namespace detail

// Sort with a key: key(x) is a number below 2^keyBits that never decreases along `less`
// (less(a, b) implies key(a) <= key(b)), e.g. an element's leading field. The result is Sort's
// (docs/architecture.md, "Sorting").
// - In core: an in-place radix sort on the key (detail::RadixSortByKey; two threads from 2^17
//   elements), ties of the key ordered by `less`.
// - Out of core, when the key spreads the elements, a distribution instead of Sort's merges:
//   1. one read counts the elements of each of up to 2^16 equal ranges of the key;
//   2. consecutive ranges are grouped into buckets that fit the working memory;
//   3. one read and write distributes the elements to their bucket's place in a second block,
//      through a write buffer per bucket that writes whole pages (partial ones when the buffer
//      is smaller than a page, down to 1/16 of one);
//   4. each bucket is read, radix-sorted in memory and written back; the blocks are exchanged.
//   Three reads and two writes of the data, no merge (whose heap compares an element of a
//   Lucy-size array about 28 times). A range that alone holds more than the working memory
//   (crowded keys) is a bucket of its own, sorted by the same distribution on the key's lower
//   bits (DistributeRange). When all keys fall in one range, or the buckets are too many for
//   1/16 of a page of write buffer each (an array larger than about 16 spare^2 / page bytes), it
//   sorts as Sort does, after the count.
// An abort (the poll throws) leaves the array a permutation of its elements (out of core: as it
// was) and every temporary block closed.
template <class T, class Less, class Key>
SortMethod SortByKey(DML& dml, Array<T>& array, Less less, Key key, int keyBits,
  const SortPoll& poll = {}, int threads = 0)
{
  if (keyBits < 1 || keyBits > 64)
  {
    throw std::invalid_argument("sipmss::storage::SortByKey: keyBits must be 1 to 64");
  }
  if (array.Size() < 2)
  {
    return SortMethod::InMemory;
  }
  if (T* base = static_cast<T*>(dml.BasePointer(array.Id())))
  {
    detail::RadixSortByKey(base, array.Size(), key, less, poll, threads);
    return SortMethod::InMemory;
  }
  double told = 0; // (the progress the count reported)
  if (detail::SortByDistribution(dml, array, less, key, keyBits, poll, threads, told))
  {
    return SortMethod::Distribution;
  }
  SortPoll rest;
  if (poll)
  {
    rest = [&poll, told](double f) { poll(told + (1.0 - told) * f); };
  }
  Sort(dml, array, less, rest, threads);
  return SortMethod::Merge;
}

// SortByKey for an array read once in sorted order and then dropped: sink(data, first, n) gets
// the elements [first, first + n) of the sorted order, in order, in chunks of at most what the
// working memory holds (in core: all of them, in place). Out of core, where the distribution
// sorts a bucket in memory it goes to the sink from there, neither written back nor read again
// (two transfers of the data fewer than SortByKey and a scan), and the array keeps its elements
// in an unspecified order; in core and after a merge the array is sorted. Progress covers the
// sort (in core and after a merge the sink's calls come after it).
template <class T, class Less, class Key>
SortMethod SortByKeyInto(DML& dml, Array<T>& array, Less less, Key key, int keyBits,
  const SortSink<T>& sink, const SortPoll& poll = {}, int threads = 0)
{
  if (keyBits < 1 || keyBits > 64)
  {
    throw std::invalid_argument("sipmss::storage::SortByKeyInto: keyBits must be 1 to 64");
  }
  const std::uint64_t n = array.Size();
  if (dml.BasePointer(array.Id()))
  {
    const SortMethod m = SortByKey(dml, array, less, key, keyBits, poll, threads);
    if (n > 0)
    {
      sink(static_cast<const T*>(dml.BasePointer(array.Id())), 0, n);
    }
    return m;
  }
  if (n < 2)
  {
    if (n == 1)
    {
      T x{};
      array.Read(0, 1, &x);
      sink(&x, 0, 1);
    }
    return SortMethod::InMemory;
  }
  double told = 0;
  if (detail::SortByDistribution(dml, array, less, key, keyBits, poll, threads, told, &sink))
  {
    return SortMethod::Distribution;
  }
  SortPoll rest;
  if (poll)
  {
    rest = [&poll, told](double f) { poll(told + (1.0 - told) * f); };
  }
  Sort(dml, array, less, rest, threads);
  const auto chunk = static_cast<std::size_t>(
    std::max<std::uint64_t>(1, std::min<std::uint64_t>(n, dml.PageBytes() / sizeof(T))));
  CountedBuffer<T> buf(dml, chunk);
  detail::ScanRange(array, 0, n, buf.Data(), chunk, sink);
  return SortMethod::Merge;
}


// Sorting elements that are produced one by one (out of core), by a key whose range [0, keyEnd)
// is known but not how the elements spread over it: the key's range is cut into equal buckets
// expected to hold what the memory spares at construction each; Add puts an element in its
// bucket's write buffer, and a full buffer is appended to a block as a segment of that bucket
// (buffers under a page through a page-sized stage, written whole)
// (no count pass, no distribution pass: the producer's pass is the distribution). Finish reads
// each bucket's segments, radix-sorts them (RadixSortByKey) and writes them to `out` in key
// order: one read and one write of the data besides the producer's. A bucket that turns out
// larger than the working memory is copied to a block of its own and sorted by Sort. The result
// is Sort's (key never decreasing along less). Every byte of working memory is charged to the DML.
template <class T, class Key, class Less>
class BucketSorter
{
public:
  BucketSorter(DML& dml, std::uint64_t n, std::uint64_t keyEnd, Key key, Less less)
    : dml_(dml)
    , n_(n)
    , key_(key)
    , less_(less)
    , segments_(dml, std::max<std::uint64_t>(n, 1))
  {
    const std::uint64_t spareBytes = dml.SpareMemory(4) / 8 * 7;
    const std::uint64_t spare = std::max<std::uint64_t>(64, spareBytes / sizeof(T));
    const std::uint64_t keys = std::max<std::uint64_t>(keyEnd, 1);
    // Buckets of an expected size of what is spare now (Finish has more: the producer's buffers
    // are gone by then), over ranges of the key of a power of two (a key's bucket is a shift).
    const std::uint64_t wanted = std::clamp<std::uint64_t>((n + spare - 1) / spare, 1, keys);
    const std::uint64_t range = (keys + wanted - 1) / wanted;
    while (this->shift_ < 62 && (std::uint64_t(2) << this->shift_) <= range)
    {
      ++this->shift_;
    }
    this->buckets_ = static_cast<std::size_t>(((keys - 1) >> this->shift_) + 1);
    // Write buffers in 3/4 of it, of at least 64 elements each. Else one bucket (its segments
    // are contiguous: one), sorted out of core at the end when large.
    this->per_ = static_cast<std::size_t>(spare * 3 / 4 / this->buckets_);
    if (this->buckets_ > 1 && this->per_ < 64)
    {
      this->buckets_ = 1;
      this->shift_ = -1;
      this->per_ = static_cast<std::size_t>(std::max<std::uint64_t>(1, spare * 3 / 4));
    }
    // Write buffers smaller than a page are appended to a page-sized buffer, written whole: a
    // segment written on its own (under a sixteenth of a page) would read its page of the file
    // into the cache first (at 8 MB the 397M-triangle layout step's 1,516 buckets of 150 faces
    // read 4.8 GB of pages never written).
    const std::uint64_t page = std::max<std::size_t>(1, dml.PageBytes() / sizeof(T));
    if (this->buckets_ > 1 && this->per_ < page && page <= spare / 8)
    {
      const auto per = static_cast<std::size_t>((spare * 3 / 4 - page) / this->buckets_);
      if (per >= 64)
      {
        this->per_ = per;
        this->stage_.emplace(dml, static_cast<std::size_t>(page));
      }
    }
    // Per bucket: its fill, its element count and its open segment (start, length); the closed
    // segments (bucket, start, length: full buffers, and one partial each at the end) go to a
    // block as they close, which Finish sorts by bucket. In memory, a table of the segments had
    // grown as n^2 / spare^2 and had not fitted 8 MB from 100M faces on.
    this->maxSegments_ = n / this->per_ + this->buckets_;
    this->records_ = Array<Segment>(dml, this->maxSegments_);
    this->table_.emplace(dml, 4 * this->buckets_);
    std::fill(this->table_->Data(), this->table_->Data() + 4 * this->buckets_, 0);
    this->buffer_.emplace(dml, this->buckets_ * this->per_);
  }
  BucketSorter(const BucketSorter&) = delete;
  BucketSorter& operator=(const BucketSorter&) = delete;

  void Add(const T& x)
  {
    if (this->received_ == this->n_)
    {
      throw std::logic_error("sipmss::storage::BucketSorter: more elements than announced");
    }
    const std::uint64_t k = this->key_(x);
    const std::size_t b = this->shift_ < 0 ? 0 : static_cast<std::size_t>(k >> this->shift_);
    if (b >= this->buckets_)
    {
      throw std::logic_error("sipmss::storage::BucketSorter: a key beyond the range");
    }
    std::uint64_t& fill = this->Fill()[b];
    (*this->buffer_)[b * this->per_ + static_cast<std::size_t>(fill)] = x;
    ++this->received_;
    if (++fill == this->per_)
    {
      this->Flush(b);
    }
  }

  // Writes the elements, sorted, to out[0, n) (out may be the producer's input, once read).
  // `threads` sorts each bucket in memory on as many (RadixSortByKey's rule).
  void Finish(Array<T>& out, const SortPoll& poll = {}, int threads = 1)
  {
    if (this->received_ != this->n_)
    {
      throw std::logic_error("sipmss::storage::BucketSorter: " + std::to_string(this->received_) +
        " elements added, " + std::to_string(this->n_) + " announced");
    }
    for (std::size_t b = 0; b < this->buckets_; ++b)
    {
      this->Flush(b);
      this->CloseSegment(b);
    }
    if (this->stage_ && this->added_ > this->staged_)
    {
      this->segments_.Write(this->staged_, this->added_ - this->staged_, this->stage_->Data());
    }
    this->stage_.reset();
    this->buffer_.reset(); // (the write buffers go; the sort's buffer takes what is spare)
    // The segments by bucket, each bucket's newest first (the order in which a chain of them
    // was followed: the same elements in the same order go to each bucket's sort).
    this->records_.Resize(std::max<std::uint64_t>(this->recordCount_, 1));
    if (this->recordCount_ > 1)
    {
      int bucketBits = 1;
      while (bucketBits < 64 && ((this->buckets_ - 1) >> bucketBits) != 0)
      {
        ++bucketBits;
      }
      SortByKey(
        this->dml_, this->records_,
        [](const Segment& x, const Segment& y) {
          return x.bucket != y.bucket ? x.bucket < y.bucket : x.start > y.start;
        },
        [](const Segment& x) { return x.bucket; }, bucketBits, SortPoll(), threads);
    }
    std::uint64_t next = 0; // (the next segment record)
    auto segmentsOf = [&](std::size_t b, auto&& f) {
      for (; next < this->recordCount_; ++next)
      {
        Segment r;
        this->records_.Read(next, 1, &r);
        if (r.bucket != b)
        {
          break;
        }
        f(r);
      }
    };
    const std::uint64_t capacity = std::min<std::uint64_t>(
      std::max<std::uint64_t>(this->n_, 1), dml_.SpareMemory(4) / 8 * 7 / sizeof(T));
    std::optional<CountedBuffer<T>> sortBuf;
    std::uint64_t at = 0;
    for (std::size_t b = 0; b < this->buckets_; ++b)
    {
      const std::uint64_t count = this->Count()[b];
      if (count == 0)
      {
        continue;
      }
      if (count <= capacity)
      {
        if (!sortBuf)
        {
          sortBuf.emplace(this->dml_, static_cast<std::size_t>(capacity));
        }
        T* data = sortBuf->Data();
        std::uint64_t filled = 0;
        segmentsOf(b, [&](const Segment& r) {
          this->segments_.ReadOnce(r.start, r.length, data + filled);
          filled += r.length;
        });
        detail::RadixSortByKey(data, count, this->key_, this->less_, SortPoll(), threads);
        out.Write(at, count, data);
      }
      else
      {
        // (crowded keys: the bucket sorted out of core on its own, copied through a chunk buffer
        // of a quarter of the spare memory)
        sortBuf.reset();
        Array<T> alone(this->dml_, count);
        auto chunkSize = [&] {
          return static_cast<std::size_t>(std::min<std::uint64_t>(
            count, std::max<std::uint64_t>(64, this->dml_.SpareMemory(4) / 4 / sizeof(T))));
        };
        {
          CountedBuffer<T> chunk(this->dml_, chunkSize());
          std::uint64_t filled = 0;
          segmentsOf(b, [&](const Segment& r) {
            detail::CopyRange(this->segments_, r.start, alone, filled, r.length, chunk);
            filled += r.length;
          });
        }
        const double from = double(at) / double(this->n_), span = double(count) / double(this->n_);
        Sort(this->dml_, alone, this->less_, poll ? SortPoll([&poll, from, span](double f) {
          poll(from + span * f);
        }) : SortPoll());
        CountedBuffer<T> chunk(this->dml_, chunkSize());
        detail::CopyRange(alone, 0, out, at, count, chunk);
      }
      at += count;
      if (poll)
      {
        poll(double(at) / double(this->n_));
      }
    }
    this->segments_.Close();
    this->records_.Close();
  }

  std::size_t Buckets() const { return this->buckets_; }
  // Elements of write buffer per bucket.
  std::size_t BufferElements() const { return this->per_; }
  // Whether the key's range could not be cut (a write buffer for each of that many buckets would
  // hold fewer than 64 elements): one bucket, sorted at the end by Sort when larger than the
  // memory. A producer that can write its elements in place and sort them itself does better
  // then.
  bool OneBucket() const { return this->shift_ < 0; }

private:
  struct Segment
  {
    std::uint64_t bucket, start, length;
  };
  std::uint64_t* Fill() { return this->table_->Data(); }
  std::uint64_t* Count() { return this->table_->Data() + this->buckets_; }
  std::uint64_t* OpenStart() { return this->table_->Data() + 2 * this->buckets_; }
  std::uint64_t* OpenLength() { return this->table_->Data() + 3 * this->buckets_; }
  // Bucket b's open segment goes to the records.
  void CloseSegment(std::size_t b)
  {
    if (this->OpenLength()[b] == 0)
    {
      return;
    }
    if (this->recordCount_ == this->maxSegments_)
    {
      throw std::logic_error("sipmss::storage::BucketSorter: the table of segments is full");
    }
    const Segment r{ b, this->OpenStart()[b], this->OpenLength()[b] };
    this->records_.Write(this->recordCount_++, 1, &r);
    this->OpenLength()[b] = 0;
  }
  void Flush(std::size_t b)
  {
    const std::uint64_t c = this->Fill()[b];
    if (c == 0)
    {
      return;
    }
    if (this->added_ + c > this->n_)
    {
      throw std::logic_error("sipmss::storage::BucketSorter: more elements than announced");
    }
    this->Append(this->buffer_->Data() + b * this->per_, c);
    if (this->OpenLength()[b] > 0 && this->OpenStart()[b] + this->OpenLength()[b] == this->added_)
    {
      this->OpenLength()[b] += c; // (right after the bucket's last segment: it grows)
    }
    else
    {
      this->CloseSegment(b);
      this->OpenStart()[b] = this->added_;
      this->OpenLength()[b] = c;
    }
    this->Count()[b] += c;
    this->added_ += c;
    this->Fill()[b] = 0;
  }

  // Writes c elements to the segments at added_: through the stage when there is one (it holds
  // [staged_, added_), a page's worth of elements, each full stage one transfer straight to
  // the file).
  void Append(const T* x, std::uint64_t c)
  {
    if (!this->stage_)
    {
      this->segments_.Write(this->added_, c, x);
      return;
    }
    const std::uint64_t page = this->stage_->Size();
    std::uint64_t held = this->added_ - this->staged_;
    while (c > 0)
    {
      const std::uint64_t k = std::min(c, page - held);
      std::copy(x, x + k, this->stage_->Data() + held);
      held += k;
      x += k;
      c -= k;
      if (held == page)
      {
        this->segments_.Write(this->staged_, page, this->stage_->Data());
        this->staged_ += page;
        held = 0;
      }
    }
  }

  DML& dml_;
  std::uint64_t n_;
  Key key_;
  Less less_;
  Array<T> segments_;
  Array<Segment> records_;
  std::size_t buckets_ = 1, per_ = 1;
  std::uint64_t maxSegments_ = 0, recordCount_ = 0;
  int shift_ = 0;
  std::uint64_t added_ = 0, received_ = 0; // (written to segments; handed to Add)
  std::optional<CountedBuffer<std::uint64_t>> table_;
  std::optional<CountedBuffer<T>> buffer_;
  std::optional<CountedBuffer<T>> stage_; // (a page of the segments, see Append)
  std::uint64_t staged_ = 0;              // (where the stage starts in the segments)
};

} // namespace sipmss::storage
