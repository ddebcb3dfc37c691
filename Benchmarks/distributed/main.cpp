// sipmss-bench-distributed: the distributed runs' work and traffic per rank.
//
//   sipmss-bench-distributed INPUT [--algorithm cluster|decimate] [--ranks 1,2,4] [--grid 300]
//                            [--target 10000] [--memory-mb M] [--write PREFIX]
//
// Reads INPUT into memory, cuts it into N pieces of consecutive faces (what reading a file by
// byte ranges gives each rank; each piece has the vertices its faces use), and clusters or
// decimates them on N ranks that are threads of this process (ThreadCommunicator: the
// collectives MPI would make). On a machine with fewer cores than ranks the wall time says
// little; each rank's CPU time (its thread's), its bytes sent and received and its rounds are
// the work per rank. Checks that the ranks' output triangles add up to the serial run's
// (clustering) or that rank 0's output is within 1% of the target (decimation). --write saves
// the serial output as PREFIX-serial.ply and rank 0's (decimation) or all ranks' (clustering)
// as PREFIX-N.ply, for `sipmss compare`.
#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/Decimate.h"
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

// Counts an output, and keeps it when asked (--write).
struct Count final : io::MeshSink
{
  std::uint64_t vertices = 0, triangles = 0;
  bool keep = false;
  Mesh m;
  void Begin(const io::MeshHeader&) override {}
  void Vertices(const io::VertexChunk& c) override
  {
    this->vertices += c.count;
    if (this->keep)
    {
      this->m.p.insert(this->m.p.end(), c.xyz, c.xyz + 3 * c.count);
    }
  }
  void Triangles(const std::uint32_t* i, std::size_t n) override
  {
    this->triangles += n;
    if (this->keep)
    {
      this->m.t.insert(this->m.t.end(), i, i + 3 * n);
    }
  }
  void End(const io::ReadStats&) override {}
};

