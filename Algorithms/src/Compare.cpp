// Metro-style mesh comparison; see Compare.h for the method.
#include "sipmss/algorithms/Compare.h"
#include "Morton.h"
#include "sipmss/algorithms/Vector.h"
#include "sipmss/storage/Threads.h"

#include "sipmss/storage/Parallel.h"
#include "sipmss/storage/Sort.h"

#include <algorithm>
#include <atomic>
#include <cmath>
#include <exception>
#include <limits>
#include <stdexcept>
#include <string>
#include <system_error>
#include <thread>

namespace sipmss::algorithms
{
namespace
{

// ---------------------------------------------------------------------------------------------
// Geometry (on the cores' vector type; the arithmetic in the order written out before it)

// The products of a coordinate array with a box axis (a row of the oriented box's axes).
inline double Dot3(const double u[3], const double v[3])
{
  return u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
}
inline Vec3 At(const double p[3])
{
  return { p[0], p[1], p[2] };
}
inline Vec3 At(const float* p)
{
  return { double(p[0]), double(p[1]), double(p[2]) };
}

// Squared distance from p to the segment [a, b] (a point when a == b).
inline double PointSegmentDistanceSquared(const Vec3& p, const Vec3& a, const Vec3& b)
{
  const Vec3 ab = b - a, ap = p - a;
  const double len2 = Dot(ab, ab);
  double t = 0.0;
  if (len2 > 0.0)
  {
    t = Dot(ap, ab) / len2;
    t = t < 0.0 ? 0.0 : (t > 1.0 ? 1.0 : t);
  }
  const Vec3 d = ap - t * ab;
  return Dot(d, d);
}

inline double Distance2To(const Vec3& p, const Vec3& q)
{
  const Vec3 d = p - q;
  return Dot(d, d);
}

// |n| / longest edge^2 <= 1e-10: the triangle is no wider than 1e-10 of its length (or is a
// segment or a point). Ericson's Voronoi-region signs would be rounding noise there; the union of
// its edges is the triangle to that accuracy.
inline bool NearlyDegenerate(const Vec3& a, const Vec3& b, const Vec3& c)
{
  const Vec3 ab = b - a, ac = c - a, bc = c - b;
  const Vec3 n = Cross(ab, ac);
  const double n2 = Dot(n, n);
  const double e2 = std::max(Dot(ab, ab), std::max(Dot(ac, ac), Dot(bc, bc)));
  return !(n2 > 1e-20 * e2 * e2);
}

inline double DegenerateDistance2(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c)
{
  return std::min(PointSegmentDistanceSquared(p, a, b),
    std::min(PointSegmentDistanceSquared(p, b, c), PointSegmentDistanceSquared(p, c, a)));
}

// Ericson, Real-Time Collision Detection, 5.1.5 (ClosestPtPointTriangle), for a triangle that is
// not NearlyDegenerate.
inline double RegularDistance2(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c)
{
  const Vec3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = Dot(ab, ap);
  const double d2 = Dot(ac, ap);
  if (d1 <= 0.0 && d2 <= 0.0)
  {
    return Dot(ap, ap); // vertex region a
  }
  const Vec3 bp = p - b;
  const double d3 = Dot(ab, bp);
  const double d4 = Dot(ac, bp);
  if (d3 >= 0.0 && d4 <= d3)
  {
    return Dot(bp, bp); // vertex region b
  }
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0)
  {
    const double v = d1 / (d1 - d3); // edge ab
    return Distance2To(p, a + v * ab);
  }
  const Vec3 cp = p - c;
  const double d5 = Dot(ab, cp);
  const double d6 = Dot(ac, cp);
  if (d6 >= 0.0 && d5 <= d6)
  {
    return Dot(cp, cp); // vertex region c
  }
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0)
  {
    const double w = d2 / (d2 - d6); // edge ac
    return Distance2To(p, a + w * ac);
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0)
  {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6)); // edge bc
    return Distance2To(p, b + w * (c - b));
  }
  // Face region (va, vb, vc > 0): the closest point is the projection onto the plane. The plane
  // distance is exact for points in the plane and needs no reconstruction of the foot point.
  const Vec3 n = Cross(ab, ac);
  const double h = Dot(n, ap);
  return h * h / Dot(n, n);
}

inline double TriangleDistance2(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c)
{
  return NearlyDegenerate(a, b, c) ? DegenerateDistance2(p, a, b, c)
                                   : RegularDistance2(p, a, b, c);
}

// The same value as TriangleDistance2 on the triangle's (exactly converted) coordinates, with the
// degeneracy test precomputed.
inline double TriangleDistance2(const Vec3& p, const float* t, bool degenerate)
{
  const Vec3 a = At(t), b = At(t + 3), c = At(t + 6);
  return degenerate ? DegenerateDistance2(p, a, b, c) : RegularDistance2(p, a, b, c);
}

// ---------------------------------------------------------------------------------------------
// Validation

void ValidateMesh(const TriangleMesh& mesh, const char* context, const char* what)
{
  const std::string prefix = std::string(context) + ": " + what + " mesh ";
  if (mesh.points.size() % 3 != 0)
  {
    throw std::invalid_argument(prefix + "has " + std::to_string(mesh.points.size()) +
      " point coordinates, not a multiple of 3");
  }
  if (mesh.triangles.size() % 3 != 0)
  {
    throw std::invalid_argument(prefix + "has " + std::to_string(mesh.triangles.size()) +
      " triangle indices, not a multiple of 3");
  }
  if (mesh.NumberOfTriangles() == 0 || mesh.NumberOfPoints() == 0)
  {
    throw std::invalid_argument(prefix + "is empty (" + std::to_string(mesh.NumberOfPoints()) +
      " points, " + std::to_string(mesh.NumberOfTriangles()) + " triangles)");
  }
  if (mesh.NumberOfTriangles() >= 0xffffffffu)
  {
    throw std::invalid_argument(prefix + "has too many triangles (" +
      std::to_string(mesh.NumberOfTriangles()) + ")");
  }
  const std::size_t np = mesh.NumberOfPoints();
  for (std::size_t i = 0; i < mesh.triangles.size(); ++i)
  {
    if (mesh.triangles[i] >= np)
    {
      throw std::invalid_argument(prefix + "triangle " + std::to_string(i / 3) +
        " refers to point " + std::to_string(mesh.triangles[i]) + " but there are only " +
        std::to_string(np) + " points");
    }
  }
  for (std::size_t i = 0; i < mesh.points.size(); ++i)
  {
    if (!std::isfinite(mesh.points[i]))
    {
      throw std::invalid_argument(
        prefix + "point " + std::to_string(i / 3) + " has a non-finite coordinate");
    }
  }
}

