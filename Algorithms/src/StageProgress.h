// A nested run's progress inside its caller's (two-stage's stages, the distributed decimation's
// passes), and its statistics added to the caller's. Internal to the algorithm cores.
#pragma once

#include "sipmss/algorithms/Common.h"

#include <algorithm>
#include <functional>
#include <string>

namespace sipmss::algorithms::detail
{
// Carries a stage's progress into the run's: the stage's [0,1] maps to [begin, end] of the
// run. The first stage's end is set from the stages' estimated work once the input's size is
// known (Sized, before any work on it); the second stage runs to 1.
class StageProgress final : public Progress
{
public:
  StageProgress(Progress& parent, const char* prefix,
    std::function<double(std::uint64_t, std::uint64_t)> share = nullptr)
    : parent_(parent)
    , begin_(parent.Position())
    , end_(share ? begin_ + 0.5 * (1.0 - begin_) : 1.0)
    , prefix_(prefix)
    , share_(std::move(share))
  {
    this->SetInterval(parent.Interval());
  }
  void Report(double f, const char* phase) override
  {
    this->label_ = std::string(this->prefix_) + phase;
    this->parent_.ReportNested(this->begin_ + (this->end_ - this->begin_) * f, this->label_.c_str());
  }
  bool Aborted() override { return this->parent_.Aborted(); }
  void Sized(std::uint64_t vertices, std::uint64_t faces) override
  {
    if (this->share_ && this->Position() == 0.0)
    {
      const double s = std::min(1.0, std::max(0.0, this->share_(vertices, faces)));
      this->end_ = this->begin_ + s * (1.0 - this->begin_);
    }
  }

private:
  Progress& parent_;
  double begin_, end_;
  const char* prefix_;
  std::function<double(std::uint64_t, std::uint64_t)> share_;
  std::string label_;
};

// Appends the phases and the passes of a nested run (a stage, a piece) to its caller's, named
// with `prefix` ("stage 2 ", "piece ", ...).
inline void AddNestedRun(RunStats& to, const RunStats& from, const char* prefix)
{
  for (PhaseStat p : from.phases)
  {
    p.name = prefix + p.name;
    to.phases.push_back(std::move(p));
  }
  for (PassStat p : from.passes)
  {
    p.run = prefix + p.run;
    to.passes.push_back(std::move(p));
  }
}
} // namespace sipmss::algorithms::detail
