// sipmss-meshgen: inputs for the demo, the tests and the benchmarks.
//
//   sipmss-meshgen scan OUTPUT [--triangles N] [--order scanner|shuffled|rings]
//       a closed, bumpy, scan-like surface (a displaced sphere) of about N triangles
//   sipmss-meshgen subdivide INPUT OUTPUT [--levels L] [--displace D] [--order scanner|shuffled]
//                            [--memory-mb MB] [--tmpdir DIR]
//       midpoint subdivision (x4 triangles per level) with a small displacement along the normal
//       so that the new triangles carry detail, as docs of ../shared/data recommend
//   sipmss-meshgen colorize INPUT OUTPUT [--cells N]
//       the same mesh with per-vertex normals (area-weighted face normals) and colors with sharp
//       borders (a 3D checkerboard of N cells along the longest axis, six colors, each with a
//       smooth shade): the colored scan of the attribute benchmarks and tests (in memory)
//
// "scanner" order: vertices sorted along the longest axis, faces by their first vertex (the way
// volumetric reconstructions such as vrip write their output); "shuffled": random order.
// `subdivide` works within a memory budget (--memory-mb, Subdivide.cpp): its blocks go to
// temporary files beyond it. `scan` holds the mesh in memory (unlike sipmss itself), except
// `scan --order rings`: the same kind of surface with its poles on the longest axis, written ring
// by ring as it is generated (vertices along that axis, faces by their first ring), in a few MB
// whatever its size: the 100M- to 1B-triangle inputs of the scale benchmarks.
// Every output is written under a temporary name beside it and renamed into place when complete;
// stopped by SIGINT or SIGTERM, a command leaves neither that file nor block files behind.
#include "sipmss/io/MeshIO.h"
#include "sipmss/io/VectorSink.h"
#include "Subdivide.h"

#include <CLI/CLI.hpp>

#include <algorithm>
#include <cerrno>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <limits>
#include <numeric>
#include <random>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <vector>

#include <signal.h>
#include <sys/resource.h>
#include <unistd.h>

using namespace sipmss;

