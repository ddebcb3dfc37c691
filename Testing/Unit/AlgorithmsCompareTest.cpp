// Tests for the Metro-style mesh comparison (sipmss/algorithms/Compare.h).
#include "sipmss/algorithms/Compare.h"

#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <map>
#include <random>
#include <stdexcept>
#include <utility>
#include <vector>

namespace
{
using namespace sipmss::algorithms;

double Dist2(const double p[3], const double a[3], const double b[3], const double c[3])
{
  return PointTriangleDistanceSquared(p, a, b, c);
}

// ---------------------------------------------------------------------------------------------
// Mesh builders

// The unit square [0,1]^2 at height z, as two triangles.
TriangleMesh Square(float z)
{
  TriangleMesh m;
  m.points = { 0, 0, z, 1, 0, z, 1, 1, z, 0, 1, z };
  m.triangles = { 0, 1, 2, 0, 2, 3 };
  return m;
}

// An icosphere of the given radius (vertices on the sphere, then rounded to float).
TriangleMesh Icosphere(int subdivisions, double radius)
{
  const double t = (1.0 + std::sqrt(5.0)) / 2.0;
  std::vector<std::array<double, 3>> v = { { -1, t, 0 }, { 1, t, 0 }, { -1, -t, 0 },
    { 1, -t, 0 }, { 0, -1, t }, { 0, 1, t }, { 0, -1, -t }, { 0, 1, -t }, { t, 0, -1 },
    { t, 0, 1 }, { -t, 0, -1 }, { -t, 0, 1 } };
  std::vector<std::array<std::uint32_t, 3>> f = { { 0, 11, 5 }, { 0, 5, 1 }, { 0, 1, 7 },
    { 0, 7, 10 }, { 0, 10, 11 }, { 1, 5, 9 }, { 5, 11, 4 }, { 11, 10, 2 }, { 10, 7, 6 },
    { 7, 1, 8 }, { 3, 9, 4 }, { 3, 4, 2 }, { 3, 2, 6 }, { 3, 6, 8 }, { 3, 8, 9 }, { 4, 9, 5 },
    { 2, 4, 11 }, { 6, 2, 10 }, { 8, 6, 7 }, { 9, 8, 1 } };
  for (int s = 0; s < subdivisions; ++s)
  {
    std::map<std::pair<std::uint32_t, std::uint32_t>, std::uint32_t> mids;
    auto mid = [&](std::uint32_t a, std::uint32_t b) {
      const auto key = std::make_pair(std::min(a, b), std::max(a, b));
      auto it = mids.find(key);
      if (it != mids.end())
      {
        return it->second;
      }
      v.push_back({ (v[a][0] + v[b][0]) / 2, (v[a][1] + v[b][1]) / 2, (v[a][2] + v[b][2]) / 2 });
      const auto id = static_cast<std::uint32_t>(v.size() - 1);
      mids[key] = id;
      return id;
    };
    std::vector<std::array<std::uint32_t, 3>> g;
    for (const auto& tri : f)
    {
      const std::uint32_t ab = mid(tri[0], tri[1]), bc = mid(tri[1], tri[2]),
                          ca = mid(tri[2], tri[0]);
      g.push_back({ tri[0], ab, ca });
      g.push_back({ tri[1], bc, ab });
      g.push_back({ tri[2], ca, bc });
      g.push_back({ ab, bc, ca });
    }
    f.swap(g);
  }
  TriangleMesh m;
  for (const auto& p : v)
  {
    const double n = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    for (int k = 0; k < 3; ++k)
    {
      m.points.push_back(static_cast<float>(p[k] / n * radius));
    }
  }
  for (const auto& tri : f)
  {
    m.triangles.insert(m.triangles.end(), tri.begin(), tri.end());
  }
  return m;
}

TriangleMesh Scaled(const TriangleMesh& m, double s)
{
  TriangleMesh r = m;
  for (float& x : r.points)
  {
    x = static_cast<float>(x * s);
  }
  return r;
}

// Random triangles of mixed sizes in [0,1]^3, a few of them degenerate.
TriangleMesh RandomSoup(std::size_t count, std::uint32_t seed)
{
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> unit(0.0f, 1.0f);
  TriangleMesh m;
  for (std::size_t i = 0; i < count; ++i)
  {
    const float size = (i % 7 == 0) ? 0.3f : 0.03f;
    const float cx = unit(rng), cy = unit(rng), cz = unit(rng);
    float p[9];
    for (int k = 0; k < 9; ++k)
    {
      p[k] = (k % 3 == 0 ? cx : (k % 3 == 1 ? cy : cz)) + size * (unit(rng) - 0.5f);
    }
    if (i % 11 == 0) // collinear
    {
      for (int k = 0; k < 3; ++k)
      {
        p[6 + k] = p[k] + 2.0f * (p[3 + k] - p[k]);
      }
    }
    if (i % 13 == 0) // a point
    {
      for (int k = 0; k < 3; ++k)
      {
        p[3 + k] = p[6 + k] = p[k];
      }
    }
    const auto base = static_cast<std::uint32_t>(m.points.size() / 3);
    m.points.insert(m.points.end(), p, p + 9);
    m.triangles.insert(m.triangles.end(), { base, base + 1, base + 2 });
  }
  return m;
}

double BruteForce(const TriangleMesh& m, const double p[3])
{
  double best = std::numeric_limits<double>::infinity();
  for (std::size_t t = 0; t < m.NumberOfTriangles(); ++t)
  {
    double v[3][3];
    for (int j = 0; j < 3; ++j)
    {
      for (int k = 0; k < 3; ++k)
      {
        v[j][k] = m.points[3 * std::size_t(m.triangles[3 * t + j]) + k];
      }
    }
    best = std::min(best, Dist2(p, v[0], v[1], v[2]));
  }
  return best;
}

double Diagonal(const TriangleMesh& m)
{
  const auto b = m.Bounds();
  return std::sqrt((b[1] - b[0]) * (b[1] - b[0]) + (b[3] - b[2]) * (b[3] - b[2]) +
    (b[5] - b[4]) * (b[5] - b[4]));
}

// ---------------------------------------------------------------------------------------------
// PointTriangleDistanceSquared

const double A[3] = { 0, 0, 0 }, B[3] = { 1, 0, 0 }, C[3] = { 0, 1, 0 };

TEST(AlgorithmsCompare, PointTriangleFaceInterior)
{
  const double p1[3] = { 0.25, 0.25, 2 };
  EXPECT_DOUBLE_EQ(Dist2(p1, A, B, C), 4.0);
  const double p2[3] = { 0.2, 0.3, -0.5 };
  EXPECT_DOUBLE_EQ(Dist2(p2, A, B, C), 0.25);
  // A tilted triangle: the plane x + y + z = 1, point (1,1,1) is 2/sqrt(3) above it over the
  // centroid.
  const double a[3] = { 1, 0, 0 }, b[3] = { 0, 1, 0 }, c[3] = { 0, 0, 1 };
  const double p3[3] = { 1, 1, 1 };
  EXPECT_NEAR(Dist2(p3, a, b, c), 4.0 / 3.0, 1e-15);
}

TEST(AlgorithmsCompare, PointTriangleBeyondVertices)
{
  const double pa1[3] = { -1, -1, 0 }, pa2[3] = { -1, -2, 3 };
  EXPECT_DOUBLE_EQ(Dist2(pa1, A, B, C), 2.0);
  EXPECT_DOUBLE_EQ(Dist2(pa2, A, B, C), 14.0);
  const double pb[3] = { 2, -1, 1 };
  EXPECT_DOUBLE_EQ(Dist2(pb, A, B, C), 3.0);
  const double pc[3] = { -1, 3, 0 };
  EXPECT_DOUBLE_EQ(Dist2(pc, A, B, C), 5.0);
  const double pc2[3] = { -0.5, 2, -2 };
  EXPECT_DOUBLE_EQ(Dist2(pc2, A, B, C), 0.25 + 1 + 4);
}

TEST(AlgorithmsCompare, PointTriangleBeyondEdges)
{
  const double pab[3] = { 0.5, -2, 1 }; // closest (0.5, 0, 0)
  EXPECT_DOUBLE_EQ(Dist2(pab, A, B, C), 5.0);
  const double pac[3] = { -3, 0.5, 0 }; // closest (0, 0.5, 0)
  EXPECT_DOUBLE_EQ(Dist2(pac, A, B, C), 9.0);
  const double pbc[3] = { 1, 1, 0 }; // closest (0.5, 0.5, 0)
  EXPECT_DOUBLE_EQ(Dist2(pbc, A, B, C), 0.5);
  const double pbc2[3] = { 1, 1, 2 };
  EXPECT_DOUBLE_EQ(Dist2(pbc2, A, B, C), 4.5);
  const double pbc3[3] = { 1.2, 0.8, -1 }; // closest (0.7, 0.3, 0)
  EXPECT_NEAR(Dist2(pbc3, A, B, C), 0.25 + 0.25 + 1, 1e-15);
}

TEST(AlgorithmsCompare, PointTriangleInPlane)
{
  const double inside[3] = { 0.1, 0.2, 0 };
  EXPECT_EQ(Dist2(inside, A, B, C), 0.0);
  EXPECT_EQ(Dist2(A, A, B, C), 0.0);
  EXPECT_EQ(Dist2(B, A, B, C), 0.0);
  EXPECT_EQ(Dist2(C, A, B, C), 0.0);
  const double onEdge[3] = { 0.5, 0.5, 0 };
  EXPECT_NEAR(Dist2(onEdge, A, B, C), 0.0, 1e-30);
  const double outside[3] = { 0.5, -0.25, 0 };
  EXPECT_DOUBLE_EQ(Dist2(outside, A, B, C), 0.0625);
}

TEST(AlgorithmsCompare, PointTriangleVertexOrderDoesNotMatter)
{
  std::mt19937 rng(7);
  std::uniform_real_distribution<double> u(-2, 2);
  for (int i = 0; i < 1000; ++i)
  {
    double a[3], b[3], c[3], p[3];
    for (int k = 0; k < 3; ++k)
    {
      a[k] = u(rng), b[k] = u(rng), c[k] = u(rng), p[k] = u(rng);
    }
    const double d = Dist2(p, a, b, c);
    EXPECT_EQ(Dist2(p, b, c, a), d); // (the corners are ordered first: bit for bit)
    EXPECT_EQ(Dist2(p, c, b, a), d);
    EXPECT_EQ(Dist2(p, a, c, b), d);
  }
}

TEST(AlgorithmsCompare, PointTriangleDegenerate)
{
  // Collinear, c beyond b.
  const double a[3] = { 0, 0, 0 }, b[3] = { 1, 0, 0 }, c[3] = { 2, 0, 0 };
  const double p1[3] = { 1, 1, 0 }, p2[3] = { 3, 0, 0 }, p3[3] = { -1, 0, 2 },
               p4[3] = { 1.5, 0, 0 };
  EXPECT_DOUBLE_EQ(Dist2(p1, a, b, c), 1.0);
  EXPECT_DOUBLE_EQ(Dist2(p2, a, b, c), 1.0);
  EXPECT_DOUBLE_EQ(Dist2(p3, a, b, c), 5.0);
  EXPECT_EQ(Dist2(p4, a, b, c), 0.0);
  // Collinear, c between a and b.
  const double b2[3] = { 2, 0, 0 }, c2[3] = { 1, 0, 0 };
  const double p5[3] = { 1.5, 0, 3 };
  EXPECT_DOUBLE_EQ(Dist2(p5, a, b2, c2), 9.0);
  // Two coincident vertices: a segment.
  const double s0[3] = { 0, 0, 0 }, s1[3] = { 0, 0, 2 };
  const double p6[3] = { 1, 0, 1 }, p7[3] = { 0, 1, 3 };
  EXPECT_DOUBLE_EQ(Dist2(p6, s0, s0, s1), 1.0);
  EXPECT_DOUBLE_EQ(Dist2(p7, s0, s1, s0), 2.0);
  // A point.
  const double q[3] = { 1, 2, 3 };
  const double p8[3] = { 1, 2, 5 }, p9[3] = { 0, 0, 0 };
  EXPECT_DOUBLE_EQ(Dist2(p8, q, q, q), 4.0);
  EXPECT_DOUBLE_EQ(Dist2(p9, q, q, q), 14.0);
  // A sliver 1e-12 wide behaves like its long edge.
  const double sl[3] = { 0.5, 1e-12, 0 };
  const double p10[3] = { 0.5, 0, 1 };
  EXPECT_NEAR(Dist2(p10, a, b2, sl), 1.0, 1e-11);
  for (const double* p : { p1, p2, p3, p5, p6, p8 })
  {
    EXPECT_TRUE(std::isfinite(Dist2(p, a, b, c)));
  }
}

// An independent formulation: projection onto the plane when it falls inside (barycentric
// coordinates by Cramer's rule), otherwise the nearest of the three edges.
double ReferenceDistance2(
  const double p[3], const double a[3], const double b[3], const double c[3])
{
  auto seg = [](const double x[3], const double s[3], const double e[3]) {
    double d[3], w[3];
    for (int k = 0; k < 3; ++k)
    {
      d[k] = e[k] - s[k];
      w[k] = x[k] - s[k];
    }
    const double dd = d[0] * d[0] + d[1] * d[1] + d[2] * d[2];
    double t = dd > 0 ? (w[0] * d[0] + w[1] * d[1] + w[2] * d[2]) / dd : 0.0;
    t = std::clamp(t, 0.0, 1.0);
    double r = 0;
    for (int k = 0; k < 3; ++k)
    {
      r += (w[k] - t * d[k]) * (w[k] - t * d[k]);
    }
    return r;
  };
  double e0[3], e1[3], v[3];
  for (int k = 0; k < 3; ++k)
  {
    e0[k] = b[k] - a[k];
    e1[k] = c[k] - a[k];
    v[k] = p[k] - a[k];
  }
  const double d00 = e0[0] * e0[0] + e0[1] * e0[1] + e0[2] * e0[2];
  const double d01 = e0[0] * e1[0] + e0[1] * e1[1] + e0[2] * e1[2];
  const double d11 = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2];
  const double d20 = v[0] * e0[0] + v[1] * e0[1] + v[2] * e0[2];
  const double d21 = v[0] * e1[0] + v[1] * e1[1] + v[2] * e1[2];
  const double den = d00 * d11 - d01 * d01;
  double best = std::min(seg(p, a, b), std::min(seg(p, b, c), seg(p, c, a)));
  if (den > 1e-12 * d00 * d11)
  {
    const double s = (d11 * d20 - d01 * d21) / den;
    const double t = (d00 * d21 - d01 * d20) / den;
    if (s >= 0 && t >= 0 && s + t <= 1)
    {
      double r = 0;
      for (int k = 0; k < 3; ++k)
      {
        const double q = a[k] + s * e0[k] + t * e1[k];
        r += (p[k] - q) * (p[k] - q);
      }
      best = std::min(best, r);
    }
  }
  return best;
}

