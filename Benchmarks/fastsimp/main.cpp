// sipmss-bench-fastsimp: fast-simplification's C++ core (pyvista/fast-simplification 0.2.0,
// Simplify.h, after Sp4cerat's Fast-Quadric-Mesh-Simplification), built from ../shared/peers at
// bench time: what pyvista users call for fast decimation. Reads a mesh into memory, runs
// Simplify::simplify_mesh to a target triangle count (aggressiveness 7, its default), writes the
// result and prints the same JSON as sipmss-bench-meshopt.
//   sipmss-bench-fastsimp INPUT OUTPUT TARGET_TRIANGLES
#include "../peers/PeerMesh.h"

#include <Simplify.h>

#include <cstdlib>

int main(int argc, char** argv)
{
  using namespace sipmss::bench;
  if (argc < 4)
  {
    std::fprintf(stderr, "usage: sipmss-bench-fastsimp INPUT OUTPUT TARGET_TRIANGLES\n");
    return 2;
  }
  try
  {
    const auto t0 = Clock::now();
    {
      PeerMesh m = ReadPeerMesh(argv[1]);
      Simplify::vertices.resize(m.p.size() / 3);
      for (std::size_t i = 0; i < Simplify::vertices.size(); ++i)
      {
        Simplify::vertices[i].p.x = m.p[3 * i];
        Simplify::vertices[i].p.y = m.p[3 * i + 1];
        Simplify::vertices[i].p.z = m.p[3 * i + 2];
      }
      Simplify::triangles.resize(m.t.size() / 3);
      for (std::size_t f = 0; f < Simplify::triangles.size(); ++f)
      {
        Simplify::Triangle& t = Simplify::triangles[f];
        t = Simplify::Triangle{};
        for (int k = 0; k < 3; ++k)
        {
          t.v[k] = static_cast<int>(m.t[3 * f + k]);
        }
      }
    }
    const auto t1 = Clock::now();
    Simplify::simplify_mesh(static_cast<int>(std::strtoll(argv[3], nullptr, 10)));
    const auto t2 = Clock::now();
    std::vector<float> p;
    p.reserve(3 * Simplify::vertices.size());
    for (const auto& v : Simplify::vertices)
    {
      p.insert(p.end(), { float(v.p.x), float(v.p.y), float(v.p.z) });
    }
    std::vector<std::uint32_t> t;
    for (const auto& tri : Simplify::triangles)
    {
      if (!tri.deleted)
      {
        t.insert(t.end(), { std::uint32_t(tri.v[0]), std::uint32_t(tri.v[1]), std::uint32_t(tri.v[2]) });
      }
    }
    WriteUsed(argv[2], p, t);
    PrintResult(Seconds(t0, t1), Seconds(t1, t2), t.size() / 3, -1);
  }
  catch (const std::exception& e)
  {
    std::fprintf(stderr, "sipmss-bench-fastsimp: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
