/**
 * @class   vtkSIPMSSFilterBase
 * @brief   shared properties of the SIPMSS filters: input file, memory budget, storage statistics
 *
 * The SIPMSS filters simplify a triangle mesh under a fixed memory budget through the SIPMSS data
 * management layer (DML): in core when the data fits MemoryBudgetMB, otherwise out of core with
 * block files in TemporaryDirectories and a page cache in memory. Input comes from the input port
 * (a vtkPolyData; polygons are triangulated, strips converted, vertices and lines ignored with a
 * warning, ghost cells (vtkGhostType DUPLICATECELL or HIDDENCELL: another piece's cells) skipped
 * and the ghost arrays not carried) or, when FileName is set, streamed straight from a PLY, STL or OBJ file (optionally
 * gzip-compressed) without loading it first.
 */
#ifndef vtkSIPMSSFilterBase_h
#define vtkSIPMSSFilterBase_h

#include "sipmssFiltersModule.h" // for export macro
#include "vtkPolyDataAlgorithm.h"

class vtkMultiProcessController;
class vtkPointData;
class vtkPolyData;

#include <cstdint>    // for std::uint8_t
#include <functional> // for std::function
#include <string>     // for std::string

#ifndef __VTK_WRAP__
namespace sipmss
{
namespace io
{
class MeshSink;
struct ReadStats;
struct ReadOptions;
}
namespace storage
{
struct Profile;
}
namespace algorithms
{
struct SimplifyRequest;
enum class Parameter : std::uint8_t;
}
}
#endif

class SIPMSSFILTERS_EXPORT vtkSIPMSSFilterBase : public vtkPolyDataAlgorithm
{
public:
  vtkTypeMacro(vtkSIPMSSFilterBase, vtkPolyDataAlgorithm);
  void PrintSelf(ostream& os, vtkIndent indent) override;

  enum OperationModes
  {
    AUTOMATIC = 0, ///< in core when the estimated cost fits the budget, else out of core
    IN_CORE = 1,
    OUT_OF_CORE = 2
  };

  ///@{
  /**
   * A PLY/STL/OBJ (.gz) file to stream instead of the input port. Empty (default): use the input.
   */
  vtkSetStringMacro(FileName);
  vtkGetStringMacro(FileName);
  ///@}

  ///@{
  /**
   * Point attributes that join the error, with weights: "NAME[:WEIGHT],..." (a weight defaults
   * to 1), e.g. "Normals:0.5,RGBA:1". A NAME is a point array of the input (its normals, its
   * unsigned char colors, its texture coordinates, a scalar array, or an array of several
   * components), or one of the keywords normals, colors (rgb, rgba), texcoords (uv): a file's
   * attributes. A weight of 1 makes a change of 1 in the attribute (colors from 0 to 1) across a
   * distance d cost about as much as moving the surface by d (meshoptimizer's weighting). Merged
   * vertices take the attributes' optimal values. Empty (default): geometry only. The CLI's
   * --attributes takes the same list.
   */
  vtkSetStringMacro(Attributes);
  vtkGetStringMacro(Attributes);
  ///@}

  ///@{
  /**
   * Memory budget of the data management layer in MiB (at least 0.0625). 0 (default) is
   * automatic: half of what this process may use (the lowest of the cgroup memory limit,
   * ulimit -v/-d and MemAvailable, read when the filter runs). -1 is unbounded (always in core).
   * The CLI's --memory-mb takes the same values (also as "auto" and "unbounded").
   */
  vtkSetClampMacro(MemoryBudgetMB, double, -1.0, VTK_DOUBLE_MAX);
  vtkGetMacro(MemoryBudgetMB, double);
  ///@}

  ///@{
  /**
   * Directories for the block files of the out-of-core mode, separated by ';'. Empty (default):
   * $TMPDIR or /tmp. Each run makes a private directory there and removes it when done.
   */
  vtkSetStringMacro(TemporaryDirectories);
  vtkGetStringMacro(TemporaryDirectories);
  ///@}

