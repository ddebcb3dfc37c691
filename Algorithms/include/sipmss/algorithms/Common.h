// Shared vocabulary of the VTK-free algorithm cores: input sources, progress/abort, statistics.
#pragma once

#include "sipmss/io/MeshIO.h"
#include "sipmss/algorithms/Communicator.h"
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

// The input has no array of the name an option gives (a lock, selection or attribute array).
class MissingArrayError : public io::MeshIOError
{
public:
  using io::MeshIOError::MeshIOError;
};

// Thrown when the caller's Progress::Aborted() returned true.
class AbortedError : public std::runtime_error
{
public:
  AbortedError()
    : std::runtime_error("aborted by the user")
  {
  }
};

// Progress and abort.
//
// The run's progress is a position in [0,1] that only moves forward. A core announces each phase
// with the work it is about to do and its estimate of the work of everything after it (in one
// unit per algorithm: measured seconds per element, see docs/architecture.md): the phase spans
// that share of what is left of the run, from the current position. An estimate that turns out
// wrong (a pass that removes fewer triangles than planned, an extra pass) changes how fast the
// rest of the run moves, never its direction; the last phase (no work after it) ends at 1, and
// Finish() reports 1.
//
// Polls: the cores call Tick() every few thousand elements of every long loop (a counter test in
// the loop, no clock read per element). Each Tick asks Aborted() (AbortedError within
// milliseconds of the request) and forwards to Report() when `interval` seconds have passed since
// the last report.
class Progress
{
public:
  virtual ~Progress() = default;
  // fraction in [0,1] of the run, never decreasing; phase: the current phase's name
  virtual void Report(double fraction, const char* phase) = 0;
  virtual bool Aborted() { return false; }

  // Starts a phase that does `work` units, with `workAfter` units (an estimate) after it: it
  // spans work / (work + workAfter) of the rest [Position(), 1]. Reports, and checks Aborted().
  void BeginPhase(const char* phase, double work, double workAfter);
  // fractionOfPhase in [0,1], non-decreasing within a phase.
  void Tick(double fractionOfPhase)
  {
    this->Move(fractionOfPhase);
    this->Poll();
  }
  // A tick that does not move (work whose share is not known, e.g. a hash table's growth):
  // checks Aborted() and reports the current position when it is due.
  void Poll()
  {
    if (this->Aborted())
    {
      throw AbortedError();
    }
    const auto now = std::chrono::steady_clock::now();
    if (now - this->last_ >= this->interval_)
    {
      this->last_ = now;
      this->Report(this->position_, this->phase_);
    }
  }
  // The end of the run: position 1, reported.
  void Finish();
  // Called by a core once it knows its input's size, before any work on it (the two-stage run
  // sizes its stages' shares from it). Default: nothing.
  virtual void Sized(std::uint64_t vertices, std::uint64_t faces)
  {
    (void)vertices;
    (void)faces;
  }
  // For a progress that carries a nested run's (two-stage): moves to `fraction` (the caller
  // keeps it non-decreasing) and reports it under `phase`.
  void ReportNested(double fraction, const char* phase)
  {
    this->begin_ = this->end_ = this->position_ = fraction;
    this->Report(fraction, phase);
  }
  double Interval() const { return std::chrono::duration<double>(this->interval_).count(); }
  double Position() const { return this->position_; }
  const char* Phase() const { return this->phase_; }
  // Report() at most this often (Tick's polls for Aborted() are not limited). Default 0.05 s.
  void SetInterval(double seconds)
  {
    this->interval_ = std::chrono::duration_cast<std::chrono::steady_clock::duration>(
      std::chrono::duration<double>(seconds));
  }

private:
  void Move(double f)
  {
    f = f < 0 ? 0 : (f > 1 ? 1 : f);
    this->position_ = this->begin_ + (this->end_ - this->begin_) * f;
  }
  const char* phase_ = "";
  double begin_ = 0, end_ = 0, position_ = 0;
  std::chrono::steady_clock::time_point last_{};
  std::chrono::steady_clock::duration interval_ = std::chrono::milliseconds(50);
};

// Progress planning for runs that chain cores (two-stage): the estimated work of a run on V
// vertices and F faces, in the cores' progress unit (measured seconds per element), and the
// estimated faces of a clustering's output.
struct ClusterOptions;
struct DecimateOptions;
double EstimateClusterWork(std::uint64_t V, std::uint64_t F, const ClusterOptions& options);
double EstimateClusterFaces(std::uint64_t V, std::uint64_t F, const ClusterOptions& options);
double EstimateDecimateWork(std::uint64_t V, std::uint64_t F, const DecimateOptions& options);
// The bytes of a clustering's structures on V vertices and F faces (what it declares to the DML).
double EstimateClusterBytes(std::uint64_t V, std::uint64_t F, const ClusterOptions& options);
// Whether a clustering on V vertices and F faces in the grid over `bounds` goes out of core under
// options.storage (the mode its Config will choose; V = 0: an input of unknown size, as one of any
// size). The clustering and two-stage reorder an incoherent input only then (docs/architecture.md,
// "Input layout").
bool ClusterGoesOutOfCore(const ClusterOptions& options, std::uint64_t V, std::uint64_t F,
  const std::array<double, 6>& bounds);