namespace
{
// SIGINT and SIGTERM. Every command writes its output under a temporary name beside OUTPUT and
// renames it into place once it is complete (WriteOutput). During `subdivide` the first signal
// is only noted: the passes see it at their next chunk and unwind, so its block files go and the
// unfinished output is removed. Otherwise, or at a second signal, the handler removes the
// unfinished output and the process ends at once.
volatile std::sig_atomic_t g_signal = 0;
volatile std::sig_atomic_t g_polled = 0;
char g_partial[4096] = ""; // the unfinished output (written before the handler can see it)

extern "C" void OnSignal(int sig)
{
  if (g_polled && !g_signal)
  {
    g_signal = sig;
    return;
  }
  if (g_partial[0])
  {
    ::unlink(g_partial);
  }
  std::signal(sig, SIG_DFL);
  std::raise(sig);
}

// Names the unfinished output for the handler ("" : none), with the signals blocked meanwhile
// (the handler never sees a half-copied name).
void SetPartial(const char* path)
{
  sigset_t block, old;
  sigemptyset(&block);
  sigaddset(&block, SIGINT);
  sigaddset(&block, SIGTERM);
  sigprocmask(SIG_BLOCK, &block, &old);
  std::snprintf(g_partial, sizeof(g_partial), "%s", path);
  sigprocmask(SIG_SETMASK, &old, nullptr);
}

// Calls write(path) with a temporary path in OUTPUT's directory (the same extension, so the same
// format), then renames it to OUTPUT; on any error the temporary file is removed.
template <class F>
void WriteOutput(const std::string& out, F&& write)
{
  const std::filesystem::path target(out);
  const std::string tmp = (target.parent_path() /
    (".partial-" + std::to_string(::getpid()) + "-" + target.filename().string()))
                            .string();
  if (tmp.size() >= sizeof(g_partial))
  {
    throw std::runtime_error(out + ": the path is too long");
  }
  SetPartial(tmp.c_str());
  try
  {
    write(tmp);
    if (std::rename(tmp.c_str(), out.c_str()) != 0)
    {
      throw std::runtime_error(out + ": cannot rename the finished output into place (" +
        std::strerror(errno) + ")");
    }
  }
  catch (...)
  {
    ::unlink(tmp.c_str());
    SetPartial("");
    throw;
  }
  SetPartial("");
}

struct Mesh
{
  std::vector<float> p;
  std::vector<std::uint32_t> t;
};

// The displaced sphere's radius at polar angle th and azimuth ph.
double ScanRadius(double th, double ph)
{
  return 1.0 + 0.08 * std::sin(5 * th) * std::cos(4 * ph) + 0.03 * std::sin(17 * th + 3 * ph) +
    0.01 * std::cos(41 * ph) * std::sin(29 * th);
}

Mesh Scan(std::uint64_t triangles)
{
  // UV sphere with n rings and 2n segments: about 4 n^2 triangles
  const int n = std::max(4, int(std::sqrt(double(triangles) / 4.0)));
  const int m = 2 * n;
  Mesh mesh;
  const auto radius = ScanRadius;
  mesh.p.insert(mesh.p.end(), { 0.f, 0.f, float(radius(0, 0)) });
  for (int i = 1; i < n; ++i)
  {
    const double th = M_PI * i / n;
    for (int j = 0; j < m; ++j)
    {
      const double ph = 2 * M_PI * j / m;
      const double r = radius(th, ph);
      mesh.p.insert(mesh.p.end(), { float(1.3 * r * std::sin(th) * std::cos(ph)),
                                    float(r * std::sin(th) * std::sin(ph)), float(r * std::cos(th)) });
    }
  }
  mesh.p.insert(mesh.p.end(), { 0.f, 0.f, float(-radius(M_PI, 0)) });
  const std::uint32_t south = std::uint32_t(mesh.p.size() / 3 - 1);
  auto id = [&](int i, int j) { return std::uint32_t(1 + (i - 1) * m + (j % m)); };
  for (int j = 0; j < m; ++j)
  {
    mesh.t.insert(mesh.t.end(), { 0, id(1, j), id(1, j + 1) });
    mesh.t.insert(mesh.t.end(), { south, id(n - 1, j + 1), id(n - 1, j) });
  }
  for (int i = 1; i < n - 1; ++i)
  {
    for (int j = 0; j < m; ++j)
    {
      mesh.t.insert(mesh.t.end(), { id(i, j), id(i + 1, j), id(i + 1, j + 1) });
      mesh.t.insert(mesh.t.end(), { id(i, j), id(i + 1, j + 1), id(i, j + 1) });
    }
  }
  return mesh;
}

// `scan --order rings`: n rings of 2n vertices between two poles on the x axis (the longest, as
// in Scan), streamed to the writer ring by ring: about 4 n^2 triangles in O(chunk) memory.
void WriteScanRings(std::uint64_t triangles, const std::string& path)
{
  const std::uint64_t n = std::max<std::uint64_t>(4, std::uint64_t(std::sqrt(double(triangles) / 4.0)));
  const std::uint64_t m = 2 * n;
  const std::uint64_t nv = 2 + (n - 1) * m;
  const std::uint64_t nt = 2 * m + 2 * m * (n - 2);
  if (nv > std::numeric_limits<std::uint32_t>::max())
  {
    throw std::runtime_error("too many vertices for 32-bit indices: " + std::to_string(nv));
  }
  auto w = io::MeshWriter::Create(path, false);
  w->Begin(nv, nt, io::VertexLayout{});
  const std::uint64_t chunk = 1 << 16;
  std::vector<float> xyz;
  xyz.reserve(3 * chunk);
  std::uint64_t first = 0;
  auto flushVertices = [&]() {
    io::VertexChunk c;
    c.first = first;
    c.count = xyz.size() / 3;
    c.xyz = xyz.data();
    w->Vertices(c);
    first += c.count;
    xyz.clear();
  };
  auto vertex = [&](double th, double ph) {
    const double r = ScanRadius(th, ph);
    xyz.insert(xyz.end(), { float(1.3 * r * std::cos(th)), float(r * std::sin(th) * std::cos(ph)),
                            float(r * std::sin(th) * std::sin(ph)) });
    if (xyz.size() == 3 * chunk)
    {
      flushVertices();
    }
  };
  vertex(0, 0);
  for (std::uint64_t i = 1; i < n; ++i)
  {
    for (std::uint64_t j = 0; j < m; ++j)
    {
      vertex(M_PI * double(i) / double(n), 2 * M_PI * double(j) / double(m));
    }
  }
  vertex(M_PI, 0);
  flushVertices();
  const std::uint32_t last = std::uint32_t(nv - 1);
  auto id = [&](std::uint64_t i, std::uint64_t j) { return std::uint32_t(1 + (i - 1) * m + (j % m)); };
  std::vector<std::uint32_t> t;
  t.reserve(3 * chunk + 6);
  auto emit = [&](std::initializer_list<std::uint32_t> v) {
    t.insert(t.end(), v);
    if (t.size() >= 3 * chunk)
    {
      w->Triangles(t.data(), t.size() / 3);
      t.clear();
    }
  };
  for (std::uint64_t j = 0; j < m; ++j)
  {
    emit({ 0, id(1, j), id(1, j + 1) });
  }
  for (std::uint64_t i = 1; i + 1 < n; ++i)
  {
    for (std::uint64_t j = 0; j < m; ++j)
    {
      emit({ id(i, j), id(i + 1, j), id(i + 1, j + 1) });
      emit({ id(i, j), id(i + 1, j + 1), id(i, j + 1) });
    }
  }
  for (std::uint64_t j = 0; j < m; ++j)
  {
    emit({ last, id(n - 1, j + 1), id(n - 1, j) });
  }
  if (!t.empty())
  {
    w->Triangles(t.data(), t.size() / 3);
  }
  w->End();
  std::printf("sipmss-meshgen: wrote %s: %llu vertices, %llu triangles\n", path.c_str(),
    (unsigned long long)nv, (unsigned long long)nt);
}

// colorize: normals and checkerboard colors (see the header comment).
void Colorize(const std::string& in, const std::string& out, int cells)
{
  Mesh mesh;
  io::VectorSink sink(mesh.p, mesh.t);
  io::ReadMesh(in, sink);
  const std::size_t nv = mesh.p.size() / 3;
  std::vector<float> normals(3 * nv, 0.0f);
  std::vector<double> acc(3 * nv, 0.0);
  for (std::size_t f = 0; f + 2 < mesh.t.size(); f += 3)
  {
    const float* a = &mesh.p[3 * std::size_t(mesh.t[f])];
    const float* b = &mesh.p[3 * std::size_t(mesh.t[f + 1])];
    const float* c = &mesh.p[3 * std::size_t(mesh.t[f + 2])];
    const double e1[3] = { double(b[0]) - a[0], double(b[1]) - a[1], double(b[2]) - a[2] };
    const double e2[3] = { double(c[0]) - a[0], double(c[1]) - a[1], double(c[2]) - a[2] };
    const double n[3] = { e1[1] * e2[2] - e1[2] * e2[1], e1[2] * e2[0] - e1[0] * e2[2],
      e1[0] * e2[1] - e1[1] * e2[0] }; // (twice the area times the unit normal)
    for (int k = 0; k < 3; ++k)
    {
      for (int d = 0; d < 3; ++d)
      {
        acc[3 * std::size_t(mesh.t[f + k]) + d] += n[d];
      }
    }
  }
  float lo[3] = { 1e30f, 1e30f, 1e30f }, hi[3] = { -1e30f, -1e30f, -1e30f };
  for (std::size_t i = 0; i < nv; ++i)
  {
    const double l = std::sqrt(acc[3 * i] * acc[3 * i] + acc[3 * i + 1] * acc[3 * i + 1] +
      acc[3 * i + 2] * acc[3 * i + 2]);
    for (int d = 0; d < 3; ++d)
    {
      normals[3 * i + d] = l > 0 ? float(acc[3 * i + d] / l) : (d == 2 ? 1.0f : 0.0f);
      lo[d] = std::min(lo[d], mesh.p[3 * i + d]);
      hi[d] = std::max(hi[d], mesh.p[3 * i + d]);
    }
  }
  const double side = std::max({ double(hi[0]) - lo[0], double(hi[1]) - lo[1], double(hi[2]) - lo[2] });
  const double cell = side > 0 ? side / cells : 1.0;
  static const std::uint8_t palette[6][3] = { { 230, 40, 40 }, { 40, 200, 60 }, { 40, 70, 230 },
    { 240, 220, 50 }, { 30, 30, 30 }, { 240, 240, 240 } };
  std::vector<std::uint8_t> rgba(4 * nv);
  for (std::size_t i = 0; i < nv; ++i)
  {
    double u[3];
    long long c = 0;
    for (int d = 0; d < 3; ++d)
    {
      u[d] = (double(mesh.p[3 * i + d]) - lo[d]) / cell;
      c += (d + 1) * static_cast<long long>(std::floor(u[d]));
    }
    const std::uint8_t* base = palette[((c % 6) + 6) % 6];
    // a smooth shade inside the cell (a linear ramp along x), so that the colors also vary
    const double shade = 0.75 + 0.25 * (u[0] - std::floor(u[0]));
    for (int k = 0; k < 3; ++k)
    {
      rgba[4 * i + k] = std::uint8_t(std::lround(std::min(255.0, base[k] * shade)));
    }
    rgba[4 * i + 3] = 255;
  }
  io::VertexLayout layout;
  layout.normals = true;
  layout.colors = true;
  auto w = io::MeshWriter::Create(out, false);
  w->Begin(nv, mesh.t.size() / 3, layout);
  io::VertexChunk chunk;
  chunk.count = nv;
  chunk.xyz = mesh.p.data();
  chunk.normals = normals.data();
  chunk.rgba = rgba.data();
  w->Vertices(chunk);
  w->Triangles(mesh.t.data(), mesh.t.size() / 3);
  w->End();
}

void Order(Mesh& mesh, const std::string& order)
{
  const std::size_t nv = mesh.p.size() / 3;
  std::vector<std::uint32_t> perm(nv);
  std::iota(perm.begin(), perm.end(), 0u);
  std::mt19937_64 rng(7);
  if (order == "shuffled")
  {
    std::shuffle(perm.begin(), perm.end(), rng);
  }
  else
  {
    float lo[3] = { 1e30f, 1e30f, 1e30f }, hi[3] = { -1e30f, -1e30f, -1e30f };
    for (std::size_t i = 0; i < nv; ++i)
      for (int d = 0; d < 3; ++d)
      {
        lo[d] = std::min(lo[d], mesh.p[3 * i + d]);
        hi[d] = std::max(hi[d], mesh.p[3 * i + d]);
      }
    int axis = 0;
    for (int d = 1; d < 3; ++d)
      if (hi[d] - lo[d] > hi[axis] - lo[axis])
        axis = d;
    std::stable_sort(perm.begin(), perm.end(),
      [&](std::uint32_t a, std::uint32_t b) { return mesh.p[3 * a + axis] < mesh.p[3 * b + axis]; });
  }
  std::vector<std::uint32_t> rank(nv);
  std::vector<float> p(mesh.p.size());
  for (std::size_t i = 0; i < nv; ++i)
  {
    rank[perm[i]] = std::uint32_t(i);
    std::copy_n(&mesh.p[3 * perm[i]], 3, &p[3 * i]);
  }
  mesh.p.swap(p);
  const std::size_t nt = mesh.t.size() / 3;
  for (auto& v : mesh.t)
    v = rank[v];
  std::vector<std::uint32_t> fperm(nt);
  std::iota(fperm.begin(), fperm.end(), 0u);
  if (order == "shuffled")
    std::shuffle(fperm.begin(), fperm.end(), rng);
  else
    std::stable_sort(fperm.begin(), fperm.end(), [&](std::uint32_t a, std::uint32_t b) {
      return *std::min_element(&mesh.t[3 * a], &mesh.t[3 * a + 3]) <
        *std::min_element(&mesh.t[3 * b], &mesh.t[3 * b + 3]);
    });
  std::vector<std::uint32_t> t(mesh.t.size());
  for (std::size_t i = 0; i < nt; ++i)
    std::copy_n(&mesh.t[3 * fperm[i]], 3, &t[3 * i]);
  mesh.t.swap(t);
}

void Write(const Mesh& mesh, const std::string& path)
{
  auto w = io::MeshWriter::Create(path, false);
  w->Begin(mesh.p.size() / 3, mesh.t.size() / 3, io::VertexLayout{});
  const std::size_t chunk = 1 << 16;
  for (std::size_t first = 0; first < mesh.p.size() / 3; first += chunk)
  {
    io::VertexChunk c;
    c.first = first;
    c.count = std::min(chunk, mesh.p.size() / 3 - first);
    c.xyz = &mesh.p[3 * first];
    w->Vertices(c);
  }
  for (std::size_t first = 0; first < mesh.t.size() / 3; first += chunk)
  {
    w->Triangles(&mesh.t[3 * first], std::min(chunk, mesh.t.size() / 3 - first));
  }
  w->End();
  std::printf("sipmss-meshgen: wrote %s: %zu vertices, %zu triangles\n", path.c_str(),
    mesh.p.size() / 3, mesh.t.size() / 3);
}
} // namespace

