/**
 * @class   vtkSIPMSSCluster
 * @brief   out-of-core uniform-grid vertex clustering with grid quadrics (SIPMSS Algorithm II)
 *
 * Lindstrom's OoCS on the SIPMSS data management layer: every vertex goes to a cell of a uniform
 * cubic grid whose longest axis has MaximumGridDimension cells; faces whose three vertices fall in
 * three distinct cells are kept (duplicates dropped); each cell's representative vertex minimizes
 * the sum of the area-weighted plane quadrics of the faces touching it. Point data (normals,
 * colors, texture coordinates, scalars) is averaged per cell. Works in a constant memory footprint
 * (MemoryBudgetMB) on inputs of any size, from the input port or streamed from FileName.
 */
#ifndef vtkSIPMSSCluster_h
#define vtkSIPMSSCluster_h

#include "sipmssFiltersModule.h" // for export macro
#include "vtkSIPMSSFilterBase.h"

class SIPMSSFILTERS_EXPORT vtkSIPMSSCluster : public vtkSIPMSSFilterBase
{
public:
  static vtkSIPMSSCluster* New();
  vtkTypeMacro(vtkSIPMSSCluster, vtkSIPMSSFilterBase);
  void PrintSelf(ostream& os, vtkIndent indent) override;

  ///@{
  /**
   * Number of grid cells along the longest axis of the bounding box (default 50).
   */
  vtkSetClampMacro(MaximumGridDimension, int, 1, 65535);
  vtkGetMacro(MaximumGridDimension, int);
  ///@}

  ///@{
  /**
   * Weight of boundary constraint quadrics: planes through the input's boundary edges keep holes
   * and borders in place (lower error on scans with holes, about 9x slower: an extra pass over
   * all edges). 0 (default): off.
   */
  vtkSetClampMacro(BoundaryWeight, double, 0.0, VTK_DOUBLE_MAX);
  vtkGetMacro(BoundaryWeight, double);
  ///@}

  ///@{
  /**
   * Grid box. By default the bounds of the input (or of the file, from a first streaming pass).
   * UseBounds = true uses Bounds instead (e.g. to cluster several pieces on one grid).
   */
  vtkSetVector6Macro(Bounds, double);
  vtkGetVector6Macro(Bounds, double);
  vtkSetMacro(UseBounds, bool);
  vtkGetMacro(UseBounds, bool);
  vtkBooleanMacro(UseBounds, bool);
  ///@}

protected:
  vtkSIPMSSCluster();
  ~vtkSIPMSSCluster() override = default;

  int RequestData(vtkInformation*, vtkInformationVector**, vtkInformationVector*) override;
#ifndef __VTK_WRAP__
  void FillRequest(sipmss::algorithms::SimplifyRequest& request) override;
#endif

  int MaximumGridDimension = 50;
  double BoundaryWeight = 0.0;
  double Bounds[6] = { 0, 1, 0, 1, 0, 1 };
  bool UseBounds = false;

private:
  vtkSIPMSSCluster(const vtkSIPMSSCluster&) = delete;
  void operator=(const vtkSIPMSSCluster&) = delete;
};

#endif
