// Algorithm I: linear-time iterative full edge collapse with quadric error metrics, on the DML.
#pragma once

#include "sipmss/algorithms/Common.h"

#include <functional>
#include <limits>
#include <memory>

namespace sipmss::algorithms
{

struct DecimateOptions
{
  std::uint64_t targetTriangles = 0; // > 0: stop at or below this many triangles
  double targetReduction = 0.9;      // used when targetTriangles == 0: fraction to remove
  double maximumError = std::numeric_limits<double>::infinity(); // stop when the cheapest
                                     // collapse costs more (quadric error, squared distance)
  int levelsOfDetail = 1;            // > 1: emit that many levels, evenly spaced in log(count)
  bool lockBoundary = false;         // boundary vertices never move
  double boundaryWeight = 100.0;     // weight of the boundary constraint quadrics
  double weldDistance = -1.0;        // >= 0: weld input vertices closer than this first
  storage::Profile storage;          // memory budget, directories, mode policy
  // Initial per-vertex quadrics, e.g. the cell quadrics of a clustering stage (two-stage).
  // Called for each input vertex index; return false to use the face quadrics only.
  std::function<bool(std::uint64_t vertex, double quadric[10])> initialQuadric;
};

// Runs Algorithm I on `input` and streams the final mesh into `output`.
// onLevel (optional) is called once per level with a callback that re-emits that level's mesh.
RunStats Decimate(const MeshSource& input, io::MeshSink& output, const DecimateOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel =
    nullptr);

} // namespace sipmss::algorithms
