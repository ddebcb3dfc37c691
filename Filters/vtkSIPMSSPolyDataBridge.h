// Private: the bridge between VTK's pipeline and the VTK-free SIPMSS cores.
#ifndef vtkSIPMSSPolyDataBridge_h
#define vtkSIPMSSPolyDataBridge_h

#include "sipmss/algorithms/Common.h"

#include "vtkSmartPointer.h"

class vtkAlgorithm;
class vtkPolyData;
class vtkSIPMSSFilterBase;

namespace vtkSIPMSSPolyDataBridge
{
// A replayable source over a vtkPolyData: polygons triangulated as fans, strips converted,
// vertices and lines skipped (counted in *skippedCells). Point data: normals, RGB(A) unsigned
// char scalars, texture coordinates and every other 1-component numeric array.
sipmss::algorithms::MeshSource PolyDataSource(vtkPolyData* input, vtkIdType* skippedCells);

// Bounds of the input's points (xmin xmax ymin ymax zmin zmax).
std::array<double, 6> Bounds(vtkPolyData* input);

// A sink that builds a vtkPolyData (float points, triangles, point data arrays).
class PolyDataSink : public sipmss::io::MeshSink
{
public:
  explicit PolyDataSink(vtkPolyData* output);
  void Begin(const sipmss::io::MeshHeader& header) override;
  void Vertices(const sipmss::io::VertexChunk& chunk) override;
  void Triangles(const std::uint32_t* indices, std::size_t count) override;
  void End(const sipmss::io::ReadStats& stats) override;

private:
  struct Impl;
  std::shared_ptr<Impl> impl_;
};

// Progress and abort through vtkAlgorithm::UpdateProgress / GetAbortExecute.
class AlgorithmProgress : public sipmss::algorithms::Progress
{
public:
  explicit AlgorithmProgress(vtkAlgorithm* algorithm);
  void Report(double fraction, const char* phase) override;
  bool Aborted() override;

private:
  vtkAlgorithm* algorithm_;
};

// The storage profile from the filter's MemoryBudgetMB, TemporaryDirectories, OperationMode.
sipmss::storage::Profile MakeProfile(vtkSIPMSSFilterBase* filter);
}

#endif
