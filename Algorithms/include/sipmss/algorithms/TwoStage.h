// The two-stage method (Garland-Shaffer multiphase, the paper's "Algorithm Two-Stage"):
// Algorithm II (grid clustering) then Algorithm I (edge collapse) on one DML. The clustered mesh
// stays in DML blocks between the stages (no vtkPolyData, no file), optionally with the cell
// quadrics carried into stage 2 as the initial vertex quadrics.
#pragma once

#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/Decimate.h"

namespace sipmss::algorithms
{

struct TwoStageOptions
{
  int gridDimension = 300;     // stage 1: maximum grid dimension
  bool carryQuadrics = true;   // stage 2 starts from the cell quadrics of stage 1
  int threads = 0;             // stage 1 threads (see ClusterOptions::threads)
  DecimateOptions decimate;    // stage 2: target, levels, boundary, ... and the storage profile
};

RunStats TwoStage(const MeshSource& input, io::MeshSink& output, const TwoStageOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel =
    nullptr);

} // namespace sipmss::algorithms
