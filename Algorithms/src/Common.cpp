#include "sipmss/algorithms/Common.h"

namespace sipmss::algorithms
{

void Progress::BeginPhase(const char* phase, double work, double workAfter)
{
  if (this->Aborted())
  {
    throw AbortedError();
  }
  work = work > 0 ? work : 0;
  workAfter = workAfter > 0 ? workAfter : 0;
  const double rest = 1.0 - this->position_;
  const double share = work + workAfter > 0 ? work / (work + workAfter) : 0.0;
  this->phase_ = phase;
  this->begin_ = this->position_;
  this->end_ = workAfter > 0 ? this->position_ + rest * share : 1.0;
  this->last_ = std::chrono::steady_clock::now();
  this->Report(this->position_, this->phase_);
}

void Progress::Finish()
{
  if (this->Aborted())
  {
    throw AbortedError();
  }
  this->begin_ = this->end_ = this->position_ = 1.0;
  this->last_ = std::chrono::steady_clock::now();
  this->Report(1.0, this->phase_);
}

MeshSource FileSource(const std::string& path)
{
  return [path](io::MeshSink& sink, const io::ReadOptions& options) {
    return io::ReadMesh(path, sink, options);
  };
}

} // namespace sipmss::algorithms
