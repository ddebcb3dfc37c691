// sipmss-bench-distributed: the distributed clustering's work and traffic per rank.
//
//   sipmss-bench-distributed INPUT [--ranks 1,2,4] [--grid 300] [--memory-mb M]
//
// Reads INPUT into memory, cuts it into N pieces of consecutive faces (what reading a file by
// byte ranges gives each rank; each piece has the vertices its faces use), and clusters them on
// N ranks that are threads of this process (ThreadCommunicator: the collectives MPI would make).
// On a machine with fewer cores than ranks the wall time says little; each rank's CPU time
// (its thread's), its bytes sent and received and its rounds are the work per rank. Checks that
// the ranks' output triangles add up to the serial run's.
#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/ThreadCommunicator.h"

#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <map>
#include <sstream>
#include <string>
#include <vector>

using namespace sipmss;
using namespace sipmss::algorithms;

namespace
{
struct Mesh
{
  std::vector<float> p;
  std::vector<std::uint32_t> t;
};

struct Load final : io::MeshSink
{
  Mesh& m;
  explicit Load(Mesh& mesh)
    : m(mesh)
  {
  }
  void Begin(const io::MeshHeader& h) override
  {
    this->m.p.reserve(3 * h.vertexCount);
    this->m.t.reserve(3 * h.faceCount);
  }
  void Vertices(const io::VertexChunk& c) override
  {
    this->m.p.insert(this->m.p.end(), c.xyz, c.xyz + 3 * c.count);
  }
  void Triangles(const std::uint32_t* i, std::size_t n) override
  {
    this->m.t.insert(this->m.t.end(), i, i + 3 * n);
  }
  void End(const io::ReadStats&) override {}
};

struct Count final : io::MeshSink
{
  std::uint64_t vertices = 0, triangles = 0;
  void Begin(const io::MeshHeader&) override {}
  void Vertices(const io::VertexChunk& c) override { this->vertices += c.count; }
  void Triangles(const std::uint32_t*, std::size_t n) override { this->triangles += n; }
  void End(const io::ReadStats&) override {}
};

MeshSource Source(const Mesh& m)
{
  return [&m](io::MeshSink& sink, const io::ReadOptions& options) {
    io::MeshHeader h;
    h.vertexCount = m.p.size() / 3;
    h.faceCount = m.t.size() / 3;
    sink.Begin(h);
    constexpr std::size_t kChunk = 1 << 16;
    for (std::size_t v = 0; v < h.vertexCount; v += kChunk)
    {
      io::VertexChunk c;
      c.first = v;
      c.count = std::min<std::size_t>(kChunk, h.vertexCount - v);
      c.xyz = m.p.data() + 3 * v;
      sink.Vertices(c);
    }
    io::ReadStats s;
    s.vertices = h.vertexCount;
    if (!options.verticesOnly)
    {
      for (std::size_t f = 0; f < h.faceCount; f += kChunk)
      {
        sink.Triangles(m.t.data() + 3 * f, std::min<std::size_t>(kChunk, h.faceCount - f));
      }
      s.triangles = h.faceCount;
      sink.End(s);
    }
    return s;
  };
}

// Rank r's consecutive faces and their vertices, renumbered in order of first use.
Mesh Piece(const Mesh& m, int ranks, int r)
{
  const std::size_t nf = m.t.size() / 3;
  const std::size_t begin = nf * std::size_t(r) / std::size_t(ranks),
                    end = nf * std::size_t(r + 1) / std::size_t(ranks);
  Mesh piece;
  std::vector<std::uint32_t> renumber(m.p.size() / 3, ~0u);
  for (std::size_t i = 3 * begin; i < 3 * end; ++i)
  {
    std::uint32_t& n = renumber[m.t[i]];
    if (n == ~0u)
    {
      n = std::uint32_t(piece.p.size() / 3);
      piece.p.insert(piece.p.end(), m.p.begin() + 3 * m.t[i], m.p.begin() + 3 * m.t[i] + 3);
    }
    piece.t.push_back(n);
  }
  return piece;
}

double ThreadSeconds()
{
  timespec ts{};
  clock_gettime(CLOCK_THREAD_CPUTIME_ID, &ts);
  return double(ts.tv_sec) + 1e-9 * double(ts.tv_nsec);
}
} // namespace

