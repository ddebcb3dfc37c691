// sipmss-meshgen subdivide within a memory budget: the mesh, its edges and the renumbering live
// in DML blocks (in core when they fit the budget, else block files and a page cache), and the
// steps are sequential passes and external sorts (storage::Sort), so a 100M-triangle output takes
// the budget plus a few MB whatever its size.
//
// The output is byte for byte the in-memory subdivision's (the tool's former only path): the new
// vertices are numbered in the order the faces first reach their edges, each draws its
// displacement from one random sequence in that order, and the scanner order sorts the vertices
// along the longest axis (ties by index) and the faces by their lowest vertex (ties by index).
// The shuffled order sends the vertices and the faces to their images by fixed permutations
// (Permutation), so it too is the same at every budget.
#include "Subdivide.h"

#include "sipmss/io/MeshIO.h"
#include "sipmss/storage/Access.h"
#include "sipmss/storage/DML.h"
#include "sipmss/storage/Hash.h"
#include "sipmss/storage/Sort.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <stdexcept>
#include <vector>

namespace sipmss::meshgen
{
namespace
{
using storage::Array;
using storage::DML;
using storage::View;

struct P3
{
  float x[3];
};
struct Tri
{
  std::uint32_t v[3];
};
// An edge of a face: its key (lower vertex << 32 | higher) and the corner that reaches it
// (3 face + slot; slots 0, 1, 2 are the edges ab, bc, ca).
struct EdgeRec
{
  std::uint64_t key;
  std::uint64_t corner;
};
// An edge's first corner, and the edge's number in key order.
struct FirstRec
{
  std::uint64_t key;
  std::uint64_t corner;
  std::uint64_t edge;
};
// A vertex by its coordinate along the sorting axis, with its index and position.
struct AxisRec
{
  float c;
  std::uint32_t index;
  P3 p;
};
// A vertex by its new index in the shuffled order, with its old index and position.
struct KeyRec
{
  std::uint32_t key;
  std::uint32_t index;
  P3 p;
};
// A face by its key (its lowest vertex, or its new index in the shuffled order), then its index.
struct FaceRec
{
  std::uint32_t key;
  std::uint32_t index;
  Tri t;
};

// A random-looking permutation of [0, n), computed element by element (no table): a 4-round
// Feistel network on the smallest even number of bits that holds n (a bijection of that range,
// rounds keyed by storage::Mix), cycle-walked until the result is below n (a bijection of
// [0, n); fewer than 4 steps on average). The shuffled order sends each vertex and each face to
// its image, so that renumbering the corners needs no lookup and the sorts read and write in
// sequence: within the budget whatever the size.
class Permutation
{
public:
  Permutation(std::uint64_t n, std::uint32_t seed)
    : n_(n)
    , seed_(seed)
  {
    while ((std::uint64_t(1) << (2 * this->half_)) < n)
    {
      ++this->half_;
    }
    this->mask_ = (std::uint64_t(1) << this->half_) - 1;
  }
  std::uint32_t operator()(std::uint64_t x) const
  {
    do
    {
      x = this->Round(x);
    } while (x >= this->n_);
    return std::uint32_t(x);
  }

private:
  std::uint64_t Round(std::uint64_t x) const
  {
    std::uint64_t l = x >> this->half_, r = x & this->mask_;
    for (std::uint32_t k = 0; k < 4; ++k)
    {
      const std::uint64_t f = storage::Mix(r ^ storage::Mix(this->seed_ + k)) & this->mask_;
      const std::uint64_t next = l ^ f;
      l = r;
      r = next;
    }
    return (l << this->half_) | r;
  }
  std::uint64_t n_;
  std::uint32_t seed_;
  int half_ = 0;
  std::uint64_t mask_ = 0;
};

constexpr std::size_t kChunk = 1 << 16;

// The run's stopRequested (SubdivideFile sets it for its duration; the passes ask it per chunk).
const std::function<bool()>* gStopRequested = nullptr;

bool StopRequested()
{
  return gStopRequested && *gStopRequested && (*gStopRequested)();
}

void CheckStop()
{
  if (StopRequested())
  {
    throw Interrupted();
  }
}

// The sorts' poll: asks the same between their rounds.
const storage::SortPoll kSortPoll = [](double) { CheckStop(); };

// Calls f(first, elements, m) for the consecutive chunks [first, first + m) of a's first n
// elements (read in order, through a buffer).
template <class T, class F>
void ForChunks(DML& dml, const Array<T>& a, std::uint64_t n, F&& f)
{
  const View<T> view(dml, a);
  std::vector<T> in(std::size_t(std::min<std::uint64_t>(kChunk, n)));
  for (std::uint64_t first = 0; first < n; first += kChunk)
  {
    CheckStop();
    const std::size_t m = std::size_t(std::min<std::uint64_t>(kChunk, n - first));
    view.GetRange(first, m, in.data());
    f(first, in.data(), m);
  }
}

// Fills `to` from `from`'s first n elements: f(i, element, out) appends `per` records to out
// for element i, and they go to to[per i ...].
template <class In, class Out, class F>
void MapChunks(DML& dml, const Array<In>& from, std::uint64_t n, Array<Out>& to, std::size_t per,
  F&& f)
{
  View<Out> w(dml, to);
  std::vector<Out> out;
  ForChunks(dml, from, n, [&](std::uint64_t first, const In* in, std::size_t m) {
    out.clear();
    for (std::size_t i = 0; i < m; ++i)
    {
      f(first + i, in[i], out);
    }
    w.SetRange(per * first, out.size(), out.data());
  });
}

// The input into blocks P (positions) and T (triangles); Begin configures the DML (`configure`,
// from the header's counts) and opens them.
class Loader final : public io::MeshSink
{
public:
  Loader(DML& dml, Array<P3>& p, Array<Tri>& t,
    std::function<void(const io::MeshHeader&)> configure)
    : dml_(dml)
    , p_(p)
    , t_(t)
    , configure_(std::move(configure))
  {
  }
  void Begin(const io::MeshHeader& header) override
  {
    this->configure_(header);
    this->p_ = Array<P3>(this->dml_, std::max<std::uint64_t>(header.vertexCount, 1));
    this->t_ = Array<Tri>(this->dml_, std::max<std::uint64_t>(header.faceCount, 1));
  }
  void Vertices(const io::VertexChunk& c) override
  {
    if (c.first + c.count > this->p_.Size())
    {
      this->p_.Resize(std::max<std::uint64_t>(c.first + c.count, 2 * this->p_.Size()));
    }
    this->nv_ = std::max<std::uint64_t>(this->nv_, c.first + c.count);
    View<P3>(this->dml_, this->p_).SetRange(c.first, c.count, reinterpret_cast<const P3*>(c.xyz));
  }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    if (this->nf_ + count > this->t_.Size())
    {
      this->t_.Resize(std::max<std::uint64_t>(this->nf_ + count, 2 * this->t_.Size()));
    }
    View<Tri>(this->dml_, this->t_).SetRange(this->nf_, count, reinterpret_cast<const Tri*>(idx));
    this->nf_ += count;
  }
  void End(const io::ReadStats&) override
  {
    this->p_.Resize(this->nv_);
    this->t_.Resize(this->nf_);
  }
  bool AbortRequested() override { return StopRequested(); }

private:
  DML& dml_;
  Array<P3>& p_;
  Array<Tri>& t_;
  std::function<void(const io::MeshHeader&)> configure_;
  std::uint64_t nv_ = 0, nf_ = 0;
};

// One level of midpoint subdivision with the displacement of the in-memory path.
void SubdivideOnce(DML& dml, Array<P3>& P, Array<Tri>& T, double displace)
{
  const std::uint64_t nv = P.Size(), nf = T.Size();
  View<P3> p(dml, P);
  View<Tri> t(dml, T);
  // Vertex normals: the faces' cross products, summed in face order.
  Array<P3> N(dml, std::max<std::uint64_t>(nv, 1));
  View<P3> n(dml, N);
  for (std::uint64_t f = 0; f < nf; ++f)
  {
    if (f % kChunk == 0)
    {
      CheckStop();
    }
    const Tri tri = t.Get(f);
    const P3 a = p.Get(tri.v[0]), b = p.Get(tri.v[1]), c = p.Get(tri.v[2]);
    const float u[3] = { b.x[0] - a.x[0], b.x[1] - a.x[1], b.x[2] - a.x[2] };
    const float v[3] = { c.x[0] - a.x[0], c.x[1] - a.x[1], c.x[2] - a.x[2] };
    const float fn[3] = { u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2],
      u[0] * v[1] - u[1] * v[0] };
    for (int k = 0; k < 3; ++k)
    {
      P3 s = n.Get(tri.v[k]);
      for (int d = 0; d < 3; ++d)
      {
        s.x[d] += fn[d];
      }
      n.Set(tri.v[k], s);
    }
  }
  // The edges of every face, sorted by key (then corner: the first corner leads its group).
  Array<EdgeRec> E(dml, std::max<std::uint64_t>(3 * nf, 1));
  MapChunks(dml, T, nf, E, 3, [](std::uint64_t f, const Tri& tri, std::vector<EdgeRec>& out) {
    for (int k = 0; k < 3; ++k)
    {
      const std::uint32_t a = tri.v[k], b = tri.v[(k + 1) % 3];
      const std::uint64_t key = a < b ? (std::uint64_t(a) << 32 | b) : (std::uint64_t(b) << 32 | a);
      out.push_back({ key, 3 * f + std::uint64_t(k) });
    }
  });
  if (nf == 0)
  {
    E.Resize(0);
  }
  storage::Sort(dml, E, [](const EdgeRec& a, const EdgeRec& b) {
    return a.key < b.key || (a.key == b.key && a.corner < b.corner);
  }, kSortPoll);
  // Each corner's edge number, and each edge's first corner.
  Array<std::uint32_t> G(dml, std::max<std::uint64_t>(3 * nf, 1));
  Array<FirstRec> FR(dml, 1);
  std::uint64_t edges = 0;
  {
    View<std::uint32_t> g(dml, G);
    std::vector<FirstRec> first;
    std::uint64_t lastKey = ~std::uint64_t(0);
    ForChunks(dml, E, E.Size(), [&](std::uint64_t, const EdgeRec* in, std::size_t m) {
      first.clear();
      for (std::size_t i = 0; i < m; ++i)
      {
        if (in[i].key != lastKey)
        {
          first.push_back({ in[i].key, in[i].corner, edges++ });
          lastKey = in[i].key;
        }
        g.Set(in[i].corner, std::uint32_t(edges - 1));
      }
      FR.Resize(std::max<std::uint64_t>(edges, 1));
      View<FirstRec>(dml, FR).SetRange(edges - first.size(), first.size(), first.data());
    });
  }
  E.Close();
  if (nv + edges >= 0xFFFFFFFFull)
  {
    throw std::runtime_error("the subdivided mesh would have more than 2^32 - 1 vertices");
  }
  FR.Resize(edges);
  storage::Sort(
    dml, FR, [](const FirstRec& a, const FirstRec& b) { return a.corner < b.corner; }, kSortPoll);
  // The new vertices in the order the faces first reach their edges: positions, and each edge's
  // vertex number.
  P.Resize(nv + edges);
  p.Refresh();
  n.Refresh();
  Array<std::uint32_t> ID(dml, std::max<std::uint64_t>(edges, 1));
  {
    View<std::uint32_t> id(dml, ID);
    std::mt19937_64 rng(42);
    std::uniform_real_distribution<float> noise(-1.f, 1.f);
    std::vector<P3> out;
    ForChunks(dml, FR, edges, [&](std::uint64_t i0, const FirstRec* in, std::size_t m) {
      out.clear();
      for (std::size_t i = 0; i < m; ++i)
      {
        const std::uint32_t a = std::uint32_t(in[i].key >> 32), b = std::uint32_t(in[i].key);
        const P3 pa = p.Get(a), pb = p.Get(b), na = n.Get(a), nb = n.Get(b);
        float nn[3];
        float len = 0, elen = 0;
        for (int d = 0; d < 3; ++d)
        {
          nn[d] = na.x[d] + nb.x[d];
          len += nn[d] * nn[d];
          const float ed = pa.x[d] - pb.x[d];
          elen += ed * ed;
        }
        len = std::sqrt(len);
        const float s = len > 0 ? float(displace) * std::sqrt(elen) * noise(rng) / len : 0.f;
        P3 q;
        for (int d = 0; d < 3; ++d)
        {
          q.x[d] = 0.5f * (pa.x[d] + pb.x[d]) + s * nn[d];
        }
        out.push_back(q);
        id.Set(in[i].edge, std::uint32_t(nv + i0 + i));
      }
      p.SetRange(nv + i0, out.size(), out.data());
    });
  }
  FR.Close();
  N.Close();
  // Four faces for each.
  Array<Tri> T2(dml, std::max<std::uint64_t>(4 * nf, 1));
  {
    const View<std::uint32_t> g(dml, G), id(dml, ID);
    MapChunks(dml, T, nf, T2, 4, [&](std::uint64_t f, const Tri& tri, std::vector<Tri>& out) {
      const std::uint32_t a = tri.v[0], b = tri.v[1], c = tri.v[2];
      const std::uint32_t ab = id.Get(g.Get(3 * f)), bc = id.Get(g.Get(3 * f + 1)),
                          ca = id.Get(g.Get(3 * f + 2));
      out.push_back({ { a, ab, ca } });
      out.push_back({ { ab, b, bc } });
      out.push_back({ { ca, bc, c } });
      out.push_back({ { ab, bc, ca } });
    });
  }
  if (nf == 0)
  {
    T2.Resize(0);
  }
  T = std::move(T2);
}

