// The decimation across ranks (DecimateOptions::communicator), on ranks that are threads of this
// process: for 1 to 4 ranks and pieces cut in several ways, the output (on rank 0) has no seam
// (as many boundary edges as the serial run's), no face twice, its triangle count within 1% of
// the target, and an RMS distance to the input within 1.1 times the serial run's.
#include "sipmss/algorithms/Compare.h"
#include "sipmss/algorithms/Decimate.h"

#include "AlgorithmsTestUtil.h"
#include "sipmss/algorithms/ThreadCommunicator.h"

#include <gtest/gtest.h>

#include <map>
#include <mutex>
#include <set>

using namespace sipmss;
using namespace sipmss::algorithms;
using sipmss::testing::Collect;
using sipmss::testing::Cut;
using sipmss::testing::MemorySource;
using sipmss::testing::Mesh;
using sipmss::testing::Piece;

namespace
{
std::vector<Collect> RunDistributed(const Mesh& m, int ranks, Cut cut,
  const DecimateOptions& options, std::vector<RunStats>* stats = nullptr)
{
  std::vector<Collect> outputs(static_cast<std::size_t>(ranks));
  std::vector<RunStats> s(static_cast<std::size_t>(ranks));
  std::vector<Mesh> pieces;
  for (int r = 0; r < ranks; ++r)
  {
    pieces.push_back(Piece(m, ranks, r, cut));
  }
  RunRanks(ranks, [&](Communicator& comm) {
    const std::size_t r = std::size_t(comm.Rank());
    DecimateOptions o = options;
    o.communicator = &comm;
    NullProgress progress;
    s[r] = Decimate(MemorySource(pieces[r]), outputs[r], o, progress);
  });
  if (stats)
  {
    *stats = s;
  }
  return outputs;
}

// Edges used by exactly one face.
std::size_t BoundaryEdges(const Mesh& m)
{
  std::map<std::pair<std::uint32_t, std::uint32_t>, int> uses;
  for (std::size_t f = 0; f < m.t.size(); f += 3)
  {
    for (int k = 0; k < 3; ++k)
    {
      const std::uint32_t a = m.t[f + k], b = m.t[f + (k + 1) % 3];
      ++uses[{ std::min(a, b), std::max(a, b) }];
    }
  }
  std::size_t n = 0;
  for (const auto& e : uses)
  {
    n += e.second == 1;
  }
  return n;
}

// Faces that come twice (the same three vertices, or the same three positions).
std::size_t DuplicateFaces(const Mesh& m)
{
  std::set<std::array<float, 9>> seen;
  std::size_t twice = 0;
  for (std::size_t f = 0; f < m.t.size(); f += 3)
  {
    std::array<std::array<float, 3>, 3> c;
    for (int k = 0; k < 3; ++k)
    {
      c[std::size_t(k)] = { m.p[3 * m.t[f + k]], m.p[3 * m.t[f + k] + 1], m.p[3 * m.t[f + k] + 2] };
    }
    std::sort(c.begin(), c.end());
    std::array<float, 9> key;
    for (int k = 0; k < 9; ++k)
    {
      key[std::size_t(k)] = c[std::size_t(k / 3)][std::size_t(k % 3)];
    }
    twice += !seen.insert(key).second;
  }
  return twice;
}

double Rms(const Mesh& input, const Mesh& output)
{
  TriangleMesh a, b;
  a.points = input.p;
  a.triangles = input.t;
  b.points = output.p;
  b.triangles = output.t;
  CompareOptions c;
  c.samples = 200000;
  return CompareMeshes(a, b, c).rms;
}

// The checks of the issue against a serial run of the same options.
void ExpectSeamless(const Mesh& m, const DecimateOptions& o, int ranks, Cut cut)
{
  NullProgress progress;
  Collect serial;
  Decimate(MemorySource(m), serial, o, progress);
  std::vector<RunStats> stats;
  const std::vector<Collect> outs = RunDistributed(m, ranks, cut, o, &stats);
  for (int r = 1; r < ranks; ++r)
  {
    EXPECT_TRUE(outs[std::size_t(r)].m.t.empty()) << "rank " << r;
    EXPECT_EQ(stats[std::size_t(r)].communication.ranks, ranks);
  }
  const Mesh& out = outs[0].m;
  const std::size_t target = o.targetTriangles;
  EXPECT_LE(double(std::max(out.t.size() / 3, target) - std::min(out.t.size() / 3, target)),
    0.01 * double(target))
    << out.t.size() / 3 << " triangles, target " << target;
  EXPECT_EQ(BoundaryEdges(out), BoundaryEdges(serial.m));
  EXPECT_EQ(DuplicateFaces(out), 0u);
  const double rmsSerial = Rms(m, serial.m), rms = Rms(m, out);
  EXPECT_LE(rms, 1.1 * rmsSerial) << rms << " against " << rmsSerial << " serial";
  EXPECT_EQ(stats[0].outputTriangles, out.t.size() / 3);
  EXPECT_GT(stats[0].achievedError, 0);
  // The point data comes along.
  EXPECT_EQ(out.scalar.size(), out.p.size() / 3);
  if (ranks > 1 && cut != Cut::LastEmpty)
  {
    EXPECT_GT(stats[1].communication.bytesSent, 0u);
  }
}

// A bumpy open sheet: an n x n grid over [0,1]^2 with z = a few waves, scalar s = x.
Mesh Sheet(int n)
{
  Mesh m;
  for (int j = 0; j <= n; ++j)
  {
    for (int i = 0; i <= n; ++i)
    {
      const double x = double(i) / n, y = double(j) / n;
      m.p.insert(m.p.end(),
        { float(x), float(y), float(0.05 * std::sin(9 * x) * std::cos(7 * y) + 0.02 * x * y) });
      m.scalar.push_back(float(x));
    }
  }
  sipmss::testing::GridTriangles(n, m.t);
  return m;
}
} // namespace

