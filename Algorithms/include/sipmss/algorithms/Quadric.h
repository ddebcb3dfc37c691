// The one quadric of every algorithm (clustering's cell quadrics, decimation's vertex quadrics,
// the two-stage hand-off between them).
#pragma once

#include <algorithm>
#include <cmath>

namespace sipmss::algorithms
{
// E(p) = p^T A p + 2 b.p + c for the symmetric 4x4 matrix [A b; b^T c], stored as its upper
// triangle by rows: a00 a01 a02 b0 a11 a12 b1 a22 b2 c.
struct Quadric
{
  double q[10];
};

inline void AddTo(Quadric& dst, const Quadric& src)
{
  for (int i = 0; i < 10; ++i)
  {
    dst.q[i] += src.q[i];
  }
}

// The quadric of the plane n.p + d = 0 (n of unit length) with weight w: the squared distance to
// the plane times w.
inline Quadric PlaneQuadric(double nx, double ny, double nz, double d, double w)
{
  return { { w * nx * nx, w * nx * ny, w * nx * nz, w * nx * d, w * ny * ny, w * ny * nz,
    w * ny * d, w * nz * nz, w * nz * d, w * d * d } };
}
// The quadric of E(p - c), for E the quadric q: the same error, about another origin.
inline Quadric Translated(const Quadric& q, const double c[3])
{
  const double* a = q.q;
  // A c
  const double ac[3] = { a[0] * c[0] + a[1] * c[1] + a[2] * c[2],
    a[1] * c[0] + a[4] * c[1] + a[5] * c[2], a[2] * c[0] + a[5] * c[1] + a[7] * c[2] };
  const double b[3] = { a[3], a[6], a[8] };
  Quadric t = q;
  t.q[3] = b[0] - ac[0];
  t.q[6] = b[1] - ac[1];
  t.q[8] = b[2] - ac[2];
  t.q[9] = a[9] - 2.0 * (b[0] * c[0] + b[1] * c[1] + b[2] * c[2]) +
    (ac[0] * c[0] + ac[1] * c[1] + ac[2] * c[2]);
  return t;
}

// E(x, y, z).
inline double QuadricValue(const double q[10], double x, double y, double z)
{
  return x * (q[0] * x + 2.0 * (q[1] * y + q[2] * z + q[3])) +
    y * (q[4] * y + 2.0 * (q[5] * z + q[6])) + z * (q[7] * z + 2.0 * q[8]) + q[9];
}

// The sum of the plane weights (each plane quadric adds its weight w, its normal being a unit
// vector): E(p) / trace is the weighted mean squared distance to the planes.
inline double QuadricTrace(const double q[10])
{
  return q[0] + q[4] + q[7];
}

// An error as RunStats reports it: the root of a weighted mean squared distance, relative to
// `diagonal` (0 when the diagonal is 0: a mesh of one point).
inline double RelativeError(double meanSquared, double diagonal)
{
  return diagonal > 0 ? std::sqrt(std::max(0.0, meanSquared)) / diagonal : 0.0;
}
} // namespace sipmss::algorithms
