// The vertex records of a chunk's faces, copied in face order by a helper thread (the clustering
// of an input read in core whose faces are not in spatial order: Cluster.cpp).
//
// In core, a face whose vertices lie anywhere in the vertex block (an input not in spatial
// order) costs three cache misses for its vertex records and one or two for its cell records.
// One thread has only so many loads in flight (its line fill buffers): the clustering of a
// shuffled Lucy-size file waited on its prefetches, not on its arithmetic. The Gatherer lets a
// second core issue the vertex loads: it copies the three records of each face into a small
// buffer, in blocks of kBlock faces, while the clustering thread adds the faces of the blocks
// already copied and prefetches their cell records from the copies (no load waits on another).
//
// The records are the same whoever copies them, and the clustering thread adds the faces in the
// input's order as before: the output does not depend on the helper. Blocks are claimed in
// order, by either thread. The clustering thread copies the block it needs when the helper has
// not claimed it yet, so a helper that is not running (a busy machine) holds nothing up but a
// block it has begun; while it waits for such a block, the clustering thread copies the next
// blocks not yet claimed. The helper reads the vertex block through its base pointer, which
// stays valid only while the clustering thread makes no call that may resize a block (a resize
// may switch the DML out of core): the caller Stop()s the helper before any such call (a
// deferred face, an append to a full block of candidates).
#pragma once

#include <algorithm>
#include <atomic>
#include <condition_variable>
#include <cstddef>
#include <cstdint>
#include <mutex>
#include <stdexcept>
#include <thread>
#include <vector>
#ifdef __SSE2__
#include <emmintrin.h>
#endif

namespace sipmss::algorithms::detail
{
// Posts made to any Gatherer in this process (a count for tests: whether a run used one).
inline std::atomic<std::uint64_t>& GatherPosts()
{
  static std::atomic<std::uint64_t> posts{ 0 };
  return posts;
}

// Rec: a vertex record, trivially copyable; Rec{} stands for a vertex not read.
template <class Rec>
class Gatherer
{
public:
  static constexpr std::size_t kBlock = 64;      // faces per claim
  static constexpr std::size_t kMaxFaces = 8192; // faces per Post (3 records each)
  static constexpr std::size_t kAheadBlocks = 4; // how far ahead Take copies while it waits

  // Starts the helper thread (std::system_error if it cannot).
  Gatherer()
    : records_(3 * kMaxFaces)
    , ready_(kMaxFaces / kBlock)
  {
    for (auto& r : this->ready_)
    {
      r.store(0, std::memory_order_relaxed);
    }
    this->thread_ = std::thread([this] { this->Loop(); });
  }
  ~Gatherer()
  {
    {
      std::lock_guard<std::mutex> lock(this->mutex_);
      this->quit_ = true;
      this->next_.store(this->blocks_, std::memory_order_relaxed);
    }
    this->posted_.notify_one();
    this->thread_.join();
  }
  Gatherer(const Gatherer&) = delete;
  Gatherer& operator=(const Gatherer&) = delete;

  // Starts copying the records of faces idx[0, count) (count <= kMaxFaces) from `base`; a vertex
  // at or past `seen` is not read (its face is deferred by the caller). Stops the last post's
  // copying first.
  void Post(const Rec* base, std::uint64_t seen, const std::uint32_t* idx, std::size_t count)
  {
    if (count > kMaxFaces)
    {
      throw std::length_error("Gatherer::Post: more than kMaxFaces faces");
    }
    this->Stop();
    GatherPosts().fetch_add(1, std::memory_order_relaxed);
    {
      std::lock_guard<std::mutex> lock(this->mutex_);
      this->base_ = base;
      this->seen_ = seen;
      this->idx_ = idx;
      this->count_ = count;
      this->blocks_ = (count + kBlock - 1) / kBlock;
      ++this->generation_; // (the blocks' ready marks of earlier posts no longer count)
      this->next_.store(0, std::memory_order_relaxed);
      this->state_.store(kPosted, std::memory_order_relaxed);
      this->posts_.store(this->generation_, std::memory_order_release);
    }
    this->posted_.notify_one();
  }

  // The records of face t (three), once Take(t / kBlock) returned.
  const Rec* Records(std::size_t t) const { return this->records_.data() + 3 * t; }

  // Whether block b is copied (without waiting).
  bool Ready(std::size_t b) const
  {
    return this->ready_[b].load(std::memory_order_acquire) == this->generation_;
  }