// The faces' records FA (one per face of T, opened with at least one element) sorted by key
// (ties by index) into T; FA is closed.
void FacesInOrder(DML& dml, Array<FaceRec>& FA, Array<Tri>& T)
{
  const std::uint64_t nf = T.Size();
  if (nf == 0)
  {
    FA.Resize(0);
  }
  storage::Sort(dml, FA, [](const FaceRec& x, const FaceRec& y) {
    return x.key < y.key || (x.key == y.key && x.index < y.index);
  }, kSortPoll);
  MapChunks(dml, FA, nf, T, 1,
    [](std::uint64_t, const FaceRec& x, std::vector<Tri>& out) { out.push_back(x.t); });
  FA.Close();
}

// The vertices' records A sorted into their new order: P in that order, each old index's rank
// (R), then the faces renumbered through R and sorted by faceKey(f, renumbered face)
// (FacesInOrder). A is closed.
template <class Rec, class FaceKey>
void Renumber(DML& dml, Array<Rec>& A, Array<P3>& P, Array<Tri>& T, FaceKey faceKey)
{
  const std::uint64_t nv = P.Size(), nf = T.Size();
  Array<std::uint32_t> R(dml, std::max<std::uint64_t>(nv, 1));
  {
    View<std::uint32_t> r(dml, R);
    MapChunks(dml, A, nv, P, 1, [&r](std::uint64_t i, const Rec& x, std::vector<P3>& out) {
      out.push_back(x.p);
      r.Set(x.index, std::uint32_t(i));
    });
  }
  A.Close();
  Array<FaceRec> FA(dml, std::max<std::uint64_t>(nf, 1));
  {
    const View<std::uint32_t> r(dml, R);
    MapChunks(dml, T, nf, FA, 1,
      [&r, &faceKey](std::uint64_t f, const Tri& t, std::vector<FaceRec>& out) {
        const Tri x = { { r.Get(t.v[0]), r.Get(t.v[1]), r.Get(t.v[2]) } };
        out.push_back({ faceKey(f, x), std::uint32_t(f), x });
      });
  }
  R.Close();
  FacesInOrder(dml, FA, T);
}

