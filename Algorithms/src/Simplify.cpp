#include "sipmss/algorithms/Simplify.h"

#include <algorithm>
#include <cmath>
#include <sstream>
#include <stdexcept>

namespace sipmss::algorithms
{

const char* ToString(Algorithm a)
{
  switch (a)
  {
    case Algorithm::Decimate:
      return "decimate";
    case Algorithm::TwoStage:
      return "two-stage";
    default:
      return "cluster";
  }
}

int AutomaticTwoStageGrid(std::uint64_t targetTriangles)
{
  const double g = std::ceil(
    std::sqrt(kTwoStageClusteredPerTarget * double(targetTriangles) / kClusteredTrianglesPerGridSquare));
  return int(std::clamp(g, double(kDefaultTwoStageGrid), double(kMaximumGrid)));
}

int SimplifyRequest::EffectiveGrid() const
{
  if (this->grid > 0)
  {
    return this->grid;
  }
  if (this->algorithm != Algorithm::TwoStage)
  {
    return kDefaultClusterGrid;
  }
  // (a reduction is of the clustered mesh's triangles, and a bound alone names no size)
  return this->targetTriangles > 0 ? AutomaticTwoStageGrid(this->targetTriangles)
                                   : kDefaultTwoStageGrid;
}

double SimplifyRequest::EffectiveBoundaryWeight() const
{
  if (this->boundaryWeight)
  {
    return *this->boundaryWeight;
  }
  return this->algorithm == Algorithm::Cluster ? kDefaultClusterBoundaryWeight
                                               : kDefaultDecimateBoundaryWeight;
}

const char* CliOption(Parameter p)
{
  switch (p)
  {
    case Parameter::TargetTriangles:
      return "--target";
    case Parameter::TargetReduction:
      return "--reduction";
    case Parameter::MaximumError:
      return "--max-error";
    case Parameter::LevelsOfDetail:
      return "--lods";
    case Parameter::Grid:
      return "--grid";
    case Parameter::Bounds:
      return "--bounds";
    case Parameter::BoundaryWeight:
      return "--boundary-weight";
    case Parameter::WeldDistance:
      return "--weld";
    case Parameter::LockArray:
      return "--lock-array";
    case Parameter::SelectionArray:
      return "--selection-array";
    case Parameter::PruneSize:
      return "--prune-size";
    case Parameter::Attributes:
      return "--attributes";
    case Parameter::MemoryBudget:
      return "--memory-mb";
    default:
      return "--threads";
  }
}

namespace
{
std::string Shown(double v)
{
  std::ostringstream s;
  s << v;
  return s.str();
}

// The words of each rule (after the parameter's name).
std::string FiniteInRange(double v, double lo, double hi)
{
  if (!std::isfinite(v))
  {
    return "must be a finite number, not " + Shown(v);
  }
  if (v < lo || v > hi)
  {
    return "must be between " + Shown(lo) + " and " + Shown(hi) + ", not " + Shown(v);
  }
  return {};
}

std::string IntegerInRange(long long v, long long lo, long long hi)
{
  if (v < lo || v > hi)
  {
    return "must be between " + std::to_string(lo) + " and " + std::to_string(hi) + ", not " +
      std::to_string(v);
  }
  return {};
}
} // namespace

std::vector<ParameterProblem> Problems(const SimplifyRequest& r)
{
  std::vector<ParameterProblem> out;
  auto check = [&](Parameter p, std::string problem) {
    if (!problem.empty())
    {
      out.push_back({ p, std::move(problem) });
    }
  };
  check(Parameter::MemoryBudget, MemoryBudgetProblem(r.memoryBudgetMB));
  check(Parameter::TargetReduction, FiniteInRange(r.targetReduction, 0, 1));
  if (std::isnan(r.maximumError) || r.maximumError < 0)
  {
    check(Parameter::MaximumError,
      "must be a number of at least 0 (infinite: no bound), not " + Shown(r.maximumError));
  }
  check(Parameter::LevelsOfDetail, IntegerInRange(r.levelsOfDetail, 1, kMaximumLevelsOfDetail));
  check(Parameter::Grid, IntegerInRange(r.grid, 0, kMaximumGrid));
  if (r.bounds)
  {
    for (int k = 0; k < 6; ++k)
    {
      if (!std::isfinite((*r.bounds)[k]))
      {
        check(Parameter::Bounds, "must be finite numbers, not " + Shown((*r.bounds)[k]));
        break;
      }
    }
  }
  if (r.boundaryWeight)
  {
    check(Parameter::BoundaryWeight, FiniteInRange(*r.boundaryWeight, 0, 1e9));
  }
  if (!std::isfinite(r.weldDistance))
  {
    check(Parameter::WeldDistance,
      "must be a finite number (negative: no welding), not " + Shown(r.weldDistance));
  }
  check(Parameter::Threads, IntegerInRange(r.threads, 0, kMaximumThreads));
  check(Parameter::PruneSize, FiniteInRange(r.pruneSize, 0, 1));
  {
    std::vector<AttributeWeight> list;
    check(Parameter::Attributes, ParseAttributeWeights(r.attributes, list));
  }
  // (two-stage moves every vertex in its first stage: nothing could stay as it was)
  const std::string decimateOnly = std::string("applies to decimation only, not to ") +
    ToString(r.algorithm) + " (whose clustering moves every vertex)";
  if (!r.lockArray.empty() && r.algorithm != Algorithm::Decimate)
  {
    check(Parameter::LockArray, decimateOnly);
  }
  if (!r.selectionArray.empty() && r.algorithm != Algorithm::Decimate)
  {
    check(Parameter::SelectionArray, decimateOnly);
  }
  if (r.weldDistance >= 0 && (!r.lockArray.empty() || !r.selectionArray.empty()))
  {
    check(Parameter::WeldDistance,
      "cannot be combined with a lock or selection array (welding would merge locked vertices "
      "into others)");
  }
  return out;
}

storage::Profile MakeProfile(const SimplifyRequest& r)
{
  storage::Profile p;
  ApplyMemoryBudget(r.memoryBudgetMB, p);
  if (r.reservedMemoryBytes && p.memoryBudget)
  {
    p.memoryBudget =
      std::max<std::uint64_t>(p.memoryBudget - std::min(p.memoryBudget, r.reservedMemoryBytes), 64u << 10);
    p.budgetOrigin += (p.budgetOrigin.empty() ? "" : "; ") + std::to_string(r.reservedMemoryBytes) +
      " bytes of it held for the file's piece";
  }
  p.directories = r.temporaryDirectories;
  p.policy = r.mode;
  return p;
}

namespace
{
// The attribute list of a request (Simplify's caller has checked Problems: a list that does not
// parse is a programming error, never silently shortened).
void ParseValidAttributes(const std::string& text, std::vector<AttributeWeight>& out)
{
  const std::string problem = ParseAttributeWeights(text, out);
  if (!problem.empty())
  {
    throw std::invalid_argument("the attribute list " + problem);
  }
}

RunStats Run(const SimplifyRequest& r, const storage::Profile& profile, const MeshSource& input,
  io::MeshSink& output, Progress& progress, const LevelCallback& onLevel)
{
  if (r.algorithm == Algorithm::Cluster)
  {
    ClusterOptions o;
    o.maximumGridDimension = r.EffectiveGrid();
    o.storage = profile;
    o.boundaryWeight = r.EffectiveBoundaryWeight();
    o.boundaryQuadrics = o.boundaryWeight > 0;
    o.threads = r.threads;
    o.communicator = r.communicator;
    ParseValidAttributes(r.attributes, o.attributes);
    if (r.bounds)
    {
      o.useBounds = true;
      o.bounds = *r.bounds;
    }
    return Cluster(input, output, o, progress);
  }
  DecimateOptions o;
  o.targetTriangles = r.targetTriangles;
  o.targetReduction = r.targetReduction;
  o.maximumError = r.maximumError;
  o.absoluteError = r.absoluteError;
  o.levelsOfDetail = r.levelsOfDetail;
  o.lockBoundary = r.lockBoundary;
  o.fitSurface = r.fitSurface;
  o.boundaryWeight = r.EffectiveBoundaryWeight();
  o.weldDistance = r.weldDistance;
  o.lockArray = r.lockArray;
  o.selectionArray = r.selectionArray;
  o.pruneSize = r.pruneSize;
  ParseValidAttributes(r.attributes, o.attributes);
  o.storage = profile;
  o.threads = r.threads;
  o.communicator = r.communicator;
  if (r.algorithm == Algorithm::Decimate)
  {
    return Decimate(input, output, o, progress, onLevel);
  }
  TwoStageOptions t;
  t.gridDimension = r.EffectiveGrid();
  t.automaticGrid = r.grid <= 0;
  t.threads = r.threads;
  t.decimate = o;
  return TwoStage(input, output, t, progress, onLevel);
}
} // namespace

RunStats Simplify(const SimplifyRequest& request, const MeshSource& input, io::MeshSink& output,
  Progress& progress, const LevelCallback& onLevel)
{
  const storage::Profile profile = MakeProfile(request);
  RunStats stats = TranslateOutOfMemory(
    progress, profile, [&] { return Run(request, profile, input, output, progress, onLevel); });
  stats.memoryBudgetBytes = profile.memoryBudget;
  stats.memoryBudgetOrigin = profile.budgetOrigin;
  return stats;
}

} // namespace sipmss::algorithms