TEST(DecimateDistributed, NoSeamsNoDuplicatesOnAClosedSurface)
{
  const Mesh m = sipmss::testing::BumpyUVSphere(50, { 3, -2, 5 }); // 10,000 triangles
  DecimateOptions o;
  o.targetTriangles = 1000;
  for (int ranks = 1; ranks <= 4; ++ranks)
  {
    for (Cut cut : { Cut::Blocks, Cut::Slabs, Cut::Interleaved, Cut::LastEmpty })
    {
      SCOPED_TRACE(std::to_string(ranks) + " ranks, cut " + std::to_string(int(cut)));
      ExpectSeamless(m, o, ranks, cut);
    }
  }
}

TEST(DecimateDistributed, AnOpenSheetKeepsItsBoundaryWhenLocked)
{
  const Mesh m = Sheet(60); // 7,200 triangles, 240 boundary edges
  DecimateOptions o;
  o.targetTriangles = 800;
  o.lockBoundary = true;
  for (int ranks : { 2, 3 })
  {
    SCOPED_TRACE(std::to_string(ranks) + " ranks");
    ExpectSeamless(m, o, ranks, Cut::Slabs);
    const std::vector<Collect> outs = RunDistributed(m, ranks, Cut::Slabs, o);
    EXPECT_EQ(BoundaryEdges(outs[0].m), BoundaryEdges(m));
  }
}

TEST(DecimateDistributed, OutOfCoreAndBoundedRounds)
{
  // A budget small enough for every rank's DML to go out of core and for the gather to take
  // many rounds: the same checks.
  const Mesh m = sipmss::testing::BumpyUVSphere(60);
  DecimateOptions o;
  o.targetTriangles = 2000;
  o.storage.policy = storage::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 1u << 20;
  ExpectSeamless(m, o, 3, Cut::Slabs);
}

