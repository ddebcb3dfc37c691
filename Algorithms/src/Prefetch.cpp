#include "sipmss/algorithms/Prefetch.h"

#include "sipmss/storage/DML.h"

#include <atomic>
#include <chrono>
#include <condition_variable>
#include <deque>
#include <exception>
#include <memory>
#include <mutex>
#include <new>
#include <thread>
#include <vector>

namespace sipmss::algorithms
{
namespace
{

// The chunks' buffers are returnable (storage::AllocateReturnable: mapped when large) so that a
// freed buffer leaves the process at once: the reader thread's allocations would otherwise stay
// resident in a malloc arena of its own, about 1 MB more peak RSS under a small budget.
template <class T>
struct MappedAllocator
{
  using value_type = T;
  MappedAllocator() = default;
  template <class U>
  MappedAllocator(const MappedAllocator<U>&) noexcept
  {
  }
  T* allocate(std::size_t n) { return static_cast<T*>(storage::AllocateReturnable(n * sizeof(T))); }
  void deallocate(T* p, std::size_t n) noexcept { storage::FreeReturnable(p, n * sizeof(T)); }
  template <class U>
  bool operator==(const MappedAllocator<U>&) const noexcept
  {
    return true;
  }
  template <class U>
  bool operator!=(const MappedAllocator<U>&) const noexcept
  {
    return false;
  }
};
template <class T>
using Buffer = std::vector<T, MappedAllocator<T>>;

struct Item
{
  enum Kind
  {
    Begin,
    Vertices,
    Triangles,
    TriangleFlags,
    End
  } kind = Begin;
  io::MeshHeader header;
  io::ReadStats stats;
  std::uint64_t first = 0;
  std::size_t count = 0;
  Buffer<float> xyz, normals, texcoords, scalars;
  Buffer<std::uint8_t> rgba;
  Buffer<std::uint32_t> triangles;
  Buffer<std::uint8_t> flags;
};

// A bounded queue of items plus a pool of spent items for reuse (no allocation per chunk once
// warm).
class Channel
{
public:
  explicit Channel(std::size_t depth)
    : depth_(depth)
  {
  }

