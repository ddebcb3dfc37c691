#include "sipmss/algorithms/TwoStage.h"

#include <algorithm>
#include <cstring>

namespace sipmss::algorithms
{
namespace
{
using storage::Array;
using storage::DML;

struct Float3
{
  float v[3];
};
struct Triangle
{
  std::uint32_t v[3];
};
struct Quadric
{
  double q[10];
};

// The stage hand-off: a MeshSink that keeps a mesh in DML blocks, and a MeshSource replaying it.
class DmlMesh final : public io::MeshSink
{
public:
  explicit DmlMesh(DML& dml)
    : dml_(dml)
  {
  }
  ~DmlMesh() override { this->Release(); }

  // Frees the stored mesh (Replay is not possible afterwards).
  void Release()
  {
    if (this->attrs_ >= 0)
    {
      this->dml_.CloseBlock(this->attrs_);
      this->attrs_ = -1;
    }
    this->points_.Close();
    this->triangles_.Close();
  }

  void Begin(const io::MeshHeader& h) override
  {
    this->header_ = h;
    this->stride_ = (h.layout.normals ? 3 : 0) + (h.layout.colors ? 1 : 0) +
      (h.layout.texcoords ? 2 : 0) + h.layout.scalars.size(); // in 4-byte words
    this->points_ = Array<Float3>(this->dml_, std::max<std::uint64_t>(h.vertexCount, 1));
    this->triangles_ = Array<Triangle>(this->dml_, std::max<std::uint64_t>(h.faceCount, 1));
    if (this->stride_)
    {
      this->attrs_ = this->dml_.OpenBlock(4 * this->stride_, std::max<std::uint64_t>(h.vertexCount, 1));
    }
  }
  void Vertices(const io::VertexChunk& c) override
  {
    this->points_.Write(c.first, c.count, reinterpret_cast<const Float3*>(c.xyz));
    if (this->stride_)
    {
      std::vector<std::uint32_t> rec(this->stride_ * c.count);
      for (std::size_t i = 0; i < c.count; ++i)
      {
        std::uint32_t* r = &rec[this->stride_ * i];
        std::size_t k = 0;
        auto put = [&](const float* src, std::size_t n) {
          std::memcpy(r + k, src, 4 * n);
          k += n;
        };
        if (c.normals)
          put(c.normals + 3 * i, 3);
        if (c.rgba)
        {
          std::memcpy(r + k, c.rgba + 4 * i, 4);
          ++k;
        }
        if (c.texcoords)
          put(c.texcoords + 2 * i, 2);
        if (c.scalars)
          put(c.scalars + this->header_.layout.scalars.size() * i, this->header_.layout.scalars.size());
      }
      this->dml_.WriteRange(this->attrs_, c.first, c.count, rec.data());
    }
  }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    this->triangles_.Write(this->triangleCount_, count, reinterpret_cast<const Triangle*>(idx));
    this->triangleCount_ += count;
  }
  void End(const io::ReadStats&) override {}

