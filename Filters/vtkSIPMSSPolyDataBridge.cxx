#include "vtkSIPMSSPolyDataBridge.h"

#include "sipmss/algorithms/Attributes.h"

#include <algorithm>

#include "vtkCellData.h"

#include "vtkAlgorithm.h"
#include "vtkCellArray.h"
#include "vtkCellArrayIterator.h"
#include "vtkDataArray.h"
#include "vtkFloatArray.h"
#include "vtkIdTypeArray.h"
#include "vtkDataSetAttributes.h"
#include "vtkPointData.h"
#include "vtkPoints.h"
#include "vtkPolyData.h"
#include "vtkUnsignedCharArray.h"

#include <algorithm>
#include <cmath>
#include <limits>
#include <string>
#include <cstring>
#include <sstream>
#include <vector>

namespace vtkSIPMSSPolyDataBridge
{
namespace io = sipmss::io;

namespace
{
// Which point-data arrays become which attributes of the core's vertex record. Every numeric
// point-data array is carried: the active normals (3 components) and texture coordinates (2) in
// their slots, the first unsigned char array of 3 or 4 components as the colour, and every
// component of every other array as one float channel. The sink rebuilds each array with its
// own name, component count, type and attribute role from the same plan.
struct AttributePlan
{
  vtkDataArray* normals = nullptr;
  vtkDataArray* colors = nullptr; // unsigned char, 3 or 4 components
  vtkDataArray* tcoords = nullptr;
  std::vector<vtkDataArray*> channels; // one per scalar channel (an array once per component)
  std::vector<int> channelComponent;
  std::vector<vtkDataArray*> others; // the arrays behind the channels, in order
  io::VertexLayout layout;
};

AttributePlan Plan(vtkPointData* pointData)
{
  AttributePlan plan;
  plan.normals = pointData->GetNormals();
  if (plan.normals && plan.normals->GetNumberOfComponents() != 3)
  {
    plan.normals = nullptr;
  }
  plan.tcoords = pointData->GetTCoords();
  if (plan.tcoords && plan.tcoords->GetNumberOfComponents() != 2)
  {
    plan.tcoords = nullptr;
  }
  for (int i = 0; i < pointData->GetNumberOfArrays(); ++i)
  {
    vtkDataArray* a = pointData->GetArray(i);
    if (!a || a == plan.normals || a == plan.tcoords || IsGhostArray(a))
    {
      continue;
    }
    const int nc = a->GetNumberOfComponents();
    if (!plan.colors && a->GetDataType() == VTK_UNSIGNED_CHAR && (nc == 3 || nc == 4))
    {
      plan.colors = a;
      continue;
    }
    plan.others.push_back(a);
    for (int k = 0; k < nc; ++k)
    {
      plan.channels.push_back(a);
      plan.channelComponent.push_back(k);
      const std::string name = a->GetName() ? a->GetName() : "array" + std::to_string(i);
      plan.layout.scalars.push_back(nc == 1 ? name : name + "_" + std::to_string(k));
    }
  }
  plan.layout.normals = plan.normals != nullptr;
  plan.layout.colors = plan.colors != nullptr;
  plan.layout.texcoords = plan.tcoords != nullptr;
  return plan;
}

} // namespace

bool IsGhostArray(vtkAbstractArray* a)
{
  return a && a->GetName() &&
    std::strcmp(a->GetName(), vtkDataSetAttributes::GhostArrayName()) == 0;
}

std::string CoreAttributeNames(vtkPolyData* input, const std::string& list, std::string& problem)
{
  problem.clear();
  std::vector<sipmss::algorithms::AttributeWeight> weights;
  if (!sipmss::algorithms::ParseAttributeWeights(list, weights).empty())
  {
    return list;
  }
  const AttributePlan plan = Plan(input->GetPointData());
  const std::vector<std::string>& scalars = plan.layout.scalars;
  for (auto& a : weights)
  {
    auto is = [&a](vtkDataArray* x) { return x && x->GetName() && a.name == x->GetName(); };
    std::string keyword;
    if (is(plan.normals))
    {
      keyword = "normals";
    }
    else if (is(plan.colors))
    {
      keyword = plan.colors->GetNumberOfComponents() == 4 ? "rgba" : "colors";
    }
    else if (is(plan.tcoords))
    {
      keyword = "texcoords";
    }
    if (keyword.empty())
    {
      continue;
    }
    // (the core takes a scalar's name before a keyword: another array called like the keyword
    // would be taken instead)
    if (std::find(scalars.begin(), scalars.end(), keyword) != scalars.end() ||
      std::find(scalars.begin(), scalars.end(), keyword + "_0") != scalars.end())
    {
      problem = "cannot tell the array '" + a.name + "' from the point array '" + keyword +
        "' of the input: rename one of them";
      return list;
    }
    a.name = keyword;
  }
  return sipmss::algorithms::FormatAttributeWeights(weights);
}

namespace
{
// A new array like `like` (type, name, components and their names) of n tuples.
vtkSmartPointer<vtkDataArray> NewArrayLike(vtkDataArray* like, vtkIdType n)
{
  vtkSmartPointer<vtkDataArray> a = vtk::TakeSmartPointer(like->NewInstance());
  a->SetName(like->GetName());
  a->SetNumberOfComponents(like->GetNumberOfComponents());
  a->CopyComponentNames(like);
  a->SetNumberOfTuples(n);
  return a;
}

// A carried float value stored into an array of like's type: integer types take the nearest
// representable value (the core interpolates in float), floating types the value.
double Representable(vtkDataArray* like, double v)
{
  const int t = like->GetDataType();
  if (t == VTK_FLOAT || t == VTK_DOUBLE)
  {
    return v;
  }
  if (!std::isfinite(v))
  {
    return 0;
  }
  return std::clamp(std::nearbyint(v), like->GetDataTypeMin(), like->GetDataTypeMax());
}
}

std::vector<std::string> PointArraysNotCarried(vtkPolyData* input)
{
  std::vector<std::string> names;
  vtkPointData* pd = input->GetPointData();
  for (int i = 0; i < pd->GetNumberOfArrays(); ++i)
  {
    if (!pd->GetArray(i)) // string, variant and other non-numeric arrays
    {
      vtkAbstractArray* a = pd->GetAbstractArray(i);
      names.emplace_back(a && a->GetName() ? a->GetName() : "(unnamed)");
    }
  }
  return names;
}

std::vector<std::string> ImpreciseIntegerArrays(vtkPolyData* input)
{
  // The core carries point data as float: integers beyond 2^24 in magnitude lose digits.
  std::vector<std::string> names;
  const AttributePlan plan = Plan(input->GetPointData());
  for (vtkDataArray* a : plan.others)
  {
    const int t = a->GetDataType();
    if (t == VTK_FLOAT || t == VTK_DOUBLE || a->GetDataTypeSize() < 4)
    {
      continue;
    }
    for (int k = 0; k < a->GetNumberOfComponents(); ++k)
    {
      double r[2];
      a->GetRange(r, k);
      if (std::max(std::fabs(r[0]), std::fabs(r[1])) > double(1 << 24))
      {
        names.emplace_back(a->GetName() ? a->GetName() : "(unnamed)");
        break;
      }
    }
  }
  return names;
}

std::array<double, 6> Bounds(vtkPolyData* input)
{
  std::array<double, 6> b{ VTK_DOUBLE_MAX, VTK_DOUBLE_MIN, VTK_DOUBLE_MAX, VTK_DOUBLE_MIN,
    VTK_DOUBLE_MAX, VTK_DOUBLE_MIN };
  vtkPoints* points = input->GetPoints();
  double p[3];
  for (vtkIdType i = 0, n = input->GetNumberOfPoints(); i < n; ++i)
  {
    points->GetPoint(i, p);
    if (!std::isfinite(p[0]) || !std::isfinite(p[1]) || !std::isfinite(p[2]))
    {
      std::ostringstream m;
      m << "point " << i << " has a non-finite coordinate (" << p[0] << ", " << p[1] << ", "
        << p[2] << ")";
      throw io::MeshIOError(m.str());
    }
    const double largest = std::max({ std::abs(p[0]), std::abs(p[1]), std::abs(p[2]) });
    if (largest > double(std::numeric_limits<float>::max()))
    {
      std::ostringstream m;
      m << "point " << i << " has a coordinate beyond single precision (" << p[0] << ", " << p[1]
        << ", " << p[2] << "): SIPMSS stores points as 32-bit floats";
      throw io::MeshIOError(m.str());
    }
    for (int k = 0; k < 3; ++k)
    {
      // (the coordinates as the core stores them: the bounds a file of these points gives)
      const double v = double(static_cast<float>(p[k]));
      b[2 * k] = std::min(b[2 * k], v);
      b[2 * k + 1] = std::max(b[2 * k + 1], v);
    }
  }
  return b;
}

sipmss::algorithms::MeshSource PolyDataSource(vtkPolyData* input, vtkIdType* skippedCells)
{
  *skippedCells = input->GetNumberOfVerts() + input->GetNumberOfLines();
  return [input](io::MeshSink& sink, const io::ReadOptions& options) {
    io::ReadStats stats;
    const vtkIdType np = input->GetNumberOfPoints();
    if (np > vtkIdType(std::numeric_limits<std::uint32_t>::max()))
    {
      throw io::MeshIOError("the input has more points than 32-bit indices can address");
    }
    AttributePlan plan = Plan(input->GetPointData());
    io::MeshHeader header;
    header.vertexCount = static_cast<std::uint64_t>(np);
    header.faceCount =
      static_cast<std::uint64_t>(input->GetNumberOfPolys() + input->GetNumberOfStrips());
    header.layout = plan.layout;
    // The one-component cell arrays, and the one ReadOptions::faceFlag names.
    vtkCellData* cd = input->GetCellData();
    vtkDataArray* flagArray = nullptr;
    for (int a = 0; a < cd->GetNumberOfArrays(); ++a)
    {
      vtkDataArray* array = cd->GetArray(a);
      if (array && array->GetName() && array->GetNumberOfComponents() == 1 &&
        !IsGhostArray(array))
      {
        header.faceScalars.emplace_back(array->GetName());
        if (header.faceScalars.back() == options.faceFlag)
        {
          flagArray = array;
        }
      }
    }
    sink.Begin(header);

    const std::size_t chunk = options.chunkElements ? options.chunkElements : 16384;
    std::vector<float> xyz, normals, tcoords, scalars;
    std::vector<std::uint8_t> rgba;
    vtkPoints* points = input->GetPoints();
    for (vtkIdType first = 0; first < np; first += vtkIdType(chunk))
    {
      if (sink.AbortRequested())
      {
        throw sipmss::algorithms::AbortedError();
      }
      const vtkIdType n = std::min<vtkIdType>(vtkIdType(chunk), np - first);
      xyz.resize(3 * n);
      double p[3];
      for (vtkIdType i = 0; i < n; ++i)
      {
        points->GetPoint(first + i, p);
        xyz[3 * i] = float(p[0]);
        xyz[3 * i + 1] = float(p[1]);
        xyz[3 * i + 2] = float(p[2]);
      }
      io::VertexChunk c;
      c.first = std::uint64_t(first);
      c.count = std::size_t(n);
      c.xyz = xyz.data();
      if (plan.normals)
      {
        normals.resize(3 * n);
        for (vtkIdType i = 0; i < n; ++i)
        {
          for (int k = 0; k < 3; ++k)
          {
            normals[3 * i + k] = float(plan.normals->GetComponent(first + i, k));
          }
        }
        c.normals = normals.data();
      }
      if (plan.colors)
      {
        rgba.resize(4 * n);
        const int nc = plan.colors->GetNumberOfComponents();
        for (vtkIdType i = 0; i < n; ++i)
        {
          for (int k = 0; k < 4; ++k)
          {
            rgba[4 * i + k] =
              k < nc ? static_cast<std::uint8_t>(plan.colors->GetComponent(first + i, k)) : 255;
          }
        }
        c.rgba = rgba.data();
      }
      if (plan.tcoords)
      {
        tcoords.resize(2 * n);
        for (vtkIdType i = 0; i < n; ++i)
        {
          tcoords[2 * i] = float(plan.tcoords->GetComponent(first + i, 0));
          tcoords[2 * i + 1] = float(plan.tcoords->GetComponent(first + i, 1));
        }
        c.texcoords = tcoords.data();
      }
      if (!plan.channels.empty())
      {
        const std::size_t ns = plan.channels.size();
        scalars.resize(ns * n);
        for (vtkIdType i = 0; i < n; ++i)
        {
          for (std::size_t s = 0; s < ns; ++s)
          {
            scalars[ns * i + s] =
              float(plan.channels[s]->GetComponent(first + i, plan.channelComponent[s]));
          }
        }
        c.scalars = scalars.data();
      }
      sink.Vertices(c);
    }
    stats.vertices = std::uint64_t(np);
    if (options.verticesOnly)
    {
      return stats;
    }

    std::vector<std::uint32_t> tri;
    tri.reserve(3 * chunk);
    std::vector<std::uint8_t> flags; // (with flagArray: the cell's flag of each triangle)
    std::uint8_t flag = 0;
    auto flush = [&]() {
      if (!tri.empty())
      {
        sink.Triangles(tri.data(), tri.size() / 3);
        if (flagArray)
        {
          sink.TriangleFlags(flags.data(), flags.size());
          flags.clear();
        }
        stats.triangles += tri.size() / 3;
        tri.clear();
      }
      if (sink.AbortRequested())
      {
        throw sipmss::algorithms::AbortedError();
      }
    };
    auto emit = [&](vtkIdType a, vtkIdType b, vtkIdType c) {
      for (const vtkIdType id : { a, b, c })
      {
        if (id < 0 || id >= np)
        {
          // checked in 64 bits: an id of 2^32 or more must not wrap to a valid index
          throw io::MeshIOError("polygon or strip " + std::to_string(stats.polygons - 1) +
            " (counting polygons, then strips) references point id " + std::to_string(id) + ", but the input has " +
            std::to_string(np) + " points");
        }
      }
      if (a == b || b == c || a == c)
      {
        ++stats.droppedFaces;
        return;
      }
      tri.push_back(std::uint32_t(a));
      tri.push_back(std::uint32_t(b));
      tri.push_back(std::uint32_t(c));
      if (flagArray)
      {
        flags.push_back(flag);
      }
      if (tri.size() >= 3 * chunk)
      {
        flush();
      }
    };
    vtkIdType npts;
    const vtkIdType* ids;
    // Ghost cells (a copy of another piece's cell, or a hidden one) are not part of this piece.
    vtkUnsignedCharArray* ghosts = input->GetCellGhostArray();
    auto ghost = [ghosts](vtkIdType cell) {
      return ghosts &&
        (ghosts->GetValue(cell) &
          (vtkDataSetAttributes::DUPLICATECELL | vtkDataSetAttributes::HIDDENCELL)) != 0;
    };
    // (cell ids: the vertices' and lines' cells first, then the polygons', then the strips')
    vtkIdType cellId = input->GetNumberOfVerts() + input->GetNumberOfLines();
    auto polys = vtk::TakeSmartPointer(input->GetPolys()->NewIterator());
    for (polys->GoToFirstCell(); !polys->IsDoneWithTraversal(); polys->GoToNextCell(), ++cellId)
    {
      if (ghost(cellId))
      {
        continue;
      }
      polys->GetCurrentCell(npts, ids);
      ++stats.polygons;
      if (flagArray)
      {
        flag = flagArray->GetComponent(cellId, 0) != 0.0 ? 1 : 0;
      }
      if (npts < 3)
      {
        ++stats.droppedFaces;
        continue;
      }
      for (vtkIdType k = 1; k + 1 < npts; ++k)
      {
        emit(ids[0], ids[k], ids[k + 1]);
      }
    }
    auto strips = vtk::TakeSmartPointer(input->GetStrips()->NewIterator());
    for (strips->GoToFirstCell(); !strips->IsDoneWithTraversal(); strips->GoToNextCell(), ++cellId)
    {
      if (ghost(cellId))
      {
        continue;
      }
      strips->GetCurrentCell(npts, ids);
      ++stats.polygons;
      if (flagArray)
      {
        flag = flagArray->GetComponent(cellId, 0) != 0.0 ? 1 : 0;
      }
      for (vtkIdType k = 0; k + 2 < npts; ++k)
      {
        if (k % 2 == 0)
        {
          emit(ids[k], ids[k + 1], ids[k + 2]);
        }
        else
        {
          emit(ids[k + 1], ids[k], ids[k + 2]);
        }
      }
    }
    flush();
    sink.End(stats);
    return stats;
  };
}

struct PolyDataSink::Impl
{
  vtkPolyData* output;
  vtkPointData* like = nullptr; // the input's point data, whose arrays the output rebuilds
  vtkSmartPointer<vtkFloatArray> points;
  vtkSmartPointer<vtkFloatArray> normals;
  vtkSmartPointer<vtkUnsignedCharArray> colors;
  vtkSmartPointer<vtkFloatArray> tcoords;
  std::vector<vtkSmartPointer<vtkFloatArray>> scalars;
  vtkSmartPointer<vtkIdTypeArray> connectivity;
  std::uint64_t vertexCount = 0;
};

PolyDataSink::PolyDataSink(vtkPolyData* output, vtkPointData* inputPointData)
  : impl_(std::make_shared<Impl>())
{
  this->impl_->output = output;
  this->impl_->like = inputPointData;
}

void PolyDataSink::Begin(const io::MeshHeader& h)
{
  Impl& m = *this->impl_;
  m.vertexCount = h.vertexCount;
  m.points = vtkSmartPointer<vtkFloatArray>::New();
  m.points->SetNumberOfComponents(3);
  m.points->SetNumberOfTuples(vtkIdType(h.vertexCount));
  if (h.layout.normals)
  {
    m.normals = vtkSmartPointer<vtkFloatArray>::New();
    m.normals->SetName("Normals");
    m.normals->SetNumberOfComponents(3);
    m.normals->SetNumberOfTuples(vtkIdType(h.vertexCount));
  }
  if (h.layout.colors)
  {
    m.colors = vtkSmartPointer<vtkUnsignedCharArray>::New();
    m.colors->SetName("RGBA");
    m.colors->SetNumberOfComponents(4);
    m.colors->SetNumberOfTuples(vtkIdType(h.vertexCount));
  }
  if (h.layout.texcoords)
  {
    m.tcoords = vtkSmartPointer<vtkFloatArray>::New();
    m.tcoords->SetName("TCoords");
    m.tcoords->SetNumberOfComponents(2);
    m.tcoords->SetNumberOfTuples(vtkIdType(h.vertexCount));
  }
  for (const std::string& name : h.layout.scalars)
  {
    auto a = vtkSmartPointer<vtkFloatArray>::New();
    a->SetName(name.c_str());
    a->SetNumberOfTuples(vtkIdType(h.vertexCount));
    m.scalars.push_back(a);
  }
  m.connectivity = vtkSmartPointer<vtkIdTypeArray>::New();
  m.connectivity->Allocate(vtkIdType(3 * h.faceCount));
}

void PolyDataSink::Vertices(const io::VertexChunk& c)
{
  Impl& m = *this->impl_;
  if (c.first + c.count > m.vertexCount)
  {
    throw io::MeshIOError("the mesh delivered more vertices than it announced");
  }
  std::copy_n(c.xyz, 3 * c.count, m.points->GetPointer(vtkIdType(3 * c.first)));
  if (m.normals && c.normals)
  {
    std::copy_n(c.normals, 3 * c.count, m.normals->GetPointer(vtkIdType(3 * c.first)));
  }
  if (m.colors && c.rgba)
  {
    std::copy_n(c.rgba, 4 * c.count, m.colors->GetPointer(vtkIdType(4 * c.first)));
  }
  if (m.tcoords && c.texcoords)
  {
    std::copy_n(c.texcoords, 2 * c.count, m.tcoords->GetPointer(vtkIdType(2 * c.first)));
  }
  if (c.scalars)
  {
    const std::size_t ns = m.scalars.size();
    for (std::size_t s = 0; s < ns; ++s)
    {
      float* dst = m.scalars[s]->GetPointer(vtkIdType(c.first));
      for (std::size_t i = 0; i < c.count; ++i)
      {
        dst[i] = c.scalars[ns * i + s];
      }
    }
  }
}

void PolyDataSink::Triangles(const std::uint32_t* idx, std::size_t count)
{
  Impl& m = *this->impl_;
  for (std::size_t i = 0; i < 3 * count; ++i)
  {
    if (idx[i] >= m.vertexCount)
    {
      throw io::MeshIOError("a triangle references a vertex beyond the mesh");
    }
    m.connectivity->InsertNextValue(vtkIdType(idx[i]));
  }
}

void PolyDataSink::End(const io::ReadStats&)
{
  Impl& m = *this->impl_;
  auto points = vtkSmartPointer<vtkPoints>::New();
  points->SetData(m.points);
  auto polys = vtkSmartPointer<vtkCellArray>::New();
  polys->SetData(3, m.connectivity);
  m.output->Initialize();
  m.output->SetPoints(points);
  m.output->SetPolys(polys);
  vtkPointData* pd = m.output->GetPointData();
  if (!m.like)
  {
    // a file's attributes: the names the file readers give them
    if (m.normals)
    {
      pd->SetNormals(m.normals);
    }
    if (m.colors)
    {
      pd->SetScalars(m.colors);
    }
    if (m.tcoords)
    {
      pd->SetTCoords(m.tcoords);
    }
    for (auto& a : m.scalars)
    {
      pd->AddArray(a);
    }
    return;
  }

  // the input's arrays: the same names, component counts, types and attribute roles
  const AttributePlan plan = Plan(m.like);
  const vtkIdType n = vtkIdType(m.vertexCount);
  auto rebuild = [&](vtkDataArray* like, const auto& valueOf) {
    vtkSmartPointer<vtkDataArray> a = NewArrayLike(like, n);
    const int nc = like->GetNumberOfComponents();
    for (vtkIdType i = 0; i < n; ++i)
    {
      for (int k = 0; k < nc; ++k)
      {
        a->SetComponent(i, k, Representable(like, valueOf(i, k)));
      }
    }
    pd->AddArray(a);
    for (int role = 0; role < vtkDataSetAttributes::NUM_ATTRIBUTES; ++role)
    {
      if (m.like->GetAttribute(role) == like)
      {
        pd->SetAttribute(a, role);
      }
    }
  };
  if (plan.normals && m.normals)
  {
    rebuild(plan.normals, [&](vtkIdType i, int k) { return double(m.normals->GetValue(3 * i + k)); });
  }
  if (plan.colors && m.colors)
  {
    rebuild(plan.colors, [&](vtkIdType i, int k) { return double(m.colors->GetValue(4 * i + k)); });
  }
  if (plan.tcoords && m.tcoords)
  {
    rebuild(plan.tcoords, [&](vtkIdType i, int k) { return double(m.tcoords->GetValue(2 * i + k)); });
  }
  std::size_t channel = 0;
  for (vtkDataArray* like : plan.others)
  {
    if (channel + std::size_t(like->GetNumberOfComponents()) > m.scalars.size())
    {
      break;
    }
    const std::size_t first = channel;
    rebuild(like, [&](vtkIdType i, int k) { return double(m.scalars[first + k]->GetValue(i)); });
    channel += std::size_t(like->GetNumberOfComponents());
  }
}

AlgorithmProgress::AlgorithmProgress(vtkAlgorithm* algorithm)
  : algorithm_(algorithm)
{
  this->SetInterval(0.05);
}

void AlgorithmProgress::Report(double fraction, const char* phase)
{
  this->algorithm_->SetProgressText(phase);
  this->algorithm_->UpdateProgress(fraction);
}

bool AlgorithmProgress::Aborted()
{
  return this->algorithm_->GetAbortExecute() != 0;
}

}
