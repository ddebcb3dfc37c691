// The placement of a quadric edge collapse (Algorithm I), as a kernel over "lanes": one edge
// (V = double) or two at a time (V = Lanes2). Used by the decimation's sweep
// (decimate/Sweep.cpp); public for its exact test.
#pragma once

#include <cstdint>
#include <limits>

namespace sipmss::algorithms::placement
{
// Written once for one edge (V = double) and for two at a time (V = Lanes2, GCC/Clang vector
// extensions: one SSE2 register per value on the x86-64 baseline; four lanes spill registers
// there and were slower). No branches: every lane computes all the candidates (endpoints,
// optimum, best point of the segment) and selects. Each lane performs exactly the scalar's IEEE
// operations in the same order, so an edge gets the same bits either way, and the same as the
// Eigen formulation this replaced (Matrix3d * Vector3d: rows 0-1 summed left to right, row 2 with
// its last two terms first). That needs no FMA contraction (the algorithms build with
// -ffp-contract=off) and doubles evaluated as doubles (FLT_EVAL_METHOD 0). The unselected
// candidates may divide by zero: that raises floating-point exception flags, which nothing reads
// (no traps are enabled). Decimate's candidate sweep places its edges in pairs, other callers one
// at a time; AlgorithmsPlacementTest checks both, bit for bit, against the Eigen solve.
template <class V>
struct PlaceOut
{
  V cost, px, py, pz, t;
};
template <class V>
struct LaneOps;
template <>
struct LaneOps<double>
{
  using M = bool;
  static double Splat(double x) { return x; }
  static M And(M a, M b) { return a && b; }
  static M Not(M a) { return !a; }
  static double Sel(M m, double a, double b) { return m ? a : b; }
};
#if defined(__GNUC__)
#define SIPMSS_LANES 1
typedef double Lanes2 __attribute__((vector_size(16)));
typedef long long Mask2 __attribute__((vector_size(16)));
template <>
struct LaneOps<Lanes2>
{
  using M = Mask2;
  static Lanes2 Splat(double x) { return Lanes2{} + x; }
  static M And(M a, M b) { return a & b; }
  static M Not(M a) { return ~a; }
  static Lanes2 Sel(M m, Lanes2 a, Lanes2 b) { return m ? a : b; }
};
#endif
// Q: the summed quadric (10 coefficients); u, v: the endpoints. Expanded around the midpoint m:
// E(m + s e) = E(m) + 2 s e.g + s^2 e.Ae with g = A m + b; at the optimum d = -A^-1 g (A
// symmetric: six distinct cofactors; the first row's three give the determinant),
// E(m + d) = E(m) + d.g. The optimum counts when well conditioned (det against the cube of the
// trace) and within one edge length of m (a nearly singular quadric's optimum slides far along
// its weak direction), else the best point of the segment; an endpoint when it is as good (to
// rounding), u before v.
#if defined(__GNUC__)
#define SIPMSS_PLACE_INLINE inline __attribute__((always_inline))
#else
#define SIPMSS_PLACE_INLINE inline
#endif
// (Always inlined: out of line, its lanes and result went through memory, 5% of a run.)
template <class V>
SIPMSS_PLACE_INLINE PlaceOut<V> PlaceLanes(const V* q, const V* u, const V* v)
{
  using L = LaneOps<V>;
  using M = typename L::M;
  const V zero = L::Splat(0.0), one = L::Splat(1.0);
  const V ex = v[0] - u[0], ey = v[1] - u[1], ez = v[2] - u[2];
  const V mx = 0.5 * (u[0] + v[0]), my = 0.5 * (u[1] + v[1]), mz = 0.5 * (u[2] + v[2]);
  const V len2 = ex * ex + ey * ey + ez * ez;
  const V tr = q[0] + q[4] + q[7];
  const V tol = 1e-10 * tr * len2; // below the rounding of the costs
  const V gx = q[0] * mx + q[1] * my + q[2] * mz + q[3];
  const V gy = q[1] * mx + q[4] * my + q[5] * mz + q[6];
  const V gz = q[2] * mx + q[5] * my + q[7] * mz + q[8];
  const V aex = q[0] * ex + q[1] * ey + q[2] * ez, aey = q[1] * ex + q[4] * ey + q[5] * ez,
          aez = q[2] * ex + q[5] * ey + q[7] * ez;
  const V em = (mx * gx + my * gy + mz * gz) + (q[3] * mx + q[6] * my + q[8] * mz) + q[9];
  const V eg = ex * gx + ey * gy + ez * gz, eae = ex * aex + ey * aey + ez * aez;
  const V cu = em - eg + 0.25 * eae, cv = em + eg + 0.25 * eae;
  const M atU = cu <= cv;
  PlaceOut<V> o = { L::Sel(atU, cu, cv), L::Sel(atU, u[0], v[0]), L::Sel(atU, u[1], v[1]),
    L::Sel(atU, u[2], v[2]), L::Sel(atU, zero, one) };
  const V a00 = q[0], a01 = q[1], a02 = q[2], a11 = q[4], a12 = q[5], a22 = q[7];
  const V c00 = a11 * a22 - a12 * a12, c01 = a02 * a12 - a01 * a22, c02 = a01 * a12 - a02 * a11;
  const V det = a00 * c00 + a01 * c01 + a02 * c02;
  const V c11 = a00 * a22 - a02 * a02, c12 = a01 * a02 - a00 * a12, c22 = a00 * a11 - a01 * a01;
  const V scale = -1.0 / det;
  const V dx = (c00 * gx + c01 * gy + c02 * gz) * scale;
  const V dy = (c01 * gx + c11 * gy + c12 * gz) * scale;
  const V dz = (c02 * gx + (c12 * gy + c22 * gz)) * scale;
  const M solved = L::And(L::And(tr > 0, det > 1e-12 * tr * tr * tr), dx * dx + dy * dy + dz * dz <= len2);
  const V cd = em + dx * gx + dy * gy + dz * gz;
  const M takeD = L::And(solved, cd < o.cost - tol);
  V td = L::Sel(len2 > 0, 0.5 + (dx * ex + dy * ey + dz * ez) / len2, zero);
  td = L::Sel(zero < td, td, zero); // min(1, max(0, t)), as std::min and std::max do it
  td = L::Sel(td < one, td, one);
  o.cost = L::Sel(takeD, cd, o.cost);
  o.px = L::Sel(takeD, mx + dx, o.px);
  o.py = L::Sel(takeD, my + dy, o.py);
  o.pz = L::Sel(takeD, mz + dz, o.pz);
  o.t = L::Sel(takeD, td, o.t);
  // The best point of the segment: s in (-1/2, 1/2) around the midpoint.
  const V sopt = -eg / eae;
  const V cs = em + sopt * eg;
  const M takeS = L::And(L::And(L::Not(solved), eae > 0),
    L::And(L::And(sopt > -0.5, sopt < 0.5), cs < o.cost - tol));
  o.cost = L::Sel(takeS, cs, o.cost);
  o.px = L::Sel(takeS, mx + sopt * ex, o.px);
  o.py = L::Sel(takeS, my + sopt * ey, o.py);
  o.pz = L::Sel(takeS, mz + sopt * ez, o.pz);
  o.t = L::Sel(takeS, sopt + 0.5, o.t);
  // Negative by rounding: 0; NaN: never.
  o.cost = L::Sel(o.cost >= 0, o.cost, L::Sel(o.cost < 0, zero, L::Splat(std::numeric_limits<double>::infinity())));
  return o;
}
} // namespace sipmss::algorithms::placement