  // Makes sure block b is copied: copies it here if the helper has not claimed it; else, while
  // the helper copies it, copies the next blocks not claimed yet (when the copying is the slower
  // side, both threads copy). Blocks are taken in order.
  void Take(std::size_t b)
  {
    for (unsigned spins = 0; !this->Ready(b);)
    {
      std::size_t claim = this->next_.load(std::memory_order_relaxed);
      if (claim < this->blocks_ && claim <= b + kAheadBlocks &&
        this->next_.compare_exchange_weak(claim, claim + 1, std::memory_order_relaxed))
      {
        this->Copy(claim);
        continue;
      }
      Pause(spins++);
    }
  }

  // Stops the helper's copying of this post (the blocks copied so far stay): from then on only
  // this thread reads the buffer and the blocks. Waits only if the helper has begun this post
  // (it then ends with the block it is copying); a post it has not begun is withdrawn.
  void Stop()
  {
    this->next_.store(this->blocks_, std::memory_order_relaxed);
    int posted = kPosted;
    if (this->state_.compare_exchange_strong(posted, kIdle, std::memory_order_acq_rel))
    {
      return;
    }
    for (unsigned spins = 0; this->state_.load(std::memory_order_acquire) != kIdle; ++spins)
    {
      Pause(spins);
    }
  }

private:
  static void Pause(unsigned spins)
  {
    if (spins < 4096)
    {
#ifdef __SSE2__
      _mm_pause();
#endif
    }
    else
    {
      std::this_thread::yield(); // (the other thread may share this core)
    }
  }

  void Copy(std::size_t b)
  {
    constexpr std::size_t kAhead = 16;
    const std::size_t end = std::min(this->count_, (b + 1) * kBlock);
    const Rec* base = this->base_;
    const std::uint32_t* idx = this->idx_;
    const std::uint64_t seen = this->seen_;
    for (std::size_t t = b * kBlock; t < end; ++t)
    {
      if (t + kAhead < this->count_)
      {
        const std::uint32_t* g = idx + 3 * (t + kAhead);
        for (int k = 0; k < 3; ++k)
        {
          if (g[k] < seen)
          {
            __builtin_prefetch(base + g[k]);
          }
        }
      }
      const std::uint32_t* f = idx + 3 * t;
      Rec* out = this->records_.data() + 3 * t;
      for (int k = 0; k < 3; ++k)
      {
        out[k] = f[k] < seen ? base[f[k]] : Rec{};
      }
    }
    this->ready_[b].store(this->generation_, std::memory_order_release);
  }

  void Loop()
  {
    std::uint64_t done = 0; // the last post handled
    for (;;)
    {
      // A short spin first (some microseconds): the next post usually comes as soon as the
      // clustering thread has added the faces copied.
      for (unsigned spins = 0;
           spins < 256 && this->posts_.load(std::memory_order_acquire) == done; ++spins)
      {
#ifdef __SSE2__
        _mm_pause();
#endif
      }
      {
        std::unique_lock<std::mutex> lock(this->mutex_);
        this->posted_.wait(lock, [&] { return this->quit_ || this->generation_ != done; });
        if (this->quit_)
        {
          return;
        }
        done = this->generation_;
        // (under the lock: no new post between reading this one and beginning it; Stop may
        // have withdrawn it)
        int posted = kPosted;
        if (!this->state_.compare_exchange_strong(posted, kRunning, std::memory_order_acq_rel))
        {
          continue;
        }
      }
      for (;;)
      {
        const std::size_t b = this->next_.fetch_add(1, std::memory_order_relaxed);
        if (b >= this->blocks_)
        {
          break;
        }
        this->Copy(b);
      }
      this->state_.store(kIdle, std::memory_order_release);
    }
  }

  std::vector<Rec> records_;
  std::vector<std::atomic<std::uint64_t>> ready_; // per block: the post that copied it
  // The post (written under the mutex before posts_ is raised; read by the helper after it).
  const Rec* base_ = nullptr;
  std::uint64_t seen_ = 0;
  const std::uint32_t* idx_ = nullptr;
  std::size_t count_ = 0, blocks_ = 0;
  std::uint64_t generation_ = 0;
  bool quit_ = false;
  alignas(64) std::atomic<std::size_t> next_{ 0 }; // the next block to claim
  // The post's state: kPosted until the helper begins it (or Stop withdraws it), kRunning until
  // it ends it, else kIdle.
  static constexpr int kIdle = 0, kPosted = 1, kRunning = 2;
  alignas(64) std::atomic<int> state_{ kIdle };
  std::atomic<std::uint64_t> posts_{ 0 };          // generation_, for the helper's spin
  std::mutex mutex_;
  std::condition_variable posted_;
  std::thread thread_;
};

} // namespace sipmss::algorithms::detail