// ---------------------------------------------------------------------------------------------
// Random numbers: splitmix64 to seed, xoshiro256** to draw. Fully specified (no <random>
// distributions, whose output is implementation-defined).

inline std::uint64_t SplitMix64(std::uint64_t& x)
{
  std::uint64_t z = (x += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}

class Rng
{
public:
  Rng(std::uint64_t seed, std::uint64_t stream, std::uint64_t chunk)
  {
    std::uint64_t x = seed;
    std::uint64_t k = SplitMix64(x);
    x = k ^ (stream * 0xD1B54A32D192ED03ull);
    k = SplitMix64(x);
    x = k ^ (chunk * 0xA0761D6478BD642Full);
    for (auto& s : this->S)
    {
      s = SplitMix64(x);
    }
  }
  std::uint64_t Next()
  {
    const std::uint64_t result = Rotl(this->S[1] * 5, 7) * 9;
    const std::uint64_t t = this->S[1] << 17;
    this->S[2] ^= this->S[0];
    this->S[3] ^= this->S[1];
    this->S[1] ^= this->S[2];
    this->S[0] ^= this->S[3];
    this->S[2] ^= t;
    this->S[3] = Rotl(this->S[3], 45);
    return result;
  }
  // Uniform in [0, 1).
  double Uniform() { return static_cast<double>(this->Next() >> 11) * 0x1.0p-53; }

private:
  static std::uint64_t Rotl(std::uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
  std::uint64_t S[4];
};

using storage::ResolveThreads;

// Runs body(chunk) for chunk in [0, count) on up to `threads` threads (the caller included).
template <typename Body>
void ParallelChunks(std::uint64_t count, int threads, const Body& body)
{
  std::atomic<std::uint64_t> next{ 0 };
  auto worker = [&](int) {
    for (std::uint64_t c = next.fetch_add(1, std::memory_order_relaxed); c < count;
         c = next.fetch_add(1, std::memory_order_relaxed))
    {
      body(c);
    }
  };
  // (a thread that cannot be started leaves its chunks to the others)
  storage::RunOnThreads(
    static_cast<int>(std::min<std::uint64_t>(count, static_cast<std::uint64_t>(std::max(threads, 1)))),
    worker);
}

// ---------------------------------------------------------------------------------------------
// Canonical order. The samples are strata of the cumulative area; so that they depend on the
// surface and not on how a file lists it, the cumulative area runs over the triangles in a
// canonical order, and each triangle's corners are taken in a canonical order too (for the
// samples and for the index's distances). A copy of a mesh with its points, its triangles or the
// corners of its triangles listed in another order then gets the same samples and the same
// distances, bit for bit.

// Whether the point at a comes before the point at b: by x, then y, then z.
template <class T>
inline bool Before(const T* a, const T* b)
{
  return a[0] != b[0] ? a[0] < b[0] : (a[1] != b[1] ? a[1] < b[1] : a[2] < b[2]);
}
inline bool PointBefore(const float* pts, std::uint32_t i, std::uint32_t j)
{
  return Before(pts + 3 * std::size_t(i), pts + 3 * std::size_t(j));
}
// Three points (their coordinates' addresses) put in Before order.
template <class T>
inline void SortThree(const T* (&v)[3])
{
  if (Before(v[1], v[0]))
  {
    std::swap(v[0], v[1]);
  }
  if (Before(v[2], v[1]))
  {
    std::swap(v[1], v[2]);
  }
  if (Before(v[1], v[0]))
  {
    std::swap(v[0], v[1]);
  }
}

// The corners of triangle t in the order of their points (SortThree).
inline std::array<std::uint32_t, 3> Corners(const TriangleMesh& mesh, std::size_t t)
{
  const float* pts = mesh.points.data();
  const float* v[3];
  for (int k = 0; k < 3; ++k)
  {
    v[k] = pts + 3 * std::size_t(mesh.triangles[3 * t + k]);
  }
  SortThree(v);
  std::array<std::uint32_t, 3> c;
  for (int k = 0; k < 3; ++k)
  {
    c[k] = static_cast<std::uint32_t>((v[k] - pts) / 3);
  }
  return c;
}

// The triangles in canonical order: by the Morton code of their centroids (21 bits an axis over
// the centroids' bounds), then by their corners' points, then by index (only triangles on the
// same three points keep the file's order). Neighbouring strata are then neighbouring pieces of
// the surface whatever the file's order.
// Also each triangle's area (on its canonical corners), in the file's order.
std::vector<std::uint32_t> CanonicalOrder(
  const TriangleMesh& mesh, int threads, std::vector<double>& areas)
{
  const std::size_t nt = mesh.NumberOfTriangles();
  const float* pts = mesh.points.data();
  if (nt == 0)
  {
    areas.clear();
    return {};
  }
  // The centroids (of the canonical corners, rounded to floats) and their bounds, then the keys:
  // two passes over chunks of triangles on the threads.
  constexpr std::size_t kChunk = std::size_t(1) << 16;
  const std::uint64_t chunks = (nt + kChunk - 1) / kChunk;
  std::vector<float> centroids(3 * nt);
  areas.resize(nt);
  std::vector<std::array<double, 6>> chunkBounds(chunks);
  const int workers = storage::ResolveThreads(threads);
  ParallelChunks(chunks, workers, [&](std::uint64_t chunk) {
    std::array<double, 6> b = { std::numeric_limits<double>::infinity(),
      std::numeric_limits<double>::infinity(), std::numeric_limits<double>::infinity(),
      -std::numeric_limits<double>::infinity(), -std::numeric_limits<double>::infinity(),
      -std::numeric_limits<double>::infinity() };
    const std::size_t end = std::min<std::size_t>(nt, (chunk + 1) * kChunk);
    for (std::size_t t = chunk * kChunk; t < end; ++t)
    {
      const std::array<std::uint32_t, 3> c = Corners(mesh, t);
      const Vec3 pa = At(pts + 3 * std::size_t(c[0]));
      const Vec3 n =
        Cross(At(pts + 3 * std::size_t(c[1])) - pa, At(pts + 3 * std::size_t(c[2])) - pa);
      areas[t] = 0.5 * std::sqrt(Dot(n, n));
      for (int k = 0; k < 3; ++k)
      {
        const auto x = static_cast<float>((double(pts[3 * std::size_t(c[0]) + k]) +
                                             double(pts[3 * std::size_t(c[1]) + k]) +
                                             double(pts[3 * std::size_t(c[2]) + k])) / 3.0);
        centroids[3 * t + k] = x;
        b[k] = std::min<double>(b[k], x);
        b[3 + k] = std::max<double>(b[3 + k], x);
      }
    }
    chunkBounds[chunk] = b;
  });
  double lo[3], hi[3];
  for (int k = 0; k < 3; ++k)
  {
    lo[k] = std::numeric_limits<double>::infinity();
    hi[k] = -std::numeric_limits<double>::infinity();
    for (const auto& b : chunkBounds)
    {
      lo[k] = std::min(lo[k], b[k]);
      hi[k] = std::max(hi[k], b[3 + k]);
    }
  }
  struct Rec
  {
    std::uint64_t key;
    std::uint32_t t;
  };
  std::vector<Rec> recs(nt);
  ParallelChunks(chunks, workers, [&](std::uint64_t chunk) {
    const std::size_t end = std::min<std::size_t>(nt, (chunk + 1) * kChunk);
    for (std::size_t t = chunk * kChunk; t < end; ++t)
    {
      std::uint64_t key = 0;
      for (int k = 0; k < 3; ++k)
      {
        const double extent = hi[k] - lo[k];
        const double f = extent > 0.0 ? (centroids[3 * t + k] - lo[k]) / extent : 0.0;
        const auto q = static_cast<std::uint64_t>(std::clamp(f, 0.0, 1.0) * double(0x1fffff));
        key |= detail::Spread21(q) << k;
      }
      recs[t] = Rec{ key, static_cast<std::uint32_t>(t) };
    }
  });
  centroids = std::vector<float>();
  auto less = [&](const Rec& a, const Rec& b) {
    if (a.key != b.key)
    {
      return a.key < b.key;
    }
    const std::array<std::uint32_t, 3> ca = Corners(mesh, a.t), cb = Corners(mesh, b.t);
    for (int v = 0; v < 3; ++v)
    {
      if (PointBefore(pts, ca[v], cb[v]))
      {
        return true;
      }
      if (PointBefore(pts, cb[v], ca[v]))
      {
        return false;
      }
    }
    return a.t < b.t;
  };
  auto keyOf = [](const Rec& r) { return r.key; };
  storage::detail::RadixSortByKey(recs.data(), nt, keyOf, less, storage::SortPoll(), workers);
  std::vector<std::uint32_t> order(nt);
  for (std::size_t i = 0; i < nt; ++i)
  {
    order[i] = recs[i].t;
  }
  return order;
}

// ---------------------------------------------------------------------------------------------
// Area table

struct AreaTable
{
  std::vector<std::uint32_t> order; // the triangles in canonical order (CanonicalOrder)
  std::vector<double> cdf;          // cdf[i] = total area of triangles order[0..i]
  double total = 0;
  std::uint32_t lastPositive = 0; // (a position in order)
};

AreaTable BuildAreaTable(const TriangleMesh& mesh, int threads)
{
  AreaTable table;
  const std::size_t nt = mesh.NumberOfTriangles();
  std::vector<double> areas;
  table.order = CanonicalOrder(mesh, threads, areas);
  table.cdf.resize(nt);
  double sum = 0.0;
  for (std::size_t i = 0; i < nt; ++i)
  {
    const double area = areas[table.order[i]];
    if (area > 0.0)
    {
      table.lastPositive = static_cast<std::uint32_t>(i);
    }
    sum += area;
    table.cdf[i] = sum;
  }
  table.total = sum;
  return table;
}

// ---------------------------------------------------------------------------------------------
// Chunked, deterministic sampling

constexpr std::uint64_t kChunkSize = 8192;

struct ChunkStats
{
  double sum = 0, sumSq = 0, max = 0;
  std::vector<double> attrSumSq, attrMax; // per attribute group
};

struct Sums
{
  double sum = 0, sumSq = 0, max = 0;
  std::vector<double> attrSumSq, attrMax;
  std::uint64_t samples = 0;
  OneSided ToOneSided() const
  {
    OneSided r;
    r.samples = this->samples;
    if (this->samples > 0)
    {
      r.mean = this->sum / static_cast<double>(this->samples);
      r.rms = std::sqrt(this->sumSq / static_cast<double>(this->samples));
      r.max = this->max;
    }
    return r;
  }
};

// Attributes (groups not empty): toMesh is the mesh `to` indexes.
Sums Sample(const TriangleMesh& from, const AreaTable& table, const MeshDistanceIndex& to,
  std::uint64_t samples, std::uint64_t seed, std::uint64_t stream, int threads,
  const TriangleMesh* toMesh = nullptr,
  const std::vector<std::array<std::size_t, 2>>& groups = {})
{
  Sums result;
  const std::size_t ng = toMesh ? groups.size() : 0;
  result.attrSumSq.assign(ng, 0.0);
  result.attrMax.assign(ng, 0.0);
  if (samples == 0)
  {
    return result;
  }
  const std::uint64_t chunks = (samples + kChunkSize - 1) / kChunkSize;
  std::vector<ChunkStats> stats(chunks);
  const double stride = table.total / static_cast<double>(samples);
  const std::size_t nt = table.cdf.size();
  const double* cdf = table.cdf.data();
  const float* pts = from.points.data();

  ParallelChunks(chunks, ResolveThreads(threads), [&](std::uint64_t chunk) {
    Rng rng(seed, stream, chunk);
    const std::uint64_t k0 = chunk * kChunkSize;
    const std::uint64_t k1 = std::min(samples, k0 + kChunkSize);
    ChunkStats s;
    s.attrSumSq.assign(ng, 0.0);
    s.attrMax.assign(ng, 0.0);
    std::size_t t = 0;
    std::uint32_t hint = MeshDistanceIndex::kNoHint;
    for (std::uint64_t k = k0; k < k1; ++k)
    {
      // Stratum k of the cumulative area, jittered; x is non-decreasing in k.
      const double x = (static_cast<double>(k) + rng.Uniform()) * stride;
      if (k == k0)
      {
        t = static_cast<std::size_t>(std::upper_bound(cdf, cdf + nt, x) - cdf);
      }
      else
      {
        while (t < nt && cdf[t] <= x)
        {
          ++t;
        }
      }
      // First triangle with cdf > x has positive area; past the end only by rounding.
      const std::size_t tri = table.order[t < nt ? t : table.lastPositive];
      const std::array<std::uint32_t, 3> corner = Corners(from, tri);
      const float* a = pts + 3 * std::size_t(corner[0]);
      const float* b = pts + 3 * std::size_t(corner[1]);
      const float* c = pts + 3 * std::size_t(corner[2]);
      const double r1 = std::sqrt(rng.Uniform());
      const double u2 = rng.Uniform();
      const double w0 = 1.0 - r1;
      const double w1 = r1 * (1.0 - u2);
      const double w2 = r1 * u2;
      const double p[3] = { w0 * a[0] + w1 * b[0] + w2 * c[0], w0 * a[1] + w1 * b[1] + w2 * c[1],
        w0 * a[2] + w1 * b[2] + w2 * c[2] };
      const MeshDistanceIndex::Hit hit = to.Nearest(p, hint);
      hint = hit.triangle;
      const double d = std::sqrt(hit.distanceSquared);
      s.sum += d;
      s.sumSq += hit.distanceSquared;
      s.max = std::max(s.max, d);
      if (ng)
      {
        // The attributes at the sample and at its nearest point on the other mesh.
        const std::array<std::uint32_t, 3> tt = Corners(*toMesh, hit.triangle);
        const float* tp = toMesh->points.data();
        double ta[3][3];
        for (int k = 0; k < 3; ++k)
        {
          for (int d3 = 0; d3 < 3; ++d3)
          {
            ta[k][d3] = tp[3 * std::size_t(tt[k]) + d3];
          }
        }
        const std::array<double, 3> bw = ClosestPointBarycentric(p, ta[0], ta[1], ta[2]);
        const std::size_t fs = from.attributeStride, ts = toMesh->attributeStride;
        const float* fa = from.attributes.data();
        const float* ttA = toMesh->attributes.data();
        for (std::size_t g = 0; g < ng; ++g)
        {
          double e2 = 0;
          for (std::size_t c = groups[g][0]; c < groups[g][0] + groups[g][1]; ++c)
          {
            const double x = w0 * fa[fs * corner[0] + c] + w1 * fa[fs * corner[1] + c] +
              w2 * fa[fs * corner[2] + c];
            const double y = bw[0] * ttA[ts * tt[0] + c] + bw[1] * ttA[ts * tt[1] + c] +
              bw[2] * ttA[ts * tt[2] + c];
            e2 += (x - y) * (x - y);
          }
          s.attrSumSq[g] += e2;
          s.attrMax[g] = std::max(s.attrMax[g], std::sqrt(e2));
        }
      }
    }
    stats[chunk] = std::move(s);
  });

  for (const ChunkStats& s : stats) // in chunk order: independent of the thread count
  {
    result.sum += s.sum;
    result.sumSq += s.sumSq;
    result.max = std::max(result.max, s.max);
    for (std::size_t g = 0; g < ng; ++g)
    {
      result.attrSumSq[g] += s.attrSumSq[g];
      result.attrMax[g] = std::max(result.attrMax[g], s.attrMax[g]);
    }
  }
  result.samples = samples;
  return result;
}

double Diagonal(const std::array<double, 6>& b)
{
  const double dx = b[1] - b[0], dy = b[3] - b[2], dz = b[5] - b[4];
  return std::sqrt(dx * dx + dy * dy + dz * dz);
}

} // namespace

// -----------------------------------------------------------------------------------------------

std::array<double, 6> TriangleMesh::Bounds() const
{
  if (this->NumberOfPoints() == 0)
  {
    return { 1, -1, 1, -1, 1, -1 };
  }
  std::array<double, 6> b = { this->points[0], this->points[0], this->points[1], this->points[1],
    this->points[2], this->points[2] };
  const std::size_t n = this->NumberOfPoints();
  for (std::size_t i = 1; i < n; ++i)
  {
    for (int k = 0; k < 3; ++k)
    {
      const double v = this->points[3 * i + k];
      b[2 * k] = std::min(b[2 * k], v);
      b[2 * k + 1] = std::max(b[2 * k + 1], v);
    }
  }
  return b;
}

double PointTriangleDistanceSquared(
  const double p[3], const double a[3], const double b[3], const double c[3])
{
  // The corners in the order of their coordinates (as Corners orders a mesh's): the same value,
  // bit for bit, whichever corner comes first and whichever way round.
  const double* v[3] = { a, b, c };
  SortThree(v);
  return TriangleDistance2(At(p), At(v[0]), At(v[1]), At(v[2]));
}

std::array<double, 3> ClosestPointBarycentric(
  const double p[3], const double a[3], const double b[3], const double c[3])
{
  return ClosestPointBarycentric(At(p), At(a), At(b), At(c));
}

std::array<double, 3> ClosestPointBarycentric(
  const Vec3& P, const Vec3& A, const Vec3& B, const Vec3& C)
{
  const Vec3 ab = B - A, ac = C - A, ap = P - A;
  auto segment = [&](const Vec3& x, const Vec3& y) { // parameter of the nearest point on x-y
    const Vec3 e = y - x;
    const double l = Dot(e, e);
    return l > 0 ? std::min(1.0, std::max(0.0, Dot(P - x, e) / l)) : 0.0;
  };
  if (NearlyDegenerate(A, B, C))
  {
    const double t0 = segment(A, B), t1 = segment(B, C), t2 = segment(C, A);
    const double d0 = Distance2To(P, A + t0 * (B - A)), d1 = Distance2To(P, B + t1 * (C - B)),
                 d2 = Distance2To(P, C + t2 * (A - C));
    if (d0 <= d1 && d0 <= d2)
    {
      return { 1 - t0, t0, 0 };
    }
    if (d1 <= d2)
    {
      return { 0, 1 - t1, t1 };
    }
    return { t2, 0, 1 - t2 };
  }
  // Ericson, Real-Time Collision Detection, 5.1.5.
  const double d1 = Dot(ab, ap), d2 = Dot(ac, ap);
  if (d1 <= 0 && d2 <= 0)
  {
    return { 1, 0, 0 };
  }
  const Vec3 bp = P - B;
  const double d3 = Dot(ab, bp), d4 = Dot(ac, bp);
  if (d3 >= 0 && d4 <= d3)
  {
    return { 0, 1, 0 };
  }
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0)
  {
    const double v = d1 / (d1 - d3);
    return { 1 - v, v, 0 };
  }
  const Vec3 cp = P - C;
  const double d5 = Dot(ab, cp), d6 = Dot(ac, cp);
  if (d6 >= 0 && d5 <= d6)
  {
    return { 0, 0, 1 };
  }
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0)
  {
    const double w = d2 / (d2 - d6);
    return { 1 - w, 0, w };
  }
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0)
  {
    const double w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
    return { 0, 1 - w, w };
  }
  const double denom = 1.0 / (va + vb + vc);
  const double v = vb * denom, w = vc * denom;
  return { 1 - v - w, v, w };
}

