// Helpers shared by the VTK-style tests.
#ifndef SIPMSSTestUtilities_h
#define SIPMSSTestUtilities_h

#include "vtkCellArray.h"
#include "vtkExecutive.h"
#include "vtkCommand.h"
#include "vtkPoints.h"
#include "vtkPolyData.h"
#include "vtkSmartPointer.h"

#include <cmath>
#include <iostream>
#include <string>

#define SIPMSS_CHECK(cond)                                                                         \
  do                                                                                               \
  {                                                                                                \
    if (!(cond))                                                                                   \
    {                                                                                              \
      std::cerr << __FILE__ << ":" << __LINE__ << ": check failed: " #cond << std::endl;          \
      return EXIT_FAILURE;                                                                         \
    }                                                                                              \
  } while (0)

// Records error events instead of printing them (the test decides what is expected).
class ErrorRecorder : public vtkCommand
{
public:
  static ErrorRecorder* New() { return new ErrorRecorder; }
  void Execute(vtkObject*, unsigned long, void* data) override
  {
    ++this->Count;
    this->All += data ? static_cast<const char*>(data) : "";
    this->All += "\n";
  }
  int Count = 0;
  std::string All; // every message received
};

// True when both meshes have identical points and triangles.
inline bool SameMesh(vtkPolyData* a, vtkPolyData* b)
{
  if (a->GetNumberOfPoints() != b->GetNumberOfPoints() ||
    a->GetNumberOfPolys() != b->GetNumberOfPolys())
  {
    return false;
  }
  for (vtkIdType i = 0; i < a->GetNumberOfPoints(); ++i)
  {
    double p[3], q[3];
    a->GetPoint(i, p);
    b->GetPoint(i, q);
    if (p[0] != q[0] || p[1] != q[1] || p[2] != q[2])
    {
      return false;
    }
  }
  vtkIdType na, nb;
  const vtkIdType *ia, *ib;
  for (vtkIdType c = 0; c < a->GetNumberOfPolys(); ++c)
  {
    a->GetPolys()->GetCellAtId(c, na, ia);
    b->GetPolys()->GetCellAtId(c, nb, ib);
    if (na != nb)
    {
      return false;
    }
    for (vtkIdType k = 0; k < na; ++k)
    {
      if (ia[k] != ib[k])
      {
        return false;
      }
    }
  }
  return true;
}

#endif
