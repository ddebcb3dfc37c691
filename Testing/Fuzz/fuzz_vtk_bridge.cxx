// libFuzzer target for the VTK bridge: random vtkPolyData (every cell type, ids out of range, negative
// or at 2^32 and beyond, NaN and infinite points, point and cell arrays of every type, component
// count and name, tuple counts that do not match) through vtkSIPMSSCluster, vtkSIPMSSDecimate and
// the two-stage path, in core and out of core. A run may end in a VTK error, never in a crash or a
// sanitizer report; an output must be a valid triangle mesh whose point arrays are input arrays
// with the same name, type and components.
#include "FuzzCommon.h" // SIPMSS_FUZZ_CHECK
#include "vtkSIPMSSCluster.h"
#include "vtkSIPMSSDecimate.h"

#include <vtkAbstractArray.h>
#include <vtkBitArray.h>
#include <vtkCellArray.h>
#include <vtkCellData.h>
#include <vtkDataArray.h>
#include <vtkIdTypeArray.h>
#include <vtkNew.h>
#include <vtkObject.h>
#include <vtkPointData.h>
#include <vtkPoints.h>
#include <vtkPolyData.h>
#include <vtkSmartPointer.h>
#include <vtkStringArray.h>

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <string>

namespace
{
// Reads the fuzzer's bytes as a stream of small decisions; zeros once they run out.
class Bytes
{
public:
  Bytes(const std::uint8_t* data, std::size_t size)
    : p_(data)
    , n_(size)
  {
  }
  std::uint8_t U8()
  {
    if (this->n_ == 0)
    {
      return 0;
    }
    --this->n_;
    return *this->p_++;
  }
  std::uint32_t U32()
  {
    std::uint32_t v = 0;
    for (int i = 0; i < 4; ++i)
    {
      v = (v << 8) | this->U8();
    }
    return v;
  }
  double Coordinate()
  {
    static const double special[] = { 0.0, 1.0, -1.0, 0.5, 1e30, -1e-30,
      std::numeric_limits<double>::quiet_NaN(), std::numeric_limits<double>::infinity(),
      -std::numeric_limits<double>::infinity(), std::numeric_limits<double>::denorm_min(),
      std::numeric_limits<double>::max(), 3.0 };
    const std::uint8_t k = this->U8();
    if (k < 24)
    {
      return special[k % 12];
    }
    return double(std::int8_t(this->U8())) / 16.0;
  }
  // A point id: mostly valid, sometimes negative, just past the end, or beyond 2^32.
  vtkIdType Id(vtkIdType points)
  {
    const std::uint8_t k = this->U8();
    switch (k % 16)
    {
      case 0:
        return -1 - vtkIdType(this->U8());
      case 1:
        return points + vtkIdType(this->U8() % 3);
      case 2:
        return (vtkIdType(1) << 32) + vtkIdType(this->U8() % 4);
      case 3:
        return std::numeric_limits<vtkIdType>::max() - vtkIdType(this->U8());
      default:
        return points > 0 ? vtkIdType(this->U8()) % points : vtkIdType(this->U8() % 3);
    }
  }

private:
  const std::uint8_t* p_;
  std::size_t n_;
};

const int kTypes[] = { VTK_CHAR, VTK_SIGNED_CHAR, VTK_UNSIGNED_CHAR, VTK_SHORT, VTK_UNSIGNED_SHORT,
  VTK_INT, VTK_UNSIGNED_INT, VTK_LONG, VTK_UNSIGNED_LONG, VTK_LONG_LONG, VTK_UNSIGNED_LONG_LONG,
  VTK_FLOAT, VTK_DOUBLE, VTK_ID_TYPE, VTK_BIT, VTK_STRING };
const char* const kNames[] = { "", "Normals", "RGB", "a", "a", "TCoords", "scalars", "x y" };

vtkSmartPointer<vtkAbstractArray> RandomArray(Bytes& in, vtkIdType tuples)
{
  const int type = kTypes[in.U8() % (sizeof(kTypes) / sizeof(kTypes[0]))];
  vtkSmartPointer<vtkAbstractArray> a =
    vtkSmartPointer<vtkAbstractArray>::Take(vtkAbstractArray::CreateArray(type));
  const int components = 1 + in.U8() % 4;
  a->SetNumberOfComponents(components);
  const std::uint8_t named = in.U8();
  if (named % 9 != 0)
  {
    a->SetName(kNames[named % (sizeof(kNames) / sizeof(kNames[0]))]);
  }
  // Sometimes a tuple count that does not match the points.
  const std::uint8_t k = in.U8();
  const vtkIdType n = k < 16 ? tuples + (k % 3) - 1 : tuples;
  a->SetNumberOfTuples(std::max<vtkIdType>(n, 0));
  if (auto* s = vtkStringArray::SafeDownCast(a))
  {
    for (vtkIdType i = 0; i < s->GetNumberOfValues(); ++i)
    {
      s->SetValue(i, std::string(in.U8() % 4, 'q'));
    }
  }
  else if (auto* d = vtkDataArray::SafeDownCast(a))
  {
    for (vtkIdType i = 0; i < d->GetNumberOfTuples(); ++i)
    {
      for (int c = 0; c < components; ++c)
      {
        const std::uint8_t v = in.U8();
        d->SetComponent(i, c, v < 8 ? in.Coordinate() : double(std::int8_t(v)));
      }
    }
  }
  return a;
}

vtkSmartPointer<vtkPolyData> RandomPolyData(Bytes& in)
{
  auto pd = vtkSmartPointer<vtkPolyData>::New();
  const vtkIdType np = in.U8() % 48;
  vtkNew<vtkPoints> points;
  points->SetDataType(in.U8() % 2 ? VTK_DOUBLE : VTK_FLOAT);
  points->SetNumberOfPoints(np);
  for (vtkIdType i = 0; i < np; ++i)
  {
    // Mostly a small grid (so that there are triangles to simplify), sometimes special values.
    const std::uint8_t k = in.U8();
    if (k < 32)
    {
      points->SetPoint(i, in.Coordinate(), in.Coordinate(), in.Coordinate());
    }
    else
    {
      points->SetPoint(i, double(i % 7), double((i / 7) % 7), double(k % 5) / 4.0);
    }
  }
  if (np > 0 || in.U8() % 2)
  {
    pd->SetPoints(points);
  }
  vtkCellArray* (vtkPolyData::*const getters[])() = { &vtkPolyData::GetVerts,
    &vtkPolyData::GetLines, &vtkPolyData::GetPolys, &vtkPolyData::GetStrips };
  void (vtkPolyData::*const setters[])(vtkCellArray*) = { &vtkPolyData::SetVerts,
    &vtkPolyData::SetLines, &vtkPolyData::SetPolys, &vtkPolyData::SetStrips };
  for (int kind = 0; kind < 4; ++kind)
  {
    const int cells = in.U8() % (kind == 2 ? 64 : 6);
    if (cells == 0)
    {
      continue;
    }
    vtkNew<vtkCellArray> ca;
    for (int c = 0; c < cells; ++c)
    {
      const std::uint8_t k = in.U8();
      const int size = k < 200 ? 3 : k % 7; // polygons: mostly triangles
      vtkIdType ids[8];
      for (int j = 0; j < size; ++j)
      {
        ids[j] = in.U8() < 224 && np > 0 ? vtkIdType(in.U8()) % np : in.Id(np);
      }
      ca->InsertNextCell(size, ids);
    }
    (pd.Get()->*setters[kind])(ca);
    (void)getters;
  }
  const int pointArrays = in.U8() % 4;
  for (int i = 0; i < pointArrays; ++i)
  {
    vtkSmartPointer<vtkAbstractArray> a = RandomArray(in, np);
    pd->GetPointData()->AddArray(a);
    auto* d = vtkDataArray::SafeDownCast(a);
    const std::uint8_t role = in.U8() % 8;
    if (d && role == 1)
    {
      pd->GetPointData()->SetNormals(d); // (refused by VTK unless 3 components)
    }
    else if (d && role == 2)
    {
      pd->GetPointData()->SetScalars(d);
    }
    else if (d && role == 3)
    {
      pd->GetPointData()->SetTCoords(d);
    }
  }
  if (in.U8() % 4 == 0)
  {
    pd->GetCellData()->AddArray(RandomArray(in, pd->GetNumberOfCells()));
  }
  return pd;
}

// The output is a triangle mesh over its points, with finite coordinates, and every point array
// is an input point array of the same name, type and components, with one tuple per point.
void CheckOutput(vtkPolyData* out, vtkPolyData* input)
{
  const vtkIdType np = out->GetNumberOfPoints();
  SIPMSS_FUZZ_CHECK(out->GetNumberOfVerts() == 0 && out->GetNumberOfLines() == 0 &&
    out->GetNumberOfStrips() == 0);
  for (vtkIdType i = 0; i < np; ++i)
  {
    double p[3];
    out->GetPoint(i, p);
    SIPMSS_FUZZ_CHECK(std::isfinite(p[0]) && std::isfinite(p[1]) && std::isfinite(p[2]));
  }
  vtkCellArray* polys = out->GetPolys();
  vtkIdType n = 0;
  const vtkIdType* ids = nullptr;
  for (polys->InitTraversal(); polys->GetNextCell(n, ids);)
  {
    SIPMSS_FUZZ_CHECK(n == 3);
    for (vtkIdType j = 0; j < n; ++j)
    {
      SIPMSS_FUZZ_CHECK(ids[j] >= 0 && ids[j] < np);
    }
  }
  vtkPointData* pdOut = out->GetPointData();
  for (int i = 0; i < pdOut->GetNumberOfArrays(); ++i)
  {
    vtkAbstractArray* a = pdOut->GetAbstractArray(i);
    SIPMSS_FUZZ_CHECK(a->GetNumberOfTuples() == np);
    bool found = false;
    vtkPointData* pdIn = input->GetPointData();
    for (int k = 0; k < pdIn->GetNumberOfArrays() && !found; ++k)
    {
      vtkAbstractArray* b = pdIn->GetAbstractArray(k);
      const char* an = a->GetName();
      const char* bn = b->GetName();
      found = ((an == nullptr) == (bn == nullptr)) && (!an || std::strcmp(an, bn) == 0) &&
        a->GetDataType() == b->GetDataType() &&
        a->GetNumberOfComponents() == b->GetNumberOfComponents();
    }
    SIPMSS_FUZZ_CHECK(found);
  }
}
} // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size)
{
  static const bool quiet = [] {
    vtkObject::GlobalWarningDisplayOff(); // errors and warnings are expected here
    return true;
  }();
  (void)quiet;
  Bytes in(data, size);
  const std::uint8_t which = in.U8() % 3;
  const std::uint8_t budget = in.U8();
  const int threads = 1 + in.U8() % 2;
  vtkSmartPointer<vtkPolyData> input = RandomPolyData(in);
  vtkSmartPointer<vtkSIPMSSFilterBase> filter;
  if (which == 0)
  {
    auto c = vtkSmartPointer<vtkSIPMSSCluster>::New();
    c->SetMaximumGridDimension(1 + in.U8() % 8);
    c->SetBoundaryWeight(in.U8() % 2 ? 0.0 : in.Coordinate());
    filter = c;
  }
  else
  {
    auto d = vtkSmartPointer<vtkSIPMSSDecimate>::New();
    d->SetTargetNumberOfTriangles(in.U8() % 40);
    if (in.U8() % 4 == 0)
    {
      d->SetMaximumError(in.Coordinate());
    }
    d->SetLockBoundary(in.U8() % 2 == 0);
    d->SetWeldDistance(in.U8() % 4 == 0 ? in.Coordinate() : 0.0);
    if (which == 2)
    {
      d->SetPreClusterGridDimension(1 + in.U8() % 8);
    }
    filter = d;
  }
  // In core, or out of core at the smallest budget (64 KiB), in the default temporary directory.
  filter->SetMemoryBudgetMB(budget % 2 ? 0.0625 : 0.0);
  filter->SetNumberOfThreads(threads);
  filter->SetInputData(input);
  filter->Update();
  vtkPolyData* out = filter->GetOutput();
  if (out && out->GetNumberOfPoints() > 0)
  {
    CheckOutput(out, input);
  }
  return 0;
}