int main(int argc, char** argv)
{
  if (argc < 2)
  {
    std::fprintf(stderr, "usage: %s INPUT [--ranks 1,2,4] [--grid 300] [--memory-mb M]\n", argv[0]);
    return 2;
  }
  std::vector<int> rankCounts = { 1, 2, 4 };
  int grid = 300;
  double memoryMB = 0;
  for (int i = 2; i + 1 < argc; i += 2)
  {
    if (!std::strcmp(argv[i], "--ranks"))
    {
      rankCounts.clear();
      std::stringstream ss(argv[i + 1]);
      std::string n;
      while (std::getline(ss, n, ','))
      {
        rankCounts.push_back(std::atoi(n.c_str()));
      }
    }
    else if (!std::strcmp(argv[i], "--grid"))
    {
      grid = std::atoi(argv[i + 1]);
    }
    else if (!std::strcmp(argv[i], "--memory-mb"))
    {
      memoryMB = std::atof(argv[i + 1]);
    }
    else
    {
      std::fprintf(stderr, "unknown option %s\n", argv[i]);
      return 2;
    }
  }
  Mesh mesh;
  {
    Load load(mesh);
    FileSource(argv[1])(load, io::ReadOptions{});
  }
  ClusterOptions options;
  options.maximumGridDimension = grid;
  options.threads = 1;
  if (memoryMB > 0)
  {
    options.storage.memoryBudget = std::uint64_t(memoryMB * 1048576.0);
  }
  NullProgress progress;
  Count serial;
  const auto start = std::chrono::steady_clock::now();
  const double cpu0 = ThreadSeconds();
  Cluster(Source(mesh), serial, options, progress);
  std::printf("%s: %zu triangles, grid %d, budget %s\n", argv[1], mesh.t.size() / 3, grid,
    memoryMB > 0 ? (std::to_string(memoryMB) + " MB").c_str() : "unbounded");
  std::printf("serial: %.2f s CPU, %.2f s wall, %llu output triangles\n", ThreadSeconds() - cpu0,
    std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(),
    (unsigned long long)serial.triangles);
  std::printf("| ranks | rank | input triangles | output triangles | CPU s | communication s | "
              "MB sent | MB received | rounds | peak DML MB |\n|---|---|---|---|---|---|---|---|---|---|\n");
  int status = 0;
  for (int n : rankCounts)
  {
    std::vector<Mesh> pieces;
    for (int r = 0; r < n; ++r)
    {
      pieces.push_back(Piece(mesh, n, r));
    }
    std::vector<RunStats> stats(static_cast<std::size_t>(n));
    std::vector<Count> outputs(static_cast<std::size_t>(n));
    std::vector<double> cpu(static_cast<std::size_t>(n));
    RunRanks(n, [&](Communicator& comm) {
      const std::size_t r = std::size_t(comm.Rank());
      ClusterOptions o = options;
      o.communicator = &comm;
      NullProgress p;
      const double c0 = ThreadSeconds();
      stats[r] = Cluster(Source(pieces[r]), outputs[r], o, p);
      cpu[r] = ThreadSeconds() - c0;
    });
    std::uint64_t total = 0;
    for (int r = 0; r < n; ++r)
    {
      const RunStats& s = stats[std::size_t(r)];
      total += outputs[std::size_t(r)].triangles;
      std::printf("| %d | %d | %zu | %llu | %.2f | %.2f | %.1f | %.1f | %llu | %.1f |\n", n, r,
        pieces[std::size_t(r)].t.size() / 3, (unsigned long long)outputs[std::size_t(r)].triangles,
        cpu[std::size_t(r)], s.communication.seconds, double(s.communication.bytesSent) / 1048576.0,
        double(s.communication.bytesReceived) / 1048576.0,
        (unsigned long long)s.communication.rounds, double(s.storage.peakBytes) / 1048576.0);
    }
    if (total != serial.triangles)
    {
      std::printf("MISMATCH: %d ranks wrote %llu triangles, the serial run %llu\n", n,
        (unsigned long long)total, (unsigned long long)serial.triangles);
      status = 1;
    }
  }
  return status;
}
