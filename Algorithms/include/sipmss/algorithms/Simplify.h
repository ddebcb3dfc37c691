// One request for every front end: the CLI (`sipmss simplify`), the VTK filters (and through them
// ParaView and Python) fill a SimplifyRequest and call Simplify(). The defaults, ranges and
// validation messages below are the only ones: the CLI's options, the filters' clamps and the
// ParaView XML's domains follow them (Testing/Python/test_sipmss_front_ends.py checks all three).
#pragma once

#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/TwoStage.h"

#include <array>
#include <functional>
#include <limits>
#include <optional>
#include <string>
#include <vector>

namespace sipmss::algorithms
{

enum class Algorithm : std::uint8_t
{
  Cluster,  // Algorithm II: grid clustering (the CLI's default)
  Decimate, // Algorithm I: iterative quadric edge collapse
  TwoStage  // clustering at a fine grid, then edge collapse
};
const char* ToString(Algorithm a); // "cluster", "decimate", "two-stage"

// (The defaults and ranges shared by every front end, kDefaultClusterGrid and the others, are in
// Common.h: the cores' option structs start from them too.)

// Everything a run of any algorithm can be asked. A field that does not apply to the algorithm
// is ignored here; the CLI refuses to be given one (a usage error), the filters have none.
struct SimplifyRequest
{
  Algorithm algorithm = Algorithm::Cluster;

  // Targets (decimate, two-stage): targetTriangles > 0 stops at or below that many triangles,
  // else targetReduction of the triangles are removed; but with a finite maximumError and no
  // targetTriangles, the bound is the only stop (targetReduction is not used).
  std::uint64_t targetTriangles = 0;
  double targetReduction = kDefaultTargetReduction;
  // An error bound (DecimateOptions::maximumError): a fraction of the input's bounding-box
  // diagonal, or a distance in its units when absoluteError. Infinite: no bound.
  double maximumError = std::numeric_limits<double>::infinity();
  bool absoluteError = false;
  int levelsOfDetail = 1;

  // Grid (cluster, two-stage): 0 is the algorithm's default (cluster: kDefaultClusterGrid;
  // two-stage: AutomaticTwoStageGrid(targetTriangles) with a triangle target, else
  // kDefaultTwoStageGrid).
  int grid = 0;
  // Cluster only: the grid's box (xmin xmax ymin ymax zmin zmax); empty: the input's bounds.
  std::optional<std::array<double, 6>> bounds;

  // Boundaries: empty is the algorithm's default (cluster: kDefaultClusterBoundaryWeight, 0 =
  // no boundary quadrics; decimate and two-stage: kDefaultDecimateBoundaryWeight).
  std::optional<double> boundaryWeight;
  bool lockBoundary = false;      // decimate, two-stage: boundary vertices never move
  // Decimate, two-stage: the final fit of the merged vertices to a sample of the input
  // (DecimateOptions::fitSurface); false: the quadrics' positions.
  bool fitSurface = true;
  double weldDistance = kNoWeld;  // decimate, two-stage: >= 0 welds closer input vertices first
  // Decimate only: point-data scalars (by name; empty: none) whose non-zero vertices never move
  // or go (lockArray), or outside of whose non-zero vertices nothing changes (selectionArray; or
  // a cell-data scalar, outside of whose non-zero faces nothing changes).
  std::string lockArray;
  std::string selectionArray;
  // Decimate, two-stage: removes disconnected pieces smaller than this fraction of the input's
  // bounding-box diagonal first (DecimateOptions::pruneSize; 0: none).
  double pruneSize = 0;
  // Every algorithm: point attributes that join the error, with weights, as
  // ParseAttributeWeights reads them ("normals:0.5,colors:1"; empty: geometry only).
  std::string attributes;

  // Storage and threads.
  double memoryBudgetMB = kAutomaticMemoryBudget; // see MemoryBudgetProblem
  std::vector<std::string> temporaryDirectories;  // empty: $TMPDIR or /tmp
  storage::ModePolicy mode = storage::ModePolicy::Automatic;
  int threads = 0; // 0: all cores; the output does not depend on it
  // Not a parameter but where the run happens: every algorithm runs across this communicator's
  // ranks (ClusterOptions::communicator, DecimateOptions::communicator, two-stage through the
  // latter; the filters pass ParaView's MPI controller). Null: here.
  Communicator* communicator = nullptr;
  // Bytes of the budget the caller holds for itself (the filters' file piece under MPI,
  // FilePiece): the run's budget is the rest (at least 64 KiB). Not with an unbounded budget.
  std::uint64_t reservedMemoryBytes = 0;

  int EffectiveGrid() const;
  double EffectiveBoundaryWeight() const;
};

// The request's parameters, for messages: each front end names them its own way (the CLI's
// option, the filter's property).
enum class Parameter : std::uint8_t
{
  TargetTriangles,
  TargetReduction,
  MaximumError,
  LevelsOfDetail,
  Grid,
  Bounds,
  BoundaryWeight,
  WeldDistance,
  LockArray,
  SelectionArray,
  PruneSize,
  Attributes,
  MemoryBudget,
  Threads
};
const char* CliOption(Parameter p); // "--target", ...

struct ParameterProblem
{
  Parameter parameter;
  std::string problem; // "must be a finite number, not nan": the words after the name
};
// What is wrong with the request, parameter by parameter (empty: nothing). The one set of rules
// of every front end.
std::vector<ParameterProblem> Problems(const SimplifyRequest& request);

// The storage profile of a request (budget, directories, mode).
storage::Profile MakeProfile(const SimplifyRequest& request);

using LevelCallback =
  std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>;

// Runs the requested algorithm on `input` into `output` (levels of detail through onLevel). The
// request must have no Problems(); a std::bad_alloc becomes an OutOfMemoryError naming the phase.
RunStats Simplify(const SimplifyRequest& request, const MeshSource& input, io::MeshSink& output,
  Progress& progress, const LevelCallback& onLevel = nullptr);

} // namespace sipmss::algorithms
