// Algorithm I of SIPMSS: a linear-time iterative full edge collapse with quadric error metrics,
// written against the DML so that it runs in core or out of core with identical results. The
// passes, their state and their files: decimate/Passes.h. Here: the pass schedule, the run
// (a pipeline of the passes) and the entry points.
#include "decimate/Passes.h"

#include "Distributed.h"
#include "StageProgress.h"
#include "sipmss/storage/Sort.h"

#include <optional>
#include <tuple>
#include <unordered_map>

// The passes (one translation unit with this file: decimate/Passes.h says why).
#include "decimate/Read.inl"
#include "decimate/Rings.inl"
#include "decimate/Prune.inl"
#include "decimate/Sweep.inl"
#include "decimate/Step.inl"
#include "decimate/Compact.inl"
#include "decimate/Fit.inl"

namespace sipmss::algorithms
{
namespace
{
// ---------------------------------------------------------------------------------------------

std::vector<std::uint64_t> Levels(const RunContext& ctx, std::uint64_t F0)
{
  std::uint64_t target = ctx.opt.targetTriangles ? ctx.opt.targetTriangles + ctx.extraTarget : 0;
  if (target == 0 && !BoundIsTheOnlyStop(ctx.opt))
  {
    // (with a bound and no target the bound is the only stop)
    double r = std::min(1.0, std::max(0.0, ctx.opt.targetReduction));
    target = std::uint64_t(std::llround(double(F0) * (1.0 - r)));
  }
  const int K = std::max(1, ctx.opt.levelsOfDetail);
  std::vector<std::uint64_t> levels(K);
  for (int i = 0; i < K; ++i)
  {
    if (i == K - 1 || F0 <= target || target == 0)
    {
      levels[i] = target;
    }
    else
    {
      // (spaced from the whole input's count in a distributed run's second pass)
      const double from = double(ctx.opt.levelsFrom ? ctx.opt.levelsFrom : F0);
      double x = from * std::pow(double(target) / from, double(i + 1) / double(K));
      levels[i] = std::max<std::uint64_t>(target, std::uint64_t(std::llround(x)));
    }
  }
  return levels;
}

// Whether a mesh of T faces is far from the next level (farRatio): larger passes, their groups
// of candidates in turn on each part of a chunk (StepChunks).
bool FarFromLevel(const RunContext& ctx, std::uint64_t T, std::uint64_t level)
{
  return double(T) > ctx.opt.farRatio * double(std::max<std::uint64_t>(level, 1));
}

// Run's pass loop, on counts only: each pass removes its planned share (a pass that removes
// fewer makes the next estimates larger: the progress then moves more slowly, never back).
std::uint64_t PassGoal(const RunContext& ctx, std::uint64_t T, std::uint64_t level)
{
  const double fraction = std::min(0.9, std::max(0.01, ctx.opt.passFraction));
  const double farFraction = std::min(0.9, std::max(fraction, ctx.opt.farPassFraction));
  // Far from the level, the cheapest collapses cost orders of magnitude less than the level's
  // error and their exact order matters less: larger passes (fewer sweeps).
  const bool far = FarFromLevel(ctx, T, level);
  const std::uint64_t step =
    std::max<std::uint64_t>(1, std::uint64_t(double(T) * (far ? farFraction : fraction)));
  return std::max(level, T > step ? T - step : 0);
}

double PassesWork(const RunContext& ctx, const MeshState& mesh, 
  std::uint64_t T, std::size_t level, const std::vector<std::uint64_t>& levels)
{
  const double vpf = VerticesPerFace(mesh);
  double work = 0;
  double nf = double(T), nv = vpf * double(T);
  for (int guard = 0; level < levels.size() && guard < 10000; ++guard)
  {
    if (T <= levels[level])
    {
      if (ctx.emitsLevels)
      {
        work += kWork::kWrite * double(T) * (1.0 + vpf);
      }
      ++level;
      continue;
    }
    const std::uint64_t goal = PassGoal(ctx, T, levels[level]);
    work += (kWork::kSweep + kWork::kOrder) * nv + kWork::kStep * double(2 * (T - goal) + 16) +
      kWork::kCompact * (nf + nv);
    T = goal;
    nf = double(T);
    nv = vpf * double(T);
  }
  return work + kWork::kWrite * double(T) * (1.0 + vpf);
}

double RestWork(
  const RunContext& ctx, const MeshState& mesh, int stage, std::uint64_t V, std::uint64_t F)
{
  double work = 0;
  if (stage <= 0 && ctx.opt.weldDistance >= 0)
  {
    work += kWork::kWeld * double(V + F);
  }
  if (stage <= 1)
  {
    work += kWork::kRings * double(F);
  }
  if (stage <= 2)
  {
    work += kWork::kQuadrics * double(F) + (ctx.opt.pruneSize > 0 ? kWork::kPrune * double(F + V) : 0.0);
  }
  // The passes from F faces (nv_ and nf_ are those of the input until the first pass).
  return work + PassesWork(ctx, mesh, F, 0, Levels(ctx, F));
}

// The error bound in the units of the costs (a squared distance per unit of trace), once the
// input's bounds are known.
// (level: the level being made; its own bound when the bound alone spaces the levels)
void SetErrorBound(RunContext& ctx, const MeshState& mesh, int level = 0)
{
  const Vec3 d = mesh.hi - mesh.lo;
  ctx.diagonal =
    ctx.opt.errorDiagonal > 0 ? ctx.opt.errorDiagonal : std::sqrt(d.x * d.x + d.y * d.y + d.z * d.z);
  if (std::isfinite(ctx.opt.maximumError))
  {
    const double e = std::max(0.0, LevelBound(ctx.opt, level) - ctx.opt.spentError) *
      (ctx.opt.absoluteError ? 1.0 : ctx.diagonal);
    ctx.maxErr2 = e * e;
  }
}

// The next level's bound when the bound alone spaces the levels: every vertex's candidate is
// looked for again (one whose collapses all exceeded the old bound has none).
void RaiseErrorBound(RunContext& ctx, MeshState& mesh, int level)
{
  SetErrorBound(ctx, mesh, level);
  mesh.BindViews();
  for (std::uint64_t v = 0; v < mesh.nv; ++v)
  {
    mesh.views.S.Set(v, State(mesh.views.S.Get(v) | kRecompute));
  }
}

void Run(RunContext& ctx, MeshState& mesh, PassState& pass, const MeshSource& input,
  io::MeshSink& output,
  const std::function<void(int, const std::function<void(io::MeshSink&)>&)>& onLevel)
{
  ctx.emitsLevels = bool(onLevel);
  Read(ctx, mesh, input);
  SetErrorBound(ctx, mesh);
  if (ctx.opt.weldDistance >= 0)
  {
    PhaseTimer timer(ctx.stats, mesh.dml, "weld");
    ctx.progress.BeginPhase("weld", kWork::kWeld * double(mesh.nv + mesh.nf),
      RestWork(ctx, mesh, 1, mesh.nv, mesh.nf));
    Weld(ctx, mesh);
  }
  BuildRings(ctx, mesh);
  if (ctx.opt.pruneSize > 0)
  {
    Prune(ctx, mesh);
  }
  BuildQuadrics(ctx, mesh);
  if (ctx.opt.trianglesPerFixedVertex > 0 && ctx.opt.targetTriangles > 0)
  {
    std::uint64_t fixed = 0;
    for (std::uint64_t v = 0; v < mesh.nv; ++v)
    {
      fixed += (mesh.views.S.Get(v) & kFixed) != 0;
    }
    ctx.extraTarget = std::uint64_t(std::llround(ctx.opt.trianglesPerFixedVertex * double(fixed)));
  }
  const std::uint64_t F0 = mesh.liveFaces;
  const std::vector<std::uint64_t> levels = Levels(ctx, F0);
  SampleInput(ctx, mesh, levels); // (before the source goes: it may hold initialSamples')
  if (ctx.opt.sourceConsumed)
  {
    ctx.opt.sourceConsumed();
    mesh.dml.Reconfigure();
    mesh.BindViews();
  }
  const int K = int(levels.size());
  auto emitLevel = [&](int level) {
    if (onLevel)
    {
      // (the final write follows the last level's: this phase never ends the run)
      ctx.progress.BeginPhase("write", kWork::kWrite * double(mesh.nv + mesh.nf),
        PassesWork(ctx, mesh, mesh.liveFaces, std::size_t(level) + 1, levels));
      onLevel(level, [&](io::MeshSink& sink) {
        Fit(ctx, mesh);
        Emit(ctx, mesh, sink);
      });
    }
  };
  {
    PhaseTimer timer(ctx.stats, mesh.dml, "collapse");
    int level = 0;
    bool compacted = false;
    while (level < K)
    {
      if (mesh.liveFaces <= levels[level])
      {
        if (!compacted)
        {
          Compact(ctx, mesh, pass);
          compacted = true;
        }
        emitLevel(level);
        ++level;
        continue;
      }
      const std::uint64_t goal = PassGoal(ctx, mesh.liveFaces, levels[level]);
      if (!Pass(ctx, mesh, pass, goal, goal == levels[level],
            FarFromLevel(ctx, mesh.liveFaces, levels[level]),
            PassesWork(ctx, mesh, goal, std::size_t(level), levels)))
      {
        // No legal collapse under the bound remains: the level is reached (the last one when
        // the bound does not space the levels).
        if (!compacted)
        {
          Compact(ctx, mesh, pass);
          compacted = true;
        }
        emitLevel(level);
        if (BoundIsTheOnlyStop(ctx.opt) && level + 1 < K)
        {
          ++level;
          RaiseErrorBound(ctx, mesh, level);
          continue;
        }
        break;
      }
      compacted = true;
    }
  }
  {
    PhaseTimer timer(ctx.stats, mesh.dml, "fit");
    Fit(ctx, mesh);
  }
  {
    PhaseTimer timer(ctx.stats, mesh.dml, "write");
    ctx.progress.BeginPhase("write", kWork::kWrite * double(mesh.nv + mesh.nf), 0.0);
    Emit(ctx, mesh, output);
  }
  ExportSamples(ctx, mesh);
  ctx.progress.Finish();
  ctx.stats.outputVertices = mesh.nv;
  ctx.stats.outputTriangles = mesh.nf;
  ctx.stats.droppedInputFaces = mesh.dropped + mesh.readerDropped;
  ctx.stats.errorDiagonal = ctx.diagonal;
  ctx.stats.achievedError = RelativeError(ctx.achievedErr2, ctx.diagonal);
  ctx.stats.storage = mesh.dml.GetStats();
}

// A run with a state of its own (the context, the mesh, the passes').
void RunOnOwnState(const DecimateOptions& options, Progress& progress, RunStats& stats,
  const MeshSource& input, io::MeshSink& output,
  const std::function<void(int, const std::function<void(io::MeshSink&)>&)>& onLevel)
{
  RunContext ctx(options, progress, stats);
  MeshState mesh(options);
  PassState pass;
  Run(ctx, mesh, pass, input, output, onLevel);
}

// The bytes of a decimation's structures on V vertices and F faces (without point data): the
// table the decimation declares (BeginInput), with the attribute extensions of `channels`
// channels (before the header is known, an estimate: 4 per attribute name; the DML counts the
// real bytes).
double DecimateBytes(std::uint64_t V, std::uint64_t F, std::size_t channels)
{
  return double(V) *
    double(sizeof(Vec3) + sizeof(Quadric) + sizeof(State) + sizeof(Cand) + sizeof(FitSample) / 2 +
      4 * sizeof(std::uint32_t) + AttributeExtraSize(channels) * sizeof(double)) +
    double(F) * double(sizeof(Tri) + 3 * sizeof(std::uint32_t));
}

// The layout step, then the decimation of the reordered copy (in the same DML, freed as soon as
// the decimation has built its own structures).
RunStats DecimateReordered(const MeshSource& input, io::MeshSink& output,
  const DecimateOptions& options, Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  DML dml;
  dml.Config(options.storage);
  RunStats before;
  detail::StoredMesh mesh(dml);
  detail::ReadAndReorder(input, mesh, dml, options.storage,
    [&options](storage::Profile& p, std::uint64_t v, std::uint64_t f) {
      p.structures.push_back({ "decimate", 1,
        std::uint64_t(DecimateBytes(v, f, 4 * options.attributes.size())), 0.0 });
    },
    [&options](std::uint64_t v, std::uint64_t f) { return EstimateDecimateWork(v, f, options); },
    progress, before, options.threads);
  DecimateOptions o = options;
  o.dml = &dml;
  o.layout = LayoutPolicy::Keep;
  o.sourceConsumed = [&mesh, &options] {
    mesh.Release();
    if (options.sourceConsumed)
    {
      options.sourceConsumed();
    }
  };
  RunStats stats;
  RunOnOwnState(o, progress, stats,
    [&mesh](io::MeshSink& sink, const io::ReadOptions& ro) { return mesh.Replay(sink, ro); },
    output, onLevel);
  stats.phases.insert(stats.phases.begin(), before.phases.begin(), before.phases.end());
  stats.layoutSteps = before.layoutSteps;
  stats.reordered = true;
  stats.layoutFarFraction = mesh.Layout().FarFraction();
  stats.storage = dml.GetStats();
  return stats;
}
} // namespace

} // namespace sipmss::algorithms

