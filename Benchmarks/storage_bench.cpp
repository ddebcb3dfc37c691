// DML benchmarks:
//  * in-core typed access (Array<T>::Get/Set, ForEachChunk) against a plain std::vector,
//    sequential and random;
//  * out-of-core sequential throughput (ForEachChunk, ReadRange) against raw pread of the same
//    file size;
//  * page replacement on a mesh-like trace: WSClock (static weights, the paper), LRU (static
//    weights, bench-only), WSClock with Adaptive shares and one clock over every page (Clock, the
//    default), at a small budget.
#include "sipmss/storage/DML.h"
#include "sipmss/storage/DMLTesting.h"

#include <benchmark/benchmark.h>

#include <fcntl.h>
#include <unistd.h>

#include <cstdint>
#include <cstdlib>
#include <random>
#include <string>
#include <vector>

namespace
{
using namespace sipmss::storage;

constexpr std::uint64_t kN = 1 << 24; // 16 Mi elements (64 MB of uint32)

std::string BenchDir()
{
  const char* t = std::getenv("TMPDIR");
  return t && *t ? t : "/tmp";
}

std::vector<std::uint32_t> RandomIndices(std::uint64_t n, std::uint64_t range)
{
  std::mt19937_64 rng(42);
  std::vector<std::uint32_t> idx(n);
  for (auto& i : idx)
  {
    i = static_cast<std::uint32_t>(rng() % range);
  }
  return idx;
}

// --- in core ------------------------------------------------------------------------------------
void BM_VectorSequentialSum(benchmark::State& state)
{
  std::vector<std::uint32_t> v(kN, 1);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    for (std::uint64_t i = 0; i < kN; ++i)
    {
      sum += v[i];
    }
    benchmark::DoNotOptimize(sum);
  }
  state.SetItemsProcessed(state.iterations() * kN);
}
BENCHMARK(BM_VectorSequentialSum)->Unit(benchmark::kMillisecond);

void BM_ArrayGetSequentialSum(benchmark::State& state)
{
  DML dml;
  Array<std::uint32_t> a(dml, kN);
  std::uint32_t one = 1;
  dml.Fill(a.Id(), &one);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    for (std::uint64_t i = 0; i < kN; ++i)
    {
      sum += a.Get(i);
    }
    benchmark::DoNotOptimize(sum);
  }
  state.SetItemsProcessed(state.iterations() * kN);
}
BENCHMARK(BM_ArrayGetSequentialSum)->Unit(benchmark::kMillisecond);

void BM_ArrayForEachChunkSum(benchmark::State& state)
{
  DML dml;
  Array<std::uint32_t> a(dml, kN);
  std::uint32_t one = 1;
  dml.Fill(a.Id(), &one);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    a.ForEachChunk(0, kN, Access::Read, [&](const std::uint32_t* d, std::uint64_t, std::uint64_t n) {
      for (std::uint64_t i = 0; i < n; ++i)
      {
        sum += d[i];
      }
    });
    benchmark::DoNotOptimize(sum);
  }
  state.SetItemsProcessed(state.iterations() * kN);
}
BENCHMARK(BM_ArrayForEachChunkSum)->Unit(benchmark::kMillisecond);

void BM_VectorSequentialWrite(benchmark::State& state)
{
  std::vector<std::uint32_t> v(kN);
  for (auto _ : state)
  {
    for (std::uint64_t i = 0; i < kN; ++i)
    {
      v[i] = static_cast<std::uint32_t>(i * 3);
    }
    benchmark::ClobberMemory();
  }
  state.SetItemsProcessed(state.iterations() * kN);
}
BENCHMARK(BM_VectorSequentialWrite)->Unit(benchmark::kMillisecond);

void BM_ArraySetSequential(benchmark::State& state)
{
  DML dml;
  Array<std::uint32_t> a(dml, kN);
  for (auto _ : state)
  {
    for (std::uint64_t i = 0; i < kN; ++i)
    {
      a.Set(i, static_cast<std::uint32_t>(i * 3));
    }
    benchmark::ClobberMemory();
  }
  state.SetItemsProcessed(state.iterations() * kN);
}
BENCHMARK(BM_ArraySetSequential)->Unit(benchmark::kMillisecond);

void BM_VectorRandomRead(benchmark::State& state)
{
  std::vector<std::uint32_t> v(kN, 1);
  const auto idx = RandomIndices(1 << 22, kN);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    for (const std::uint32_t i : idx)
    {
      sum += v[i];
    }
    benchmark::DoNotOptimize(sum);
  }
  state.SetItemsProcessed(state.iterations() * idx.size());
}
BENCHMARK(BM_VectorRandomRead)->Unit(benchmark::kMillisecond);