// Scanner order: vertices along the longest axis (ties by index), faces by their lowest vertex
// (ties by index), both by external sorts.
void ScannerOrder(DML& dml, Array<P3>& P, Array<Tri>& T)
{
  const std::uint64_t nv = P.Size();
  float lo[3] = { 1e30f, 1e30f, 1e30f }, hi[3] = { -1e30f, -1e30f, -1e30f };
  ForChunks(dml, P, nv, [&](std::uint64_t, const P3* in, std::size_t m) {
    for (std::size_t i = 0; i < m; ++i)
    {
      for (int d = 0; d < 3; ++d)
      {
        lo[d] = std::min(lo[d], in[i].x[d]);
        hi[d] = std::max(hi[d], in[i].x[d]);
      }
    }
  });
  int axis = 0;
  for (int d = 1; d < 3; ++d)
  {
    if (hi[d] - lo[d] > hi[axis] - lo[axis])
    {
      axis = d;
    }
  }
  Array<AxisRec> A(dml, std::max<std::uint64_t>(nv, 1));
  MapChunks(dml, P, nv, A, 1, [axis](std::uint64_t i, const P3& q, std::vector<AxisRec>& out) {
    out.push_back({ q.x[axis], std::uint32_t(i), q });
  });
  if (nv == 0)
  {
    A.Resize(0);
  }
  storage::Sort(dml, A, [](const AxisRec& x, const AxisRec& y) {
    return x.c < y.c || (!(y.c < x.c) && x.index < y.index);
  }, kSortPoll);
  Renumber(dml, A, P, T, [](std::uint64_t, const Tri& x) {
    return std::min({ x.v[0], x.v[1], x.v[2] });
  });
}

