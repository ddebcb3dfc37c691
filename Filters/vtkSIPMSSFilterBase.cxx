#include "vtkSIPMSSFilterBase.h"

#include "vtkSIPMSSCommunicator.h"
#include "vtkSIPMSSPolyDataBridge.h"

#include "vtkCellData.h"
#include "vtkInformation.h"
#include "vtkInformationVector.h"
#include "vtkMultiProcessController.h"
#include "vtkObjectFactory.h"
#include "vtkPointData.h"
#include "vtkPolyData.h"
#include "vtkSmartPointer.h"

#include "sipmss/algorithms/FilePiece.h"
#include "sipmss/algorithms/Simplify.h"

#include <algorithm>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <vector>

vtkSIPMSSFilterBase::vtkSIPMSSFilterBase()
{
  this->SetController(vtkMultiProcessController::GetGlobalController());
}

vtkCxxSetObjectMacro(vtkSIPMSSFilterBase, Controller, vtkMultiProcessController);

vtkSIPMSSFilterBase::~vtkSIPMSSFilterBase()
{
  this->SetController(nullptr);
  this->SetRankStatistics(nullptr);
  this->SetFileName(nullptr);
  this->SetAttributes(nullptr);
  this->SetTemporaryDirectories(nullptr);
}

int vtkSIPMSSFilterBase::FillInputPortInformation(int port, vtkInformation* info)
{
  if (!this->Superclass::FillInputPortInformation(port, info))
  {
    return 0;
  }
  // The input is optional: FileName streams a file instead.
  info->Set(vtkAlgorithm::INPUT_IS_OPTIONAL(), 1);
  return 1;
}

const char* vtkSIPMSSFilterBase::PropertyName(sipmss::algorithms::Parameter parameter)
{
  using sipmss::algorithms::Parameter;
  switch (parameter)
  {
    case Parameter::TargetTriangles:
      return "TargetNumberOfTriangles";
    case Parameter::TargetReduction:
      return "TargetReduction";
    case Parameter::MaximumError:
      return "MaximumError";
    case Parameter::LevelsOfDetail:
      return "NumberOfLevelsOfDetail";
    case Parameter::Grid:
      return "MaximumGridDimension";
    case Parameter::Bounds:
      return "Bounds";
    case Parameter::BoundaryWeight:
      return "BoundaryWeight";
    case Parameter::WeldDistance:
      return "WeldDistance";
    case Parameter::LockArray:
      return "LockArray";
    case Parameter::SelectionArray:
      return "SelectionArray";
    case Parameter::PruneSize:
      return "PruneSize";
    case Parameter::Attributes:
      return "Attributes";
    case Parameter::MemoryBudget:
      return "MemoryBudgetMB";
    default:
      return "NumberOfThreads";
  }
}

