/**
 * @class   vtkSIPMSSDecimate
 * @brief   linear-time iterative full edge collapse with quadric error metrics (SIPMSS Algorithm I)
 *
 * Each pass collapses a set of independent low-cost edges (no global priority queue, so the run is
 * linear in the input size) at their quadric-optimal positions, rejecting collapses that flip a
 * face, break the link condition or create a zero-area face; boundaries are kept by constraint
 * quadrics (or locked). Each pass yields a level of detail. All per-vertex and per-face state lives
 * in the SIPMSS data management layer, so a run works in a fixed memory budget (MemoryBudgetMB) and
 * finishes in core as the mesh shrinks.
 *
 * Output port 0: the final mesh. Output port 1: a vtkMultiBlockDataSet with the
 * NumberOfLevelsOfDetail levels, finest first (the last block equals port 0).
 */
#ifndef vtkSIPMSSDecimate_h
#define vtkSIPMSSDecimate_h

#include "sipmssFiltersModule.h" // for export macro
#include "vtkSIPMSSFilterBase.h"

class vtkStringArray;

class SIPMSSFILTERS_EXPORT vtkSIPMSSDecimate : public vtkSIPMSSFilterBase
{
public:
  static vtkSIPMSSDecimate* New();
  vtkTypeMacro(vtkSIPMSSDecimate, vtkSIPMSSFilterBase);
  void PrintSelf(ostream& os, vtkIndent indent) override;

  ///@{
  /**
   * Stop at this many triangles. 0 (default): use TargetReduction, or with a MaximumError go as
   * far as the bound allows.
   */
  vtkSetClampMacro(TargetNumberOfTriangles, vtkIdType, 0, VTK_ID_MAX);
  vtkGetMacro(TargetNumberOfTriangles, vtkIdType);
  ///@}

  ///@{
  /**
   * Fraction of the triangles to remove when TargetNumberOfTriangles is 0 and MaximumError is
   * not set (default 0.9).
   */
  vtkSetClampMacro(TargetReduction, double, 0.0, 1.0);
  vtkGetMacro(TargetReduction, double);
  ///@}

  ///@{
  /**
   * An error bound: no collapse whose error (the RMS distance of the merged vertex to the
   * input's planes it stands for, GetAchievedError's measure) exceeds this fraction of the
   * input's bounding-box diagonal, or this distance in the input's units when AbsoluteError is
   * on. Default: no bound. With a bound and TargetNumberOfTriangles 0, the bound is the only stop
   * (TargetReduction is not used): the run goes as far as the bound allows.
   */
  vtkSetClampMacro(MaximumError, double, 0.0, VTK_DOUBLE_MAX);
  vtkGetMacro(MaximumError, double);
  vtkSetMacro(AbsoluteError, bool);
  vtkGetMacro(AbsoluteError, bool);
  vtkBooleanMacro(AbsoluteError, bool);
  ///@}

  ///@{
  /**
   * Number of levels of detail on output port 1 (default 1: only the final mesh), finest
   * first: spaced evenly in log(triangles) down to the target, or with a MaximumError and no
   * TargetNumberOfTriangles each one stopping at half of the next one's bound.
   */
  vtkSetClampMacro(NumberOfLevelsOfDetail, int, 1, 64);
  vtkGetMacro(NumberOfLevelsOfDetail, int);
  ///@}

  ///@{
  /**
   * Keep boundary vertices where they are (default off: boundaries are kept by weighted
   * constraint quadrics, BoundaryWeight).
   */
  vtkSetMacro(LockBoundary, bool);
  vtkGetMacro(LockBoundary, bool);
  vtkBooleanMacro(LockBoundary, bool);
  /**
   * Fit the merged vertices to the input (default on): each moves along its normal so that the
   * output's faces pass through a sample of the input's vertices in the least-squares sense,
   * never above the largest error of a vertex. Off: the quadrics' positions.
   */
  vtkSetMacro(FitSurface, bool);
  vtkGetMacro(FitSurface, bool);
  vtkBooleanMacro(FitSurface, bool);
  vtkSetClampMacro(BoundaryWeight, double, 0.0, VTK_DOUBLE_MAX);
  vtkGetMacro(BoundaryWeight, double);
  ///@}