// -----------------------------------------------------------------------------------------------
// MeshDistanceIndex: a binary BVH built with the binned surface-area heuristic (median split
// below a depth limit, which bounds the depth), leaves of at most 4 triangles, inner nodes in
// depth-first order holding their children's bounds.
//
// The bounds are oriented boxes: per child the cheaper (by surface area) of its axis-aligned box
// and a box aligned with its mean normal. For a surface patch the latter is nearly flat. That
// matters when the query distance d is large against the triangle size s: axis-aligned boxes of
// tilted patches are as thick as they are wide, and all those within ~sqrt(d * s) of the foot
// point reach into the query ball (measured: a 1M-triangle sphere against its copy scaled by 1.5,
// 1100 triangle tests per query with axis-aligned boxes, 20-40 with oriented ones). Near queries
// cost about 20% more than with axis-aligned boxes.

namespace
{
constexpr std::uint32_t kLeafSize = 4;
constexpr std::uint32_t kParallelMinimum = 1u << 16; // subtrees smaller than this stay serial
constexpr int kSahDepth = 64; // deeper nodes split at the median: depth <= 64 + 32
constexpr int kBins = 16;
constexpr std::uint32_t kExactFit = 64; // boxes of subtrees up to this size fit the vertices
// Squared lower bounds are scaled by this before pruning: the float axes are orthonormal only to
// ~1e-7, so a box bound may exceed the true distance by that relative amount.
constexpr double kBoundShrink = 1.0 - 4e-6;

struct Box
{
  float lo[3] = { std::numeric_limits<float>::infinity(), std::numeric_limits<float>::infinity(),
    std::numeric_limits<float>::infinity() };
  float hi[3] = { -std::numeric_limits<float>::infinity(),
    -std::numeric_limits<float>::infinity(), -std::numeric_limits<float>::infinity() };
  void Grow(const float* lo3, const float* hi3)
  {
    for (int k = 0; k < 3; ++k)
    {
      this->lo[k] = std::min(this->lo[k], lo3[k]);
      this->hi[k] = std::max(this->hi[k], hi3[k]);
    }
  }
  void Grow(const Box& b) { this->Grow(b.lo, b.hi); }
  double HalfArea() const
  {
    const double dx = double(this->hi[0]) - this->lo[0];
    const double dy = double(this->hi[1]) - this->lo[1];
    const double dz = double(this->hi[2]) - this->lo[2];
    return dx * dy + dy * dz + dz * dx;
  }
};

// Fits a box with the given (float, nearly orthonormal) axes around the points that
// forEach(f) passes to f (as double[3]). The half extents are measured from the float-rounded
// center, padded by `pad` plus a bound on the rounding of the projections, and rounded up to
// float: the stored box contains every point. Returns the surface-area cost.
template <typename ForEach>
double FitBox(const float axes[3][3], const ForEach& forEach, double pad, float center[3],
  float half[3])
{
  double axis[3][3];
  for (int a = 0; a < 3; ++a)
  {
    for (int k = 0; k < 3; ++k)
    {
      axis[a][k] = axes[a][k];
    }
  }
  double lo[3], hi[3];
  for (int a = 0; a < 3; ++a)
  {
    lo[a] = std::numeric_limits<double>::infinity();
    hi[a] = -std::numeric_limits<double>::infinity();
  }
  double magnitude = 0.0;
  forEach([&](const double x[3]) {
    for (int a = 0; a < 3; ++a)
    {
      const double s = Dot3(x, axis[a]);
      lo[a] = std::min(lo[a], s);
      hi[a] = std::max(hi[a], s);
    }
    magnitude = std::max(magnitude, std::abs(x[0]) + std::abs(x[1]) + std::abs(x[2]));
  });
  for (int k = 0; k < 3; ++k)
  {
    double c = 0.0;
    for (int a = 0; a < 3; ++a)
    {
      c += 0.5 * (lo[a] + hi[a]) * axis[a][k];
    }
    center[k] = static_cast<float>(c);
  }
  const double c[3] = { center[0], center[1], center[2] };
  // (x - c).a = x.a - c.a up to a few ulps of |x| + |c| (|a| ~ 1).
  pad += 1e-14 * (magnitude + std::abs(c[0]) + std::abs(c[1]) + std::abs(c[2]));
  for (int a = 0; a < 3; ++a)
  {
    const double ca = Dot3(c, axis[a]);
    const double h = std::max(hi[a] - ca, ca - lo[a]) + pad;
    const float f = static_cast<float>(h);
    half[a] = double(f) >= h ? f : std::nextafter(f, std::numeric_limits<float>::infinity());
  }
  return double(half[0]) * half[1] + double(half[1]) * half[2] + double(half[2]) * half[0];
}

// Calls f(x) for the 8 corners x = center + sum(+-half[a] * axis[a]) of a box. With axes
// orthonormal only to ~1e-7 these are within 1e-6 * (sum of half) of the true corners.
template <typename Box3, typename F>
void ForEachCorner(const Box3& box, const F& f)
{
  for (int i = 0; i < 8; ++i)
  {
    double x[3] = { box.center[0], box.center[1], box.center[2] };
    for (int a = 0; a < 3; ++a)
    {
      const double s = (i >> a & 1) ? double(box.half[a]) : -double(box.half[a]);
      for (int k = 0; k < 3; ++k)
      {
        x[k] += s * double(box.axis[a][k]);
      }
    }
    f(x);
  }
}
} // namespace

