#include "vtkSIPMSSDecimate.h"

#include "vtkSIPMSSPolyDataBridge.h"

#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/TwoStage.h"

#include "vtkDataObject.h"
#include "vtkInformation.h"
#include "vtkInformationVector.h"
#include "vtkMultiBlockDataSet.h"
#include "vtkNew.h"
#include "vtkObjectFactory.h"
#include "vtkPolyData.h"

#include <cmath>

vtkStandardNewMacro(vtkSIPMSSDecimate);

vtkSIPMSSDecimate::vtkSIPMSSDecimate()
{
  this->SetNumberOfOutputPorts(2);
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
    [this, levels](const Source& source, bool, const std::array<double, 6>&,
      sipmss::io::MeshSink& sink, const sipmss::storage::Profile& profile,
      sipmss::algorithms::Progress& progress) {
      sipmss::algorithms::DecimateOptions options;
      options.targetTriangles = static_cast<std::uint64_t>(this->TargetNumberOfTriangles);
      options.targetReduction = this->TargetReduction;
      options.maximumError =
        this->MaximumError >= VTK_DOUBLE_MAX ? std::numeric_limits<double>::infinity() : this->MaximumError;
      options.levelsOfDetail = this->NumberOfLevelsOfDetail;
      options.lockBoundary = this->LockBoundary;
      options.boundaryWeight = this->BoundaryWeight;
      options.weldDistance = this->WeldDistance;
      options.storage = profile;
      options.threads = this->NumberOfThreads;
      auto onLevel = [this, levels](int level, const std::function<void(sipmss::io::MeshSink&)>& emit) {
        vtkNew<vtkPolyData> lod;
        vtkSIPMSSPolyDataBridge::PolyDataSink lodSink(lod, this->InputPointData);
        emit(lodSink);
        levels->SetBlock(static_cast<unsigned int>(level), lod);
        levels->GetMetaData(static_cast<unsigned int>(level))
          ->Set(vtkMultiBlockDataSet::NAME(), ("LOD " + std::to_string(level)).c_str());
      };
      if (this->PreClusterGridDimension > 0)
      {
        sipmss::algorithms::TwoStageOptions two;
        two.gridDimension = this->PreClusterGridDimension;
        two.decimate = options;
        return sipmss::algorithms::TwoStage(source, sink, two, progress, onLevel);
      }
      return sipmss::algorithms::Decimate(source, sink, options, progress, onLevel);
    });
}

std::string vtkSIPMSSDecimate::ParameterProblem()
{
  const std::pair<const char*, double> values[] = { { "TargetReduction", this->TargetReduction },
    { "BoundaryWeight", this->BoundaryWeight }, { "WeldDistance", this->WeldDistance } };
  for (const auto& [name, value] : values)
  {
    std::string problem = FiniteProblem(name, value);
    if (!problem.empty())
    {
      return problem;
    }
  }
  // MaximumError may be infinite (no bound), but not NaN
  return std::isnan(this->MaximumError) ? "MaximumError must be a number, not nan" : std::string();
}

void vtkSIPMSSDecimate::PrintSelf(ostream& os, vtkIndent indent)
{
  this->Superclass::PrintSelf(os, indent);
  os << indent << "TargetNumberOfTriangles: " << this->TargetNumberOfTriangles << "\n";
  os << indent << "TargetReduction: " << this->TargetReduction << "\n";
  os << indent << "MaximumError: " << this->MaximumError << "\n";
  os << indent << "NumberOfLevelsOfDetail: " << this->NumberOfLevelsOfDetail << "\n";
  os << indent << "LockBoundary: " << this->LockBoundary << "\n";
  os << indent << "BoundaryWeight: " << this->BoundaryWeight << "\n";
  os << indent << "WeldDistance: " << this->WeldDistance << "\n";
  os << indent << "PreClusterGridDimension: " << this->PreClusterGridDimension << "\n";
}