int vtkSIPMSSFilterBase::Simplify(vtkInformationVector** inputVector, vtkPolyData* output,
  const sipmss::algorithms::LevelCallback& onLevel)
{
  namespace bridge = vtkSIPMSSPolyDataBridge;
  this->UsedInCore = this->UsedOutOfCore = false;
  this->PeakStorageBytes = this->PeakTemporaryFileBytes = this->PageHits = this->PageMisses = 0;
  this->MemoryBudgetBytes = 0;
  this->LayoutFarFraction = -1;
  this->Reordered = false;
  this->BytesRead = this->BytesWritten = this->Reconfigurations = 0;
  this->InputBytesRead = 0;
  this->ElapsedSeconds = 0;
  this->InputTriangles = this->OutputTriangles = 0;
  this->AchievedReduction = 0;
  this->AchievedError = -1;
  this->ErrorDiagonal = 0;
  this->GridDimension = 0;
  this->PrunedComponents = this->PrunedTriangles = 0;
  this->NumberOfRanks = 1;
  this->BytesSent = this->BytesReceived = 0;
  this->CommunicationSeconds = 0;
  this->SetRankStatistics("");

  // Under MPI (a controller of several processes): the filters run across the ranks on the
  // pipeline's pieces, or on the pieces of a file (FilePiece): each rank reads its own by byte
  // ranges, or rank 0 reads a file that cannot be read so and sends every rank its piece.
  vtkMultiProcessController* controller = this->Controller;
  const int ranks = controller ? controller->GetNumberOfProcesses() : 1;
  const bool fileRun = this->FileName && *this->FileName;
  bool distributed = ranks > 1 && !fileRun;
  std::optional<vtkSIPMSSCommunicator> communicator;

  // The request, and the same rules as the CLI's: NaN, infinities and meaningless values are
  // errors before any work.
  sipmss::algorithms::SimplifyRequest request;
  request.memoryBudgetMB = this->MemoryBudgetMB;
  if (const char* dirs = this->TemporaryDirectories)
  {
    std::stringstream ss(dirs);
    std::string d;
    while (std::getline(ss, d, ';'))
    {
      if (!d.empty())
      {
        request.temporaryDirectories.push_back(d);
      }
    }
  }
  request.mode = this->OperationMode == IN_CORE ? sipmss::storage::ModePolicy::InCore
    : this->OperationMode == OUT_OF_CORE        ? sipmss::storage::ModePolicy::OutOfCore
                                                : sipmss::storage::ModePolicy::Automatic;
  request.threads = this->NumberOfThreads;
  request.attributes = this->Attributes ? this->Attributes : "";
  this->FillRequest(request);
  if (distributed)
  {
    communicator.emplace(controller);
    request.communicator = &*communicator;
  }
  const auto problems = sipmss::algorithms::Problems(request);
  if (!problems.empty())
  {
    vtkErrorMacro(<< this->PropertyName(problems.front().parameter) << " "
                  << problems.front().problem << ".");
    output->Initialize();
    return 0;
  }
  sipmss::algorithms::MeshSource source;
  vtkSmartPointer<vtkPolyData> repaired; // the input without the point arrays that cannot be read
  bool haveBounds = false;
  std::array<double, 6> bounds{};
  std::string what;
  std::unique_ptr<sipmss::algorithms::FilePiece> piece;
  std::uint64_t inputBytes = 0; // (a whole file's reads)
  if (fileRun)
  {
    what = this->FileName;
    if (ranks > 1)
    {
      // Every rank reads its piece, in a DML of its own with an eighth of the budget (the run
      // gets the rest), or all ranks agree that the file cannot be read in pieces.
      communicator.emplace(controller);
      const sipmss::storage::Profile pieceProfile = sipmss::algorithms::ReservePieceBudget(request);
      bridge::AlgorithmProgress pieceProgress(this);
      try
      {
        piece = std::make_unique<sipmss::algorithms::FilePiece>(
          this->FileName, *communicator, pieceProfile, pieceProgress);
      }
      catch (const sipmss::algorithms::AbortedError&)
      {
        output->Initialize();
        return 1;
      }
      catch (const std::exception& e)
      {
        vtkErrorMacro("Cannot simplify " << what << ": " << e.what());
        output->Initialize();
        return 0;
      }
      // (read by byte ranges, or read by rank 0 and scattered: every rank has its piece)
      distributed = true;
      request.communicator = &*communicator;
      source = piece->Source();
    }
    if (!piece)
    {
      source = [file = sipmss::algorithms::FileSource(this->FileName), &inputBytes](
                 sipmss::io::MeshSink& sink, const sipmss::io::ReadOptions& options) {
        const sipmss::io::ReadStats read = file(sink, options);
        inputBytes += read.bytes;
        return read;
      };
    }
  }
  else
  {
    vtkPolyData* input = vtkPolyData::GetData(inputVector[0], 0);
    if (!input)
    {
      vtkErrorMacro("No input: connect a vtkPolyData or set FileName.");
      return 0;
    }
    if (!distributed &&
      (input->GetNumberOfPoints() == 0 || input->GetNumberOfPolys() + input->GetNumberOfStrips() == 0))
    {
      // (a rank's empty piece still takes part in a distributed run)
      vtkWarningMacro("The input has no polygons: the output is empty.");
      output->Initialize();
      return 1;
    }
    // A point array whose tuple count is not the number of points cannot be read per point:
    // the run goes on without it (a shallow copy; the input keeps it).
    std::vector<std::string> wrongLength;
    for (int i = 0; i < input->GetPointData()->GetNumberOfArrays(); ++i)
    {
      vtkAbstractArray* a = input->GetPointData()->GetAbstractArray(i);
      if (a && a->GetNumberOfTuples() != input->GetNumberOfPoints())
      {
        wrongLength.emplace_back(std::string(a->GetName() ? a->GetName() : "(unnamed)") + " (" +
          std::to_string(a->GetNumberOfTuples()) + " tuples)");
      }
    }
    if (!wrongLength.empty())
    {
      repaired = vtkSmartPointer<vtkPolyData>::New();
      repaired->ShallowCopy(input);
      vtkPointData* pd = repaired->GetPointData();
      for (int i = pd->GetNumberOfArrays() - 1; i >= 0; --i)
      {
        vtkAbstractArray* a = pd->GetAbstractArray(i);
        if (a && a->GetNumberOfTuples() != input->GetNumberOfPoints())
        {
          pd->RemoveArray(i);
        }
      }
      input = repaired;
      std::string names;
      for (const auto& n : wrongLength)
      {
        names += (names.empty() ? "" : ", ") + n;
      }
      vtkWarningMacro("Point arrays whose tuple count is not the number of points ("
        << input->GetNumberOfPoints() << ") are not carried: dropping " << names << ".");
    }
    vtkIdType skipped = 0;
    source = bridge::PolyDataSource(input, &skipped);
    std::string ambiguous;
    request.attributes = bridge::CoreAttributeNames(input, request.attributes, ambiguous);
    std::string problem;
    if (!ambiguous.empty())
    {
      problem = std::string(this->PropertyName(sipmss::algorithms::Parameter::Attributes)) + " " +
        ambiguous + ".";
    }
    for (const auto& p : sipmss::algorithms::Problems(request))
    {
      // (the input's array names as keywords may name one attribute twice: Normals and normals)
      problem = std::string(this->PropertyName(p.parameter)) + " " + p.problem + ".";
      break;
    }
    if (!problem.empty() && distributed)
    {
      // (this piece's arrays: the run fails on every rank, none waits for this one)
      source = [problem](sipmss::io::MeshSink&, const sipmss::io::ReadOptions&)
        -> sipmss::io::ReadStats { throw std::runtime_error(problem); };
      request.attributes.clear();
    }
    else if (!problem.empty())
    {
      vtkErrorMacro(<< problem);
      output->Initialize();
      return 0;
    }
    if (skipped)
    {
      vtkWarningMacro("Ignoring " << skipped << " vertex and line cells of the input.");
    }
    auto list = [](const std::vector<std::string>& names) {
      std::string s;
      for (const auto& n : names)
      {
        s += (s.empty() ? "" : ", ") + n;
      }
      return s;
    };
    std::vector<std::string> cellArrays;
    for (int i = 0; i < input->GetCellData()->GetNumberOfArrays(); ++i)
    {
      vtkAbstractArray* a = input->GetCellData()->GetAbstractArray(i);
      if (bridge::IsGhostArray(a))
      {
        continue; // (the pieces' ghost cells, skipped: not the user's data)
      }
      cellArrays.emplace_back(a && a->GetName() ? a->GetName() : "(unnamed)");
    }
    if (!cellArrays.empty())
    {
      vtkWarningMacro("Cell data is not carried (the simplified faces are new): dropping "
        << list(cellArrays) << ".");
    }
    const std::vector<std::string> notCarried = bridge::PointArraysNotCarried(input);
    if (!notCarried.empty())
    {
      vtkWarningMacro("Non-numeric point data is not carried: dropping " << list(notCarried) << ".");
    }
    const std::vector<std::string> imprecise = bridge::ImpreciseIntegerArrays(input);
    if (!imprecise.empty())
    {
      vtkWarningMacro("Point data is carried in single precision: integer values beyond 2^24 of "
        << list(imprecise) << " come out rounded.");
    }
    this->InputPointData = input->GetPointData();
    haveBounds = true;
    what = "the input";
  }

  // the input's point data for the output sinks (cleared when the run ends)
  struct ClearInputPointData
  {
    vtkSIPMSSFilterBase* self;
    ~ClearInputPointData() { self->InputPointData = nullptr; }
  } clearInputPointData{ this };
  bridge::AlgorithmProgress progress(this);
  bridge::PolyDataSink sink(output, this->InputPointData);
  try
  {
    if (haveBounds && distributed)
    {
      // The ranks find the bounds together (the core's first pass). A bad point here fails
      // this rank's read there, where every rank learns of it (none waits for this one).
      try
      {
        bridge::Bounds(vtkPolyData::GetData(inputVector[0], 0));
      }
      catch (const std::exception& e)
      {
        const std::string message = e.what();
        source = [message](sipmss::io::MeshSink&, const sipmss::io::ReadOptions&)
          -> sipmss::io::ReadStats { throw std::runtime_error(message); };
      }
    }
    else if (haveBounds)
    {
      bounds = bridge::Bounds(vtkPolyData::GetData(inputVector[0], 0));
      if (!request.bounds)
      {
        request.bounds = bounds; // (a clustering needs no bounds pass)
      }
    }
    const auto start = std::chrono::steady_clock::now();
    sipmss::algorithms::RunStats stats =
      sipmss::algorithms::Simplify(request, source, sink, progress, onLevel);
    this->MemoryBudgetBytes = stats.memoryBudgetBytes;
    this->ElapsedSeconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    this->InputTriangles = stats.inputTriangles;
    this->OutputTriangles = stats.outputTriangles;
    this->AchievedReduction = stats.inputTriangles
      ? 1.0 - double(stats.outputTriangles) / double(stats.inputTriangles)
      : 0.0;
    this->LayoutFarFraction = stats.layoutFarFraction;
    this->AchievedError = stats.achievedError;
    this->ErrorDiagonal = stats.errorDiagonal;
    this->GridDimension = stats.gridDimension;
    this->PrunedComponents = stats.prunedComponents;
    this->PrunedTriangles = stats.prunedTriangles;
    this->Reordered = stats.reordered;
    this->UsedInCore = stats.storage.usedInCore;
    this->UsedOutOfCore = stats.storage.usedOutOfCore;
    this->PeakStorageBytes = stats.storage.peakBytes;
    this->PeakTemporaryFileBytes = stats.storage.peakFileBytes;
    for (const std::string& note : stats.storage.notes)
    {
      vtkWarningMacro(<< note); // e.g. a full temporary directory and where the files went
    }
    if (!distributed || controller->GetLocalProcessId() == 0)
    {
      // (about the whole result, the same on every rank: said once)
      for (const std::string& warning : stats.warnings)
      {
        vtkWarningMacro(<< warning); // e.g. a two-stage bound the clustering used up
      }
    }
    this->PageHits = stats.storage.hits;
    this->PageMisses = stats.storage.misses;
    this->BytesRead = stats.storage.bytesRead;
    this->BytesWritten = stats.storage.bytesWritten;
    this->Reconfigurations = stats.storage.reconfigurations;
    this->InputBytesRead = piece ? piece->BytesRead() : inputBytes;
    if (distributed)
    {
      // The run's exchanges, and a scattered file's (FilePiece::Traffic).
      sipmss::algorithms::CommunicationStats c = stats.communication;
      sipmss::algorithms::CommunicationStats scatter;
      if (piece)
      {
        scatter = piece->Traffic();
        c.Add(scatter); // (this rank's; every rank's scatter is gathered below)
      }
      this->NumberOfRanks = c.ranks;
      this->BytesSent = c.bytesSent;
      this->BytesReceived = c.bytesReceived;
      this->CommunicationSeconds = c.seconds;
      // (every rank's figures, gathered by the run before its output; the file's pieces' bytes
      // read and the scatter's here, on every rank: all of them have a piece)
      std::vector<double> fileFigures(5 * std::size_t(ranks), 0.0);
      if (piece)
      {
        double mine[5] = { double(this->InputBytesRead), double(scatter.bytesSent),
          double(scatter.bytesReceived), scatter.seconds, double(scatter.rounds) };
        controller->AllGather(mine, fileFigures.data(), 5);
      }
      std::ostringstream text;
      for (std::size_t r = 0; 4 * r + 3 < c.perRank.size(); ++r)
      {
        const double* f = c.perRank.data() + 4 * r;
        const double* g = fileFigures.data() + 5 * std::min(r, std::size_t(ranks - 1));
        text << (r ? "; " : "") << "rank " << r << ": " << std::uint64_t(f[0] + g[1])
             << " bytes sent, " << std::uint64_t(f[1] + g[2]) << " received, " << f[2] + g[3]
             << " s in communication, " << std::uint64_t(f[3] + g[4]) << " exchanges";
        if (piece)
        {
          text << ", " << std::uint64_t(g[0]) << " input bytes read";
        }
      }
      this->SetRankStatistics(text.str().c_str());
    }
    if (stats.droppedInputFaces)
    {
      vtkWarningMacro("Dropped " << stats.droppedInputFaces << " degenerate faces of " << what
        << " (fewer than 3 distinct vertices, zero area, or the same vertices as another face).");
    }
  }
  catch (const sipmss::algorithms::AbortedError&)
  {
    output->Initialize();
    return 1; // VTK convention: an aborted filter produces an empty output, no error
  }
  catch (const std::exception& e)
  {
    output->Initialize();
    vtkErrorMacro("Cannot simplify " << what << ": " << e.what());
    return 0;
  }
  this->UpdateProgress(1.0);
  return 1;
}

