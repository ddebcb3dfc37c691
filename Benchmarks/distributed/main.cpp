// sipmss-bench-distributed: the distributed runs' work, reads and traffic per rank.
//
//   sipmss-bench-distributed INPUT [--algorithm cluster|decimate|two-stage] [--ranks 1,2,4]
//                            [--grid 300] [--target 10000] [--memory-mb M] [--write PREFIX]
//
// Runs the algorithm on INPUT once serially from the file, then on N ranks that are threads of
// this process (ThreadCommunicator: the collectives MPI would make), each rank reading its piece
// of the file by byte ranges (binary PLY or STL), or rank 0 reading any other file and sending
// the ranks their pieces (FilePiece, with an eighth of the budget as the filters give it), as the
// File sources do under MPI. On a machine with fewer cores than
// ranks the wall time says little; each rank's CPU time (its thread's: reading its piece, its
// work, its share of the exchanges), its bytes read, sent and received and its rounds are the
// work per rank. Checks that the ranks' output triangles add up to the serial run's
// (clustering) or that rank 0's output is within 1% of the target (decimation, two-stage).
// --write saves the serial output as PREFIX-serial.ply and rank 0's (decimation) or all ranks'
// (clustering) as PREFIX-N.ply, for `sipmss compare`.
#include "sipmss/algorithms/FilePiece.h"
#include "sipmss/algorithms/Simplify.h"
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
      "usage: %s INPUT [--algorithm cluster|decimate|two-stage] [--ranks 1,2,4] [--grid 300] "
      "[--target 10000] [--memory-mb M] [--write PREFIX]\n",
      argv[0]);
    return 2;
  }
  std::vector<int> rankCounts = { 1, 2, 4 };
  int grid = 300;
  double memoryMB = 0;
  std::uint64_t target = 10000;
  std::string algorithm = "cluster";
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
      (!std::strcmp(argv[i + 1], "cluster") || !std::strcmp(argv[i + 1], "decimate") ||
        !std::strcmp(argv[i + 1], "two-stage")))
    {
      algorithm = argv[i + 1];
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
  const bool decimate = algorithm != "cluster";
  // The request the filters would make (one thread per rank; a budget or unbounded).
  SimplifyRequest request;
  request.algorithm = algorithm == "two-stage" ? Algorithm::TwoStage
    : decimate                                 ? Algorithm::Decimate
                                               : Algorithm::Cluster;
  request.targetTriangles = target;
  request.grid = grid;
  request.threads = 1;
  request.memoryBudgetMB = memoryMB > 0 ? memoryMB : kUnboundedMemoryBudget;
  // One run (comm: null for the serial run).
  auto run = [](const SimplifyRequest& r, const MeshSource& source, Count& out, Communicator* comm) {
    SimplifyRequest on = r;
    on.communicator = comm;
    NullProgress p;
    return Simplify(on, source, out, p);
  };
  Count serial;
  serial.keep = !prefix.empty();
  const auto start = std::chrono::steady_clock::now();
  const double cpu0 = ThreadSeconds();
  std::uint64_t serialBytes = 0;
  const MeshSource file = FileSource(argv[1]);
  const RunStats serialStats = run(request,
    [&file, &serialBytes](io::MeshSink& sink, const io::ReadOptions& ro) {
      const io::ReadStats read = file(sink, ro);
      serialBytes += read.bytes;
      return read;
    },
    serial, nullptr);
  const double serialCpu = ThreadSeconds() - cpu0;
  std::printf("%s: %llu triangles, %s, budget %s\n", argv[1],
    (unsigned long long)serialStats.inputTriangles,
    (algorithm == "cluster" ? "cluster at grid " + std::to_string(grid)
        : algorithm + " to " + std::to_string(target) +
          (algorithm == "two-stage" ? " (grid " + std::to_string(grid) + ")" : ""))
      .c_str(),
    memoryMB > 0 ? (std::to_string(memoryMB) + " MB").c_str() : "unbounded");
  std::printf("serial: %.2f s CPU, %.2f s wall, %.1f MB read, %llu output triangles, peak DML "
              "%.1f MB\n",
    serialCpu, std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count(),
    double(serialBytes) / 1048576.0, (unsigned long long)serial.triangles,
    double(serialStats.storage.peakBytes) / 1048576.0);
  if (!prefix.empty())
  {
    Write(prefix + "-serial.ply", { &serial.m });
  }
  std::printf("| ranks | rank | input triangles | output triangles | CPU s | communication s | "
              "MB read | MB sent | MB received | rounds | peak DML MB |\n"
              "|---|---|---|---|---|---|---|---|---|---|---|\n");
  int status = 0;
  for (int n : rankCounts)
  {
    std::vector<RunStats> stats(static_cast<std::size_t>(n));
    std::vector<std::uint64_t> bytesRead(static_cast<std::size_t>(n)),
      pieceFaces(static_cast<std::size_t>(n));
    std::vector<Count> outputs(static_cast<std::size_t>(n));
    std::vector<double> cpu(static_cast<std::size_t>(n));
    for (Count& o : outputs)
    {
      o.keep = !prefix.empty();
    }
    RunRanks(n, [&](Communicator& comm) {
      const std::size_t r = std::size_t(comm.Rank());
      const double c0 = ThreadSeconds();
      SimplifyRequest mine = request;
      const storage::Profile pieceProfile = ReservePieceBudget(mine);
      NullProgress p;
      FilePiece piece(argv[1], comm, pieceProfile, p);
      stats[r] = run(mine, piece.Source(), outputs[r], &comm);
      // (a file that cannot be read by byte ranges is scattered by rank 0: its traffic counts)
      stats[r].communication.Add(piece.Traffic());
      cpu[r] = ThreadSeconds() - c0;
      bytesRead[r] = piece.BytesRead();
      pieceFaces[r] = piece.Faces();
    });
    std::uint64_t total = 0;
    std::vector<const Mesh*> written;
    for (int r = 0; r < n; ++r)
    {
      const RunStats& s = stats[std::size_t(r)];
      total += outputs[std::size_t(r)].triangles;
      written.push_back(&outputs[std::size_t(r)].m);
      std::printf("| %d | %d | %llu | %llu | %.2f | %.2f | %.1f | %.1f | %.1f | %llu | %.1f |\n", n,
        r, (unsigned long long)pieceFaces[std::size_t(r)],
        (unsigned long long)outputs[std::size_t(r)].triangles, cpu[std::size_t(r)],
        s.communication.seconds, double(bytesRead[std::size_t(r)]) / 1048576.0,
        double(s.communication.bytesSent) / 1048576.0,
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