struct MeshDistanceIndex::Builder
{
  const float* triangles; // 9 per triangle, mesh order
  const float* boxes;     // 6 per triangle (lo xyz, hi xyz), mesh order
  std::uint32_t* order;   // leaf order -> mesh triangle

  struct Built
  {
    Child child;
    Box aabb;          // exact axis-aligned bounds
    double normal[3];  // sum of the triangles' (unnormalized) normals
  };

  float Centroid(std::uint32_t t, int axis) const
  {
    const float* b = this->boxes + 6 * std::size_t(t);
    return 0.5f * (b[axis] + b[3 + axis]);
  }

  // Chooses the split of order[begin, end) and partitions it; returns the first of the right
  // half, strictly inside (begin, end).
  std::uint32_t Split(std::uint32_t begin, std::uint32_t end, int depth)
  {
    const std::uint32_t n = end - begin;
    float clo[3], chi[3];
    for (int k = 0; k < 3; ++k)
    {
      clo[k] = std::numeric_limits<float>::infinity();
      chi[k] = -std::numeric_limits<float>::infinity();
    }
    for (std::uint32_t i = begin; i < end; ++i)
    {
      for (int k = 0; k < 3; ++k)
      {
        const float c = this->Centroid(this->order[i], k);
        clo[k] = std::min(clo[k], c);
        chi[k] = std::max(chi[k], c);
      }
    }
    int axis = 0;
    for (int k = 1; k < 3; ++k)
    {
      if (chi[k] - clo[k] > chi[axis] - clo[axis])
      {
        axis = k;
      }
    }

    // Binned SAH along the longest centroid axis.
    const double extent = double(chi[axis]) - clo[axis];
    if (depth < kSahDepth && extent > 0.0)
    {
      const double scale = kBins / extent;
      const float lo = clo[axis];
      auto binOf = [this, axis, scale, lo](std::uint32_t t) {
        const double x = (double(this->Centroid(t, axis)) - lo) * scale;
        return std::min(kBins - 1, static_cast<int>(x));
      };
      Box bins[kBins];
      std::uint32_t counts[kBins] = {};
      for (std::uint32_t i = begin; i < end; ++i)
      {
        const std::uint32_t t = this->order[i];
        const int bin = binOf(t);
        ++counts[bin];
        bins[bin].Grow(this->boxes + 6 * std::size_t(t), this->boxes + 6 * std::size_t(t) + 3);
      }
      double rightArea[kBins];
      std::uint32_t rightCount[kBins];
      Box acc;
      std::uint32_t cnt = 0;
      for (int b = kBins - 1; b > 0; --b)
      {
        acc.Grow(bins[b]);
        cnt += counts[b];
        rightArea[b] = cnt ? acc.HalfArea() : 0.0;
        rightCount[b] = cnt;
      }
      acc = Box();
      cnt = 0;
      int bestBin = 0;
      double bestCost = std::numeric_limits<double>::infinity();
      for (int b = 1; b < kBins; ++b) // split before bin b
      {
        acc.Grow(bins[b - 1]);
        cnt += counts[b - 1];
        if (cnt == 0 || rightCount[b] == 0)
        {
          continue;
        }
        const double cost = acc.HalfArea() * cnt + rightArea[b] * rightCount[b];
        if (cost < bestCost)
        {
          bestCost = cost;
          bestBin = b;
        }
      }
      if (bestBin > 0)
      {
        const std::uint32_t* mid = std::partition(this->order + begin, this->order + end,
          [&binOf, bestBin](std::uint32_t t) { return binOf(t) < bestBin; });
        const auto m = static_cast<std::uint32_t>(mid - this->order);
        if (m > begin && m < end)
        {
          return m;
        }
      }
    }

    // Median on the longest centroid axis (also when all centroids coincide).
    const std::uint32_t mid = begin + n / 2;
    std::nth_element(this->order + begin, this->order + mid, this->order + end,
      [this, axis](std::uint32_t x, std::uint32_t y) {
        const float cx = this->Centroid(x, axis), cy = this->Centroid(y, axis);
        return cx < cy || (cx == cy && x < y); // a total order: the same tree every time
      });
    return mid;
  }