// Writes the meshes as one PLY (each mesh's indices shifted past the previous ones' vertices).
void Write(const std::string& path, const std::vector<const Mesh*>& meshes)
{
  std::uint64_t nv = 0, nt = 0;
  for (const Mesh* m : meshes)
  {
    nv += m->p.size() / 3;
    nt += m->t.size() / 3;
  }
  auto w = io::MeshWriter::Create(path);
  w->Begin(nv, nt, io::VertexLayout{});
  std::uint64_t first = 0;
  for (const Mesh* m : meshes)
  {
    io::VertexChunk c;
    c.first = first;
    c.count = m->p.size() / 3;
    c.xyz = m->p.data();
    w->Vertices(c);
    first += c.count;
  }
  first = 0;
  for (const Mesh* m : meshes)
  {
    std::vector<std::uint32_t> t(m->t);
    for (auto& i : t)
    {
      i += std::uint32_t(first);
    }
    w->Triangles(t.data(), t.size() / 3);
    first += m->p.size() / 3;
  }
  w->End();
}

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
    std::fprintf(stderr,
      "usage: %s INPUT [--algorithm cluster|decimate] [--ranks 1,2,4] [--grid 300] "
      "[--target 10000] [--memory-mb M] [--write PREFIX]\n",
      argv[0]);
    return 2;
  }
  std::vector<int> rankCounts = { 1, 2, 4 };
  int grid = 300;
  double memoryMB = 0;
  std::uint64_t target = 10000;
  bool decimate = false;
  std::string prefix;
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
    else if (!std::strcmp(argv[i], "--target"))
    {
      target = std::strtoull(argv[i + 1], nullptr, 10);
    }
    else if (!std::strcmp(argv[i], "--algorithm") &&
      (!std::strcmp(argv[i + 1], "cluster") || !std::strcmp(argv[i + 1], "decimate")))
    {
      decimate = !std::strcmp(argv[i + 1], "decimate");
    }
    else if (!std::strcmp(argv[i], "--memory-mb"))
    {
      memoryMB = std::atof(argv[i + 1]);
    }
    else if (!std::strcmp(argv[i], "--write"))
    {
      prefix = argv[i + 1];
    }
    else
    {
      std::fprintf(stderr, "unknown option or value: %s %s\n", argv[i], argv[i + 1]);
      return 2;
    }
  }
  Mesh mesh;
  {
    Load load(mesh);
    FileSource(argv[1])(load, io::ReadOptions{});
  }
  storage::Profile storage;
  if (memoryMB > 0)
  {
    storage.memoryBudget = std::uint64_t(memoryMB * 1048576.0);
  }
  // One run of the chosen algorithm (comm: null for the serial run).
  auto run = [&](const MeshSource& source, Count& out, Communicator* comm) {
    NullProgress p;
    if (decimate)
    {
      DecimateOptions o;
      o.targetTriangles = target;
      o.threads = 1;
      o.storage = storage;
      o.communicator = comm;
      return Decimate(source, out, o, p);
    }
    ClusterOptions o;
    o.maximumGridDimension = grid;
    o.threads = 1;
    o.storage = storage;
    o.communicator = comm;
    return Cluster(source, out, o, p);
  };
  Count serial;
  serial.keep = !prefix.empty();
  const auto start = std::chrono::steady_clock::now();
  const double cpu0 = ThreadSeconds();
  run(Source(mesh), serial, nullptr);
  const double serialCpu = ThreadSeconds() - cpu0;
  std::printf("%s: %zu triangles, %s, budget %s\n", argv[1], mesh.t.size() / 3,
    decimate ? ("decimate to " + std::to_string(target)).c_str()
             : ("cluster at grid " + std::to_string(grid)).c_str(),
    memoryMB > 0 ? (std::to_string(memoryMB) + " MB").c_str() : "unbounded");
  std::printf("serial: %.2f s CPU, %.2f s wall, %llu output triangles\n", serialCpu,
    std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(),
    (unsigned long long)serial.triangles);
  if (!prefix.empty())
  {
    Write(prefix + "-serial.ply", { &serial.m });
  }
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
    for (Count& o : outputs)
    {
      o.keep = !prefix.empty();
    }
    RunRanks(n, [&](Communicator& comm) {
      const std::size_t r = std::size_t(comm.Rank());
      const double c0 = ThreadSeconds();
      stats[r] = run(Source(pieces[r]), outputs[r], &comm);
      cpu[r] = ThreadSeconds() - c0;
    });
    std::uint64_t total = 0;
    std::vector<const Mesh*> written;
    for (int r = 0; r < n; ++r)
    {
      const RunStats& s = stats[std::size_t(r)];
      total += outputs[std::size_t(r)].triangles;
      written.push_back(&outputs[std::size_t(r)].m);
      std::printf("| %d | %d | %zu | %llu | %.2f | %.2f | %.1f | %.1f | %llu | %.1f |\n", n, r,
        pieces[std::size_t(r)].t.size() / 3, (unsigned long long)outputs[std::size_t(r)].triangles,
        cpu[std::size_t(r)], s.communication.seconds, double(s.communication.bytesSent) / 1048576.0,
        double(s.communication.bytesReceived) / 1048576.0,
        (unsigned long long)s.communication.rounds, double(s.storage.peakBytes) / 1048576.0);
    }
    if (!prefix.empty())
    {
      Write(prefix + "-" + std::to_string(n) + ".ply", written);
    }
    const bool ok = decimate
      ? (double(std::max(total, target) - std::min(total, target)) <= 0.01 * double(target))
      : total == serial.triangles;
    if (!ok)
    {
      std::printf("MISMATCH: %d ranks wrote %llu triangles, the serial run %llu, the target %llu\n",
        n, (unsigned long long)total, (unsigned long long)serial.triangles,
        (unsigned long long)target);
      status = 1;
    }
  }
  return status;
}