TEST(AlgorithmsCompare, PointTriangleRandomCrossCheck)
{
  std::mt19937 rng(12345);
  std::uniform_real_distribution<double> u(-1, 1);
  const int n = 150; // dense barycentric grid
  for (int trial = 0; trial < 200; ++trial)
  {
    double a[3], b[3], c[3], p[3];
    for (int k = 0; k < 3; ++k)
    {
      a[k] = u(rng), b[k] = u(rng), c[k] = u(rng), p[k] = 2 * u(rng);
    }
    const double exact = Dist2(p, a, b, c);
    EXPECT_NEAR(exact, ReferenceDistance2(p, a, b, c), 1e-12);

    // Dense sampling approximates from above; the grid leaves no triangle point farther than
    // (longest edge / n) from a grid point.
    double approx = std::numeric_limits<double>::infinity();
    for (int i = 0; i <= n; ++i)
    {
      for (int j = 0; i + j <= n; ++j)
      {
        const double s = double(i) / n, t = double(j) / n;
        double r = 0;
        for (int k = 0; k < 3; ++k)
        {
          const double q = a[k] + s * (b[k] - a[k]) + t * (c[k] - a[k]);
          r += (p[k] - q) * (p[k] - q);
        }
        approx = std::min(approx, r);
      }
    }
    double longest = 0;
    for (const auto& e : { std::make_pair(a, b), std::make_pair(b, c), std::make_pair(c, a) })
    {
      double l = 0;
      for (int k = 0; k < 3; ++k)
      {
        l += (e.first[k] - e.second[k]) * (e.first[k] - e.second[k]);
      }
      longest = std::max(longest, std::sqrt(l));
    }
    EXPECT_LE(exact, approx + 1e-12);
    EXPECT_LE(std::sqrt(approx), std::sqrt(exact) + longest / n + 1e-12);
  }
}