  // Bounds `out` (ref already set): the cheaper of the axis-aligned box and the box aligned with
  // the mean normal. Small subtrees fit their vertices; larger ones their children's boxes
  // (kids, or null).
  void Bound(Built& out, std::uint32_t begin, std::uint32_t end, const Built* kids) const
  {
    Child& c = out.child;
    // The axis-aligned box, from the exact bounds.
    const Box& bb = out.aabb;
    for (int a = 0; a < 3; ++a)
    {
      for (int k = 0; k < 3; ++k)
      {
        c.axis[a][k] = a == k ? 1.0f : 0.0f;
      }
    }
    const double cost = FitBox(c.axis,
      [&bb](const auto& f) {
        for (int i = 0; i < 8; ++i)
        {
          const double x[3] = { (i & 1) ? bb.hi[0] : bb.lo[0], (i & 2) ? bb.hi[1] : bb.lo[1],
            (i & 4) ? bb.hi[2] : bb.lo[2] };
          f(x);
        }
      },
      0.0, c.center, c.half);

    const double nn = std::sqrt(Dot3(out.normal, out.normal));
    if (!(nn > 0.0))
    {
      return;
    }
    const double w[3] = { out.normal[0] / nn, out.normal[1] / nn, out.normal[2] / nn };
    // u: the longest axis of the bounds that is not close to w, made orthogonal to w.
    int order3[3] = { 0, 1, 2 };
    std::sort(order3, order3 + 3, [&bb](int x, int y) {
      return double(bb.hi[x]) - bb.lo[x] > double(bb.hi[y]) - bb.lo[y];
    });
    const int k = std::abs(w[order3[0]]) > 0.9 ? order3[1] : order3[0];
    double u[3] = { -w[k] * w[0], -w[k] * w[1], -w[k] * w[2] };
    u[k] += 1.0;
    const double un = std::sqrt(Dot3(u, u));
    const double v[3] = { w[1] * u[2] - w[2] * u[1], w[2] * u[0] - w[0] * u[2],
      w[0] * u[1] - w[1] * u[0] };
    float axes[3][3];
    for (int i = 0; i < 3; ++i)
    {
      axes[0][i] = static_cast<float>(u[i] / un);
      axes[1][i] = static_cast<float>(v[i] / un);
      axes[2][i] = static_cast<float>(w[i]);
    }
    float center[3], half[3];
    double oriented;
    if (kids == nullptr)
    {
      oriented = FitBox(axes,
        [this, begin, end](const auto& f) {
          for (std::uint32_t i = begin; i < end; ++i)
          {
            const float* t = this->triangles + 9 * std::size_t(this->order[i]);
            for (int j = 0; j < 3; ++j)
            {
              const double x[3] = { t[3 * j], t[3 * j + 1], t[3 * j + 2] };
              f(x);
            }
          }
        },
        0.0, center, half);
    }
    else
    {
      double pad = 0.0; // covers the corner approximation of ForEachCorner
      for (int j = 0; j < 2; ++j)
      {
        const float* h = kids[j].child.half;
        pad = std::max(pad, 1e-6 * (double(h[0]) + h[1] + h[2]));
      }
      oriented = FitBox(axes,
        [kids](const auto& f) {
          ForEachCorner(kids[0].child, f);
          ForEachCorner(kids[1].child, f);
        },
        pad, center, half);
    }
    if (oriented < cost)
    {
      std::copy_n(center, 3, c.center);
      std::copy_n(half, 3, c.half);
      std::copy_n(&axes[0][0], 9, &c.axis[0][0]);
    }
  }