// The run across ranks (one translation unit with this file: it runs the passes above).
#include "decimate/Distributed.inl"

namespace sipmss::algorithms
{

RunStats Decimate(const MeshSource& input, io::MeshSink& output, const DecimateOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  return TranslateOutOfMemory(progress, options.storage, [&] {
    if (options.communicator && options.communicator->Size() > 1)
    {
      return DecimateDistributed(input, output, options, progress, onLevel);
    }
    if (!options.dml && options.layout == LayoutPolicy::Reorder)
    {
      return DecimateReordered(input, output, options, progress, onLevel);
    }
    try
    {
      RunStats stats;
      RunOnOwnState(options, progress, stats, input, output, onLevel);
      return stats;
    }
    catch (const detail::ReorderNeeded&)
    {
      // (the loader found the first faces far apart: the run starts again on a reordered copy)
      return DecimateReordered(input, output, options, progress, onLevel);
    }
  });
}
double EstimateDecimateWork(std::uint64_t V, std::uint64_t F, const DecimateOptions& options)
{
  NullProgress none;
  RunStats stats;
  DecimateOptions o = options;
  o.dml = nullptr;
  RunContext ctx(o, none, stats);
  MeshState mesh(o);
  return Plan(ctx, mesh, V, F);
}

} // namespace sipmss::algorithms