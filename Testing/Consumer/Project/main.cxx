// A consumer of the installed/exported SIPMSS::Filters: decimates a sphere to a triangle target
// and checks the result. Exit code 0 only if the output is a non-empty triangle mesh at the target.
#include "vtkSIPMSSDecimate.h"

#include "vtkCellArray.h"
#include "vtkNew.h"
#include "vtkPolyData.h"
#include "vtkSphereSource.h"

#include <iostream>

int main()
{
  vtkNew<vtkSphereSource> sphere;
  sphere->SetThetaResolution(80);
  sphere->SetPhiResolution(80);
  sphere->Update();
  const vtkIdType inTriangles = sphere->GetOutput()->GetNumberOfPolys();
  const vtkIdType target = inTriangles / 4;

  vtkNew<vtkSIPMSSDecimate> decimate;
  decimate->SetInputConnection(sphere->GetOutputPort());
  decimate->SetTargetNumberOfTriangles(target);
  decimate->Update();
  vtkPolyData* out = decimate->GetOutput();
  const vtkIdType outTriangles = out->GetNumberOfPolys();
  std::cout << "vtkSIPMSSDecimate: " << inTriangles << " -> " << outTriangles
            << " triangles (target " << target << ")\n";

  // The target is an upper bound the filter reaches on a closed sphere to within a few percent.
  if (outTriangles > target || outTriangles < target * 9 / 10)
  {
    std::cerr << "FAIL: " << outTriangles << " triangles, expected at most " << target
              << " and at least " << target * 9 / 10 << "\n";
    return 1;
  }
  if (out->GetNumberOfCells() != outTriangles || out->GetPolys()->IsHomogeneous() != 3)
  {
    std::cerr << "FAIL: the output is not a triangle mesh\n";
    return 1;
  }
  return 0;
}
