// sipmss-bench-meshopt: the peer for the decimation benchmarks. Reads a mesh with SIPMSS's
// streaming reader into memory, runs meshoptimizer's meshopt_simplify (or meshopt_simplifySloppy)
// to a target triangle count, writes the result, and prints JSON with the read and simplify times.
//   sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES [sloppy]
#include "sipmss/io/MeshIO.h"
#include "sipmss/io/VectorSink.h"

#include <meshoptimizer.h>

#include <algorithm>
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <string>
#include <vector>

int main(int argc, char** argv)
{
  if (argc < 4)
  {
    std::fprintf(stderr, "usage: sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES [sloppy]\n");
    return 2;
  }
  try
  {
    const auto t0 = std::chrono::steady_clock::now();
    struct
    {
      std::vector<float> p;
      std::vector<std::uint32_t> t;
    } m;
    sipmss::io::VectorSink sink(m.p, m.t);
    sipmss::io::ReadMesh(argv[1], sink);
    const auto t1 = std::chrono::steady_clock::now();
    const std::size_t target = std::strtoull(argv[3], nullptr, 10) * 3;
    std::vector<unsigned int> out(m.t.size());
    const bool sloppy = argc > 4 && std::string(argv[4]) == "sloppy";
    float err = 0;
    const std::size_t n = sloppy
      ? meshopt_simplifySloppy(out.data(), m.t.data(), m.t.size(), m.p.data(), m.p.size() / 3,
          3 * sizeof(float), target, 1e9f, &err)
      : meshopt_simplify(out.data(), m.t.data(), m.t.size(), m.p.data(), m.p.size() / 3,
          3 * sizeof(float), target, 1e9f, 0, &err);
    out.resize(n);
    const auto t2 = std::chrono::steady_clock::now();
    // write the used vertices only
    std::vector<unsigned int> remap(m.p.size() / 3, ~0u);
    std::vector<float> pts;
    for (auto& v : out)
    {
      if (remap[v] == ~0u)
      {
        remap[v] = static_cast<unsigned int>(pts.size() / 3);
        pts.insert(pts.end(), &m.p[3 * v], &m.p[3 * v + 3]);
      }
      v = remap[v];
    }
    auto w = sipmss::io::MeshWriter::Create(argv[2]);
    w->Begin(pts.size() / 3, out.size() / 3, sipmss::io::VertexLayout{});
    sipmss::io::VertexChunk c;
    c.count = pts.size() / 3;
    c.xyz = pts.data();
    if (c.count)
      w->Vertices(c);
    if (!out.empty())
      w->Triangles(out.data(), out.size() / 3);
    w->End();
    std::printf("{\"read\": %.6f, \"filter\": %.6f, \"triangles\": %zu}\n",
      std::chrono::duration<double>(t1 - t0).count(), std::chrono::duration<double>(t2 - t1).count(),
      out.size() / 3);
  }
  catch (const std::exception& e)
  {
    std::fprintf(stderr, "sipmss-bench-meshopt: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
