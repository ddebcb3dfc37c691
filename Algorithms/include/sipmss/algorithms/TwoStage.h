// The two-stage method (Garland-Shaffer multiphase, the paper's "Algorithm Two-Stage"):
// Algorithm II (grid clustering) then Algorithm I (edge collapse) on one DML. The clustered mesh
// stays in DML blocks between the stages (no vtkPolyData, no file), optionally with the cell
// quadrics carried into stage 2 as the initial vertex quadrics. With decimate.communicator of
// more than one rank, both stages run across the ranks: the distributed clustering, then the
// distributed decimation of its pieces (the output on rank 0; carryQuadrics is refused).
#pragma once

#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/Decimate.h"

namespace sipmss::algorithms
{

struct TwoStageOptions
{
  int gridDimension = kDefaultTwoStageGrid; // stage 1: maximum grid dimension
  // Stage 2 starts from the cell quadrics of stage 1. Off: since non-manifold edges collapse it
  // measures worse (Lucy-size to 10K: RMS 1.66e-4 with, 1.50e-4 without; David-size 1.60e-4 /
  // 1.46e-4; Dragon-size 3.32e-4 / 3.25e-4).
  bool carryQuadrics = false;
  // gridDimension was chosen for the target (AutomaticTwoStageGrid): when it is finer than
  // kDefaultTwoStageGrid and its clustered mesh would keep at least kStageOneSkipFraction of the
  // input's triangles (kClusteredTrianglesPerGridSquare * g^2 against the header's count; on one
  // rank, with the automatic layout), stage 1 is skipped and the input decimated as it is
  // (RunStats::gridDimension 0). A given grid always runs stage 1.
  bool automaticGrid = false;
  int threads = 0;             // stage 1 threads (see ClusterOptions::threads)
  DecimateOptions decimate;    // stage 2: target, levels, boundary, ... and the storage profile
};

RunStats TwoStage(const MeshSource& input, io::MeshSink& output, const TwoStageOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel =
    nullptr);

} // namespace sipmss::algorithms