  // Streams the stored mesh (the same chunk protocol as the readers).
  io::ReadStats Replay(io::MeshSink& sink, const io::ReadOptions& options)
  {
    sink.Begin(this->header_);
    const io::VertexLayout& L = this->header_.layout;
    const std::size_t ns = L.scalars.size();
    // at most about 1 MiB of buffers per chunk, whatever the number of vertex properties
    const std::size_t perVertex = 12 + (L.normals ? 12 : 0) + (L.texcoords ? 8 : 0) + 8 * ns +
      (L.colors ? 8 : 0);
    const std::size_t chunk = std::clamp<std::size_t>((std::size_t(1) << 20) / perVertex, 1,
      options.chunkElements ? options.chunkElements : 16384);
    std::vector<float> xyz, normals, tex, scalars;
    std::vector<std::uint8_t> rgba;
    std::vector<std::uint32_t> rec;
    for (std::uint64_t first = 0; first < this->header_.vertexCount; first += chunk)
    {
      const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, this->header_.vertexCount - first));
      xyz.resize(3 * n);
      this->points_.Read(first, n, reinterpret_cast<Float3*>(xyz.data()));
      io::VertexChunk c;
      c.first = first;
      c.count = n;
      c.xyz = xyz.data();
      if (this->stride_)
      {
        rec.resize(this->stride_ * n);
        this->dml_.ReadRange(this->attrs_, first, n, rec.data());
        normals.resize(L.normals ? 3 * n : 0);
        rgba.resize(L.colors ? 4 * n : 0);
        tex.resize(L.texcoords ? 2 * n : 0);
        scalars.resize(ns * n);
        for (std::size_t i = 0; i < n; ++i)
        {
          const std::uint32_t* r = &rec[this->stride_ * i];
          std::size_t k = 0;
          if (L.normals)
          {
            std::memcpy(&normals[3 * i], r + k, 12);
            k += 3;
          }
          if (L.colors)
          {
            std::memcpy(&rgba[4 * i], r + k, 4);
            ++k;
          }
          if (L.texcoords)
          {
            std::memcpy(&tex[2 * i], r + k, 8);
            k += 2;
          }
          if (ns)
          {
            std::memcpy(&scalars[ns * i], r + k, 4 * ns);
          }
        }
        c.normals = L.normals ? normals.data() : nullptr;
        c.rgba = L.colors ? rgba.data() : nullptr;
        c.texcoords = L.texcoords ? tex.data() : nullptr;
        c.scalars = ns ? scalars.data() : nullptr;
      }
      sink.Vertices(c);
      if (sink.AbortRequested())
      {
        throw AbortedError();
      }
    }
    io::ReadStats st;
    st.vertices = this->header_.vertexCount;
    if (options.verticesOnly)
    {
      return st;
    }
    std::vector<Triangle> tris;
    for (std::uint64_t first = 0; first < this->triangleCount_; first += chunk)
    {
      const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, this->triangleCount_ - first));
      tris.resize(n);
      this->triangles_.Read(first, n, tris.data());
      sink.Triangles(reinterpret_cast<const std::uint32_t*>(tris.data()), n);
      if (sink.AbortRequested())
      {
        throw AbortedError();
      }
    }
    st.triangles = st.polygons = this->triangleCount_;
    sink.End(st);
    return st;
  }

private:
  DML& dml_;
  io::MeshHeader header_;
  std::size_t stride_ = 0;
  Array<Float3> points_;
  Array<Triangle> triangles_;
  storage::BlockId attrs_ = -1;
  std::uint64_t triangleCount_ = 0;
};

// Carries a stage's progress into the run's: the stage's [0,1] maps to [begin, end] of the
// run. The first stage's end is set from the stages' estimated work once the input's size is
// known (Sized, before any work on it); the second stage runs to 1.
class StageProgress final : public Progress
{
public:
  StageProgress(Progress& parent, const char* prefix,
    std::function<double(std::uint64_t, std::uint64_t)> share = nullptr)
    : parent_(parent)
    , begin_(parent.Position())
    , end_(share ? begin_ + 0.5 * (1.0 - begin_) : 1.0)
    , prefix_(prefix)
    , share_(std::move(share))
  {
    this->SetInterval(parent.Interval());
  }
  void Report(double f, const char* phase) override
  {
    this->label_ = std::string(this->prefix_) + phase;
    this->parent_.ReportNested(this->begin_ + (this->end_ - this->begin_) * f, this->label_.c_str());
  }
  bool Aborted() override { return this->parent_.Aborted(); }
  void Sized(std::uint64_t vertices, std::uint64_t faces) override
  {
    if (this->share_ && this->Position() == 0.0)
    {
      const double s = std::min(1.0, std::max(0.0, this->share_(vertices, faces)));
      this->end_ = this->begin_ + s * (1.0 - this->begin_);
    }
  }

private:
  Progress& parent_;
  double begin_, end_;
  const char* prefix_;
  std::function<double(std::uint64_t, std::uint64_t)> share_;
  std::string label_;
};

void Prefix(std::vector<PhaseStat>& phases, std::size_t from, const char* prefix)
{
  for (std::size_t i = from; i < phases.size(); ++i)
  {
    phases[i].name = prefix + phases[i].name;
  }
}
} // namespace