  ///@{
  /**
   * AUTOMATIC (default), IN_CORE or OUT_OF_CORE.
   */
  vtkSetClampMacro(OperationMode, int, AUTOMATIC, OUT_OF_CORE);
  vtkGetMacro(OperationMode, int);
  ///@}

  ///@{
  /**
   * Threads of the run. 0 (default): all cores. Out of core, Algorithm I's phases use at most
   * two, the second with half of the memory budget's pages. The output does not depend on it.
   * Lower it when several filters or MPI ranks share a machine (pvbatch under mpirun).
   */
  vtkSetClampMacro(NumberOfThreads, int, 0, 256);
  vtkGetMacro(NumberOfThreads, int);
  ///@}

  ///@{
  /**
   * Statistics of the last run.
   */
  vtkGetMacro(UsedInCore, bool);
  // The budget the run had in bytes (the automatic one as it was computed; 0: unbounded).
  vtkGetMacro(MemoryBudgetBytes, vtkTypeUInt64);
  // The input's layout: the share of its first faces far apart in index order (-1: not
  // measured), and whether the run reordered it first (docs/architecture.md, "Input layout").
  vtkGetMacro(LayoutFarFraction, double);
  vtkGetMacro(Reordered, bool);
  vtkGetMacro(UsedOutOfCore, bool);
  vtkGetMacro(PeakStorageBytes, vtkTypeUInt64);
  // The largest size the temporary block files reached together (disk).
  vtkGetMacro(PeakTemporaryFileBytes, vtkTypeUInt64);
  vtkGetMacro(PageHits, vtkTypeUInt64);
  vtkGetMacro(PageMisses, vtkTypeUInt64);
  vtkGetMacro(BytesRead, vtkTypeUInt64);
  vtkGetMacro(BytesWritten, vtkTypeUInt64);
  vtkGetMacro(Reconfigurations, vtkTypeUInt64);
  vtkGetMacro(ElapsedSeconds, double);
  // Triangles in and out, and the fraction of the input's triangles removed (0 before a run).
  vtkGetMacro(InputTriangles, vtkTypeUInt64);
  vtkGetMacro(OutputTriangles, vtkTypeUInt64);
  vtkGetMacro(AchievedReduction, double);
  // The error of the run's merges (the largest RMS distance of a merged vertex to the input's
  // planes it stands for) as a fraction of the input's bounding-box diagonal, and that diagonal
  // (-1 and 0 before a run; docs/architecture.md, "Error bound").
  vtkGetMacro(AchievedError, double);
  vtkGetMacro(ErrorDiagonal, double);
  // The grid the last run clustered on (vtkSIPMSSCluster's, or two-stage's stage 1: with
  // vtkSIPMSSDecimate's PreClusterGridDimension -1 the automatic one); 0: no clustering (also an
  // automatic two-stage that skipped stage 1).
  vtkGetMacro(GridDimension, int);
  // Disconnected pieces the run removed (vtkSIPMSSDecimate's PruneSize) and their triangles.
  vtkGetMacro(PrunedComponents, vtkTypeUInt64);
  vtkGetMacro(PrunedTriangles, vtkTypeUInt64);
  // Bytes of the input file this rank read in the last run (all its passes; 0 for a pipeline
  // input). Under MPI a binary PLY or STL is read by byte ranges, each rank about 1/N of the
  // file; any other file by rank 0 alone (the others' 0), which sends the ranks their pieces.
  vtkGetMacro(InputBytesRead, vtkTypeUInt64);
  // A run across MPI ranks (a controller of several processes): the ranks, this rank's bytes
  // sent to and received from the others and its seconds in communication, and every rank's
  // figures as text ("rank 0: ... ; rank 1: ..."; empty for a serial run).
  vtkGetMacro(NumberOfRanks, int);
  vtkGetMacro(BytesSent, vtkTypeUInt64);
  vtkGetMacro(BytesReceived, vtkTypeUInt64);
  vtkGetMacro(CommunicationSeconds, double);
  vtkGetStringMacro(RankStatistics);
  ///@}

