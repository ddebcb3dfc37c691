#include "vtkSIPMSSDecimate.h"

#include "vtkSIPMSSPolyDataBridge.h"

#include "sipmss/algorithms/Simplify.h"
#include "sipmss/io/MeshIO.h"

#include "vtkDataObject.h"
#include "vtkInformation.h"
#include "vtkInformationVector.h"
#include "vtkMultiBlockDataSet.h"
#include "vtkNew.h"
#include "vtkObjectFactory.h"
#include "vtkPolyData.h"
#include "vtkStringArray.h"

#include <algorithm>
#include <exception>
#include <filesystem>
#include <system_error>
#include <limits>
#include <string>

vtkStandardNewMacro(vtkSIPMSSDecimate);

vtkSIPMSSDecimate::vtkSIPMSSDecimate()
{
  this->SetNumberOfOutputPorts(2);
  this->FilePointArrays = vtkStringArray::New();
  this->FileArrays = vtkStringArray::New();
}

void vtkSIPMSSDecimate::ReadFileArrayNames()
{
  this->FilePointArrays->Initialize();
  this->FileArrays->Initialize();
  if (!this->FileName || !*this->FileName)
  {
    return;
  }
  // Only a regular file is opened here: a pipe would lose what this read takes from it before
  // the run reads it.
  std::error_code error;
  if (!std::filesystem::is_regular_file(this->FileName, error))
  {
    return;
  }
  sipmss::io::MeshHeader header;
  try
  {
    header = sipmss::io::ReadProperties(this->FileName);
  }
  catch (const std::exception&)
  {
    return; // (no choices: the run reports what is wrong with the file)
  }
  for (const std::string& name : header.layout.scalars)
  {
    this->FilePointArrays->InsertNextValue(name);
    this->FileArrays->InsertNextValue(name);
  }
  for (const std::string& name : header.faceScalars)
  {
    // (a name both arrays have selects the point array: listed once)
    if (this->FilePointArrays->LookupValue(name) < 0)
    {
      this->FileArrays->InsertNextValue(name);
    }
  }
}

vtkStringArray* vtkSIPMSSDecimate::GetFilePointArrayNames()
{
  this->ReadFileArrayNames();
  return this->FilePointArrays;
}

vtkStringArray* vtkSIPMSSDecimate::GetFileArrayNames()
{
  this->ReadFileArrayNames();
  return this->FileArrays;
}

int vtkSIPMSSDecimate::FillOutputPortInformation(int port, vtkInformation* info)
{
  if (port == 1)
  {
    info->Set(vtkDataObject::DATA_TYPE_NAME(), "vtkMultiBlockDataSet");
    return 1;
  }
  return this->Superclass::FillOutputPortInformation(port, info);
}

int vtkSIPMSSDecimate::RequestData(
  vtkInformation*, vtkInformationVector** inputVector, vtkInformationVector* outputVector)
{
  vtkPolyData* output = vtkPolyData::GetData(outputVector, 0);
  vtkMultiBlockDataSet* levels = vtkMultiBlockDataSet::GetData(outputVector, 1);
  levels->Initialize();
  return this->Simplify(inputVector, output,
    [this, levels](int level, const std::function<void(sipmss::io::MeshSink&)>& emit) {
      vtkNew<vtkPolyData> lod;
      vtkSIPMSSPolyDataBridge::PolyDataSink lodSink(lod, this->InputPointData);
      emit(lodSink);
      levels->SetBlock(static_cast<unsigned int>(level), lod);
      levels->GetMetaData(static_cast<unsigned int>(level))
        ->Set(vtkMultiBlockDataSet::NAME(), ("LOD " + std::to_string(level)).c_str());
    });
}

void vtkSIPMSSDecimate::FillRequest(sipmss::algorithms::SimplifyRequest& request)
{
  using sipmss::algorithms::Algorithm;
  request.algorithm = this->PreClusterGridDimension != 0 ? Algorithm::TwoStage : Algorithm::Decimate;
  request.grid = std::max(this->PreClusterGridDimension, 0); // (-1: 0, the automatic grid)
  request.targetTriangles = static_cast<std::uint64_t>(this->TargetNumberOfTriangles);
  request.targetReduction = this->TargetReduction;
  request.maximumError =
    this->MaximumError >= VTK_DOUBLE_MAX ? std::numeric_limits<double>::infinity() : this->MaximumError;
  request.absoluteError = this->AbsoluteError;
  request.pruneSize = this->PruneSize;
  request.levelsOfDetail = this->NumberOfLevelsOfDetail;
  request.lockBoundary = this->LockBoundary;
  request.fitSurface = this->FitSurface;
  request.boundaryWeight = this->BoundaryWeight;
  request.weldDistance = this->WeldDistance;
  request.lockArray = this->LockArray ? this->LockArray : "";
  request.selectionArray = this->SelectionArray ? this->SelectionArray : "";
}

vtkSIPMSSDecimate::~vtkSIPMSSDecimate()
{
  this->SetLockArray(nullptr);
  this->SetSelectionArray(nullptr);
  this->FilePointArrays->Delete();
  this->FileArrays->Delete();
}

const char* vtkSIPMSSDecimate::PropertyName(sipmss::algorithms::Parameter parameter)
{
  return parameter == sipmss::algorithms::Parameter::Grid ? "PreClusterGridDimension"
                                                         : this->Superclass::PropertyName(parameter);
}

void vtkSIPMSSDecimate::PrintSelf(ostream& os, vtkIndent indent)
{
  this->Superclass::PrintSelf(os, indent);
  os << indent << "TargetNumberOfTriangles: " << this->TargetNumberOfTriangles << "\n";
  os << indent << "TargetReduction: " << this->TargetReduction << "\n";
  os << indent << "MaximumError: " << this->MaximumError << "\n";
  os << indent << "AbsoluteError: " << this->AbsoluteError << "\n";
  os << indent << "PruneSize: " << this->PruneSize << "\n";
  os << indent << "NumberOfLevelsOfDetail: " << this->NumberOfLevelsOfDetail << "\n";
  os << indent << "LockBoundary: " << this->LockBoundary << "\n";
  os << indent << "FitSurface: " << this->FitSurface << "\n";
  os << indent << "BoundaryWeight: " << this->BoundaryWeight << "\n";
  os << indent << "WeldDistance: " << this->WeldDistance << "\n";
  os << indent << "PreClusterGridDimension: " << this->PreClusterGridDimension << "\n";
  os << indent << "LockArray: " << (this->LockArray ? this->LockArray : "(none)") << "\n";
  os << indent << "SelectionArray: " << (this->SelectionArray ? this->SelectionArray : "(none)")
     << "\n";
}