// Shuffled order: each vertex and each face to its image by a Permutation (one for each), by
// external sorts in the same bounded memory as the scanner order (the tool's former shuffle held
// the whole mesh in memory: 4.8 GB at 100M triangles).
void ShuffledOrder(DML& dml, Array<P3>& P, Array<Tri>& T)
{
  const std::uint64_t nv = P.Size(), nf = T.Size();
  const Permutation pv(nv, 0x9e3779b9u), pf(nf, 0x7f4a7c15u);
  Array<KeyRec> A(dml, std::max<std::uint64_t>(nv, 1));
  MapChunks(dml, P, nv, A, 1, [&pv](std::uint64_t i, const P3& q, std::vector<KeyRec>& out) {
    out.push_back({ pv(i), std::uint32_t(i), q });
  });
  if (nv == 0)
  {
    A.Resize(0);
  }
  storage::Sort(
    dml, A, [](const KeyRec& x, const KeyRec& y) { return x.key < y.key; }, kSortPoll);
  MapChunks(dml, A, nv, P, 1,
    [](std::uint64_t, const KeyRec& x, std::vector<P3>& out) { out.push_back(x.p); });
  A.Close();
  Array<FaceRec> FA(dml, std::max<std::uint64_t>(nf, 1));
  MapChunks(dml, T, nf, FA, 1, [&](std::uint64_t f, const Tri& t, std::vector<FaceRec>& out) {
    out.push_back({ pf(f), std::uint32_t(f), { { pv(t.v[0]), pv(t.v[1]), pv(t.v[2]) } } });
  });
  FacesInOrder(dml, FA, T);
}
} // namespace

