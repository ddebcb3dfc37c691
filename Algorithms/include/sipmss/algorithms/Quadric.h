// The one quadric of every algorithm (clustering's cell quadrics, decimation's vertex quadrics,
// the two-stage hand-off between them).
#pragma once

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
} // namespace sipmss::algorithms