// Defaults and ranges shared by every front end (SimplifyRequest, Simplify.h) and the cores'
// option structs.
constexpr int kDefaultClusterGrid = 50;   // cluster: cells along the longest axis
constexpr int kDefaultTwoStageGrid = 300; // two-stage: stage 1's grid (the coarsest automatic one)
// Two-stage with a triangle target T and no grid given: stage 1's grid is 300, or finer when the
// target needs it: the grid whose clustered mesh has about kTwoStageClusteredPerTarget * T
// triangles, a scan's clustered mesh having about kClusteredTrianglesPerGridSquare * g^2
// triangles at grid g (Dragon-size 3.8, Lucy-size 3.0 at grid 300): max(300, ceil(sqrt(16 T /
// 3.4))), finer than 300 from 19,126 triangles on (docs/architecture.md, "Two-stage's grid").
constexpr double kTwoStageClusteredPerTarget = 16;
constexpr double kClusteredTrianglesPerGridSquare = 3.4;
// Two-stage with an automatic grid finer than kDefaultTwoStageGrid (a large target) skips stage 1
// and decimates the input as it is when the clustered mesh would keep at least this fraction of
// the input's triangles (TwoStageOptions::automaticGrid): clustering then saves stage 2 little
// and costs more than it saves (docs/architecture.md, "Two-stage's grid").
constexpr double kStageOneSkipFraction = 0.7;
int AutomaticTwoStageGrid(std::uint64_t targetTriangles);
constexpr int kMaximumGrid = 65535;
constexpr double kDefaultTargetReduction = 0.9;
constexpr double kDefaultClusterBoundaryWeight = 0;    // off
constexpr double kDefaultDecimateBoundaryWeight = 100; // decimate, two-stage
constexpr double kNoWeld = -1;
constexpr int kMaximumLevelsOfDetail = 64;
constexpr int kMaximumThreads = 256;

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

// The memory budget of every front end (CLI --memory-mb, the filters' MemoryBudgetMB), in MiB:
// 0 (the default) is automatic, a share of the memory this process may use
// (storage::AutomaticBudget: half of the lowest of the cgroup limit, ulimit -v/-d and
// MemAvailable); -1 is unbounded (always in core); else at least kMinimumMemoryBudgetMB (a
// smaller budget would round to nothing) and at most 1e9. MemoryBudgetProblem returns what is
// wrong with `megabytes`, or an empty string.
constexpr double kAutomaticMemoryBudget = 0;
constexpr double kUnboundedMemoryBudget = -1;
constexpr double kMinimumMemoryBudgetMB = 0.0625; // 64 KiB
std::string MemoryBudgetProblem(double megabytes);
// The CLI's words for the two special values ("auto", "unbounded") or a number; false if the
// text is neither.
bool ParseMemoryBudget(const std::string& text, double& megabytes);
// Sets profile.memoryBudget and profile.budgetOrigin from a valid front-end value.
void ApplyMemoryBudget(double megabytes, storage::Profile& profile);

// Thrown instead of std::bad_alloc by the cores: names the phase, the budget, how it was chosen
// and the option to change.
class OutOfMemoryError : public std::runtime_error
{
public:
  using std::runtime_error::runtime_error;
};
std::string OutOfMemoryMessage(const char* phase, const storage::Profile& profile);
// Runs f(); a std::bad_alloc becomes an OutOfMemoryError for the progress's current phase.
template <class F>
auto TranslateOutOfMemory(const Progress& progress, const storage::Profile& profile, F&& f)
  -> decltype(f())
{
  try
  {
    return f();
  }
  catch (const std::bad_alloc&)
  {
    throw OutOfMemoryError(OutOfMemoryMessage(progress.Phase(), profile));
  }
}

// A source that streams a file through the IO readers.
// tmpdir: where a FIFO or device input is copied as it is first read (empty: $TMPDIR or /tmp).
MeshSource FileSource(const std::string& path, const std::string& tmpdir = {});

// One timed phase of a run, for --stats-json and the filters' statistics.
struct PhaseStat
{
  std::string name;
  double seconds = 0;
  storage::Mode mode = storage::Mode::InCore;
};

