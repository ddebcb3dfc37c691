// What a distributed run needs of MPI, as a small interface: the cores stay free of MPI (and of
// VTK). The VTK module implements it over vtkMultiProcessController (vtkSIPMSSCommunicator),
// the tests over threads in one process.
#pragma once

#include <chrono>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace sipmss::algorithms
{
class Communicator
{
public:
  virtual ~Communicator() = default;
  virtual int Rank() const = 0;
  virtual int Size() const = 0;
  // Element-wise reductions over all ranks, in place. Collective: every rank calls them in the
  // same order.
  virtual void AllReduceMin(double* values, std::size_t n) = 0;
  virtual void AllReduceMax(double* values, std::size_t n) = 0;
  virtual void AllReduceSum(std::uint64_t* values, std::size_t n) = 0;
  // A personalized exchange: send[r] goes to rank r (send.size() == Size()); on return
  // received[r] holds what rank r sent to this one. Collective.
  virtual void Exchange(const std::vector<std::vector<std::uint8_t>>& send,
    std::vector<std::vector<std::uint8_t>>& received) = 0;
};

// What one rank of a distributed run sent and received, and the time it spent in collectives
// (waiting for the other ranks included).
struct CommunicationStats
{
  int rank = 0;
  int ranks = 1;
  std::uint64_t bytesSent = 0;     // to the other ranks (not to itself)
  std::uint64_t bytesReceived = 0; // from the other ranks
  std::uint64_t rounds = 0;        // exchanges
  double seconds = 0;
  // Every rank's bytes sent, bytes received, seconds and rounds (4 values a rank, by rank),
  // gathered before the output is written.
  std::vector<double> perRank;

  // Adds another part of the same run's traffic (e.g. two-stage's first stage, a file's scatter);
  // perRank element-wise where both have it.
  void Add(const CommunicationStats& o)
  {
    this->bytesSent += o.bytesSent;
    this->bytesReceived += o.bytesReceived;
    this->rounds += o.rounds;
    this->seconds += o.seconds;
    for (std::size_t i = 0; i < this->perRank.size() && i < o.perRank.size(); ++i)
    {
      this->perRank[i] += o.perRank[i];
    }
  }
};
} // namespace sipmss::algorithms
