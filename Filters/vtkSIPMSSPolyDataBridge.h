// Private: the bridge between VTK's pipeline and the VTK-free SIPMSS cores.
#ifndef vtkSIPMSSPolyDataBridge_h
#define vtkSIPMSSPolyDataBridge_h

#include "sipmss/algorithms/Common.h"

#include "vtkSmartPointer.h"

class vtkAbstractArray;
class vtkAlgorithm;
class vtkPointData;
class vtkPolyData;

namespace vtkSIPMSSPolyDataBridge
{
// A replayable source over a vtkPolyData: polygons triangulated as fans, strips converted,
// vertices and lines skipped (counted in *skippedCells). Point data: normals, RGB(A) unsigned
// char scalars, texture coordinates and every other 1-component numeric array.
sipmss::algorithms::MeshSource PolyDataSource(vtkPolyData* input, vtkIdType* skippedCells);

// An attribute list (algorithms::ParseAttributeWeights' syntax) with the names of the input's
// arrays that the core carries as normals, colors or texture coordinates given as the core's
// keywords (normals, colors, texcoords); other names are the core's already (scalar arrays, and
// NAME for the components NAME_0, NAME_1, ... of a larger array). A list that does not parse is
// returned as it is. A name that would become a keyword the input also has as a point array's name
// (e.g. the normals "N" and another array called "normals") sets `problem` (the list is returned
// as it is).
std::string CoreAttributeNames(vtkPolyData* input, const std::string& list, std::string& problem);

// Bounds of the input's points (xmin xmax ymin ymax zmin zmax).
// The input's bounds; throws MeshIOError naming the first point with a non-finite coordinate
// (the filters call it for every pipeline input before a run).
std::array<double, 6> Bounds(vtkPolyData* input);

// Whether `a` is a ghost array (vtkGhostType): it describes the pieces of the input, not the
// surface, so it is neither carried (the output's points and cells are new) nor a choice for a
// selection, and the ghost cells it marks are skipped.
bool IsGhostArray(vtkAbstractArray* a);

// Names of the input's point arrays that are not numeric (string, variant): not carried.
std::vector<std::string> PointArraysNotCarried(vtkPolyData* input);
// Names of the input's integer point arrays with values beyond 2^24 in magnitude: the core carries
// point data as float, so they come out rounded.
std::vector<std::string> ImpreciseIntegerArrays(vtkPolyData* input);

// A sink that builds a vtkPolyData (float points, triangles, point data arrays).
class PolyDataSink : public sipmss::io::MeshSink
{
public:
  // With inputPointData (the input's point data), the output's point data rebuilds its arrays:
  // the same names, component counts, types and attribute roles (integers take the nearest
  // value); without it, a file's attributes get the readers' names (Normals, RGBA, TCoords).
  explicit PolyDataSink(vtkPolyData* output, vtkPointData* inputPointData = nullptr);
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

}

#endif
