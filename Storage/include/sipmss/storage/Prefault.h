// Fresh memory made present ahead of its first use, on a thread of its own.
//
// The first write to a page of fresh anonymous memory faults: the kernel takes a page and zeroes
// it (on a virtual machine the host may first have to back it). For a run in core that is a
// large part of the phases that fill new blocks: on this project's development VM, reading
// Lucy-size into the decimation's blocks spent 90% of its samples in the kernel's clear_page.
// A Prefaulter asks the kernel to make given ranges present (madvise MADV_POPULATE_WRITE,
// Linux 5.14 and later), 2 MiB at a time, while the caller fills them from the start: the
// zeroing then runs on another core. The kernel never changes the contents of a page that is
// present, so the caller may write the ranges at the same time; what it wrote stays.
//
// The ranges must stay mapped until Stop() (the destructor stops too): stop before a range is
// freed or moved (a block's Resize, CloseBlock, the DML's destruction or reconfiguration).
#pragma once

#include <atomic>
#include <cstddef>
#include <thread>
#include <vector>

namespace sipmss::storage
{
class Prefaulter
{
public:
  struct Range
  {
    void* data = nullptr;
    std::size_t bytes = 0;
  };
  Prefaulter() = default;
  ~Prefaulter() { this->Stop(); }
  Prefaulter(const Prefaulter&) = delete;
  Prefaulter& operator=(const Prefaulter&) = delete;

  // Starts making the ranges present, in order, on a thread of its own (after stopping a
  // previous start). False when nothing is started: no range, or no thread could be made.
  bool Start(std::vector<Range> ranges);
  // Stops at the next 2 MiB step and waits for the thread (nothing when none runs).
  void Stop() noexcept;
  // Bytes made present so far (whole steps), and whether the kernel refused the request (an
  // older kernel: the thread then stops at once; nothing is lost but the head start).
  std::size_t Populated() const { return this->populated_.load(std::memory_order_relaxed); }
  bool Refused() const { return this->refused_.load(std::memory_order_relaxed); }

  // One range made present now, on the calling thread; false when the kernel refuses.
  static bool Populate(void* data, std::size_t bytes);

private:
  std::thread thread_;
  std::atomic<bool> stop_{ false };
  std::atomic<bool> refused_{ false };
  std::atomic<std::size_t> populated_{ 0 };
};
} // namespace sipmss::storage
