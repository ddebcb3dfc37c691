// sipmss-bench-meshopt (Debian's meshoptimizer 0.18) and sipmss-bench-meshopt12 (meshoptimizer
// 1.2 built from ../shared/peers at bench time): the meshoptimizer peers of the decimation
// benchmarks. Reads a mesh into memory, runs one simplifier to a target triangle count, writes
// the result, and prints JSON with the read and simplify times and meshoptimizer's result_error.
//   sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES [simplify|sloppy|update|attributes]
// update (meshopt_simplifyWithUpdate: positions placed optimally) and attributes
// (meshopt_simplifyWithAttributes with area-weighted vertex normals, weight 0.5 each) need 1.2.
#include "../peers/PeerMesh.h"

#include <meshoptimizer.h>

#include <cmath>
#include <cstdlib>
#include <stdexcept>

namespace
{
// Area-weighted vertex normals, normalized (3 floats per vertex).
std::vector<float> VertexNormals(const sipmss::bench::PeerMesh& m)
{
  std::vector<float> n(m.p.size(), 0.f);
  for (std::size_t f = 0; f < m.t.size(); f += 3)
  {
    const float* a = &m.p[3 * m.t[f]];
    const float* b = &m.p[3 * m.t[f + 1]];
    const float* c = &m.p[3 * m.t[f + 2]];
    const float u[3] = { b[0] - a[0], b[1] - a[1], b[2] - a[2] };
    const float v[3] = { c[0] - a[0], c[1] - a[1], c[2] - a[2] };
    const float x[3] = { u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0] };
    for (int k = 0; k < 3; ++k)
    {
      for (int d = 0; d < 3; ++d)
      {
        n[3 * m.t[f + k] + d] += x[d];
      }
    }
  }
  for (std::size_t i = 0; i < n.size(); i += 3)
  {
    const float l = std::sqrt(n[i] * n[i] + n[i + 1] * n[i + 1] + n[i + 2] * n[i + 2]);
    for (int d = 0; d < 3 && l > 0; ++d)
    {
      n[i + d] /= l;
    }
  }
  return n;
}
} // namespace

int main(int argc, char** argv)
{
  using namespace sipmss::bench;
  if (argc < 4)
  {
    std::fprintf(stderr,
      "usage: sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES [simplify|sloppy|update|attributes]\n");
    return 2;
  }
  try
  {
    const auto t0 = Clock::now();
    PeerMesh m = ReadPeerMesh(argv[1]);
    const auto t1 = Clock::now();
    const std::size_t target = std::strtoull(argv[3], nullptr, 10) * 3;
    const std::string mode = argc > 4 ? argv[4] : "simplify";
    const std::size_t nv = m.p.size() / 3;
    std::vector<unsigned int> out(m.t.size());
    float err = 0;
    std::size_t n = 0;
    if (mode == "simplify")
    {
      n = meshopt_simplify(out.data(), m.t.data(), m.t.size(), m.p.data(), nv, 3 * sizeof(float),
        target, 1e9f, 0, &err);
    }
    else if (mode == "sloppy")
    {
      n = meshopt_simplifySloppy(out.data(), m.t.data(), m.t.size(), m.p.data(), nv,
        3 * sizeof(float), target, 1e9f, &err);
    }
#if MESHOPTIMIZER_VERSION >= 1000
    else if (mode == "update")
    {
      out.assign(m.t.begin(), m.t.end());
      n = meshopt_simplifyWithUpdate(out.data(), out.size(), m.p.data(), nv, 3 * sizeof(float),
        nullptr, 0, nullptr, 0, nullptr, target, 1e9f, 0, &err);
    }
    else if (mode == "attributes")
    {
      const std::vector<float> normals = VertexNormals(m);
      const float weights[3] = { 0.5f, 0.5f, 0.5f };
      n = meshopt_simplifyWithAttributes(out.data(), m.t.data(), m.t.size(), m.p.data(), nv,
        3 * sizeof(float), normals.data(), 3 * sizeof(float), weights, 3, nullptr, target, 1e9f,
        0, &err);
    }
#endif
    else
    {
      throw std::runtime_error("unknown or unsupported mode " + mode + " (meshoptimizer " +
        std::to_string(MESHOPTIMIZER_VERSION) + ")");
    }
    out.resize(n);
    const auto t2 = Clock::now();
    WriteUsed(argv[2], m.p, std::vector<std::uint32_t>(out.begin(), out.end()));
    PrintResult(Seconds(t0, t1), Seconds(t1, t2), out.size() / 3, err);
  }
  catch (const std::exception& e)
  {
    std::fprintf(stderr, "sipmss-bench-meshopt: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
