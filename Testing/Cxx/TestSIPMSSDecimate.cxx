// vtkSIPMSSDecimate: reduction target, levels of detail on port 1, in core == out of core,
// point data carried, attributes in the error by their VTK names, bad input.
#include "vtkSIPMSSDecimate.h"

#include "SIPMSSTestUtilities.h"

#include "vtkFloatArray.h"
#include "vtkMultiBlockDataSet.h"
#include "vtkNew.h"
#include "vtkPointData.h"
#include "vtkSphereSource.h"
#include "vtkUnsignedCharArray.h"

namespace
{
int TestSphere()
{
  vtkNew<vtkSphereSource> sphere;
  sphere->SetThetaResolution(120);
  sphere->SetPhiResolution(120);
  sphere->Update();
  vtkPolyData* in = sphere->GetOutput();
  vtkNew<vtkFloatArray> x;
  x->SetName("x");
  for (vtkIdType i = 0; i < in->GetNumberOfPoints(); ++i)
  {
    x->InsertNextValue(static_cast<float>(in->GetPoint(i)[0]));
  }
  in->GetPointData()->AddArray(x);
  const vtkIdType inTris = in->GetNumberOfPolys();

  vtkNew<vtkSIPMSSDecimate> a;
  a->SetInputData(in);
  a->SetTargetNumberOfTriangles(1000);
  a->SetNumberOfLevelsOfDetail(3);
  a->SetOperationMode(vtkSIPMSSFilterBase::IN_CORE);
  a->Update();
  vtkPolyData* out = a->GetOutput();
  SIPMSS_CHECK(out->GetNumberOfPolys() <= 1000);
  SIPMSS_CHECK(out->GetNumberOfPolys() >= 900);
  // every output point on the unit sphere's neighbourhood, x carried
  vtkDataArray* ox = out->GetPointData()->GetArray("x");
  SIPMSS_CHECK(ox != nullptr);
  for (vtkIdType i = 0; i < out->GetNumberOfPoints(); ++i)
  {
    const double* p = out->GetPoint(i);
    const double r = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    SIPMSS_CHECK(std::abs(r - 0.5) < 0.05);
    SIPMSS_CHECK(std::abs(ox->GetTuple1(i) - p[0]) < 0.05);
  }
  // levels of detail: decreasing, the last equals port 0
  vtkMultiBlockDataSet* lods = vtkMultiBlockDataSet::SafeDownCast(a->GetOutputDataObject(1));
  SIPMSS_CHECK(lods && lods->GetNumberOfBlocks() == 3);
  vtkIdType previous = inTris + 1;
  for (unsigned int l = 0; l < 3; ++l)
  {
    vtkPolyData* lod = vtkPolyData::SafeDownCast(lods->GetBlock(l));
    SIPMSS_CHECK(lod != nullptr);
    SIPMSS_CHECK(lod->GetNumberOfPolys() < previous);
    previous = lod->GetNumberOfPolys();
  }
  SIPMSS_CHECK(previous == out->GetNumberOfPolys());

  vtkNew<vtkSIPMSSDecimate> b;
  b->SetInputData(in);
  b->SetTargetNumberOfTriangles(1000);
  b->SetNumberOfLevelsOfDetail(3); // the same pass schedule as a
  b->SetOperationMode(vtkSIPMSSFilterBase::OUT_OF_CORE);
  b->SetMemoryBudgetMB(64.0 / 1024.0);
  b->Update();
  SIPMSS_CHECK(b->GetUsedOutOfCore());
  SIPMSS_CHECK(SameMesh(out, b->GetOutput()));

  // One thread (a's ran on all cores): the same mesh.
  vtkNew<vtkSIPMSSDecimate> c;
  c->SetInputData(in);
  c->SetTargetNumberOfTriangles(1000);
  c->SetNumberOfLevelsOfDetail(3);
  c->SetOperationMode(vtkSIPMSSFilterBase::IN_CORE);
  SIPMSS_CHECK(c->GetNumberOfThreads() == 0);
  c->SetNumberOfThreads(1);
  SIPMSS_CHECK(c->GetNumberOfThreads() == 1);
  c->SetNumberOfThreads(-3); // clamped
  SIPMSS_CHECK(c->GetNumberOfThreads() == 0);
  c->SetNumberOfThreads(1);
  c->Update();
  SIPMSS_CHECK(SameMesh(out, c->GetOutput()));
  return EXIT_SUCCESS;
}

// Attributes named as the pipeline names them (the sphere's Normals, an RGB array): they change
// the result, keep their arrays' names and types, give the same bytes out of core; a name the
// input lacks, or one attribute named twice, is an error.
int TestAttributes()
{
  vtkNew<vtkSphereSource> sphere;
  sphere->SetThetaResolution(90);
  sphere->SetPhiResolution(90);
  sphere->Update();
  vtkPolyData* in = sphere->GetOutput();
  vtkNew<vtkUnsignedCharArray> colors;
  colors->SetName("Colors");
  colors->SetNumberOfComponents(3);
  for (vtkIdType i = 0; i < in->GetNumberOfPoints(); ++i)
  {
    const bool red = in->GetPoint(i)[0] > 0.1;
    colors->InsertNextTuple3(red ? 230 : 20, 40, red ? 20 : 230);
  }
  in->GetPointData()->AddArray(colors);
  SIPMSS_CHECK(in->GetPointData()->GetNormals() != nullptr);
  auto run = [&](const char* attributes, int mode) {
    vtkSmartPointer<vtkSIPMSSDecimate> d = vtkSmartPointer<vtkSIPMSSDecimate>::New();
    d->SetInputData(in);
    d->SetTargetNumberOfTriangles(600);
    d->SetAttributes(attributes);
    d->SetOperationMode(mode);
    if (mode == vtkSIPMSSFilterBase::OUT_OF_CORE)
    {
      d->SetMemoryBudgetMB(64.0 / 1024.0);
    }
    d->Update();
    return d;
  };
  auto plain = run("", vtkSIPMSSFilterBase::IN_CORE);
  auto aware = run("Colors:1,Normals:0.5", vtkSIPMSSFilterBase::IN_CORE);
  auto ooc = run("Colors:1,Normals:0.5", vtkSIPMSSFilterBase::OUT_OF_CORE);
  SIPMSS_CHECK(aware->GetOutput()->GetNumberOfPolys() == 600);
  SIPMSS_CHECK(!SameMesh(plain->GetOutput(), aware->GetOutput()));
  SIPMSS_CHECK(ooc->GetUsedOutOfCore());
  SIPMSS_CHECK(SameMesh(aware->GetOutput(), ooc->GetOutput()));
  vtkDataArray* oc = aware->GetOutput()->GetPointData()->GetArray("Colors");
  SIPMSS_CHECK(oc && oc->GetDataType() == VTK_UNSIGNED_CHAR && oc->GetNumberOfComponents() == 3);
  vtkDataArray* ocOoc = ooc->GetOutput()->GetPointData()->GetArray("Colors");
  SIPMSS_CHECK(ocOoc != nullptr);
  for (vtkIdType i = 0; i < oc->GetNumberOfTuples(); ++i)
  {
    for (int k = 0; k < 3; ++k)
    {
      SIPMSS_CHECK(oc->GetComponent(i, k) == ocOoc->GetComponent(i, k));
    }
  }
  SIPMSS_CHECK(aware->GetOutput()->GetPointData()->GetNormals() != nullptr);
  for (const char* bad : { "Nope:1", "Normals:1,normals:2" })
  {
    vtkNew<ErrorRecorder> errors;
    vtkNew<vtkSIPMSSDecimate> d;
    d->AddObserver(vtkCommand::ErrorEvent, errors);
    d->GetExecutive()->AddObserver(vtkCommand::ErrorEvent, errors);
    d->SetInputData(in);
    d->SetAttributes(bad);
    d->Update();
    SIPMSS_CHECK(errors->Count > 0);
    SIPMSS_CHECK(d->GetOutput()->GetNumberOfPoints() == 0);
    const std::string what = std::string(bad) == "Nope:1" ? "'Nope'" : "twice";
    SIPMSS_CHECK(errors->All.find(what) != std::string::npos);
  }
  // Another point array called like the keyword the normals become: refused, not mixed up.
  vtkNew<vtkFloatArray> shadow;
  shadow->SetName("normals");
  shadow->SetNumberOfTuples(in->GetNumberOfPoints());
  shadow->Fill(0.0);
  in->GetPointData()->AddArray(shadow);
  {
    vtkNew<ErrorRecorder> errors;
    vtkNew<vtkSIPMSSDecimate> d;
    d->AddObserver(vtkCommand::ErrorEvent, errors);
    d->GetExecutive()->AddObserver(vtkCommand::ErrorEvent, errors);
    d->SetInputData(in);
    d->SetAttributes("Normals:1");
    d->Update();
    SIPMSS_CHECK(errors->Count > 0);
    SIPMSS_CHECK(errors->All.find("cannot tell the array 'Normals'") != std::string::npos);
  }
  in->GetPointData()->RemoveArray("normals");
  return EXIT_SUCCESS;
}

int TestBadInput()
{
  vtkNew<ErrorRecorder> errors;
  vtkNew<vtkSIPMSSDecimate> bad;
  bad->AddObserver(vtkCommand::ErrorEvent, errors);
  bad->GetExecutive()->AddObserver(vtkCommand::ErrorEvent, errors);
  bad->SetFileName("/nonexistent/sipmss-missing.obj");
  bad->Update();
  SIPMSS_CHECK(errors->Count > 0);
  SIPMSS_CHECK(errors->All.find("sipmss-missing.obj") != std::string::npos);
  return EXIT_SUCCESS;
}
}

int TestSIPMSSDecimate(int, char*[])
{
  if (TestSphere() != EXIT_SUCCESS || TestAttributes() != EXIT_SUCCESS ||
    TestBadInput() != EXIT_SUCCESS)
  {
    return EXIT_FAILURE;
  }
  std::cout << "TestSIPMSSDecimate passed" << std::endl;
  return EXIT_SUCCESS;
}
