// N ranks in one process, one thread each: a Communicator without MPI (the same collectives),
// for the distributed tests and the scaling benchmark.
#pragma once

#include "sipmss/algorithms/Communicator.h"

#include <algorithm>
#include <condition_variable>
#include <exception>
#include <functional>
#include <mutex>
#include <thread>
#include <vector>

namespace sipmss::algorithms
{
class ThreadGroup
{
public:
  explicit ThreadGroup(int n)
    : n_(n)
    , doubles_(std::size_t(n))
    , words_(std::size_t(n))
    , mail_(std::size_t(n))
  {
  }
  int Size() const { return this->n_; }
  // All ranks arrive before any leaves.
  void Barrier()
  {
    std::unique_lock<std::mutex> lock(this->m_);
    const std::uint64_t generation = this->generation_;
    if (++this->arrived_ == this->n_)
    {
      this->arrived_ = 0;
      ++this->generation_;
      this->cv_.notify_all();
      return;
    }
    this->cv_.wait(lock, [&] { return this->generation_ != generation; });
  }
  std::vector<std::vector<double>>& Doubles() { return this->doubles_; }
  std::vector<std::vector<std::uint64_t>>& Words() { return this->words_; }
  std::vector<std::vector<std::vector<std::uint8_t>>>& Mail() { return this->mail_; }

private:
  int n_;
  std::mutex m_;
  std::condition_variable cv_;
  int arrived_ = 0;
  std::uint64_t generation_ = 0;
  std::vector<std::vector<double>> doubles_;
  std::vector<std::vector<std::uint64_t>> words_;
  std::vector<std::vector<std::vector<std::uint8_t>>> mail_; // [from][to]
};

class ThreadCommunicator final : public Communicator
{
public:
  ThreadCommunicator(ThreadGroup& group, int rank)
    : group_(group)
    , rank_(rank)
  {
  }
  int Rank() const override { return this->rank_; }
  int Size() const override { return this->group_.Size(); }
  void AllReduceMin(double* v, std::size_t n) override
  {
    this->Reduce(v, n, [](double a, double b) { return std::min(a, b); });
  }
  void AllReduceMax(double* v, std::size_t n) override
  {
    this->Reduce(v, n, [](double a, double b) { return std::max(a, b); });
  }
  void AllReduceSum(std::uint64_t* v, std::size_t n) override
  {
    auto& w = this->group_.Words();
    w[this->rank_].assign(v, v + n);
    this->group_.Barrier();
    for (std::size_t i = 0; i < n; ++i)
    {
      v[i] = 0;
      for (const auto& r : w)
      {
        v[i] += r[i];
      }
    }
    this->group_.Barrier();
  }
  void Exchange(const std::vector<std::vector<std::uint8_t>>& send,
    std::vector<std::vector<std::uint8_t>>& received) override
  {
    auto& mail = this->group_.Mail();
    mail[this->rank_] = send;
    this->group_.Barrier();
    received.resize(mail.size());
    for (std::size_t r = 0; r < mail.size(); ++r)
    {
      received[r] = mail[r][this->rank_];
    }
    this->group_.Barrier();
  }

private:
  template <class Op>
  void Reduce(double* v, std::size_t n, Op op)
  {
    auto& d = this->group_.Doubles();
    d[this->rank_].assign(v, v + n);
    this->group_.Barrier();
    for (std::size_t i = 0; i < n; ++i)
    {
      for (const auto& r : d)
      {
        v[i] = op(v[i], r[i]);
      }
    }
    this->group_.Barrier();
  }
  ThreadGroup& group_;
  int rank_;
};

// Runs f(communicator) on n ranks (threads) and waits for them; rethrows the first failure.
inline void RunRanks(int n, const std::function<void(Communicator&)>& f)
{
  ThreadGroup group(n);
  std::vector<std::exception_ptr> failures(static_cast<std::size_t>(n));
  std::vector<std::thread> threads;
  for (int r = 0; r < n; ++r)
  {
    threads.emplace_back([&, r] {
      ThreadCommunicator comm(group, r);
      try
      {
        f(comm);
      }
      catch (...)
      {
        failures[std::size_t(r)] = std::current_exception();
      }
    });
  }
  for (auto& t : threads)
  {
    t.join();
  }
  for (auto& e : failures)
  {
    if (e)
    {
      std::rethrow_exception(e);
    }
  }
}
} // namespace sipmss::algorithms