void BM_ArrayGetRandomRead(benchmark::State& state)
{
  DML dml;
  Array<std::uint32_t> a(dml, kN);
  std::uint32_t one = 1;
  dml.Fill(a.Id(), &one); // touch the memory like the vector (calloc pages are shared zeros)
  const auto idx = RandomIndices(1 << 22, kN);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    for (const std::uint32_t i : idx)
    {
      sum += a.Get(i);
    }
    benchmark::DoNotOptimize(sum);
  }
  state.SetItemsProcessed(state.iterations() * idx.size());
}
BENCHMARK(BM_ArrayGetRandomRead)->Unit(benchmark::kMillisecond);

// --- out of core sequential ------------------------------------------------------------------
constexpr std::uint64_t kFileBytes = 256ull << 20;
constexpr std::uint64_t kOocBudget = 4ull << 20;

Profile OocProfile(std::uint64_t budget)
{
  Profile p;
  p.directories = { BenchDir() };
  p.memoryBudget = budget;
  p.policy = ModePolicy::OutOfCore;
  return p;
}

void FillOoc(DML& dml, Array<std::uint64_t>& a)
{
  a.ForEachChunk(0, a.Size(), Access::Write, [](std::uint64_t* d, std::uint64_t first, std::uint64_t n) {
    for (std::uint64_t i = 0; i < n; ++i)
    {
      d[i] = first + i;
    }
  });
  (void)dml;
}

void BM_OocSequentialForEachChunk(benchmark::State& state)
{
  DML dml;
  dml.Config(OocProfile(kOocBudget));
  Array<std::uint64_t> a(dml, kFileBytes / 8);
  FillOoc(dml, a);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    a.ForEachChunk(0, a.Size(), Access::Read, [&](const std::uint64_t* d, std::uint64_t, std::uint64_t n) {
      for (std::uint64_t i = 0; i < n; ++i)
      {
        sum += d[i];
      }
    });
    benchmark::DoNotOptimize(sum);
  }
  state.SetBytesProcessed(state.iterations() * kFileBytes);
  state.counters["pageKiB"] = static_cast<double>(DMLTestAccess::PageSize(dml)) / 1024.0;
}
BENCHMARK(BM_OocSequentialForEachChunk)->Unit(benchmark::kMillisecond);

void BM_OocSequentialReadRange(benchmark::State& state)
{
  DML dml;
  dml.Config(OocProfile(kOocBudget));
  Array<std::uint64_t> a(dml, kFileBytes / 8);
  FillOoc(dml, a);
  std::vector<std::uint64_t> buf((1 << 20) / 8);
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    for (std::uint64_t first = 0; first < a.Size(); first += buf.size())
    {
      a.Read(first, buf.size(), buf.data());
      for (const std::uint64_t x : buf)
      {
        sum += x;
      }
    }
    benchmark::DoNotOptimize(sum);
  }
  state.SetBytesProcessed(state.iterations() * kFileBytes);
}
BENCHMARK(BM_OocSequentialReadRange)->Unit(benchmark::kMillisecond);

void BM_RawFileSequentialRead(benchmark::State& state)
{
  const std::string path = BenchDir() + "/sipmss-bench-raw-" + std::to_string(::getpid());
  const int fd = ::open(path.c_str(), O_RDWR | O_CREAT | O_TRUNC, 0600);
  if (fd < 0)
  {
    state.SkipWithError("cannot create the raw file");
    return;
  }
  ::unlink(path.c_str());
  const std::size_t chunk = static_cast<std::size_t>(state.range(0));
  std::vector<std::uint64_t> buf(chunk / 8);
  for (std::uint64_t off = 0; off < kFileBytes; off += chunk)
  {
    for (std::size_t i = 0; i < buf.size(); ++i)
    {
      buf[i] = off / 8 + i;
    }
    if (::pwrite(fd, buf.data(), chunk, static_cast<off_t>(off)) != static_cast<ssize_t>(chunk))
    {
      state.SkipWithError("write failed");
      ::close(fd);
      return;
    }
  }
  for (auto _ : state)
  {
    std::uint64_t sum = 0;
    for (std::uint64_t off = 0; off < kFileBytes; off += chunk)
    {
      if (::pread(fd, buf.data(), chunk, static_cast<off_t>(off)) != static_cast<ssize_t>(chunk))
      {
        state.SkipWithError("read failed");
        break;
      }
      for (const std::uint64_t x : buf)
      {
        sum += x;
      }
    }
    benchmark::DoNotOptimize(sum);
  }
  ::close(fd);
  state.SetBytesProcessed(state.iterations() * kFileBytes);
}
BENCHMARK(BM_RawFileSequentialRead)->Arg(64 << 10)->Arg(1 << 20)->Unit(benchmark::kMillisecond);