// ---------------------------------------------------------------------------------------------
// MeshDistanceIndex

TEST(AlgorithmsCompare, IndexNearestMatchesBruteForceOnSoup)
{
  const TriangleMesh soup = RandomSoup(3000, 99);
  const MeshDistanceIndex index(soup);
  EXPECT_EQ(index.NumberOfTriangles(), soup.NumberOfTriangles());
  std::mt19937 rng(5);
  std::uniform_real_distribution<double> u(-0.5, 1.5);
  std::uniform_int_distribution<std::uint32_t> tri(0, 2999);
  for (int i = 0; i < 1500; ++i)
  {
    double p[3];
    if (i % 5 == 0) // exactly on a triangle vertex
    {
      const std::uint32_t t = tri(rng);
      for (int k = 0; k < 3; ++k)
      {
        p[k] = soup.points[3 * std::size_t(soup.triangles[3 * t]) + k];
      }
    }
    else
    {
      for (double& x : p)
      {
        x = u(rng);
      }
    }
    const double brute = BruteForce(soup, p);
    const MeshDistanceIndex::Hit hit = index.Nearest(p);
    ASSERT_EQ(hit.distanceSquared, brute) << "query " << i;
    // The hint never changes the answer.
    ASSERT_EQ(index.Nearest(p, tri(rng)).distanceSquared, brute) << "query " << i;
    // The reported triangle is at that distance.
    double v[3][3];
    for (int j = 0; j < 3; ++j)
    {
      for (int k = 0; k < 3; ++k)
      {
        v[j][k] = soup.points[3 * std::size_t(soup.triangles[3 * hit.triangle + j]) + k];
      }
    }
    ASSERT_EQ(Dist2(p, v[0], v[1], v[2]), brute);
  }
}