SubdivideStats SubdivideFile(const std::string& input, const std::string& output, int levels,
  double displace, Order order, std::uint64_t memoryBudget,
  const std::vector<std::string>& directories, const std::function<bool()>& stopRequested)
{
  struct StopScope
  {
    explicit StopScope(const std::function<bool()>& f) { gStopRequested = &f; }
    ~StopScope() { gStopRequested = nullptr; }
  } stopScope(stopRequested);
  // The mode is chosen once, from an upper bound of the blocks of the last level (no switch in
  // the middle of a step: its views keep their pointers): with V vertices and F faces, a level
  // holds at most 24 V + 40 E + 120 F bytes, E <= 3 F edges, and makes V + E vertices and 4 F
  // faces; either order 40 V + 32 F. Inputs of unknown size (no counts in the header) go
  // out of core whenever there is a budget.
  DML dml;
  Array<P3> P;
  Array<Tri> T;
  auto configure = [&](const io::MeshHeader& header) {
    storage::Profile profile;
    profile.memoryBudget = memoryBudget;
    profile.directories = directories;
    double v = double(header.vertexCount), f = double(header.faceCount), bytes = 12 * v + 12 * f;
    for (int l = 0; l < levels; ++l)
    {
      bytes = std::max(bytes, 24 * v + 40 * 3 * f + 120 * f);
      v += 3 * f;
      f *= 4;
    }
    bytes = std::max(bytes, 40 * v + 32 * f);
    const bool unknown = header.vertexCount == 0 && header.faceCount == 0;
    const bool outOfCore = memoryBudget > 0 && (unknown || bytes > double(memoryBudget));
    profile.policy = outOfCore ? storage::ModePolicy::OutOfCore : storage::ModePolicy::InCore;
    if (!outOfCore)
    {
      profile.memoryBudget = 0; // (in core: within the budget by the bound above)
    }
    dml.Config(profile);
  };
  {
    Loader loader(dml, P, T, configure);
    try
    {
      io::ReadMesh(input, loader);
    }
    catch (const io::ReadAbortedError&)
    {
      throw Interrupted();
    }
  }
  for (int l = 0; l < levels; ++l)
  {
    SubdivideOnce(dml, P, T, displace);
  }
  if (order == Order::Scanner)
  {
    ScannerOrder(dml, P, T);
  }
  else
  {
    ShuffledOrder(dml, P, T);
  }
  // The output, streamed from the blocks.
  const std::uint64_t nv = P.Size(), nf = T.Size();
  auto w = io::MeshWriter::Create(output, false);
  w->Begin(nv, nf, io::VertexLayout{});
  ForChunks(dml, P, nv, [&w](std::uint64_t first, const P3* in, std::size_t m) {
    io::VertexChunk c;
    c.first = first;
    c.count = m;
    c.xyz = in->x;
    w->Vertices(c);
  });
  ForChunks(dml, T, nf,
    [&w](std::uint64_t, const Tri* in, std::size_t m) { w->Triangles(in->v, m); });
  w->End();
  const storage::Stats s = dml.GetStats();
  return { nv, nf, s.usedOutOfCore, s.peakBytes, s.peakFileBytes };
}

} // namespace sipmss::meshgen