  std::unique_ptr<Item> Fresh()
  {
    std::lock_guard<std::mutex> lock(this->mutex_);
    if (this->pool_.empty())
    {
      return std::make_unique<Item>();
    }
    auto item = std::move(this->pool_.back());
    this->pool_.pop_back();
    return item;
  }
  void Recycle(std::unique_ptr<Item> item)
  {
    std::lock_guard<std::mutex> lock(this->mutex_);
    this->pool_.push_back(std::move(item));
  }
  // false when the consumer has stopped
  bool Push(std::unique_ptr<Item> item)
  {
    std::unique_lock<std::mutex> lock(this->mutex_);
    this->notFull_.wait(lock, [&] { return this->items_.size() < this->depth_ || this->stopped_; });
    if (this->stopped_)
    {
      return false;
    }
    this->items_.push_back(std::move(item));
    this->notEmpty_.notify_one();
    return true;
  }
  // nullptr when the producer is done (then Error() may hold its exception). While it waits,
  // poll() runs every 50 ms (it may throw: an abort while the reader is inside a long chunk).
  template <class Poll>
  std::unique_ptr<Item> Pop(Poll&& poll)
  {
    std::unique_lock<std::mutex> lock(this->mutex_);
    while (!this->notEmpty_.wait_for(lock, std::chrono::milliseconds(50),
      [&] { return !this->items_.empty() || this->finished_; }))
    {
      lock.unlock();
      poll();
      lock.lock();
    }
    if (this->items_.empty())
    {
      return nullptr;
    }
    auto item = std::move(this->items_.front());
    this->items_.pop_front();
    this->notFull_.notify_one();
    return item;
  }
  void Finish(std::exception_ptr error)
  {
    std::lock_guard<std::mutex> lock(this->mutex_);
    this->error_ = error;
    this->finished_ = true;
    this->notEmpty_.notify_all();
  }
  void Stop()
  {
    std::lock_guard<std::mutex> lock(this->mutex_);
    this->stopped_ = true;
    this->stopFlag.store(true);
    this->notFull_.notify_all();
  }
  std::exception_ptr Error()
  {
    std::lock_guard<std::mutex> lock(this->mutex_);
    return this->error_;
  }
  std::atomic<bool> stopFlag{ false };

private:
  std::mutex mutex_;
  std::condition_variable notFull_, notEmpty_;
  std::deque<std::unique_ptr<Item>> items_;
  std::vector<std::unique_ptr<Item>> pool_;
  std::size_t depth_;
  bool finished_ = false;
  bool stopped_ = false;
  std::exception_ptr error_;
};

class StoppedError : public std::runtime_error
{
public:
  StoppedError()
    : std::runtime_error("stopped")
  {
  }
};

// The reader's side: copies every call into an item.
class ProducerSink final : public io::MeshSink
{
public:
  explicit ProducerSink(Channel& c)
    : channel_(c)
  {
  }
  void Begin(const io::MeshHeader& h) override
  {
    this->scalars_ = h.layout.scalars.size();
    auto item = this->channel_.Fresh();
    item->kind = Item::Begin;
    item->header = h;
    this->Send(std::move(item));
  }
  void Vertices(const io::VertexChunk& c) override
  {
    auto item = this->channel_.Fresh();
    Release(item->triangles); // (a spent triangle item: its buffer would stay with it for good)
    Release(item->flags);
    item->kind = Item::Vertices;
    item->first = c.first;
    item->count = c.count;
    item->xyz.assign(c.xyz, c.xyz + 3 * c.count);
    Copy(item->normals, c.normals, 3 * c.count);
    Copy(item->rgba, c.rgba, 4 * c.count);
    Copy(item->texcoords, c.texcoords, 2 * c.count);
    Copy(item->scalars, c.scalars, this->scalars_ * c.count);
    this->Send(std::move(item));
  }
  void Triangles(const std::uint32_t* indices, std::size_t count) override
  {
    auto item = this->channel_.Fresh();
    ReleaseVertices(*item);
    item->kind = Item::Triangles;
    item->count = count;
    item->triangles.assign(indices, indices + 3 * count);
    this->Send(std::move(item));
  }
  void TriangleFlags(const std::uint8_t* flags, std::size_t count) override
  {
    auto item = this->channel_.Fresh();
    ReleaseVertices(*item);
    item->kind = Item::TriangleFlags;
    item->count = count;
    item->flags.assign(flags, flags + count);
    this->Send(std::move(item));
  }
  void End(const io::ReadStats& stats) override
  {
    auto item = this->channel_.Fresh();
    item->kind = Item::End;
    item->stats = stats;
    this->Send(std::move(item));
  }
  bool AbortRequested() override { return this->channel_.stopFlag.load(); }

private:
  // A pooled item keeps only the buffers of the kind it carries now: the queue holds at most
  // depth + 2 chunks' buffers, not twice that once the read turns from vertices to triangles.
  template <class T>
  static void Release(Buffer<T>& v)
  {
    Buffer<T>().swap(v);
  }
  static void ReleaseVertices(Item& item)
  {
    Release(item.xyz);
    Release(item.normals);
    Release(item.texcoords);
    Release(item.scalars);
    Release(item.rgba);
  }
  template <class T>
  static void Copy(Buffer<T>& dst, const T* src, std::size_t n)
  {
    if (src)
    {
      dst.assign(src, src + n);
    }
    else
    {
      dst.clear();
    }
  }
  void Send(std::unique_ptr<Item> item)
  {
    if (!this->channel_.Push(std::move(item)))
    {
      throw StoppedError();
    }
  }
  Channel& channel_;
  std::size_t scalars_ = 0;
};

void Dispatch(Item& item, io::MeshSink& sink)
{
  switch (item.kind)
  {
    case Item::Begin:
      sink.Begin(item.header);
      break;
    case Item::Vertices:
    {
      io::VertexChunk c;
      c.first = item.first;
      c.count = item.count;
      c.xyz = item.xyz.data();
      c.normals = item.normals.empty() ? nullptr : item.normals.data();
      c.rgba = item.rgba.empty() ? nullptr : item.rgba.data();
      c.texcoords = item.texcoords.empty() ? nullptr : item.texcoords.data();
      c.scalars = item.scalars.empty() ? nullptr : item.scalars.data();
      sink.Vertices(c);
      break;
    }
    case Item::Triangles:
      sink.Triangles(item.triangles.data(), item.count);
      break;
    case Item::TriangleFlags:
      sink.TriangleFlags(item.flags.data(), item.count);
      break;
    case Item::End:
      sink.End(item.stats);
      break;
  }
}

} // namespace

MeshSource Prefetched(MeshSource source, std::size_t depth)
{
  return [source = std::move(source), depth](
           io::MeshSink& sink, const io::ReadOptions& options) -> io::ReadStats {
    Channel channel(depth < 1 ? 1 : depth);
    io::ReadStats result;
    std::thread reader([&] {
      std::exception_ptr error;
      try
      {
        ProducerSink producer(channel);
        result = source(producer, options);
      }
      catch (const StoppedError&)
      {
      }
      catch (...)
      {
        error = std::current_exception();
      }
      channel.Finish(error);
    });
    try
    {
      const auto poll = [&] {
        if (sink.AbortRequested())
        {
          throw AbortedError();
        }
      };
      while (auto item = channel.Pop(poll))
      {
        if (sink.AbortRequested())
        {
          throw AbortedError();
        }
        Dispatch(*item, sink);
        channel.Recycle(std::move(item));
      }
    }
    catch (...)
    {
      channel.Stop();
      reader.join();
      throw;
    }
    reader.join();
    if (std::exception_ptr e = channel.Error())
    {
      std::rethrow_exception(e);
    }
    return result;
  };
}

} // namespace sipmss::algorithms