// One pass of the decimation (Algorithm I, docs/architecture.md "Algorithm I and the two-stage
// method in brief"): its sizes, its work and where its time went.
struct PassStat
{
  std::string run; // "" for a run of its own; "stage 2 ", "piece ", "gathered " as in phases
  std::uint64_t vertices = 0;       // vertices at the pass's start (dead ones included)
  std::uint64_t triangles = 0;      // live triangles at the pass's start
  std::uint64_t goal = 0;           // the triangle count the pass stops at
  std::uint64_t trianglesAfter = 0; // live triangles at its end
  std::uint64_t activeVertices = 0; // vertices that went over their edges (step 1)
  std::uint64_t edgesPlaced = 0;    // edges given a placement and a cost (step 1)
  std::uint64_t candidates = 0;     // candidates taken in cost order (step 2)
  std::uint64_t collapses = 0;      // collapses made (step 3)
  std::uint64_t illegal = 0;        // candidates found illegal (step 3)
  // Its four steps: the candidate sweep, the cost order, the collapse step, the compaction.
  // Out of core, the step's I/O by array: "positions", "quadrics", "faces", "ring offsets",
  // "ring faces", "states", "candidates", "order", "remap", "attributes", "attribute terms",
  // "fit samples", "face selection", "fitted positions", in that order, then "other" (blocks
  // the pass does not name, or closed during the step); only those with I/O. They add up to
  // the step's totals.
  struct ArrayIo
  {
    std::string name;
    std::uint64_t misses = 0, bytesRead = 0, bytesWritten = 0;
  };
  struct Step
  {
    double seconds = 0;
    std::uint64_t bytesRead = 0, bytesWritten = 0, misses = 0; // the DML's, during the step
    std::vector<ArrayIo> arrays;
  };
  Step sweep, order, step, compact;
  storage::Mode mode = storage::Mode::InCore; // the DML's at the pass's end
};

// One part of the layout step (docs/architecture.md, "Input layout"), in the order they ran:
// "vertices by key", "inverse", "point data" (inputs with point data), "faces renumbered",
// "faces sorted". The DML's I/O during the part, and its block files' size at the end.
struct LayoutStepStat
{
  std::string name;
  double seconds = 0;
  std::uint64_t bytesRead = 0, bytesWritten = 0, fileBytes = 0;
};

// The layout step for inputs whose vertices and faces are not in a spatially coherent order
// (docs/architecture.md, "Input layout"). Automatic: the first faces are measured and an
// incoherent input is copied into the DML and reordered (vertices along a Morton curve, faces by
// their lowest vertex) before the core runs on it: always in the decimation, only out of core in
// the clustering and two-stage. Keep: never. Reorder: always (the result is the core's on the
// reordered mesh, in any storage mode).
enum class LayoutPolicy : std::uint8_t
{
  Automatic,
  Keep,
  Reorder
};

struct RunStats
{
  // The input's layout as measured (share of faces far from their neighbours in index order;
  // -1: not measured, the run fit in memory) and whether the run reordered it.
  double layoutFarFraction = -1;
  bool reordered = false;
  std::vector<LayoutStepStat> layoutSteps; // the reorder's parts, when it ran
  std::uint64_t inputVertices = 0;
  std::uint64_t inputTriangles = 0;
  std::uint64_t outputVertices = 0;
  std::uint64_t outputTriangles = 0;
  std::uint64_t droppedInputFaces = 0;
  // Disconnected pieces removed by DecimateOptions::pruneSize, and their triangles.
  std::uint64_t prunedComponents = 0;
  std::uint64_t prunedTriangles = 0;
  // The error of the run's merges (docs/architecture.md, "Error bound"): the largest
  // sqrt(Q(p) / trace(Q)) of a merged vertex (a collapse's survivor, a cluster's representative),
  // the area-weighted RMS distance of its position to the planes of the input faces it stands
  // for, divided by errorDiagonal, the input's bounding-box diagonal (-1: not measured, no run).
  double achievedError = -1;
  double errorDiagonal = 0;
  // The grid the run clustered on (Cluster's maximumGridDimension, two-stage's stage 1; through
  // Simplify() the one SimplifyRequest::EffectiveGrid chose); 0: no clustering (decimation, a
  // two-stage run that skipped stage 1).
  int gridDimension = 0;
  std::vector<PhaseStat> phases;
  std::vector<PassStat> passes; // the decimation's passes, in order (none for a clustering)
  storage::Stats storage; // the DML's statistics at the end of the run (peak, hits, misses, ...)
  // The budget the run had (bytes, 0: unbounded) and how it was chosen (empty: given), as
  // Simplify() computed it once for the run.
  std::uint64_t memoryBudgetBytes = 0;
  std::string memoryBudgetOrigin;
  // A distributed run (ClusterOptions::communicator): this rank's share of the traffic.
  CommunicationStats communication;
  // What the user should know about the result (the CLI prints them as warnings, also with
  // --quiet, and lists them in the stats JSON; the filters report them as VTK warnings).
  std::vector<std::string> warnings;
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