namespace
{
RunStats TwoStageRun(const MeshSource& input, io::MeshSink& output, const TwoStageOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  DML dml;
  dml.Config(options.decimate.storage);
  RunStats stats;

  // Stage 1: clustering into the hand-off mesh, cell quadrics kept per output vertex.
  DmlMesh handoff(dml);
  Array<Quadric> quadrics(dml, 1);
  {
    ClusterOptions co;
    co.maximumGridDimension = options.gridDimension;
    co.storage = options.decimate.storage;
    co.threads = options.threads;
    co.dml = &dml;
    if (options.carryQuadrics)
    {
      co.exportQuadric = [&quadrics](std::uint64_t v, const double q[10]) {
        if (v >= quadrics.Size())
        {
          quadrics.Resize(std::max<std::uint64_t>(v + 1, 2 * quadrics.Size()));
        }
        Quadric r;
        std::copy_n(q, 10, r.q);
        quadrics.Set(v, r);
      };
    }
    // Stage 1's share of the run: its work against stage 2's on the estimated clustered mesh
    // (about half as many vertices as faces).
    DecimateOptions d2 = options.decimate;
    StageProgress p1(progress, "stage 1: ", [co, d2](std::uint64_t V, std::uint64_t F) {
      const double w1 = EstimateClusterWork(V, F, co);
      const double faces = EstimateClusterFaces(V, F, co);
      const double w2 =
        EstimateDecimateWork(std::uint64_t(faces / 2), std::uint64_t(faces), d2);
      return w1 + w2 > 0 ? w1 / (w1 + w2) : 0.5;
    });
    RunStats s1 = Cluster(input, handoff, co, p1);
    stats.inputVertices = s1.inputVertices;
    stats.inputTriangles = s1.inputTriangles;
    stats.droppedInputFaces = s1.droppedInputFaces;
    stats.phases = std::move(s1.phases);
    Prefix(stats.phases, 0, "stage 1 ");
  }
  dml.Reconfigure(); // stage 1's input-sized blocks are gone

  // Stage 2: edge collapse on the DML-resident clustered mesh.
  DecimateOptions dopt = options.decimate;
  dopt.dml = &dml;
  if (options.carryQuadrics)
  {
    dopt.initialQuadric = [&quadrics](std::uint64_t v, double q[10]) {
      if (v >= quadrics.Size())
      {
        return false;
      }
      // Cluster exports a2 ab ac b2 bc c2 ad bd cd d2; Decimate takes the 4x4 upper triangle by
      // rows: a2 ab ac ad b2 bc bd c2 cd d2.
      const Quadric r = quadrics.Get(v);
      static constexpr int kFromCluster[10] = { 0, 1, 2, 6, 3, 4, 7, 5, 8, 9 };
      for (int k = 0; k < 10; ++k)
      {
        q[k] = r.q[kFromCluster[k]];
      }
      return true;
    };
  }
  // Once stage 2 holds the mesh and its quadrics, the hand-off blocks go: the run moves in core
  // as soon as stage 2's own blocks fit.
  dopt.sourceConsumed = [&handoff, &quadrics]() {
    handoff.Release();
    quadrics.Close();
  };
  StageProgress p2(progress, "stage 2: ");
  const std::size_t from = stats.phases.size();
  RunStats s2 = Decimate(
    [&handoff](io::MeshSink& sink, const io::ReadOptions& ro) { return handoff.Replay(sink, ro); },
    output, dopt, p2, onLevel);
  stats.phases.insert(stats.phases.end(), s2.phases.begin(), s2.phases.end());
  Prefix(stats.phases, from, "stage 2 ");
  stats.outputVertices = s2.outputVertices;
  stats.outputTriangles = s2.outputTriangles;
  stats.storage = dml.GetStats();
  return stats;
}
} // namespace

RunStats TwoStage(const MeshSource& input, io::MeshSink& output, const TwoStageOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  return TranslateOutOfMemory(progress, options.decimate.storage,
    [&] { return TwoStageRun(input, output, options, progress, onLevel); });
}

} // namespace sipmss::algorithms