TEST(AlgorithmsCompare, IndexNearestMatchesBruteForceNearASurface)
{
  const TriangleMesh sphere = Icosphere(4, 1.0); // 5120 triangles
  const MeshDistanceIndex serial(sphere, 1);
  const MeshDistanceIndex parallel(sphere, 2);
  EXPECT_EQ(serial.NumberOfNodes(), parallel.NumberOfNodes());
  std::mt19937 rng(11);
  std::normal_distribution<double> g(0, 1);
  std::uniform_real_distribution<double> r(0.9, 1.1);
  for (int i = 0; i < 600; ++i)
  {
    double p[3] = { g(rng), g(rng), g(rng) };
    const double len = std::sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    const double radius = i % 50 == 0 ? 0.05 : r(rng); // a few deep inside
    for (double& x : p)
    {
      x *= radius / len;
    }
    const double brute = BruteForce(sphere, p);
    const MeshDistanceIndex::Hit a = serial.Nearest(p);
    const MeshDistanceIndex::Hit b = parallel.Nearest(p);
    ASSERT_EQ(a.distanceSquared, brute);
    ASSERT_EQ(b.distanceSquared, brute);
    EXPECT_EQ(a.triangle, b.triangle);
  }
}

TEST(AlgorithmsCompare, IndexNearestMatchesBruteForceFarFromOriginAndTilted)
{
  // Georeferenced-style coordinates (small triangles 1e5 away from the origin) and a tilted,
  // wavy height field, queried near and far: the oriented boxes must stay conservative.
  TriangleMesh far = RandomSoup(1500, 17);
  for (std::size_t i = 0; i < far.points.size(); ++i)
  {
    far.points[i] += (i % 3 == 0) ? 1e5f : (i % 3 == 1 ? -2e4f : 3e3f);
  }
  TriangleMesh field;
  const int g = 40;
  for (int i = 0; i <= g; ++i)
  {
    for (int j = 0; j <= g; ++j)
    {
      const double x = double(i) / g, y = double(j) / g;
      const double z = 0.05 * std::sin(6 * x) * std::cos(4 * y);
      field.points.insert(field.points.end(), { static_cast<float>(0.6 * x - 0.8 * z + 0.3 * y),
                                                static_cast<float>(y),
                                                static_cast<float>(0.8 * x + 0.6 * z) });
    }
  }
  for (int i = 0; i < g; ++i)
  {
    for (int j = 0; j < g; ++j)
    {
      const auto a = static_cast<std::uint32_t>(i * (g + 1) + j);
      const std::uint32_t b = a + 1, c = a + g + 1, d = c + 1;
      field.triangles.insert(field.triangles.end(), { a, b, d, a, d, c });
    }
  }
  std::mt19937 rng(23);
  std::uniform_real_distribution<double> u(-1.0, 2.0);
  for (const TriangleMesh* mesh : { &far, &field })
  {
    const MeshDistanceIndex index(*mesh, 2);
    const auto b = mesh->Bounds();
    for (int q = 0; q < 400; ++q)
    {
      double p[3];
      for (int k = 0; k < 3; ++k)
      {
        p[k] = b[2 * k] + u(rng) * (b[2 * k + 1] - b[2 * k]);
      }
      ASSERT_EQ(index.Nearest(p).distanceSquared, BruteForce(*mesh, p)) << "query " << q;
    }
  }
}

