// The placement kernel of Algorithm I (sipmss/algorithms/Placement.h) against the formulation it
// replaced: an Eigen solve with branches. Bit for bit, for one edge and for two lanes, on quadrics
// of every rank (mesh-like sums of face planes, a plane, a crease, nothing), on coincident
// endpoints and on nearly singular systems.
#include "sipmss/algorithms/Placement.h"

#include <Eigen/Dense>
#include <gtest/gtest.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <limits>
#include <random>
#include <vector>

namespace
{
namespace pl = sipmss::algorithms::placement;

struct Result
{
  double cost, p[3], t;
  int how; // 0: an endpoint, 1: the optimum, 2: the best point of the segment
};

// Symmetric quadric, upper triangle row by row: a00 a01 a02 b0 | a11 a12 b1 | a22 b2 | c.
using Q10 = std::array<double, 10>;

void AddPlane(Q10& q, const double n[3], double d, double w)
{
  q[0] += w * n[0] * n[0];
  q[1] += w * n[0] * n[1];
  q[2] += w * n[0] * n[2];
  q[3] += w * n[0] * d;
  q[4] += w * n[1] * n[1];
  q[5] += w * n[1] * n[2];
  q[6] += w * n[1] * d;
  q[7] += w * n[2] * n[2];
  q[8] += w * n[2] * d;
  q[9] += w * d * d;
}

// The reference: the branchy formulation with Eigen's 3x3 product, as Decimate had it.
Result Reference(const Q10& Q, const double pu[3], const double pv[3])
{
  const double* q = Q.data();
  const double e[3] = { pv[0] - pu[0], pv[1] - pu[1], pv[2] - pu[2] };
  const double m[3] = { 0.5 * (pu[0] + pv[0]), 0.5 * (pu[1] + pv[1]), 0.5 * (pu[2] + pv[2]) };
  const double len2 = e[0] * e[0] + e[1] * e[1] + e[2] * e[2];
  const double tr = q[0] + q[4] + q[7];
  const double tol = 1e-10 * tr * len2;
  const double g[3] = { q[0] * m[0] + q[1] * m[1] + q[2] * m[2] + q[3],
    q[1] * m[0] + q[4] * m[1] + q[5] * m[2] + q[6], q[2] * m[0] + q[5] * m[1] + q[7] * m[2] + q[8] };
  const double Ae[3] = { q[0] * e[0] + q[1] * e[1] + q[2] * e[2],
    q[1] * e[0] + q[4] * e[1] + q[5] * e[2], q[2] * e[0] + q[5] * e[1] + q[7] * e[2] };
  const double Em =
    (m[0] * g[0] + m[1] * g[1] + m[2] * g[2]) + (q[3] * m[0] + q[6] * m[1] + q[8] * m[2]) + q[9];
  const double eg = e[0] * g[0] + e[1] * g[1] + e[2] * g[2];
  const double eAe = e[0] * Ae[0] + e[1] * Ae[1] + e[2] * Ae[2];
  const double cu = Em - eg + 0.25 * eAe, cv = Em + eg + 0.25 * eAe;
  Result best = cu <= cv ? Result{ cu, { pu[0], pu[1], pu[2] }, 0.0, 0 }
                         : Result{ cv, { pv[0], pv[1], pv[2] }, 1.0, 0 };
  bool solved = false;
  if (tr > 0)
  {
    const double a00 = q[0], a01 = q[1], a02 = q[2], a11 = q[4], a12 = q[5], a22 = q[7];
    const double c00 = a11 * a22 - a12 * a12, c01 = a02 * a12 - a01 * a22,
                 c02 = a01 * a12 - a02 * a11;
    const double det = a00 * c00 + a01 * c01 + a02 * c02;
    if (det > 1e-12 * tr * tr * tr)
    {
      const double c12 = a01 * a02 - a00 * a12;
      Eigen::Matrix3d adj;
      adj << c00, c01, c02, c01, a00 * a22 - a02 * a02, c12, c02, c12, a00 * a11 - a01 * a01;
      const Eigen::Vector3d d = (adj * Eigen::Vector3d(g[0], g[1], g[2])) * (-1.0 / det);
      if (d.squaredNorm() <= len2)
      {
        solved = true;
        const double c = Em + d.x() * g[0] + d.y() * g[1] + d.z() * g[2];
        if (c < best.cost - tol)
        {
          const double t =
            len2 > 0 ? 0.5 + (d.x() * e[0] + d.y() * e[1] + d.z() * e[2]) / len2 : 0.0;
          best = { c, { m[0] + d.x(), m[1] + d.y(), m[2] + d.z() }, std::min(1.0, std::max(0.0, t)),
            1 };
        }
      }
    }
  }
  if (!solved && eAe > 0)
  {
    const double s = -eg / eAe;
    if (s > -0.5 && s < 0.5)
    {
      const double c = Em + s * eg;
      if (c < best.cost - tol)
      {
        best = { c, { m[0] + s * e[0], m[1] + s * e[1], m[2] + s * e[2] }, s + 0.5, 2 };
      }
    }
  }
  if (!(best.cost >= 0))
  {
    best.cost = best.cost < 0 ? 0.0 : std::numeric_limits<double>::infinity();
  }
  return best;
}

struct Case
{
  Q10 q;
  double pu[3], pv[3];
};

bool SameBits(double a, double b)
{
  return std::memcmp(&a, &b, sizeof(double)) == 0;
}

void ExpectSame(const Result& r, double cost, double px, double py, double pz, double t,
  std::size_t i, const char* what)
{
  EXPECT_TRUE(SameBits(r.cost, cost)) << what << " case " << i << ": cost " << r.cost << " vs " << cost;
  EXPECT_TRUE(SameBits(r.p[0], px) && SameBits(r.p[1], py) && SameBits(r.p[2], pz))
    << what << " case " << i;
  EXPECT_TRUE(SameBits(r.t, t)) << what << " case " << i << ": t " << r.t << " vs " << t;
}

std::vector<Case> Cases()
{
  std::mt19937_64 rng(20261122);
  std::uniform_real_distribution<double> U(-1.0, 1.0);
  std::vector<Case> cases;
  auto unit = [&](double n[3]) {
    double l = 0;
    do
    {
      n[0] = U(rng);
      n[1] = U(rng);
      n[2] = U(rng);
      l = std::sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
    } while (l < 1e-3);
    n[0] /= l;
    n[1] /= l;
    n[2] /= l;
  };
  for (int i = 0; i < 20000; ++i)
  {
    Case c{};
    const int kind = i % 6;
    for (int k = 0; k < 3; ++k)
    {
      c.pu[k] = U(rng);
      c.pv[k] = c.pu[k] + 0.01 * U(rng);
    }
    double n[3];
    if (kind == 0 || kind == 5)
    {
      // A patch of a curved surface: planes near the edge (kind 5: near-parallel, ill-posed).
      const int planes = 4 + i % 9;
      for (int p = 0; p < planes; ++p)
      {
        unit(n);
        if (kind == 5)
        {
          n[0] = 0.001 * n[0];
          n[1] = 0.001 * n[1];
          n[2] = 1.0;
        }
        const double d = -(n[0] * c.pu[0] + n[1] * c.pu[1] + n[2] * c.pu[2]) + 1e-3 * U(rng);
        AddPlane(c.q, n, d, 1e-4 * (1.0 + U(rng)));
      }
    }
    else if (kind == 1 || kind == 2)
    {
      // One plane (a flat region) or two (a crease): singular.
      for (int p = 0; p < kind; ++p)
      {
        unit(n);
        AddPlane(c.q, n, -(n[0] * c.pu[0] + n[1] * c.pu[1] + n[2] * c.pu[2]), 0.5);
      }
    }
    else if (kind == 3)
    {
      // No quadric at all: every point costs nothing (the endpoint u wins the tie).
    }
    else
    {
      // Coincident endpoints.
      for (int k = 0; k < 3; ++k)
      {
        c.pv[k] = c.pu[k];
      }
      unit(n);
      AddPlane(c.q, n, 0.1 * U(rng), 1.0);
    }
    cases.push_back(c);
  }
  return cases;
}

TEST(AlgorithmsPlacement, OneEdgeMatchesTheEigenSolveBitForBit)
{
  const std::vector<Case> cases = Cases();
  int how[3] = { 0, 0, 0 };
  for (std::size_t i = 0; i < cases.size(); ++i)
  {
    const Case& c = cases[i];
    const Result r = Reference(c.q, c.pu, c.pv);
    const pl::PlaceOut<double> o = pl::PlaceLanes<double>(c.q.data(), c.pu, c.pv);
    ExpectSame(r, o.cost, o.px, o.py, o.pz, o.t, i, "one edge");
    ++how[r.how];
  }
  // Every outcome of the reference occurs.
  EXPECT_GT(how[0], 1000) << "endpoints";
  EXPECT_GT(how[1], 1000) << "optima";
  EXPECT_GT(how[2], 100) << "points of the segment";
}

#ifdef SIPMSS_LANES
TEST(AlgorithmsPlacement, TwoLanesMatchTheEigenSolveBitForBit)
{
  const std::vector<Case> cases = Cases();
  for (std::size_t i = 0; i + 1 < cases.size(); i += 2)
  {
    pl::Lanes2 q[10], u[3], v[3];
    for (int k = 0; k < 10; ++k)
    {
      q[k] = pl::Lanes2{ cases[i].q[k], cases[i + 1].q[k] };
    }
    for (int k = 0; k < 3; ++k)
    {
      u[k] = pl::Lanes2{ cases[i].pu[k], cases[i + 1].pu[k] };
      v[k] = pl::Lanes2{ cases[i].pv[k], cases[i + 1].pv[k] };
    }
    const pl::PlaceOut<pl::Lanes2> o = pl::PlaceLanes<pl::Lanes2>(q, u, v);
    for (int l = 0; l < 2; ++l)
    {
      const Case& c = cases[i + l];
      const Result r = Reference(c.q, c.pu, c.pv);
      ExpectSame(r, o.cost[l], o.px[l], o.py[l], o.pz[l], o.t[l], i + l, "two lanes");
    }
  }
}
#endif
} // namespace