  ///@{
  /**
   * The processes the filter runs on (default: the global controller, ParaView's MPI controller
   * under pvbatch and pvserver). With more than one, vtkSIPMSSCluster clusters the ranks' pieces
   * together on one grid (each rank's output is its piece of the serial result).
   * vtkSIPMSSDecimate decimates the ranks' pieces together: each piece with its border locked,
   * then the joined results on rank 0, whose output is the whole mesh without seams (the others'
   * outputs are empty); with a PreClusterGridDimension (two-stage) the clustering runs across
   * the ranks first. A FileName run of a binary PLY or binary STL reads the file by byte ranges,
   * each rank its share of the faces and the vertices they use, and runs across the ranks as
   * above; rank 0 reads any other file once and sends every rank such a piece (then the same).
   */
  virtual void SetController(vtkMultiProcessController*);
  vtkGetObjectMacro(Controller, vtkMultiProcessController);
  ///@}

protected:
  vtkSIPMSSFilterBase();
  ~vtkSIPMSSFilterBase() override;

  int FillInputPortInformation(int port, vtkInformation* info) override;

#ifndef __VTK_WRAP__
  // The filter's request: the base fills the storage and thread properties, the subclass its
  // algorithm and parameters (FillRequest). The request's rules (algorithms::Problems) are
  // checked before any work and reported with PropertyName's names.
  virtual void FillRequest(sipmss::algorithms::SimplifyRequest& request) = 0;
  virtual const char* PropertyName(sipmss::algorithms::Parameter parameter);
  // Runs the request on the input port or FileName into output (levels of detail through
  // onLevel); fills the statistics, reports errors.
  int Simplify(vtkInformationVector** inputVector, vtkPolyData* output,
    const std::function<void(int level, const std::function<void(sipmss::io::MeshSink&)>& emit)>&
      onLevel = nullptr);
#endif
#ifndef __VTK_WRAP__
  // During a run on the input port: the input's point data, whose arrays every output (also
  // a level of detail) rebuilds with their names, types and roles. Null for FileName runs.
  vtkPointData* InputPointData = nullptr;
#endif

  vtkMultiProcessController* Controller = nullptr;
  char* FileName = nullptr;
  char* Attributes = nullptr;
  double MemoryBudgetMB = 0.0;
  char* TemporaryDirectories = nullptr;
  int OperationMode = AUTOMATIC;
  int NumberOfThreads = 0;

  bool UsedInCore = false;
  bool UsedOutOfCore = false;
  vtkTypeUInt64 MemoryBudgetBytes = 0;
  double LayoutFarFraction = -1;
  bool Reordered = false;
  vtkTypeUInt64 PeakStorageBytes = 0;
  vtkTypeUInt64 PeakTemporaryFileBytes = 0;
  vtkTypeUInt64 PageHits = 0;
  vtkTypeUInt64 PageMisses = 0;
  vtkTypeUInt64 BytesRead = 0;
  vtkTypeUInt64 InputBytesRead = 0;
  vtkTypeUInt64 BytesWritten = 0;
  vtkTypeUInt64 Reconfigurations = 0;
  double ElapsedSeconds = 0.0;
  vtkTypeUInt64 InputTriangles = 0;
  vtkTypeUInt64 OutputTriangles = 0;
  int NumberOfRanks = 1;
  vtkTypeUInt64 BytesSent = 0;
  vtkTypeUInt64 BytesReceived = 0;
  double CommunicationSeconds = 0.0;
  char* RankStatistics = nullptr;
  vtkSetStringMacro(RankStatistics);
  double AchievedReduction = 0.0;
  double AchievedError = -1.0;
  double ErrorDiagonal = 0.0;
  int GridDimension = 0;
  vtkTypeUInt64 PrunedComponents = 0;
  vtkTypeUInt64 PrunedTriangles = 0;

private:
  vtkSIPMSSFilterBase(const vtkSIPMSSFilterBase&) = delete;
  void operator=(const vtkSIPMSSFilterBase&) = delete;
};

#endif