  // Builds order[begin, end) appending inner nodes to `nodes` (node indices relative to it).
  Built Build(std::uint32_t begin, std::uint32_t end, std::vector<Node>& nodes, int depth,
    int parallelDepth)
  {
    const std::uint32_t n = end - begin;
    if (n <= kLeafSize)
    {
      Built leaf;
      leaf.normal[0] = leaf.normal[1] = leaf.normal[2] = 0.0;
      for (std::uint32_t i = begin; i < end; ++i)
      {
        const std::uint32_t t = this->order[i];
        const float* b = this->boxes + 6 * std::size_t(t);
        leaf.aabb.Grow(b, b + 3);
        const float* x = this->triangles + 9 * std::size_t(t);
        const double ab[3] = { double(x[3]) - x[0], double(x[4]) - x[1], double(x[5]) - x[2] };
        const double ac[3] = { double(x[6]) - x[0], double(x[7]) - x[1], double(x[8]) - x[2] };
        leaf.normal[0] += ab[1] * ac[2] - ab[2] * ac[1];
        leaf.normal[1] += ab[2] * ac[0] - ab[0] * ac[2];
        leaf.normal[2] += ab[0] * ac[1] - ab[1] * ac[0];
      }
      leaf.child.ref = begin << 3 | n;
      this->Bound(leaf, begin, end, nullptr);
      return leaf;
    }
    const std::uint32_t mid = this->Split(begin, end, depth);

    const std::size_t self = nodes.size();
    nodes.emplace_back();
    Built kids[2];
    // The right subtree on another thread into its own node array, spliced after the left one:
    // the same layout as the serial build.
    std::vector<Node> rightNodes;
    std::exception_ptr failure;
    std::thread worker;
    if (parallelDepth > 0 && n >= kParallelMinimum)
    {
      try
      {
        worker = std::thread([&]() {
          try
          {
            kids[1] = this->Build(mid, end, rightNodes, depth + 1, parallelDepth - 1);
          }
          catch (...)
          {
            failure = std::current_exception();
          }
        });
      }
      catch (const std::system_error&)
      {
        // No thread available: build serially below.
      }
    }
    if (worker.joinable())
    {
      try
      {
        kids[0] = this->Build(begin, mid, nodes, depth + 1, parallelDepth - 1);
      }
      catch (...)
      {
        worker.join();
        throw;
      }
      worker.join();
      if (failure)
      {
        std::rethrow_exception(failure);
      }
      const auto offset = static_cast<std::uint32_t>(nodes.size());
      for (Node& node : rightNodes)
      {
        for (Child& c : node.child)
        {
          if ((c.ref & 7) == 0)
          {
            c.ref += offset << 3;
          }
        }
      }
      if ((kids[1].child.ref & 7) == 0)
      {
        kids[1].child.ref += offset << 3;
      }
      nodes.insert(nodes.end(), rightNodes.begin(), rightNodes.end());
    }
    else
    {
      kids[0] = this->Build(begin, mid, nodes, depth + 1, 0);
      kids[1] = this->Build(mid, end, nodes, depth + 1, 0);
    }
    nodes[self].child[0] = kids[0].child;
    nodes[self].child[1] = kids[1].child;

    Built inner;
    inner.child.ref = static_cast<std::uint32_t>(self) << 3;
    inner.aabb = kids[0].aabb;
    inner.aabb.Grow(kids[1].aabb);
    for (int k = 0; k < 3; ++k)
    {
      inner.normal[k] = kids[0].normal[k] + kids[1].normal[k];
    }
    this->Bound(inner, begin, end, n <= kExactFit ? nullptr : kids);
    return inner;
  }
};

