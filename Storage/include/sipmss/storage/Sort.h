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

} // namespace sipmss::storage
