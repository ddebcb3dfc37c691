// Algorithm II: Lindstrom's out-of-core uniform-grid vertex clustering with grid quadrics (OoCS),
// on the DML, with indexed-face input.
#pragma once

#include "sipmss/algorithms/Attributes.h"
#include "sipmss/algorithms/Common.h"

namespace sipmss::algorithms
{

// Where a cell's representative vertex goes when the quadric minimizer leaves the cell.
enum class ClusterFallback : std::uint8_t
{
  Mean,         // the mean of the cell's input vertices (default; measured better, see docs)
  SampledVertex // one of the cell's input vertices, as the paper does (the first one seen)
};

struct ClusterOptions
{
  int maximumGridDimension = kDefaultClusterGrid; // cells along the longest bounding-box axis (the paper's m.g.d.)
  bool useBounds = false;        // true: `bounds` is the grid's box, no bounds pass is made
  std::array<double, 6> bounds{}; // xmin xmax ymin ymax zmin zmax
  ClusterFallback fallback = ClusterFallback::Mean;
  // How far (in cell sizes) the quadric minimizer may lie outside its cell before the fallback
  // is used. The paper uses 0 (the cell itself). Measured on the Dragon-size input at grid 300
  // (RMS error / bbox diagonal): 0 -> 4.47e-5, 0.5 -> 3.84e-5, 1 -> 3.81e-5, unbounded -> 3.80e-5
  // (vtkQuadricClustering: 3.94e-5). 1 keeps each vertex in its cell's 3x3x3 neighbourhood.
  double placementSlack = 1.0;
  // Boundary constraint quadrics (planes through the input's boundary edges, perpendicular to
  // their faces, weighted by boundaryWeight * edge length^2) keep holes and borders in place. Costs
  // a second pass over all input edges; see docs/benchmarks.md for what it measures.
  bool boundaryQuadrics = false;
  double boundaryWeight = 1.0;
  // Relative threshold for the pseudo-inverse: eigenvalues below this times the largest are
  // treated as zero (rank-deficient quadrics of flat or linear cells).
  double singularThreshold = 1e-3;
  storage::Profile storage; // memory budget, directories, mode policy
  // Threads: 0 = automatic (the input is read and parsed on a second thread while the clustering
  // runs, when the machine has more than one core), 1 = everything on the calling thread. The
  // output is identical for any value.
  int threads = 0;
  // Optional: run on this DML (already configured by the caller, e.g. the two-stage method that
  // keeps the clustered mesh in it for the second stage). Default: a DML of the run's own.
  storage::DML* dml = nullptr;
  // Optional: called once the input has been read for the last time (the caller may free it).
  std::function<void()> sourceConsumed;
  // The layout step for incoherent inputs (only for a run on a DML of its own).
  LayoutPolicy layout = LayoutPolicy::Automatic;
  // Attribute-aware error (Attributes.h): these point attributes, with their weights, join the
  // cell quadrics; a representative takes their optimal values at its position (the other point
  // data: the cell's mean). Empty: geometry only.
  std::vector<AttributeWeight> attributes;
  // Optional: called for each output vertex with its cell's (geometric) quadric (the layout of
  // Quadric.h).
  std::function<void(std::uint64_t vertex, const double quadric[10])> exportQuadric;
  // The cells' sums in fixed point (docs/architecture.md, "Exact cell sums"): the result does not
  // depend on the order or the split of the faces. Off, they are doubles added in the input's
  // order: the clustering pass is about 1.7x faster in core and the result differs in its last
  // bits with the order of the faces (two-stage's first stage, whose second stage depends on the
  // order anyway). A distributed run needs it on.
  bool exactSums = true;
  // The output's order: false, the vertices in the order their cells were first met in the input
  // and the triangles by their first vertex's cell; true, the vertices in grid order (by cell:
  // x, then y, then z) and the triangles sorted by their lowest vertex, for any order of the
  // input (two-stage's hand-off of an incoherent input, so that its second stage reads a
  // coherent mesh). Only while the cell records are in memory when the output is written (out
  // of core the first-seen order stays); not across ranks (`communicator`).
  bool gridOrder = false;
  // Optional: run across the ranks of this communicator, `input` being this rank's piece of the
  // mesh and `output` receiving this rank's piece of the result (docs/architecture.md,
  // "Distributed clustering"): the union of the pieces is the serial result. Every rank calls
  // Cluster with the same options. Not with boundary planes on more than one rank, nor with
  // exportQuadric; the input is not reordered (LayoutPolicy is ignored). `dml` may be given
  // (two-stage's stage 1 across ranks).
  Communicator* communicator = nullptr;
};

// Grid geometry derived from the bounds and the maximum grid dimension.
struct ClusterGrid
{
  std::array<double, 3> origin{};
  double cellSize = 1;
  std::array<std::uint32_t, 3> dims{ 1, 1, 1 };
  static ClusterGrid Make(const std::array<double, 6>& bounds, int maximumGridDimension);
  std::uint64_t Key(double x, double y, double z) const;
};

// Runs Algorithm II: `input` is read once (twice when the bounds are not given: a vertices-only
// bounds pass first) and the clustered mesh is streamed into `output`.
RunStats Cluster(const MeshSource& input, io::MeshSink& output, const ClusterOptions& options,
  Progress& progress);

} // namespace sipmss::algorithms
