#include "sipmss/algorithms/Common.h"

#include "sipmss/storage/Memory.h"

#include <sstream>

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

std::string MemoryBudgetProblem(double megabytes)
{
  if (megabytes == kAutomaticMemoryBudget || megabytes == kUnboundedMemoryBudget ||
    (megabytes >= kMinimumMemoryBudgetMB && megabytes <= 1e9))
  {
    return {};
  }
  std::ostringstream m;
  m << "must be 0 (automatic), -1 (unbounded) or between " << kMinimumMemoryBudgetMB
    << " (64 KiB) and 1e9 MiB, not " << megabytes;
  return m.str();
}

bool ParseMemoryBudget(const std::string& text, double& megabytes)
{
  if (text == "auto" || text == "automatic")
  {
    megabytes = kAutomaticMemoryBudget;
    return true;
  }
  if (text == "unbounded")
  {
    megabytes = kUnboundedMemoryBudget;
    return true;
  }
  std::istringstream in(text);
  double v = 0;
  in >> v;
  if (!in || !in.eof() || text.empty())
  {
    return false;
  }
  megabytes = v;
  return true;
}

namespace
{
std::string MiB(std::uint64_t bytes)
{
  std::ostringstream m;
  m.setf(std::ios::fixed);
  m.precision(bytes < (std::uint64_t(10) << 20) ? 2 : 0);
  m << static_cast<double>(bytes) / (1024.0 * 1024.0) << " MiB";
  return m.str();
}
} // namespace

void ApplyMemoryBudget(double megabytes, storage::Profile& profile)
{
  if (megabytes == kUnboundedMemoryBudget)
  {
    profile.memoryBudget = 0;
    profile.budgetOrigin = "unbounded";
  }
  else if (megabytes == kAutomaticMemoryBudget)
  {
    const storage::MemoryLimit available = storage::AvailableMemory();
    profile.memoryBudget = storage::AutomaticBudget(available);
    profile.budgetOrigin = profile.memoryBudget == 0
      ? "automatic: no memory limit known, unbounded"
      : "automatic: half of the " + MiB(available.bytes) + " left under " + available.source;
  }
  else
  {
    profile.memoryBudget = static_cast<std::uint64_t>(megabytes * 1024.0 * 1024.0);
    profile.budgetOrigin.clear();
  }
}

std::string OutOfMemoryMessage(const char* phase, const storage::Profile& profile)
{
  std::string m = "out of memory";
  if (phase && *phase)
  {
    m += std::string(" in the ") + phase + " phase";
  }
  if (profile.memoryBudget == 0)
  {
    m += " with an unbounded memory budget";
  }
  else
  {
    m += " with a memory budget of " + MiB(profile.memoryBudget);
  }
  if (!profile.budgetOrigin.empty() && profile.budgetOrigin != "unbounded")
  {
    m += " (" + profile.budgetOrigin + ")";
  }
  m += profile.memoryBudget == 0
    ? ": set a budget (--memory-mb auto or MiB, MemoryBudgetMB 0 or MiB) so that what does not "
      "fit goes to disk, or free memory"
    : ": set a smaller budget (--memory-mb, MemoryBudgetMB) so that more of the run goes to "
      "disk, or free memory";
  return m;
}

// Every pass reads the same input (io::MeshInputFile: a FIFO or /dev/stdin is copied once to an
// unlinked temporary file as it is first read). An input without a vertex, or whose full read
// gives no valid triangle, is the same named error for every algorithm and filter (the CLI's
// words): "FILE: nothing to simplify: the input has no valid triangle[ (N degenerate faces were
// dropped)]". A reader stopped by the sink's AbortRequested() is an AbortedError.
MeshSource FileSource(const std::string& path, const std::string& tmpdir)
{
  auto input = std::make_shared<io::MeshInputFile>(path, tmpdir);
  return [input](io::MeshSink& sink, const io::ReadOptions& options) {
    io::ReadStats stats;
    try
    {
      stats = input->Read(sink, options);
    }
    catch (const io::ReadAbortedError&)
    {
      throw AbortedError();
    }
    if (stats.vertices == 0 || (!options.verticesOnly && stats.triangles == 0))
    {
      throw io::MeshIOError(input->Path() +
        ": nothing to simplify: the input has no valid triangle" +
        (stats.droppedFaces
            ? " (" + std::to_string(stats.droppedFaces) + " degenerate faces were dropped)"
            : std::string()));
    }
    return stats;
  };
}

} // namespace sipmss::algorithms