TEST(AlgorithmsCompare, IndexSingleAndDegenerateTriangles)
{
  TriangleMesh one;
  one.points = { 0, 0, 0, 1, 0, 0, 0, 1, 0 };
  one.triangles = { 0, 1, 2 };
  const MeshDistanceIndex index(one);
  const double p[3] = { 0.25, 0.25, 3 };
  EXPECT_DOUBLE_EQ(index.Nearest(p).distanceSquared, 9.0);
  EXPECT_EQ(index.Nearest(p).triangle, 0u);

  TriangleMesh segment; // only a zero-area triangle
  segment.points = { 0, 0, 1, 1, 0, 1, 2, 0, 1 };
  segment.triangles = { 0, 1, 2 };
  const MeshDistanceIndex seg(segment);
  const double q[3] = { 1.5, 2, 1 };
  EXPECT_DOUBLE_EQ(seg.Nearest(q).distanceSquared, 4.0);
}

// ---------------------------------------------------------------------------------------------
// CompareMeshes / SampleDistance

TEST(AlgorithmsCompare, IdenticalMeshesAreZero)
{
  const TriangleMesh sphere = Icosphere(3, 2.0);
  CompareOptions options;
  options.samples = 20000;
  const CompareResult r = CompareMeshes(sphere, sphere, options);
  // Sample points are computed in double from float vertices; their distance to their own
  // triangle is rounding (~1e-16), not an exact zero.
  EXPECT_NEAR(r.mean, 0.0, 1e-12);
  EXPECT_NEAR(r.rms, 0.0, 1e-12);
  EXPECT_NEAR(r.hausdorff, 0.0, 1e-12);
  EXPECT_NEAR(r.hausdorffAbsolute, 0.0, 1e-12);
  EXPECT_NEAR(r.forwardRms, 0.0, 1e-12);
  EXPECT_NEAR(r.backwardRms, 0.0, 1e-12);
  EXPECT_EQ(r.samples, 20000u);
  EXPECT_DOUBLE_EQ(r.diagonal, Diagonal(sphere));
  EXPECT_GT(r.diagonal, 6.0); // the bounding box of a radius-2 sphere, nearly 4 x 4 x 4

  // The same surface with the triangles listed in another order and orientation.
  TriangleMesh shuffled = sphere;
  std::mt19937 rng(3);
  std::vector<std::array<std::uint32_t, 3>> tris;
  for (std::size_t t = 0; t < sphere.NumberOfTriangles(); ++t)
  {
    tris.push_back({ sphere.triangles[3 * t + 2], sphere.triangles[3 * t + 1],
      sphere.triangles[3 * t] });
  }
  std::shuffle(tris.begin(), tris.end(), rng);
  shuffled.triangles.clear();
  for (const auto& t : tris)
  {
    shuffled.triangles.insert(shuffled.triangles.end(), t.begin(), t.end());
  }
  const CompareResult s = CompareMeshes(sphere, shuffled, options);
  EXPECT_NEAR(s.hausdorff, 0.0, 1e-12);
}

TEST(AlgorithmsCompare, OffsetSquareIsExactlyTheOffset)
{
  const TriangleMesh reference = Square(0.0f);
  const TriangleMesh candidate = Square(0.1f);
  CompareOptions options;
  options.samples = 10000;
  const CompareResult r = CompareMeshes(reference, candidate, options);
  const double offset = static_cast<double>(0.1f); // the float coordinate actually stored
  const double diag = std::sqrt(2.0);
  EXPECT_DOUBLE_EQ(r.diagonal, diag);
  EXPECT_NEAR(r.mean, offset / diag, 1e-9);
  EXPECT_NEAR(r.rms, offset / diag, 1e-9);
  EXPECT_NEAR(r.hausdorff, offset / diag, 1e-9);
  EXPECT_NEAR(r.forwardRms, offset / diag, 1e-9);
  EXPECT_NEAR(r.backwardRms, offset / diag, 1e-9);
  EXPECT_NEAR(r.meanAbsolute, offset, 1e-12);
  EXPECT_NEAR(r.rmsAbsolute, offset, 1e-12);
  EXPECT_NEAR(r.hausdorffAbsolute, offset, 1e-12);
  EXPECT_EQ(r.samples, 10000u);
}