MeshDistanceIndex::MeshDistanceIndex(const TriangleMesh& mesh, int threads)
{
  ValidateMesh(mesh, "MeshDistanceIndex", "the indexed");
  const std::size_t nt = mesh.NumberOfTriangles();
  if (nt >= (std::size_t(1) << 29))
  {
    throw std::invalid_argument("MeshDistanceIndex: the indexed mesh has " + std::to_string(nt) +
      " triangles; at most 2^29 - 1 are supported");
  }
  std::vector<float> triangles(9 * nt);
  std::vector<float> boxes(6 * nt);
  double scale = 0.0;
  for (std::size_t t = 0; t < nt; ++t)
  {
    // (the file's corner order here: the nodes' mean normals, the axes of their boxes, need the
    // triangles' orientation, which the canonical order below does not keep)
    Box box;
    for (int v = 0; v < 3; ++v)
    {
      const float* x = mesh.points.data() + 3 * std::size_t(mesh.triangles[3 * t + v]);
      std::copy_n(x, 3, triangles.data() + 9 * t + 3 * v);
      box.Grow(x, x);
    }
    std::copy_n(box.lo, 3, boxes.data() + 6 * t);
    std::copy_n(box.hi, 3, boxes.data() + 6 * t + 3);
    for (int k = 0; k < 3; ++k)
    {
      scale = std::max(scale, std::max(std::abs(double(box.lo[k])), std::abs(double(box.hi[k]))));
    }
  }
  this->Scale = scale;

  std::vector<std::uint32_t> order(nt);
  for (std::size_t t = 0; t < nt; ++t)
  {
    order[t] = static_cast<std::uint32_t>(t);
  }
  int depth = 0;
  for (int t = ResolveThreads(threads); t > 1; t = (t + 1) / 2)
  {
    ++depth;
  }
  Builder builder{ triangles.data(), boxes.data(), order.data() };
  this->Nodes.reserve(nt / 2 + 1);
  this->Root = builder.Build(0, static_cast<std::uint32_t>(nt), this->Nodes, 0, depth).child;
  boxes = std::vector<float>();

  this->Triangles.resize(9 * nt);
  this->Degenerate.resize(nt);
  for (std::size_t i = 0; i < nt; ++i)
  {
    // The corners in canonical order (as Corners orders them), as PointTriangleDistanceSquared
    // takes them.
    const float* src = triangles.data() + 9 * std::size_t(order[i]);
    const float* v[3] = { src, src + 3, src + 6 };
    SortThree(v);
    float* dst = this->Triangles.data() + 9 * i;
    for (int k = 0; k < 3; ++k)
    {
      std::copy_n(v[k], 3, dst + 3 * k);
    }
    this->Degenerate[i] = NearlyDegenerate(At(dst), At(dst + 3), At(dst + 6)) ? 1 : 0;
  }
  this->Original = std::move(order);
  this->Position.resize(nt);
  for (std::size_t i = 0; i < nt; ++i)
  {
    this->Position[this->Original[i]] = static_cast<std::uint32_t>(i);
  }
}