void vtkSIPMSSFilterBase::PrintSelf(ostream& os, vtkIndent indent)
{
  this->Superclass::PrintSelf(os, indent);
  os << indent << "FileName: " << (this->FileName ? this->FileName : "(none)") << "\n";
  os << indent << "Attributes: " << (this->Attributes ? this->Attributes : "(none)") << "\n";
  os << indent << "MemoryBudgetMB: " << this->MemoryBudgetMB << "\n";
  os << indent << "TemporaryDirectories: "
     << (this->TemporaryDirectories ? this->TemporaryDirectories : "(default)") << "\n";
  os << indent << "OperationMode: " << this->OperationMode << "\n";
  os << indent << "NumberOfThreads: " << this->NumberOfThreads << "\n";
  os << indent << "UsedInCore: " << this->UsedInCore << "\n";
  os << indent << "UsedOutOfCore: " << this->UsedOutOfCore << "\n";
  os << indent << "PeakStorageBytes: " << this->PeakStorageBytes << "\n";
  os << indent << "PeakTemporaryFileBytes: " << this->PeakTemporaryFileBytes << "\n";
  os << indent << "MemoryBudgetBytes: " << this->MemoryBudgetBytes << "\n";
  os << indent << "LayoutFarFraction: " << this->LayoutFarFraction << "\n";
  os << indent << "Reordered: " << this->Reordered << "\n";
  os << indent << "PageHits: " << this->PageHits << "\n";
  os << indent << "PageMisses: " << this->PageMisses << "\n";
  os << indent << "InputTriangles: " << this->InputTriangles << "\n";
  os << indent << "OutputTriangles: " << this->OutputTriangles << "\n";
  os << indent << "AchievedReduction: " << this->AchievedReduction << "\n";
  os << indent << "AchievedError: " << this->AchievedError << "\n";
  os << indent << "ErrorDiagonal: " << this->ErrorDiagonal << "\n";
  os << indent << "GridDimension: " << this->GridDimension << "\n";
  os << indent << "PrunedComponents: " << this->PrunedComponents << "\n";
  os << indent << "PrunedTriangles: " << this->PrunedTriangles << "\n";
}