TEST(AlgorithmsCompare, ScaledSphereWithinAnalyticBounds)
{
  // For a convex polyhedron P containing the origin and s > 1, every point of either surface is
  // between (s-1)*r_in and (s-1)*R from the other surface (r_in: the smallest distance from the
  // origin to a face plane, R: the largest vertex norm). The float rounding of the scaled copy
  // moves vertices by ~1e-7.
  const TriangleMesh reference = Icosphere(3, 1.0);
  const double s = 1.05;
  const TriangleMesh candidate = Scaled(reference, s);
  double rin = std::numeric_limits<double>::infinity(), R = 0;
  for (std::size_t t = 0; t < reference.NumberOfTriangles(); ++t)
  {
    double v[3][3];
    for (int j = 0; j < 3; ++j)
    {
      for (int k = 0; k < 3; ++k)
      {
        v[j][k] = reference.points[3 * std::size_t(reference.triangles[3 * t + j]) + k];
      }
      R = std::max(R, std::sqrt(v[j][0] * v[j][0] + v[j][1] * v[j][1] + v[j][2] * v[j][2]));
    }
    const double origin[3] = { 0, 0, 0 };
    rin = std::min(rin, std::sqrt(Dist2(origin, v[0], v[1], v[2])));
  }
  ASSERT_GT(rin, 0.98); // subdivision 3: the faces are close to the sphere

  CompareOptions options;
  options.samples = 50000;
  const CompareResult r = CompareMeshes(reference, candidate, options);
  const double lo = (s - 1) * rin - 1e-6, hi = (s - 1) * R + 1e-6;
  const double diag = Diagonal(reference);
  EXPECT_GE(r.meanAbsolute, lo);
  EXPECT_LE(r.meanAbsolute, r.rmsAbsolute);
  EXPECT_LE(r.rmsAbsolute, r.hausdorffAbsolute);
  EXPECT_LE(r.hausdorffAbsolute, hi);
  EXPECT_NEAR(r.mean, r.meanAbsolute / diag, 1e-15);
  EXPECT_NEAR(r.hausdorff, r.hausdorffAbsolute / diag, 1e-15);
  EXPECT_GE(r.forwardRms * diag, lo);
  EXPECT_LE(r.forwardRms * diag, hi);
  EXPECT_GE(r.backwardRms * diag, lo);
  EXPECT_LE(r.backwardRms * diag, hi);

  const OneSided forward = SampleDistance(reference, candidate, 50000, 1, 2);
  EXPECT_GE(forward.mean, lo);
  EXPECT_LE(forward.max, hi);
  EXPECT_EQ(forward.samples, 50000u);
  // CompareMeshes' forward half is SampleDistance with the same seed.
  EXPECT_DOUBLE_EQ(forward.rms / diag, r.forwardRms);
}

TEST(AlgorithmsCompare, SamplingIsAreaUniform)
{
  // The unit square split into four triangles of unequal area (a fan around (0.2, 0.7)),
  // measured against the single point (0, 0, 1) (a zero-area triangle). For uniform points:
  // E[d^2] = E[x^2 + y^2 + 1] = 5/3, E[d] by quadrature, max d = sqrt(3) at (1, 1).
  TriangleMesh from;
  from.points = { 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 0.2f, 0.7f, 0 };
  from.triangles = { 0, 1, 4, 1, 2, 4, 2, 3, 4, 3, 0, 4 };
  TriangleMesh to;
  to.points = { 0, 0, 1 };
  to.triangles = { 0, 0, 0 };
  const OneSided d = SampleDistance(from, to, 1000000, 42, 2);
  double expectedMean = 0;
  const int n = 1000;
  for (int i = 0; i < n; ++i)
  {
    for (int j = 0; j < n; ++j)
    {
      const double x = (i + 0.5) / n, y = (j + 0.5) / n;
      expectedMean += std::sqrt(x * x + y * y + 1);
    }
  }
  expectedMean /= double(n) * n;
  // Standard errors at 1e6 samples: ~1.7e-4 (mean), ~1.9e-4 (rms). Picking triangles by count
  // instead of area would put the rms off by ~5e-3.
  EXPECT_NEAR(d.mean, expectedMean, 8e-4);
  EXPECT_NEAR(d.rms, std::sqrt(5.0 / 3.0), 8e-4);
  EXPECT_LE(d.max, std::sqrt(3.0) + 1e-12);
  EXPECT_GT(d.max, std::sqrt(3.0) - 0.01);

  // Inside one triangle: (0,0,0), (1,0,0), (0,1,0) against its corner (0,0,0). Uniform points
  // have E[x^2 + y^2] = 1/3 (standard error of the rms ~1.8e-4 at 1e6 samples); barycentric
  // coordinates without the sqrt trick put the rms off by ~0.1.
  TriangleMesh tri;
  tri.points = { 0, 0, 0, 1, 0, 0, 0, 1, 0 };
  tri.triangles = { 0, 1, 2 };
  TriangleMesh corner;
  corner.points = { 0, 0, 0 };
  corner.triangles = { 0, 0, 0 };
  const OneSided c = SampleDistance(tri, corner, 1000000, 9, 2);
  EXPECT_NEAR(c.rms, std::sqrt(1.0 / 3.0), 9e-4);
  EXPECT_LE(c.max, 1.0 + 1e-12);
}