  ///@{
  /**
   * First remove every disconnected piece whose bounding-box diagonal is below this fraction of
   * the input's (e.g. 0.01; default 0: keep every piece). A piece with a vertex that LockArray or
   * SelectionArray keeps stays. GetPrunedComponents() and GetPrunedTriangles() count them.
   */
  vtkSetClampMacro(PruneSize, double, 0.0, 1.0);
  vtkGetMacro(PruneSize, double);
  ///@}

  ///@{
  /**
   * Two-stage simplification (the paper's Algorithm Two-Stage): when > 0, the input is first
   * clustered on a grid with this maximum dimension (as vtkSIPMSSCluster, e.g. 300), and the
   * clustered mesh, kept in the storage layer, is then decimated. Much faster on huge inputs at
   * the same quality (measured). -1: two-stage on the automatic grid, as the command line's
   * two-stage without --grid: 300, or with a TargetNumberOfTriangles T above 19,125 the grid
   * whose clustered mesh has about 16 T triangles, ceil(sqrt(16 T / 3.4)); when that finer grid
   * would keep at least 0.7 of the input's triangles (3.4 g^2 of them), stage 1 is skipped and
   * the input decimated directly (GetGridDimension() is then 0). 0 (default): decimate the
   * input directly.
   */
  vtkSetClampMacro(PreClusterGridDimension, int, -1, 65535);
  vtkGetMacro(PreClusterGridDimension, int);
  ///@}

  ///@{
  /**
   * Weld input vertices closer than this distance first. Negative (default): no welding.
   */
  vtkSetMacro(WeldDistance, double);
  vtkGetMacro(WeldDistance, double);
  ///@}

  ///@{
  /**
   * Locks and selections by a point-data array of the input (its name; empty or null, the
   * default: none). LockArray: vertices where it is not 0 stay in the output at their exact
   * positions, with their point data. Not with WeldDistance >= 0 (welding merges vertices).
   * SelectionArray: only vertices where it is not 0 move or go, and every triangle without one
   * is kept as it was; or, when it names a one-component cell array (and no point array), every
   * cell where it is 0 is kept as it was (its corners never move or go). A multi-component point
   * array is named NAME_K per component. Decimation only (not with PreClusterGridDimension != 0,
   * whose clustering moves every vertex).
   */
  vtkSetStringMacro(LockArray);
  vtkGetStringMacro(LockArray);
  vtkSetStringMacro(SelectionArray);
  vtkGetStringMacro(SelectionArray);
  ///@}

  ///@{
  /**
   * The names LockArray and SelectionArray can take in a FileName run, from the file's header
   * alone (io::ReadProperties: a PLY's vertex and face properties, also gzip-compressed; STL and
   * OBJ name none): GetFilePointArrayNames() lists its point arrays (LockArray's choices),
   * GetFileArrayNames() its point arrays, then its cell arrays (SelectionArray's). Read again at
   * each call; empty without a FileName, for anything but a regular file (a pipe is never read
   * here) or when the header cannot be read (the run then says why). ParaView's File sources list them in their drop-downs.
   */
  vtkStringArray* GetFilePointArrayNames();
  vtkStringArray* GetFileArrayNames();
  ///@}

protected:
  vtkSIPMSSDecimate();
  ~vtkSIPMSSDecimate() override;

  int FillOutputPortInformation(int port, vtkInformation* info) override;
  int RequestData(vtkInformation*, vtkInformationVector**, vtkInformationVector*) override;
#ifndef __VTK_WRAP__
  void FillRequest(sipmss::algorithms::SimplifyRequest& request) override;
  const char* PropertyName(sipmss::algorithms::Parameter parameter) override;
#endif

  vtkIdType TargetNumberOfTriangles = 0;
  double TargetReduction = 0.9;
  double MaximumError = VTK_DOUBLE_MAX;
  bool AbsoluteError = false;
  double PruneSize = 0.0;
  int NumberOfLevelsOfDetail = 1;
  bool LockBoundary = false;
  bool FitSurface = true;
  double BoundaryWeight = 100.0;
  double WeldDistance = -1.0;
  int PreClusterGridDimension = 0;
  char* LockArray = nullptr;
  char* SelectionArray = nullptr;

private:
  // Fills FilePointArrays and FileArrays from FileName's header.
  void ReadFileArrayNames();
  vtkStringArray* FilePointArrays = nullptr;
  vtkStringArray* FileArrays = nullptr;

  vtkSIPMSSDecimate(const vtkSIPMSSDecimate&) = delete;
  void operator=(const vtkSIPMSSDecimate&) = delete;
};

#endif
