#include "vtkSIPMSSCluster.h"

#include "vtkSIPMSSPolyDataBridge.h"

#include "sipmss/algorithms/Cluster.h"

#include "vtkInformationVector.h"
#include "vtkObjectFactory.h"
#include "vtkPolyData.h"

#include <string>

vtkStandardNewMacro(vtkSIPMSSCluster);

vtkSIPMSSCluster::vtkSIPMSSCluster() = default;

int vtkSIPMSSCluster::RequestData(
  vtkInformation*, vtkInformationVector** inputVector, vtkInformationVector* outputVector)
{
  vtkPolyData* output = vtkPolyData::GetData(outputVector, 0);
  return this->Simplify(inputVector, output,
    [this](const Source& source, bool haveBounds, const std::array<double, 6>& bounds,
      sipmss::io::MeshSink& sink, const sipmss::storage::Profile& profile,
      sipmss::algorithms::Progress& progress) {
      sipmss::algorithms::ClusterOptions options;
      options.maximumGridDimension = this->MaximumGridDimension;
      options.storage = profile;
      options.threads = this->NumberOfThreads;
      options.boundaryQuadrics = this->BoundaryWeight > 0;
      options.boundaryWeight = this->BoundaryWeight;
      if (this->UseBounds)
      {
        options.useBounds = true;
        std::copy_n(this->Bounds, 6, options.bounds.begin());
      }
      else if (haveBounds)
      {
        options.useBounds = true;
        options.bounds = bounds;
      }
      return sipmss::algorithms::Cluster(source, sink, options, progress);
    });
}

std::string vtkSIPMSSCluster::ParameterProblem()
{
  std::string problem = FiniteProblem("BoundaryWeight", this->BoundaryWeight);
  for (int k = 0; k < 6 && problem.empty() && this->UseBounds; ++k)
  {
    problem = FiniteProblem("Bounds", this->Bounds[k]);
  }
  return problem;
}

void vtkSIPMSSCluster::PrintSelf(ostream& os, vtkIndent indent)
{
  this->Superclass::PrintSelf(os, indent);
  os << indent << "MaximumGridDimension: " << this->MaximumGridDimension << "\n";
  os << indent << "UseBounds: " << this->UseBounds << "\n";
  os << indent << "BoundaryWeight: " << this->BoundaryWeight << "\n";
}