TEST(AlgorithmsCompare, DegenerateTrianglesAreNeverSampledButAreTargets)
{
  // `from`: the unit square plus a zero-area triangle far above it.
  TriangleMesh from = Square(0.0f);
  from.points.insert(from.points.end(), { 0, 0, 100, 1, 0, 100, 2, 0, 100 });
  from.triangles.insert(from.triangles.end(), { 4, 5, 6 });
  const OneSided d = SampleDistance(from, Square(0.0f), 50000, 3, 2);
  EXPECT_LT(d.max, 1e-12); // nothing sampled at z = 100

  // `to`: only a collinear triangle (a segment) hovering 0.01 over the line x = 0.5.
  TriangleMesh to;
  to.points = { 0.5f, -1, 0.01f, 0.5f, 0, 0.01f, 0.5f, 2, 0.01f };
  to.triangles = { 0, 1, 2 };
  const OneSided e = SampleDistance(Square(0.0f), to, 50000, 3, 2);
  // Distances are sqrt((x - 0.5)^2 + 0.01^2): the max is at x = 0 or 1.
  EXPECT_LE(e.max, std::sqrt(0.25 + 0.0001) + 1e-6);
  EXPECT_GT(e.max, 0.49);
  EXPECT_GE(e.mean, 0.01 - 1e-6);
}

TEST(AlgorithmsCompare, DeterministicAcrossThreadCounts)
{
  const TriangleMesh reference = Icosphere(3, 1.0);
  TriangleMesh candidate = Icosphere(2, 1.0);
  for (std::size_t i = 0; i < candidate.points.size(); i += 3)
  {
    candidate.points[i] *= 1.0f + 0.02f * std::sin(7.0f * candidate.points[i + 1]);
  }
  CompareOptions options;
  options.samples = 50001; // several chunks, the last one partial
  options.seed = 77;
  options.threads = 1;
  const CompareResult one = CompareMeshes(reference, candidate, options);
  for (int threads : { 2, 3, 0 })
  {
    options.threads = threads;
    const CompareResult other = CompareMeshes(reference, candidate, options);
    EXPECT_EQ(one.mean, other.mean) << threads;
    EXPECT_EQ(one.rms, other.rms) << threads;
    EXPECT_EQ(one.hausdorff, other.hausdorff) << threads;
    EXPECT_EQ(one.forwardRms, other.forwardRms) << threads;
    EXPECT_EQ(one.backwardRms, other.backwardRms) << threads;
    EXPECT_EQ(one.samples, other.samples) << threads;
  }
  const OneSided a = SampleDistance(candidate, reference, 30000, 5, 1);
  const OneSided b = SampleDistance(candidate, reference, 30000, 5, 2);
  EXPECT_EQ(a.mean, b.mean);
  EXPECT_EQ(a.rms, b.rms);
  EXPECT_EQ(a.max, b.max);

  // Another seed: other samples, a close estimate.
  options.seed = 78;
  options.threads = 2;
  const CompareResult seeded = CompareMeshes(reference, candidate, options);
  EXPECT_NE(seeded.mean, one.mean);
  EXPECT_NEAR(seeded.mean, one.mean, 0.05 * one.mean);
}

// The same surface listed in another order: its points, its triangles and each triangle's
// corners (rotated or reversed). The samples follow a canonical order of the triangles and of
// their corners, so every number is the same, bit for bit (before, the strata ran over the
// file's order: a shuffled copy of Lucy-size gave a Hausdorff distance 5% apart).
TriangleMesh Reordered(const TriangleMesh& m, std::uint32_t seed)
{
  std::mt19937 rng(seed);
  const std::size_t nv = m.NumberOfPoints(), nt = m.NumberOfTriangles();
  std::vector<std::uint32_t> newOf(nv), tris(nt);
  for (std::uint32_t i = 0; i < nv; ++i)
  {
    newOf[i] = i;
  }
  for (std::uint32_t t = 0; t < nt; ++t)
  {
    tris[t] = t;
  }
  std::shuffle(newOf.begin(), newOf.end(), rng);
  std::shuffle(tris.begin(), tris.end(), rng);
  TriangleMesh r;
  r.attributeStride = m.attributeStride;
  r.points.resize(m.points.size());
  r.attributes.resize(m.attributes.size());
  for (std::size_t i = 0; i < nv; ++i)
  {
    std::copy_n(&m.points[3 * i], 3, &r.points[3 * std::size_t(newOf[i])]);
    std::copy_n(m.attributes.data() + m.attributeStride * i, m.attributeStride,
      r.attributes.data() + m.attributeStride * std::size_t(newOf[i]));
  }
  for (std::size_t k = 0; k < nt; ++k)
  {
    const std::uint32_t* c = &m.triangles[3 * std::size_t(tris[k])];
    const int turn = static_cast<int>(rng() % 6); // three rotations, each either way round
    for (int v = 0; v < 3; ++v)
    {
      const int from = turn < 3 ? (v + turn) % 3 : (turn - v + 3) % 3;
      r.triangles.push_back(newOf[c[from]]);
    }
  }
  return r;
}