MeshDistanceIndex::Hit MeshDistanceIndex::Nearest(const double p[3], std::uint32_t hint) const
{
  // A box is pruned only when its (shrunk) distance exceeds the best distance by delta, far more
  // than the rounding of the distance computations (a few ulps of the coordinates): a pruned
  // triangle can then never have a computed distance below the returned one, so the result
  // equals the brute-force minimum bit for bit.
  const double pmax = std::max(std::abs(p[0]), std::max(std::abs(p[1]), std::abs(p[2])));
  const double delta = 1e-12 * (this->Scale + pmax);
  const Vec3 point = At(p);

  Hit best;
  best.distanceSquared = std::numeric_limits<double>::infinity();
  best.triangle = kNoHint;
  double bound2 = std::numeric_limits<double>::infinity();
  const float* tris = this->Triangles.data();
  const std::uint8_t* degenerate = this->Degenerate.data();
  auto consider = [&](std::uint32_t position) {
    const double d2 = TriangleDistance2(point, tris + 9 * std::size_t(position), degenerate[position]);
    if (d2 < best.distanceSquared)
    {
      best.distanceSquared = d2;
      best.triangle = this->Original[position];
      const double r = std::sqrt(d2) + delta;
      bound2 = r * r;
    }
  };
  if (hint != kNoHint && hint < this->Position.size())
  {
    consider(this->Position[hint]);
  }

  auto boxDistance2 = [p](const Child& c) {
    const double q[3] = { p[0] - c.center[0], p[1] - c.center[1], p[2] - c.center[2] };
    double d2 = 0.0;
    for (int a = 0; a < 3; ++a)
    {
      const double s = q[0] * c.axis[a][0] + q[1] * c.axis[a][1] + q[2] * c.axis[a][2];
      const double e = std::max(std::abs(s) - double(c.half[a]), 0.0);
      d2 += e * e;
    }
    return d2 * kBoundShrink;
  };

  struct Entry
  {
    const Child* child;
    double d2;
  };
  Entry stack[128]; // at most depth + 1 entries; depth <= kSahDepth + 32
  int top = 0;
  stack[top++] = Entry{ &this->Root, boxDistance2(this->Root) };
  while (top > 0)
  {
    const Entry e = stack[--top];
    if (e.d2 > bound2)
    {
      continue;
    }
    const std::uint32_t ref = e.child->ref;
    if ((ref & 7) != 0)
    {
      const std::uint32_t first = ref >> 3, count = ref & 7;
      for (std::uint32_t i = 0; i < count; ++i)
      {
        consider(first + i);
      }
      continue;
    }
    const Node& node = this->Nodes[ref >> 3];
    const double d0 = boxDistance2(node.child[0]);
    const double d1 = boxDistance2(node.child[1]);
    // Push the farther child first so the nearer one is searched first.
    const int nearer = d1 < d0 ? 1 : 0;
    const double dn = nearer ? d1 : d0, df = nearer ? d0 : d1;
    if (df <= bound2)
    {
      stack[top++] = Entry{ &node.child[1 - nearer], df };
    }
    if (dn <= bound2)
    {
      stack[top++] = Entry{ &node.child[nearer], dn };
    }
  }
  return best;
}

// -----------------------------------------------------------------------------------------------

OneSided SampleDistance(const TriangleMesh& from, const TriangleMesh& to, std::uint64_t samples,
  std::uint64_t seed, int threads)
{
  ValidateMesh(from, "SampleDistance", "the 'from'");
  ValidateMesh(to, "SampleDistance", "the 'to'");
  const AreaTable table = BuildAreaTable(from, threads);
  if (!(table.total > 0.0))
  {
    throw std::invalid_argument(
      "SampleDistance: the 'from' mesh has zero total area; it cannot be sampled");
  }
  if (samples == 0)
  {
    return OneSided{};
  }
  const MeshDistanceIndex index(to, threads);
  return Sample(from, table, index, samples, seed, 0, threads).ToOneSided();
}

CompareResult CompareMeshes(
  const TriangleMesh& reference, const TriangleMesh& candidate, const CompareOptions& options)
{
  ValidateMesh(reference, "CompareMeshes", "the reference");
  ValidateMesh(candidate, "CompareMeshes", "the candidate");
  const AreaTable refTable = BuildAreaTable(reference, options.threads);
  if (!(refTable.total > 0.0))
  {
    throw std::invalid_argument(
      "CompareMeshes: the reference mesh has zero total area (all triangles degenerate)");
  }
  const AreaTable candTable = BuildAreaTable(candidate, options.threads);
  if (!(candTable.total > 0.0))
  {
    throw std::invalid_argument(
      "CompareMeshes: the candidate mesh has zero total area (all triangles degenerate)");
  }

  std::uint64_t samples = options.samples;
  if (samples == 0)
  {
    const std::uint64_t larger = std::max<std::uint64_t>(
      reference.NumberOfTriangles(), candidate.NumberOfTriangles());
    samples = std::min<std::uint64_t>(std::max<std::uint64_t>(100000, 2 * larger), 2000000);
  }

  const std::vector<std::array<std::size_t, 2>>& groups = options.attributeGroups;
  for (const auto& g : groups)
  {
    for (const TriangleMesh* m : { &reference, &candidate })
    {
      if (g[0] + g[1] > m->attributeStride ||
        m->attributes.size() != m->attributeStride * m->NumberOfPoints())
      {
        throw std::invalid_argument(std::string("CompareMeshes: the ") +
          (m == &reference ? "reference" : "candidate") +
          " mesh lacks the attribute values the comparison asks for");
      }
    }
  }
  Sums forward, backward;
  {
    const MeshDistanceIndex candIndex(candidate, options.threads);
    forward = Sample(reference, refTable, candIndex, samples, options.seed, 0, options.threads,
      &candidate, groups);
  }
  {
    const MeshDistanceIndex refIndex(reference, options.threads);
    backward = Sample(candidate, candTable, refIndex, samples, options.seed, 1, options.threads,
      &reference, groups);
  }

  CompareResult r;
  r.diagonal = Diagonal(reference.Bounds());
  r.samples = samples;
  // Pooled over the samples of both sides (the same number on each).
  const double n = 2.0 * static_cast<double>(samples);
  r.meanAbsolute = (forward.sum + backward.sum) / n;
  r.rmsAbsolute = std::sqrt((forward.sumSq + backward.sumSq) / n);
  r.hausdorffAbsolute = std::max(forward.max, backward.max);
  r.mean = r.meanAbsolute / r.diagonal;
  r.rms = r.rmsAbsolute / r.diagonal;
  r.hausdorff = r.hausdorffAbsolute / r.diagonal;
  r.forwardRms = forward.ToOneSided().rms / r.diagonal;
  r.backwardRms = backward.ToOneSided().rms / r.diagonal;
  for (std::size_t g = 0; g < groups.size(); ++g)
  {
    r.attributeRms.push_back(std::sqrt((forward.attrSumSq[g] + backward.attrSumSq[g]) / n));
    r.attributeMax.push_back(std::max(forward.attrMax[g], backward.attrMax[g]));
  }
  return r;
}

} // namespace sipmss::algorithms
