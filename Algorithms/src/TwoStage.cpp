#include "sipmss/algorithms/TwoStage.h"

#include <cmath>
#include "sipmss/algorithms/Quadric.h"

#include "StageProgress.h"
#include "StoredMesh.h"

#include <algorithm>
#include <cstring>
#include <optional>
#include <sstream>
#include <string>

#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace sipmss::algorithms
{
namespace
{
using detail::AddNestedRun;
using detail::StageProgress;
using storage::Array;
using storage::DML;
} // namespace

namespace
{
using OnLevel = std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>;

// Stage 1's share of the run: its work against stage 2's on the estimated clustered mesh (about
// half as many vertices as faces).
std::function<double(std::uint64_t, std::uint64_t)> StageOneShare(
  const ClusterOptions& co, const DecimateOptions& d2)
{
  return [co, d2](std::uint64_t V, std::uint64_t F) {
    const double w1 = EstimateClusterWork(V, F, co);
    const double faces = EstimateClusterFaces(V, F, co);
    const double w2 = EstimateDecimateWork(std::uint64_t(faces / 2), std::uint64_t(faces), d2);
    return w1 + w2 > 0 ? w1 / (w1 + w2) : 0.5;
  };
}

// Stage 2's options: on the run's DML, the errors relative to the input's box, and what the
// grid left of a bound (nothing but exact collapses when the grid alone exceeds it: the two
// stages' errors add up).
DecimateOptions StageTwoOptions(const TwoStageOptions& options, const RunStats& s1, DML& dml)
{
  DecimateOptions dopt = options.decimate;
  dopt.dml = &dml;
  dopt.errorDiagonal = s1.errorDiagonal;
  if (std::isfinite(dopt.maximumError))
  {
    const double used =
      std::max(0.0, s1.achievedError) * (dopt.absoluteError ? s1.errorDiagonal : 1.0);
    dopt.spentError += used;
  }
  return dopt;
}

// A warning when the grid alone used up the error bound of the run or of some of its levels:
// their decimation may make only collapses without error, so they stay at about the clustered
// mesh's size.
void WarnSpentBound(const DecimateOptions& dopt, RunStats& stats)
{
  if (!std::isfinite(dopt.maximumError) || dopt.spentError <= 0)
  {
    return;
  }
  const int K = std::max(1, dopt.levelsOfDetail);
  int spent = 0; // the finest levels, 0 to spent - 1, have a bound no larger than the grid's error
  while (spent < K && LevelBound(dopt, spent) <= dopt.spentError)
  {
    ++spent;
  }
  if (spent == 0)
  {
    return;
  }
  std::ostringstream m;
  m << "two-stage: the clustering's error (" << dopt.spentError
    << (dopt.absoluteError ? "" : " of the diagonal") << ") already reaches the error bound of "
    << (K == 1 ? std::string("the run")
          : spent == K ? std::string("every level of detail")
          : spent == 1 ? std::string("level of detail 0")
                       : "levels of detail 0 to " + std::to_string(spent - 1))
    << " (" << LevelBound(dopt, spent - 1) << "): only collapses without error (in flat regions) are made there, so "
    << (K == 1 ? "the output stays" : spent == 1 ? "that level stays" : "those levels stay")
    << " at about the clustered mesh's size; a finer grid leaves more of the bound to the "
       "decimation";
  stats.warnings.push_back(m.str());
}

// Stage 2 on the clustered mesh, its statistics added to the run's. Stage 2 measures its
// collapses against the clustered mesh's planes (with the cell quadrics carried, against those
// and the cells' input planes together): the two stages' errors add up (a bound of the distance
// to the input's planes, not a measure of it).
RunStats RunStageTwo(detail::StoredMesh& handoff, io::MeshSink& output, const DecimateOptions& dopt,
  Progress& progress, const OnLevel& onLevel, const RunStats& s1, RunStats& stats)
{
  StageProgress p2(progress, "stage 2: ");
  RunStats s2 = Decimate(
    [&handoff](io::MeshSink& sink, const io::ReadOptions& ro) { return handoff.Replay(sink, ro); },
    output, dopt, p2, onLevel);
  AddNestedRun(stats, s2, "stage 2 ");
  stats.outputVertices = s2.outputVertices;
  stats.outputTriangles = s2.outputTriangles;
  stats.prunedComponents = s2.prunedComponents; // (pieces of the clustered mesh)
  stats.prunedTriangles = s2.prunedTriangles;
  stats.errorDiagonal = s1.errorDiagonal;
  stats.achievedError = std::max(0.0, s1.achievedError) + std::max(0.0, s2.achievedError);
  stats.warnings.insert(stats.warnings.end(), s2.warnings.begin(), s2.warnings.end());
  WarnSpentBound(dopt, stats);
  return s2;
}

// Two-stage across ranks (DecimateOptions::communicator with more than one rank): stage 1 is
// the distributed clustering (each rank's piece of the exact serial clustering, its vertices
// at the same positions on every rank that shares them), stage 2 the distributed decimation
// of those pieces (borders locked, then joined and decimated on rank 0). Both stages use this
// rank's one DML; the clustered piece is freed as soon as stage 2 has read it.
RunStats TwoStageDistributed(const MeshSource& input, io::MeshSink& output,
  const TwoStageOptions& options, Progress& progress, const OnLevel& onLevel)
{
  if (options.carryQuadrics)
  {
    throw std::invalid_argument("two-stage carries no cell quadrics on more than one rank");
  }
  DML dml;
  dml.Config(options.decimate.storage);
  RunStats stats;
  detail::StoredMesh handoff(dml);
  RunStats s1;
  {
    ClusterOptions co;
    co.maximumGridDimension = options.gridDimension;
    co.storage = options.decimate.storage;
    co.threads = options.threads;
    co.attributes = options.decimate.attributes;
    co.communicator = options.decimate.communicator;
    co.dml = &dml; // (exact sums: the distributed clustering needs them)
    StageProgress p1(progress, "stage 1: ", StageOneShare(co, options.decimate));
    s1 = Cluster(input, handoff, co, p1);
    stats.inputVertices = s1.inputVertices;
    stats.inputTriangles = s1.inputTriangles;
    stats.droppedInputFaces = s1.droppedInputFaces;
    AddNestedRun(stats, s1, "stage 1 ");
  }
  dml.Reconfigure();

  // (the whole input's box, agreed by the ranks; each stage's error is already the maximum over
  // the ranks)
  DecimateOptions dopt = StageTwoOptions(options, s1, dml);
  dopt.sourceConsumed = [&handoff]() { handoff.Release(); };
  const RunStats s2 = RunStageTwo(handoff, output, dopt, progress, onLevel, s1, stats);
  // This rank's traffic in both stages.
  stats.communication = s2.communication;
  stats.communication.Add(s1.communication);
  stats.gridDimension = options.gridDimension;
  stats.storage = dml.GetStats();
  return stats;
}

// TwoStageOptions::automaticGrid: whether stage 1 would keep too much of the input to pay.
bool SkipsStageOne(const TwoStageOptions& options, const detail::LayoutProbe& probe)
{
  const double g = double(options.gridDimension);
  return options.automaticGrid && options.gridDimension > kDefaultTwoStageGrid &&
    probe.faces > 0 &&
    kClusteredTrianglesPerGridSquare * g * g >= kStageOneSkipFraction * double(probe.faces);
}

RunStats TwoStageRun(const MeshSource& input, io::MeshSink& output, const TwoStageOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  DML dml;
  dml.Config(options.decimate.storage);
  RunStats stats;

  // The layout step for an incoherent input when stage 1 goes out of core: the input is copied
  // into the DML and reordered, and stage 1 reads the copy (freed once read). In core stage 1
  // reads the input as it is (its lookups are fetched ahead; docs/architecture.md, "Input
  // layout"). The probe is stage 1's bounds pass: the grid's box comes from it.
  ClusterOptions probeOptions;
  probeOptions.maximumGridDimension = options.gridDimension;
  probeOptions.attributes = options.decimate.attributes;
  detail::LayoutProbe probe;
  const bool probed = options.decimate.layout == LayoutPolicy::Automatic;
  if (probed)
  {
    PhaseTimer timer(stats, dml, "stage 1 bounds");
    probe = detail::ProbeLayout(input, progress);
  }
  if (SkipsStageOne(options, probe))
  {
    // The decimation alone, on the input as it is (its own DML; this one holds nothing yet).
    RunStats alone = Decimate(input, output, options.decimate, progress, onLevel);
    for (PhaseStat& phase : stats.phases)
    {
      phase.name = "probe"; // (the bounds pass that measured the input)
    }
    alone.phases.insert(alone.phases.begin(), stats.phases.begin(), stats.phases.end());
    alone.gridDimension = 0;
    return alone;
  }
  auto stage1OutOfCore = [&] {
    // (a header without sizes, the probe stopped before the end: an input of unknown size)
    const std::uint64_t v = probe.vertices ? probe.vertices : (probe.complete ? probe.verticesSeen : 0);
    ClusterOptions stage1 = probeOptions;
    stage1.storage = options.decimate.storage;
    return ClusterGoesOutOfCore(stage1, v, probe.faces ? probe.faces : 2 * v, probe.bounds);
  };
  std::optional<detail::StoredMesh> reordered;
  MeshSource stage1Input = input;
  if (options.decimate.layout == LayoutPolicy::Reorder ||
    (probe.Incoherent() && stage1OutOfCore()))
  {
    detail::StoredMesh& mesh = reordered.emplace(dml);
    detail::ReadAndReorder(input, mesh, dml, options.decimate.storage,
      [&probeOptions](storage::Profile& p, std::uint64_t v, std::uint64_t f) {
        p.structures.push_back(
          { "stage 1", 1, std::uint64_t(EstimateClusterBytes(v, f, probeOptions)), 0.0 });
      },
      [&probeOptions, &options](std::uint64_t v, std::uint64_t f) {
        return EstimateClusterWork(v, f, probeOptions) +
          EstimateDecimateWork(v / 8, f / 8, options.decimate);
      },
      progress, stats, options.threads);
    stage1Input = [&mesh](io::MeshSink& sink, const io::ReadOptions& ro) {
      return mesh.Replay(sink, ro);
    };
    stats.reordered = true;
    stats.layoutFarFraction = mesh.Layout().FarFraction();
  }
  else
  {
    stats.layoutFarFraction = probe.measured ? probe.farFraction : -1.0;
  }

  // Stage 1: clustering into the hand-off mesh, cell quadrics kept per output vertex.
  RunStats s1;
  detail::StoredMesh handoff(dml);
  Array<Quadric> quadrics(dml, 1);
  {
    ClusterOptions co;
    co.maximumGridDimension = options.gridDimension;
    co.storage = options.decimate.storage;
    co.threads = options.threads;
    co.attributes = options.decimate.attributes;
    co.dml = &dml;
    // (doubles: the second stage depends on the order of the faces anyway, and the exact sums
    // would make this stage about 1.7x slower)
    co.exactSums = false;
    // An incoherent input read as it is (in core): the clustered mesh in grid order, which the
    // second stage reads as it would a scanner-ordered one (the cells' first-seen order would be
    // as incoherent as the input: Dragon-size's stage 2 took 0.35 s against 0.18 s).
    co.gridOrder = probe.Incoherent() && !reordered;
    if (options.carryQuadrics)
    {
      co.exportQuadric = [&quadrics](std::uint64_t v, const double q[10]) {
        if (v >= quadrics.Size())
        {
          quadrics.Resize(std::max<std::uint64_t>(v + 1, 2 * quadrics.Size()));
        }
        Quadric r;
        std::copy_n(q, 10, r.q);
        quadrics.Set(v, r);
      };
    }
    StageProgress p1(progress, "stage 1: ", StageOneShare(co, options.decimate));
    if (probed && !reordered && probe.verticesSeen > 0)
    {
      co.useBounds = true;
      co.bounds = probe.bounds;
    }
    if (reordered)
    {
      co.useBounds = true;
      co.bounds = reordered->Bounds();
      co.sourceConsumed = [&reordered] { reordered.reset(); };
      co.threads = 1; // (no reader thread: the copy is read from this DML, single-threaded)
    }
    s1 = Cluster(stage1Input, handoff, co, p1);
    stats.inputVertices = s1.inputVertices;
    stats.inputTriangles = s1.inputTriangles;
    stats.droppedInputFaces = s1.droppedInputFaces;
    AddNestedRun(stats, s1, "stage 1 ");
  }
  dml.Reconfigure(); // stage 1's input-sized blocks are gone
#if defined(__GLIBC__)
  // Stage 1's reader thread (Prefetched) freed its chunk buffers into a malloc arena of its own,
  // which keeps them resident; stage 2 would add its memory on top (the 400M-triangle file at
  // 8 MB: 0.8 MB more peak RSS than the clustering alone).
  ::malloc_trim(0);
#endif

  // Stage 2: edge collapse on the DML-resident clustered mesh.
  DecimateOptions dopt = StageTwoOptions(options, s1, dml);
  if (options.carryQuadrics)
  {
    dopt.initialQuadric = [&quadrics](std::uint64_t v, double q[10]) {
      if (v >= quadrics.Size())
      {
        return false;
      }
      // (both in the one layout of Quadric.h)
      const Quadric r = quadrics.Get(v);
      std::copy_n(r.q, 10, q);
      return true;
    };
  }
  // Once stage 2 holds the mesh and its quadrics, the hand-off blocks go: the run moves in core
  // as soon as stage 2's own blocks fit.
  dopt.sourceConsumed = [&handoff, &quadrics]() {
    handoff.Release();
    quadrics.Close();
  };
  RunStageTwo(handoff, output, dopt, progress, onLevel, s1, stats);
  stats.gridDimension = options.gridDimension;
  stats.storage = dml.GetStats();
  return stats;
}
} // namespace

RunStats TwoStage(const MeshSource& input, io::MeshSink& output, const TwoStageOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  return TranslateOutOfMemory(progress, options.decimate.storage, [&] {
    const Communicator* comm = options.decimate.communicator;
    return comm && comm->Size() > 1
      ? TwoStageDistributed(input, output, options, progress, onLevel)
      : TwoStageRun(input, output, options, progress, onLevel);
  });
}

} // namespace sipmss::algorithms