// --- replacement policies on a mesh-like trace --------------------------------------------------
// A face pass over an indexed mesh: faces are read in order; each face reads the positions of
// its three vertices and updates their quadrics. Vertex indices follow the faces with locality
// (a window around a moving front, like a scan-ordered scan) plus 2% random references.
// Pages are fixed at 16 KiB so the comparison is about replacement, not page size.
struct Quadric
{
  double q[10];
};
struct Vec3
{
  float x, y, z;
};
struct Tri
{
  std::uint32_t v[3];
};

constexpr std::uint32_t kVertices = 1 << 18;
constexpr std::uint32_t kFaces = 2 * kVertices;

enum class PolicyCase
{
  WSClock,
  Lru,
  Adaptive,
  Clock
};

void BM_MeshTrace(benchmark::State& state)
{
  const auto policy = static_cast<PolicyCase>(state.range(0));
  const std::uint64_t budget = static_cast<std::uint64_t>(state.range(1)) << 20;
  Stats last;
  for (auto _ : state)
  {
    state.PauseTiming();
    DML dml;
    Profile p = OocProfile(budget);
    p.pagePolicy = policy == PolicyCase::Adaptive ? PagePolicy::Adaptive
      : policy == PolicyCase::Clock               ? PagePolicy::Clock
                                                  : PagePolicy::StaticWeight;
    p.pageSize = 16 * 1024;
    dml.Config(p);
    DMLTestAccess::SetReplacement(dml, policy == PolicyCase::Lru ? Replacement::Lru : Replacement::WSClock);
    Array<Vec3> pos(dml, kVertices);
    Array<Quadric> quad(dml, kVertices);
    Array<Tri> faces(dml, kFaces);
    std::mt19937 rng(7);
    faces.ForEachChunk(0, kFaces, Access::Write, [&](Tri* t, std::uint64_t first, std::uint64_t n) {
      for (std::uint64_t i = 0; i < n; ++i)
      {
        const std::uint64_t front = (first + i) / 2;
        for (auto& v : t[i].v)
        {
          const std::uint64_t local = front + rng() % 4096;
          v = rng() % 50 == 0 ? rng() % kVertices
                              : static_cast<std::uint32_t>(std::min<std::uint64_t>(local, kVertices - 1));
        }
      }
    });
    const Stats before = dml.GetStats();
    state.ResumeTiming();

    for (std::uint32_t f = 0; f < kFaces; ++f)
    {
      const Tri t = faces.Get(f);
      Vec3 c{ 0, 0, 0 };
      for (const std::uint32_t v : t.v)
      {
        const Vec3 x = pos.Get(v);
        c.x += x.x;
        c.y += x.y;
        c.z += x.z;
      }
      for (const std::uint32_t v : t.v)
      {
        Quadric q = quad.Get(v);
        q.q[0] += c.x;
        q.q[4] += c.y;
        q.q[9] += c.z;
        quad.Set(v, q);
      }
    }

    state.PauseTiming();
    last = dml.GetStats();
    last.misses -= before.misses;
    last.hits -= before.hits;
    last.bytesRead -= before.bytesRead;
    last.bytesWritten -= before.bytesWritten;
    state.ResumeTiming();
  }
  state.counters["misses"] = static_cast<double>(last.misses);
  state.counters["missRate%"] = 100.0 * static_cast<double>(last.misses) /
    static_cast<double>(last.misses + last.hits);
  state.counters["readMiB"] = static_cast<double>(last.bytesRead) / (1 << 20);
  state.counters["writtenMiB"] = static_cast<double>(last.bytesWritten) / (1 << 20);
  state.counters["peakKiB"] = static_cast<double>(last.peakBytes) / 1024.0;
}
BENCHMARK(BM_MeshTrace)
  ->ArgNames({ "policy", "budgetMiB" })
  ->Args({ 0, 4 })
  ->Args({ 1, 4 })
  ->Args({ 2, 4 })
  ->Args({ 3, 4 })
  ->Args({ 0, 1 })
  ->Args({ 1, 1 })
  ->Args({ 2, 1 })
  ->Args({ 3, 1 })
  ->Iterations(1)
  ->Unit(benchmark::kMillisecond);

} // namespace

BENCHMARK_MAIN();