TEST(AlgorithmsCompare, TheOrderOfAFileChangesNothing)
{
  TriangleMesh reference = Icosphere(4, 1.0);
  TriangleMesh candidate = Icosphere(2, 1.0);
  for (TriangleMesh* m : { &reference, &candidate })
  {
    m->attributeStride = 3;
    for (std::size_t i = 0; i < m->points.size(); i += 3)
    {
      m->points[i] *= 1.0f + 0.02f * std::sin(7.0f * m->points[i + 1]);
      const float* p = &m->points[i];
      m->attributes.insert(m->attributes.end(),
        { p[0] > 0 ? 1.0f : 0.0f, 0.5f + 0.5f * p[1], p[2] * p[2] });
    }
  }
  CompareOptions options;
  options.samples = 40000;
  options.seed = 9;
  options.threads = 2;
  options.attributeGroups = { { 0, 3 } };
  const CompareResult base = CompareMeshes(reference, candidate, options);
  const OneSided baseSide = SampleDistance(reference, candidate, 30000, 3, 2);
  for (std::uint32_t seed : { 1u, 2u })
  {
    const TriangleMesh ref2 = Reordered(reference, seed), cand2 = Reordered(candidate, seed + 10);
    using Pair = std::pair<const TriangleMesh*, const TriangleMesh*>;
    for (const auto& [r, c] :
      { Pair(&ref2, &candidate), Pair(&reference, &cand2), Pair(&ref2, &cand2) })
    {
      const CompareResult other = CompareMeshes(*r, *c, options);
      EXPECT_EQ(base.mean, other.mean) << seed;
      EXPECT_EQ(base.rms, other.rms) << seed;
      EXPECT_EQ(base.hausdorff, other.hausdorff) << seed;
      EXPECT_EQ(base.forwardRms, other.forwardRms) << seed;
      EXPECT_EQ(base.backwardRms, other.backwardRms) << seed;
      ASSERT_EQ(other.attributeRms.size(), 1u);
      EXPECT_EQ(base.attributeRms[0], other.attributeRms[0]) << seed;
      EXPECT_EQ(base.attributeMax[0], other.attributeMax[0]) << seed;
    }
    const OneSided side = SampleDistance(ref2, cand2, 30000, 3, 2);
    EXPECT_EQ(baseSide.rms, side.rms) << seed;
    EXPECT_EQ(baseSide.max, side.max) << seed;
  }
  EXPECT_GT(base.rms, 0.0);
  EXPECT_GT(base.attributeRms[0], 0.0);
}

TEST(AlgorithmsCompare, DefaultSampleCount)
{
  const TriangleMesh small = Icosphere(2, 1.0);  // 320 triangles
  const TriangleMesh large = Icosphere(6, 1.0);  // 81920 triangles
  CompareOptions options;
  EXPECT_EQ(CompareMeshes(small, small, options).samples, 100000u);
  EXPECT_EQ(CompareMeshes(small, large, options).samples, 2u * 81920u);
}

TEST(AlgorithmsCompare, InvalidInputThrows)
{
  const TriangleMesh good = Square(0.0f);
  const TriangleMesh empty;
  EXPECT_THROW(CompareMeshes(empty, good), std::invalid_argument);
  EXPECT_THROW(CompareMeshes(good, empty), std::invalid_argument);
  try
  {
    CompareMeshes(empty, good);
  }
  catch (const std::invalid_argument& e)
  {
    EXPECT_NE(std::string(e.what()).find("empty"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("reference"), std::string::npos) << e.what();
  }
  TriangleMesh pointsOnly;
  pointsOnly.points = { 0, 0, 0 };
  EXPECT_THROW(CompareMeshes(good, pointsOnly), std::invalid_argument);

  TriangleMesh badIndex = good;
  badIndex.triangles[4] = 17;
  EXPECT_THROW(CompareMeshes(good, badIndex), std::invalid_argument);

  TriangleMesh badSize = good;
  badSize.points.pop_back();
  EXPECT_THROW(CompareMeshes(badSize, good), std::invalid_argument);

  TriangleMesh nan = good;
  nan.points[1] = std::numeric_limits<float>::quiet_NaN();
  EXPECT_THROW(CompareMeshes(good, nan), std::invalid_argument);

  TriangleMesh flat; // only a zero-area triangle: nothing to sample
  flat.points = { 0, 0, 0, 1, 0, 0, 2, 0, 0 };
  flat.triangles = { 0, 1, 2 };
  EXPECT_THROW(CompareMeshes(flat, good), std::invalid_argument);
  EXPECT_THROW(CompareMeshes(good, flat), std::invalid_argument);
  EXPECT_THROW(SampleDistance(flat, good, 10, 1, 1), std::invalid_argument);
  EXPECT_NO_THROW(SampleDistance(good, flat, 10, 1, 1)); // a zero-area target is fine
  EXPECT_THROW(SampleDistance(good, empty, 10, 1, 1), std::invalid_argument);
  EXPECT_THROW(MeshDistanceIndex{ empty }, std::invalid_argument);

  const OneSided none = SampleDistance(good, good, 0, 1, 1);
  EXPECT_EQ(none.samples, 0u);
  EXPECT_EQ(none.mean, 0.0);
}

TEST(AlgorithmsCompare, Bounds)
{
  TriangleMesh m;
  const auto e = m.Bounds();
  EXPECT_GT(e[0], e[1]); // empty: min > max
  m.points = { 1, -2, 3, -1, 5, 0.5f };
  const auto b = m.Bounds();
  EXPECT_EQ(b, (std::array<double, 6>{ -1, 1, -2, 5, 0.5, 3 }));
  EXPECT_EQ(m.NumberOfPoints(), 2u);
  EXPECT_EQ(m.NumberOfTriangles(), 0u);
}

} // namespace