int main(int argc, char** argv)
{
  CLI::App app{ "sipmss-meshgen: generated inputs for SIPMSS demos, tests and benchmarks" };
  app.require_subcommand(1);
  std::string out, in, order = "scanner";
  std::uint64_t triangles = 200000;
  int levels = 1;
  double displace = 0.02;
  auto* scan = app.add_subcommand("scan", "a bumpy closed scan-like surface");
  scan->add_option("OUTPUT", out)->required();
  scan->add_option("--triangles", triangles, "about this many triangles")->check(CLI::Range(16.0, 4e9));
  scan->add_option("--order", order,
        "scanner, shuffled, or rings (streamed as generated, in bounded memory)")
    ->check(CLI::IsMember({ "scanner", "shuffled", "rings" }));
  auto* sub = app.add_subcommand("subdivide", "midpoint subdivision with displacement");
  sub->add_option("INPUT", in)->required();
  sub->add_option("OUTPUT", out)->required();
  sub->add_option("--levels", levels)->check(CLI::Range(0, 6));
  sub->add_option("--displace", displace, "displacement as a fraction of the edge length");
  sub->add_option("--order", order)->check(CLI::IsMember({ "scanner", "shuffled" }));
  double memoryMB = 512;
  std::vector<std::string> tmpdirs;
  sub->add_option("--memory-mb", memoryMB,
       "memory budget of the mesh and its sorts in MiB (default 512; 0: unbounded); beyond it "
       "they go to temporary files")
    ->check(CLI::Range(0.0625, 1e9) | CLI::IsMember({ "0" }));
  sub->add_option("--tmpdir", tmpdirs, "directory for the temporary files (repeatable)")
    ->expected(1)
    ->allow_extra_args(false)
    ->multi_option_policy(CLI::MultiOptionPolicy::TakeAll);
  auto* colorize = app.add_subcommand("colorize",
    "the input with per-vertex normals and checkerboard colors (sharp borders)");
  std::string colorIn, colorOut;
  int cells = 8;
  colorize->add_option("INPUT", colorIn)->required();
  colorize->add_option("OUTPUT", colorOut)->required();
  colorize->add_option("--cells", cells, "checkerboard cells along the longest axis (default 8)")
    ->check(CLI::Range(1, 100000));
  try
  {
    app.parse(argc, argv);
  }
  catch (const CLI::ParseError& e)
  {
    return app.exit(e) == 0 ? 0 : 2;
  }
  std::signal(SIGINT, OnSignal);
  std::signal(SIGTERM, OnSignal);
  try
  {
    if (*colorize)
    {
      std::error_code same;
      if (std::filesystem::equivalent(colorIn, colorOut, same))
      {
        throw std::runtime_error(colorOut + ": is the input file " + colorIn +
          " (the same file); choose another output path");
      }
      WriteOutput(colorOut, [&](const std::string& path) { Colorize(colorIn, path, cells); });
      return 0;
    }
    if (*scan && order == "rings")
    {
      WriteOutput(out, [&](const std::string& path) { WriteScanRings(triangles, path); });
      return 0;
    }
    if (*sub)
    {
      // The input is the user's data: never its own output (also through a link or ./ path).
      std::error_code same;
      if (std::filesystem::equivalent(in, out, same))
      {
        throw std::runtime_error(out + ": is the input file " + in +
          " (the same file); choose another output path");
      }
      meshgen::SubdivideStats s;
      g_polled = 1;
      WriteOutput(out, [&](const std::string& path) {
        s = meshgen::SubdivideFile(in, path, levels, displace,
          order == "scanner" ? meshgen::Order::Scanner : meshgen::Order::Shuffled,
          std::uint64_t(memoryMB * 1048576.0), tmpdirs, [] { return g_signal != 0; });
      });
      g_polled = 0;
      // (the blocks are what the budget bounds; the process's peak adds the code, the reader's
      // and writer's buffers and the sorts' working memory)
      struct rusage ru = {};
      getrusage(RUSAGE_SELF, &ru);
      std::printf("sipmss-meshgen: wrote %s: %llu vertices, %llu triangles (%s, %.1f MB of blocks"
                  " in memory at most, %.1f MB of temporary files, peak RSS of the process"
                  " %.1f MiB)\n",
        out.c_str(), (unsigned long long)s.vertices, (unsigned long long)s.triangles,
        s.outOfCore ? "out of core" : "in core", double(s.peakBytes) / 1e6,
        double(s.peakFileBytes) / 1e6, double(ru.ru_maxrss) / 1024.0);
      return 0;
    }
    Mesh mesh = Scan(triangles);
    Order(mesh, order);
    WriteOutput(out, [&](const std::string& path) { Write(mesh, path); });
  }
  catch (const meshgen::Interrupted&)
  {
    std::fprintf(stderr, "sipmss-meshgen: interrupted; nothing was written\n");
    return 128 + int(g_signal);
  }
  catch (const std::exception& e)
  {
    std::fprintf(stderr, "sipmss-meshgen: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