TEST(DecimateDistributed, AnErrorBoundIsKeptAcrossRanks)
{
  // With a bound and no target the run goes as far as the bound allows: the achieved error
  // (carried through both passes by the quadrics) stays within it, and the output is not far
  // from the serial run's size.
  const Mesh m = sipmss::testing::BumpyUVSphere(50);
  DecimateOptions o;
  o.maximumError = 2e-3;
  NullProgress progress;
  Collect serial;
  const RunStats s = Decimate(MemorySource(m), serial, o, progress);
  std::vector<RunStats> stats;
  const std::vector<Collect> outs = RunDistributed(m, 3, Cut::Slabs, o, &stats);
  for (const RunStats& r : stats)
  {
    EXPECT_LE(r.achievedError, o.maximumError);
    EXPECT_DOUBLE_EQ(r.errorDiagonal, s.errorDiagonal);
  }
  EXPECT_EQ(BoundaryEdges(outs[0].m), 0u);
  EXPECT_EQ(DuplicateFaces(outs[0].m), 0u);
  EXPECT_LT(outs[0].m.t.size(), m.t.size() / 4);
  EXPECT_LT(double(outs[0].m.t.size()), 1.25 * double(serial.m.t.size()));
}

TEST(DecimateDistributed, AFailureOnOneRankReachesEveryRank)
{
  // Rank 1's progress aborts at some point of the run, or its piece has a face that names a
  // vertex it does not have: every rank fails, none waits.
  struct AbortLater final : Progress
  {
    int polls = 0;
    int limit;
    explicit AbortLater(int n)
      : limit(n)
    {
    }
    void Report(double, const char*) override {}
    bool Aborted() override { return ++this->polls > this->limit; }
  };
  const Mesh m = sipmss::testing::BumpyUVSphere(30);
  for (int limit : { 0, 5, 40, 200, 1000000 })
  {
    std::mutex mutex;
    int failed = 0;
    RunRanks(3, [&](Communicator& comm) {
      DecimateOptions o;
      o.targetTriangles = 300;
      o.communicator = &comm;
      Collect out;
      NullProgress quiet;
      AbortLater aborting(limit);
      Progress& progress = comm.Rank() == 1 ? static_cast<Progress&>(aborting) : quiet;
      try
      {
        const Mesh piece = Piece(m, 3, comm.Rank(), Cut::Slabs);
        Decimate(MemorySource(piece), out, o, progress);
      }
      catch (const std::exception&)
      {
        std::lock_guard<std::mutex> lock(mutex);
        ++failed;
      }
    });
    EXPECT_TRUE(failed == 0 || failed == 3) << "abort after " << limit << " polls: " << failed;
    EXPECT_EQ(failed, limit == 0 ? 3 : limit == 1000000 ? 0 : failed) << limit;
  }
  std::mutex mutex;
  int failed = 0;
  RunRanks(2, [&](Communicator& comm) {
    DecimateOptions o;
    o.targetTriangles = 300;
    o.communicator = &comm;
    Mesh piece = Piece(m, 2, comm.Rank(), Cut::Slabs);
    if (comm.Rank() == 1)
    {
      piece.t.insert(piece.t.end(), { std::uint32_t(piece.p.size() / 3 + 5), 0, 1 });
    }
    Collect out;
    NullProgress progress;
    try
    {
      Decimate(MemorySource(piece), out, o, progress);
    }
    catch (const std::exception&)
    {
      std::lock_guard<std::mutex> lock(mutex);
      ++failed;
    }
  });
  EXPECT_EQ(failed, 2);
}

TEST(DecimateDistributed, OneRankIsTheSerialRun)
{
  const Mesh m = sipmss::testing::BumpyUVSphere(30);
  DecimateOptions o;
  o.targetTriangles = 500;
  NullProgress progress;
  Collect serial;
  const Mesh piece = Piece(m, 1, 0, Cut::Blocks); // (its vertices in order of first use)
  Decimate(MemorySource(piece), serial, o, progress);
  const std::vector<Collect> outs = RunDistributed(m, 1, Cut::Blocks, o);
  EXPECT_EQ(outs[0].m.p, serial.m.p);
  EXPECT_EQ(outs[0].m.t, serial.m.t);
}
