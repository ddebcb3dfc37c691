// Shared vocabulary of the VTK-free algorithm cores: input sources, progress/abort, statistics.
#pragma once

#include "sipmss/io/MeshIO.h"
#include "sipmss/storage/DML.h"

#include <array>
#include <chrono>
#include <cstdint>
#include <functional>
#include <stdexcept>
#include <string>
#include <vector>

namespace sipmss::algorithms
{

// Thrown when the caller's Progress::Aborted() returned true.
class AbortedError : public std::runtime_error
{
public:
  AbortedError()
    : std::runtime_error("aborted by the user")
  {
  }
};

// Progress and abort. The cores call Tick() often (cheap); it forwards to Report() at most every
// `interval` seconds and throws AbortedError when Aborted() says so.
class Progress
{
public:
  virtual ~Progress() = default;
  virtual void Report(double fraction, const char* phase) = 0; // fraction in [0,1] of the run
  virtual bool Aborted() { return false; }

  // Sets the phase and its share [begin, end) of the whole run.
  void BeginPhase(const char* phase, double begin, double end)
  {
    this->phase_ = phase;
    this->begin_ = begin;
    this->end_ = end;
    this->Emit(0.0);
  }
  // fractionOfPhase in [0,1]
  void Tick(double fractionOfPhase)
  {
    auto now = std::chrono::steady_clock::now();
    if (now - this->last_ >= this->interval_)
    {
      this->Emit(fractionOfPhase);
    }
  }
  void SetInterval(double seconds)
  {
    this->interval_ = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
      std::chrono::duration<double>(seconds));
  }

private:
  void Emit(double f)
  {
    this->last_ = std::chrono::steady_clock::now();
    if (this->Aborted())
    {
      throw AbortedError();
    }
    f = f < 0 ? 0 : (f > 1 ? 1 : f);
    this->Report(this->begin_ + (this->end_ - this->begin_) * f, this->phase_);
  }
  const char* phase_ = "";
  double begin_ = 0, end_ = 1;
  std::chrono::steady_clock::time_point last_{};
  std::chrono::steady_clock::duration interval_ = std::chrono::milliseconds(50);
};

// A progress that reports nothing and never aborts.
class NullProgress final : public Progress
{
public:
  void Report(double, const char*) override {}
};

// A replayable mesh input: each call streams the whole mesh (header, vertex chunks, triangle
// chunks, end) into the sink. Files replay by re-reading; in-memory meshes by re-emitting.
// Algorithms may call it more than once (e.g. a bounds pass with verticesOnly).
using MeshSource = std::function<io::ReadStats(io::MeshSink& sink, const io::ReadOptions& options)>;

// A source that streams a file through the IO readers.
MeshSource FileSource(const std::string& path);

// One timed phase of a run, for --stats-json and the filters' statistics.
struct PhaseStat
{
  std::string name;
  double seconds = 0;
  storage::Mode mode = storage::Mode::InCore;
};

struct RunStats
{
  std::uint64_t inputVertices = 0;
  std::uint64_t inputTriangles = 0;
  std::uint64_t outputVertices = 0;
  std::uint64_t outputTriangles = 0;
  std::uint64_t droppedInputFaces = 0;
  std::vector<PhaseStat> phases;
  storage::Stats storage; // the DML's statistics at the end of the run (peak, hits, misses, ...)
};

// Times one phase and records the DML mode in use when it ends.
class PhaseTimer
{
public:
  PhaseTimer(RunStats& stats, storage::DML& dml, std::string name)
    : stats_(stats)
    , dml_(dml)
    , name_(std::move(name))
    , start_(std::chrono::steady_clock::now())
  {
  }
  ~PhaseTimer()
  {
    PhaseStat p;
    p.name = this->name_;
    p.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - this->start_).count();
    p.mode = this->dml_.GetMode();
    this->stats_.phases.push_back(std::move(p));
  }

private:
  RunStats& stats_;
  storage::DML& dml_;
  std::string name_;
  std::chrono::steady_clock::time_point start_;
};

} // namespace sipmss::algorithms
