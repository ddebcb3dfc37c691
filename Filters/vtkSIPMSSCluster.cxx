#include "vtkSIPMSSCluster.h"

#include "vtkSIPMSSPolyDataBridge.h"

#include "sipmss/algorithms/Simplify.h"

#include <algorithm>

#include "vtkInformationVector.h"
#include "vtkObjectFactory.h"
#include "vtkPolyData.h"

#include <string>

vtkStandardNewMacro(vtkSIPMSSCluster);

vtkSIPMSSCluster::vtkSIPMSSCluster() = default;

int vtkSIPMSSCluster::RequestData(
  vtkInformation*, vtkInformationVector** inputVector, vtkInformationVector* outputVector)
{
  return this->Simplify(inputVector, vtkPolyData::GetData(outputVector, 0));
}

void vtkSIPMSSCluster::FillRequest(sipmss::algorithms::SimplifyRequest& request)
{
  request.algorithm = sipmss::algorithms::Algorithm::Cluster;
  request.grid = this->MaximumGridDimension;
  request.boundaryWeight = this->BoundaryWeight;
  if (this->UseBounds)
  {
    request.bounds.emplace();
    std::copy_n(this->Bounds, 6, request.bounds->begin());
  }
}

void vtkSIPMSSCluster::PrintSelf(ostream& os, vtkIndent indent)
{
  this->Superclass::PrintSelf(os, indent);
  os << indent << "MaximumGridDimension: " << this->MaximumGridDimension << "\n";
  os << indent << "UseBounds: " << this->UseBounds << "\n";
  os << indent << "BoundaryWeight: " << this->BoundaryWeight << "\n";
}
