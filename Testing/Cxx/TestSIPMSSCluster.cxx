// vtkSIPMSSCluster: exact results on a cube, in core == out of core, abort, bad input, pipeline.
#include "vtkSIPMSSCluster.h"

#include "SIPMSSTestUtilities.h"

#include "vtkCubeSource.h"
#include "vtkFloatArray.h"
#include "vtkNew.h"
#include "vtkPointData.h"
#include "vtkSphereSource.h"
#include "vtkTriangleFilter.h"

#include <set>
#include <vector>

namespace
{
int TestCube()
{
  // A closed cube, each corner in its own cell (grid 2): the 12 triangles survive, and each
  // representative is the intersection of the corner's 3 face planes: exactly the corner.
  vtkNew<vtkCubeSource> cube;
  cube->SetBounds(0, 2, 0, 2, 0, 2);
  vtkNew<vtkTriangleFilter> tri;
  tri->SetInputConnection(cube->GetOutputPort());
  vtkNew<vtkSIPMSSCluster> cluster;
  cluster->SetInputConnection(tri->GetOutputPort());
  cluster->SetMaximumGridDimension(2);
  cluster->Update();
  vtkPolyData* out = cluster->GetOutput();
  SIPMSS_CHECK(out->GetNumberOfPolys() == 12);
  SIPMSS_CHECK(out->GetNumberOfPoints() == 8);
  std::set<std::vector<double>> corners;
  for (vtkIdType i = 0; i < out->GetNumberOfPoints(); ++i)
  {
    double p[3];
    out->GetPoint(i, p);
    for (double c : p)
    {
      SIPMSS_CHECK(std::abs(c) < 1e-6 || std::abs(c - 2) < 1e-6);
    }
    corners.insert({ std::round(p[0]), std::round(p[1]), std::round(p[2]) });
  }
  SIPMSS_CHECK(corners.size() == 8);
  // One cell for everything: no triangle survives.
  cluster->SetMaximumGridDimension(1);
  cluster->Update();
  SIPMSS_CHECK(cluster->GetOutput()->GetNumberOfPolys() == 0);
  return EXIT_SUCCESS;
}

int TestInCoreEqualsOutOfCore()
{
  vtkNew<vtkSphereSource> sphere;
  sphere->SetThetaResolution(200);
  sphere->SetPhiResolution(200);
  sphere->Update();
  // a point scalar to check point data averaging
  vtkNew<vtkFloatArray> height;
  height->SetName("height");
  vtkPolyData* in = sphere->GetOutput();
  for (vtkIdType i = 0; i < in->GetNumberOfPoints(); ++i)
  {
    height->InsertNextValue(static_cast<float>(in->GetPoint(i)[2]));
  }
  in->GetPointData()->AddArray(height);

  vtkNew<vtkSIPMSSCluster> a;
  a->SetInputData(in);
  a->SetMaximumGridDimension(20);
  a->SetOperationMode(vtkSIPMSSFilterBase::IN_CORE);
  a->Update();
  vtkNew<vtkSIPMSSCluster> b;
  b->SetInputData(in);
  b->SetMaximumGridDimension(20);
  b->SetOperationMode(vtkSIPMSSFilterBase::OUT_OF_CORE);
  b->SetMemoryBudgetMB(64.0 / 1024.0); // 64 KiB
  b->Update();
  SIPMSS_CHECK(a->GetOutput()->GetNumberOfPolys() > 100);
  SIPMSS_CHECK(a->GetOutput()->GetNumberOfPolys() < in->GetNumberOfPolys());
  SIPMSS_CHECK(SameMesh(a->GetOutput(), b->GetOutput()));
  SIPMSS_CHECK(a->GetUsedInCore() && !a->GetUsedOutOfCore());
  SIPMSS_CHECK(b->GetUsedOutOfCore());
  SIPMSS_CHECK(b->GetPeakStorageBytes() <= 64 * 1024);
  SIPMSS_CHECK(b->GetPageMisses() > 0);
  // point data carried and averaged: the height of a representative is near its z
  vtkDataArray* h = a->GetOutput()->GetPointData()->GetArray("height");
  SIPMSS_CHECK(h != nullptr);
  const double cell = 1.0 / 20;
  for (vtkIdType i = 0; i < a->GetOutput()->GetNumberOfPoints(); ++i)
  {
    SIPMSS_CHECK(std::abs(h->GetTuple1(i) - a->GetOutput()->GetPoint(i)[2]) <= 2 * cell);
  }
  return EXIT_SUCCESS;
}

int TestAbortAndErrors()
{
  vtkNew<vtkSphereSource> sphere;
  sphere->SetThetaResolution(300);
  sphere->SetPhiResolution(300);
  vtkNew<vtkSIPMSSCluster> cluster;
  cluster->SetInputConnection(sphere->GetOutputPort());
  // Abort from a progress observer: the output is empty, no error.
  struct Abort : vtkCommand
  {
    static Abort* New() { return new Abort; }
    void Execute(vtkObject* caller, unsigned long, void*) override
    {
      ++this->Calls;
      static_cast<vtkAlgorithm*>(caller)->SetAbortExecute(1);
    }
    int Calls = 0;
  };
  vtkNew<Abort> abort;
  const unsigned long tag = cluster->AddObserver(vtkCommand::ProgressEvent, abort);
  cluster->Update();
  SIPMSS_CHECK(abort->Calls > 0);
  SIPMSS_CHECK(cluster->GetOutput()->GetNumberOfPolys() == 0);
  cluster->RemoveObserver(tag);
  cluster->SetAbortExecute(0);
  cluster->Modified();
  cluster->Update();
  SIPMSS_CHECK(cluster->GetOutput()->GetNumberOfPolys() > 0);

  // A missing file: an error event naming the file, not a crash.
  vtkNew<ErrorRecorder> errors;
  vtkNew<vtkSIPMSSCluster> bad;
  bad->AddObserver(vtkCommand::ErrorEvent, errors);
  bad->GetExecutive()->AddObserver(vtkCommand::ErrorEvent, errors);
  bad->SetFileName("/nonexistent/sipmss-missing.ply");
  bad->Update();
  SIPMSS_CHECK(errors->Count > 0);
  SIPMSS_CHECK(errors->All.find("sipmss-missing.ply") != std::string::npos);
  SIPMSS_CHECK(bad->GetOutput()->GetNumberOfPoints() == 0);
  return EXIT_SUCCESS;
}
}

int TestSIPMSSCluster(int, char*[])
{
  if (TestCube() != EXIT_SUCCESS || TestInCoreEqualsOutOfCore() != EXIT_SUCCESS ||
    TestAbortAndErrors() != EXIT_SUCCESS)
  {
    return EXIT_FAILURE;
  }
  std::cout << "TestSIPMSSCluster passed" << std::endl;
  return EXIT_SUCCESS;
}
