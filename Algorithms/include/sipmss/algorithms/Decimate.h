// Algorithm I: linear-time iterative full edge collapse with quadric error metrics, on the DML.
#pragma once

#include "sipmss/algorithms/Attributes.h"
#include "sipmss/algorithms/Common.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <functional>
#include <optional>
#include <limits>
#include <memory>
#include <string>

namespace sipmss::algorithms
{

struct DecimateOptions
{
  std::uint64_t targetTriangles = 0; // > 0: stop at or below this many triangles
  double targetReduction = kDefaultTargetReduction; // used when targetTriangles == 0: fraction to remove
  // An error bound: no collapse whose error (RunStats::achievedError's measure, a distance)
  // exceeds maximumError times the input's bounding-box diagonal (times 1 when absoluteError).
  // Infinite: no bound. With targetTriangles 0, a finite bound is the only stop (targetReduction
  // is not used): the run goes as far as the bound allows.
  // With levelsOfDetail K > 1 and no target the levels are spaced by the bound instead:
  // level i (0 = the finest) stops where no collapse under maximumError / 2^(K-1-i) remains
  // (LevelBoundFraction).
  double maximumError = std::numeric_limits<double>::infinity();
  bool absoluteError = false;
  // The part of maximumError already spent on this input (two-stage's stage 2: the grid's
  // error, in the same unit): every level's bound is reduced by it.
  double spentError = 0;
  // > 0: the diagonal that relative errors refer to (two-stage: the original input's); 0: that
  // of this run's input.
  double errorDiagonal = 0;
  int levelsOfDetail = 1;            // > 1: emit that many levels, evenly spaced in log(count) (or by maximumError)
  bool lockBoundary = false;         // boundary vertices never move
  // Locks and selections by a point-data scalar of the input (a name of its layout's scalars;
  // empty: none). lockArray: a vertex where it is not 0 stays in the output at its exact
  // position, with its point data (a neighbour may merge into it, or it into a neighbour that
  // then takes its position and its lock). selectionArray: only vertices where it is not 0 move
  // or go; the others are locked, so every face with no selected vertex is in the output with
  // the same corners. A selectionArray that names no point scalar but a face scalar of the
  // input (MeshHeader::faceScalars, read as TriangleFlags) selects faces: the corners of every
  // face where it is 0 are locked, so those faces are in the output as they were. Such an input
  // is not reordered under LayoutPolicy::Automatic (the reordered copy does not carry the
  // flags: LayoutPolicy::Reorder, or a source that sends no TriangleFlags, is an error). Not with
  // weldDistance >= 0 (welding would merge locked vertices away).
  std::string lockArray;
  std::string selectionArray;
  // > 0: first remove every disconnected piece (vertices joined by faces) whose bounding-box
  // diagonal is below this fraction of the input's (errorDiagonal when given), unless it holds a
  // vertex the lock or selection array keeps. RunStats counts them.
  double pruneSize = 0;
  // Attribute-aware error (Attributes.h): these point attributes, with their weights, join the
  // quadrics; a merged vertex takes their optimal values. Empty: geometry only.
  std::vector<AttributeWeight> attributes;
  double boundaryWeight = kDefaultDecimateBoundaryWeight; // weight of the boundary constraint quadrics
  double weldDistance = kNoWeld;    // >= 0: weld input vertices closer than this first
  storage::Profile storage;          // memory budget, directories, mode policy
  // Optional: run on this DML (already configured by the caller, e.g. the two-stage method that
  // keeps the clustered mesh in it). Default: a DML of the run's own, configured from `storage`
  // with the run's structures.
  storage::DML* dml = nullptr;
  // Initial per-vertex quadrics, e.g. the cell quadrics of a clustering stage (two-stage).
  // Called for each input vertex index; return false to use the face quadrics only. Layout:
  // that of Quadric.h (a00 a01 a02 b0 a11 a12 b1 a22 b2 c), in input coordinates.
  std::function<bool(std::uint64_t vertex, double quadric[10])> initialQuadric;
  // With initialQuadric: a vertex for which it returns true takes that quadric instead of its
  // faces' planes (its boundary planes are still added). The distributed run's second pass: the
  // quadrics its first pass accumulated already hold those faces' planes.
  bool initialQuadricReplacesFaces = false;
  // Called for each output vertex (of the final mesh, as it is written) with its accumulated
  // quadric, in the layout and coordinates of initialQuadric.
  std::function<void(std::uint64_t vertex, const double quadric[10])> finalQuadric;
  // The point the run's coordinates are taken about (in double precision; an input coordinate
  // far below its distance from this point rounds). Empty: the first input vertex. The
  // distributed run gives every rank's first pass the same one, so that the borders the pieces
  // share come out at the same coordinates on every rank.
  std::optional<std::array<double, 3>> origin;
  // > 0: the triangle count that the levels of detail are spaced from (the distributed run's
  // second pass: the whole input's); 0: this run's input's.
  std::uint64_t levelsFrom = 0;
  // > 0 (with a target): the target grows by this many triangles for each vertex the run keeps
  // fixed (lockBoundary, locks, selections), counted once the rings are built. The distributed
  // run's pieces: their locked borders would otherwise take their share of the target, and the
  // rest of the piece would be decimated far below it.
  double trianglesPerFixedVertex = 0;
  // Where the run happens: with more than one rank, each rank decimates its own piece with the
  // piece's border locked, and rank 0 gathers the results (the borders joined again by their
  // positions) and decimates them to the target (decimate/Distributed.inl): the output is on
  // rank 0, the other ranks' outputs are empty. Null or one rank: here, as always.
  Communicator* communicator = nullptr;
  // Called once the source and initialQuadric are no longer needed (before the collapse
  // passes): a caller that keeps the input in the same DML frees it there, so that the run can
  // move in core sooner.
  std::function<void()> sourceConsumed;
  // The layout step for incoherent inputs (only for a run on a DML of its own; two-stage takes
  // it from here for its whole run).
  LayoutPolicy layout = LayoutPolicy::Automatic;
  // Pass schedule: each pass removes at most this fraction of the remaining triangles (the
  // cheapest collapses; only their endpoints are exclusive), and never goes below the next
  // level's target.
  double passFraction = 0.25;
  // ... and this fraction while the mesh has more than farRatio times the next level's
  // triangles (a pass takes every candidate it can when >= 0.5). Measured (docs/benchmarks.md):
  // Lucy-size to 10K 31 s -> 21 s in core, RMS +1%; Dragon-size (81x its target) +0.6%.
  // farRatio 20 instead (A/B): Dragon-size -3% time and RMS -0.3%, David-size -6%
  // and RMS +1.0%, Lucy-size no faster (in core +2%, at 8 MB +3%) and RMS +0.9%: not taken.
  double farPassFraction = 0.5;
  double farRatio = 50.0;
  // The final fit (decimate/Fit.inl): before each output is written, every vertex that stands
  // for merged input vertices moves along its normal so that the output's faces pass through
  // a sample of the input's vertices in the least-squares sense (the quadrics place a vertex
  // on the input's planes; between the vertices a flat face then cuts a curved surface on one
  // side only). A move never raises the vertex's quadric error above the largest of the
  // output's vertices before the fit (RunStats::achievedError stays true); vertices kept fixed,
  // and vertices no collapse touched, stay exactly where they are; point data is not changed.
  // false: the quadric-optimal positions (the distributed run's first pass, whose output is not
  // the result).
  bool fitSurface = true;
  // The final fit's samples across ranks (decimate/Distributed.inl). finalSamples: called after
  // the run for each sample of the input (its position, in input coordinates) with the output
  // vertex that stands for it; samples are then taken even without fitSurface, and even when
  // nothing collapses. initialSamples: gives the samples (positions in input coordinates, the
  // input vertices that stand for them) instead of the input's own vertices.
  using SampleCallback = std::function<void(const double p[3], std::uint64_t vertex)>;
  SampleCallback finalSamples;
  // > 0: the samples are sized for an output of this many triangles (the distributed run's
  // pieces: their share of the result, not of their slack); 0: the finest level's.
  std::uint64_t fitSampleTriangles = 0;
  std::function<void(const SampleCallback&)> initialSamples;
  // Threads of the candidate sweep, the collapse step and the quadrics when in core (<= 0: the
  // hardware's). The result does not depend on it.
  int threads = 0;
  // Vertices per chunk of the collapse step (collapses inside a chunk run in parallel with the
  // other chunks'; the others one at a time). 0: automatic (at least 32768, at most 64 chunks).
  // The result depends on it, not on the threads or the storage mode.
  std::uint64_t stepChunkSize = 0;
  // A collapse is rejected when a surviving face's normal turns so that the cosine between its
  // new and old normal falls below this (0.2: about 78 degrees; flips are always rejected).
  double minNormalCosine = 0.2;
};

// Whether the error bound is the only stop (no target count): then it also spaces the levels.
inline bool BoundIsTheOnlyStop(const DecimateOptions& o)
{
  return o.targetTriangles == 0 && std::isfinite(o.maximumError);
}

// The fraction of maximumError that level `level` of K stops at when the bound alone spaces
// the levels: 2^-(K-1-level) (the last level takes the whole bound).
inline double LevelBoundFraction(int level, int levels)
{
  return std::ldexp(1.0, -std::max(0, levels - 1 - level));
}

// The error bound of level `level` in maximumError's unit (before spentError is taken off): its
// LevelBoundFraction of maximumError when the bound alone spaces the levels, else maximumError.
inline double LevelBound(const DecimateOptions& o, int level)
{
  return BoundIsTheOnlyStop(o)
    ? o.maximumError * LevelBoundFraction(level, std::max(1, o.levelsOfDetail))
    : o.maximumError;
}

// Runs Algorithm I on `input` and streams the final mesh into `output`.
// onLevel (optional) is called once per level with a callback that re-emits that level's mesh.
RunStats Decimate(const MeshSource& input, io::MeshSink& output, const DecimateOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel =
    nullptr);

} // namespace sipmss::algorithms
