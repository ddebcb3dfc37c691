#include "vtkSIPMSSFilterBase.h"

#include "vtkSIPMSSPolyDataBridge.h"

#include "vtkCellData.h"
#include "vtkInformation.h"
#include "vtkInformationVector.h"
#include "vtkObjectFactory.h"
#include "vtkPointData.h"
#include "vtkPolyData.h"
#include "vtkSmartPointer.h"

#include <cmath>
#include <string>
#include <vector>

vtkSIPMSSFilterBase::vtkSIPMSSFilterBase() = default;

vtkSIPMSSFilterBase::~vtkSIPMSSFilterBase()
{
  this->SetFileName(nullptr);
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

int vtkSIPMSSFilterBase::Simplify(vtkInformationVector** inputVector, vtkPolyData* output,
  const CoreRun& run)
{
  namespace bridge = vtkSIPMSSPolyDataBridge;
  this->UsedInCore = this->UsedOutOfCore = false;
  this->PeakStorageBytes = this->PeakTemporaryFileBytes = this->PageHits = this->PageMisses = 0;
  this->MemoryBudgetBytes = 0;
  this->LayoutFarFraction = -1;
  this->Reordered = false;
  this->BytesRead = this->BytesWritten = this->Reconfigurations = 0;
  this->ElapsedSeconds = 0;

  // The same rules as the CLI's: NaN, infinities and meaningless values are errors.
  std::string problem = sipmss::algorithms::MemoryBudgetProblem(this->MemoryBudgetMB);
  if (!problem.empty())
  {
    problem = "MemoryBudgetMB " + problem;
  }
  else
  {
    problem = this->ParameterProblem();
  }
  if (!problem.empty())
  {
    vtkErrorMacro(<< problem << ".");
    output->Initialize();
    return 0;
  }

  sipmss::algorithms::MeshSource source;
  vtkSmartPointer<vtkPolyData> repaired; // the input without the point arrays that cannot be read
  bool haveBounds = false;
  std::array<double, 6> bounds{};
  std::string what;
  if (this->FileName && *this->FileName)
  {
    source = sipmss::algorithms::FileSource(this->FileName);
    what = this->FileName;
  }
  else
  {
    vtkPolyData* input = vtkPolyData::GetData(inputVector[0], 0);
    if (!input)
    {
      vtkErrorMacro("No input: connect a vtkPolyData or set FileName.");
      return 0;
    }
    if (input->GetNumberOfPoints() == 0 || input->GetNumberOfPolys() + input->GetNumberOfStrips() == 0)
    {
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
    if (haveBounds)
    {
      bounds = bridge::Bounds(vtkPolyData::GetData(inputVector[0], 0));
    }
    const auto start = std::chrono::steady_clock::now();
    const sipmss::storage::Profile profile = bridge::MakeProfile(this);
    this->MemoryBudgetBytes = profile.memoryBudget;
    sipmss::algorithms::RunStats stats = sipmss::algorithms::TranslateOutOfMemory(progress,
      profile, [&] { return run(source, haveBounds, bounds, sink, profile, progress); });
    this->ElapsedSeconds =
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    this->LayoutFarFraction = stats.layoutFarFraction;
    this->Reordered = stats.reordered;
    this->UsedInCore = stats.storage.usedInCore;
    this->UsedOutOfCore = stats.storage.usedOutOfCore;
    this->PeakStorageBytes = stats.storage.peakBytes;
    this->PeakTemporaryFileBytes = stats.storage.peakFileBytes;
    for (const std::string& note : stats.storage.notes)
    {
      vtkWarningMacro(<< note); // e.g. a full temporary directory and where the files went
    }
    this->PageHits = stats.storage.hits;
    this->PageMisses = stats.storage.misses;
    this->BytesRead = stats.storage.bytesRead;
    this->BytesWritten = stats.storage.bytesWritten;
    this->Reconfigurations = stats.storage.reconfigurations;
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

std::string vtkSIPMSSFilterBase::FiniteProblem(const char* name, double value)
{
  return std::isfinite(value) ? std::string()
                              : std::string(name) + " must be a finite number, not " + std::to_string(value);
}

void vtkSIPMSSFilterBase::PrintSelf(ostream& os, vtkIndent indent)
{
  this->Superclass::PrintSelf(os, indent);
  os << indent << "FileName: " << (this->FileName ? this->FileName : "(none)") << "\n";
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
}
