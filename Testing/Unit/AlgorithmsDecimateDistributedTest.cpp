// The decimation and two-stage across ranks (DecimateOptions::communicator), on ranks that are
// threads of this process: for 1 to 4 ranks and pieces cut in several ways, the output (on
// rank 0) has no seam (as many boundary edges as the serial run's), no face twice, its triangle
// count within 1% of the target, and an RMS distance to the input within 1.1 times the serial
// run's.
#include "sipmss/algorithms/Compare.h"
#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/TwoStage.h"

#include "AlgorithmsTestUtil.h"
#include "sipmss/algorithms/ThreadCommunicator.h"

#include <gtest/gtest.h>

#include <map>
#include <mutex>
#include <set>

using namespace sipmss;
using namespace sipmss::algorithms;
using sipmss::testing::AbortLater;
using sipmss::testing::Collect;
using sipmss::testing::Cut;
using sipmss::testing::MemorySource;
using sipmss::testing::Mesh;
using sipmss::testing::Piece;

namespace
{
// One run of the algorithm under test on one rank (comm: null for the serial run).
using Run = std::function<RunStats(const MeshSource&, io::MeshSink&, Communicator*)>;

Run DecimateRun(const DecimateOptions& options)
{
  return [options](const MeshSource& source, io::MeshSink& out, Communicator* comm) {
    DecimateOptions o = options;
    o.communicator = comm;
    NullProgress progress;
    return Decimate(source, out, o, progress);
  };
}

Run TwoStageRun(const TwoStageOptions& options)
{
  return [options](const MeshSource& source, io::MeshSink& out, Communicator* comm) {
    TwoStageOptions o = options;
    o.decimate.communicator = comm;
    NullProgress progress;
    return TwoStage(source, out, o, progress);
  };
}

std::vector<Collect> RunDistributed(
  const Mesh& m, int ranks, Cut cut, const Run& run, std::vector<RunStats>* stats = nullptr)
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
    s[r] = run(MemorySource(pieces[r]), outputs[r], &comm);
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
void ExpectSeamless(
  const Mesh& m, const Run& run, std::size_t target, int ranks, Cut cut, double rmsRatio = 1.1)
{
  Collect serial;
  run(MemorySource(m), serial, nullptr);
  std::vector<RunStats> stats;
  const std::vector<Collect> outs = RunDistributed(m, ranks, cut, run, &stats);
  for (int r = 1; r < ranks; ++r)
  {
    EXPECT_TRUE(outs[std::size_t(r)].m.t.empty()) << "rank " << r;
    EXPECT_EQ(stats[std::size_t(r)].communication.ranks, ranks);
  }
  const Mesh& out = outs[0].m;
  EXPECT_LE(double(std::max(out.t.size() / 3, target) - std::min(out.t.size() / 3, target)),
    0.01 * double(target))
    << out.t.size() / 3 << " triangles, target " << target;
  EXPECT_EQ(BoundaryEdges(out), BoundaryEdges(serial.m));
  EXPECT_EQ(DuplicateFaces(out), 0u);
  const double rmsSerial = Rms(m, serial.m), rms = Rms(m, out);
  EXPECT_LE(rms, rmsRatio * rmsSerial) << rms << " against " << rmsSerial << " serial";
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
      ExpectSeamless(m, DecimateRun(o), o.targetTriangles, ranks, cut);
    }
  }
}

TEST(DecimateDistributed, TheFitLowersTheErrorAcrossRanks)
{
  // Rank 0 fits the result to the pieces' samples of the input (each with the gathered vertex
  // that stands for it), as the serial run does to its own.
  // Also with a bound and no target (the pieces then sample as the serial run does: every
  // second vertex, not for an output of one triangle).
  const Mesh m = sipmss::testing::BumpyUVSphere(50, { 3, -2, 5 });
  DecimateOptions byTarget;
  byTarget.targetTriangles = 1000;
  DecimateOptions byBound;
  byBound.targetTriangles = 0;
  byBound.maximumError = 0.004;
  for (const DecimateOptions& o : { byTarget, byBound })
  {
    DecimateOptions plain = o;
    plain.fitSurface = false;
    for (int ranks : { 1, 2, 3 })
    {
      for (Cut cut : { Cut::Slabs, Cut::Interleaved })
      {
        SCOPED_TRACE(std::to_string(ranks) + " ranks, cut " + std::to_string(int(cut)) +
          (o.targetTriangles ? ", a target" : ", a bound"));
        const Mesh fitted = RunDistributed(m, ranks, cut, DecimateRun(o))[0].m;
        const Mesh unfitted = RunDistributed(m, ranks, cut, DecimateRun(plain))[0].m;
        EXPECT_EQ(fitted.t, unfitted.t); // (the fit moves vertices only)
        EXPECT_LT(Rms(m, fitted), 0.95 * Rms(m, unfitted)) << fitted.t.size() / 3 << " triangles";
      }
    }
  }
}

TEST(DecimateDistributed, LongBordersDoNotTakeThePiecesShare)
{
  // Fine pieces with a small target: each cut has as many vertices as the pieces' share of the
  // target has triangles. The pieces keep their share beside their locked borders (else the
  // rest of a piece goes far below it, and the RMS is many times the serial run's).
  const Mesh m = sipmss::testing::BumpyUVSphere(120); // 57,600 triangles, rings of 240 vertices
  DecimateOptions o;
  o.targetTriangles = 600;
  o.threads = 1;
  for (int ranks : { 2, 4 })
  {
    SCOPED_TRACE(std::to_string(ranks) + " ranks");
    ExpectSeamless(m, DecimateRun(o), o.targetTriangles, ranks, Cut::Blocks);
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
    ExpectSeamless(m, DecimateRun(o), o.targetTriangles, ranks, Cut::Slabs);
    const std::vector<Collect> outs = RunDistributed(m, ranks, Cut::Slabs, DecimateRun(o));
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
  ExpectSeamless(m, DecimateRun(o), o.targetTriangles, 3, Cut::Slabs);
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
  const std::vector<Collect> outs = RunDistributed(m, 3, Cut::Slabs, DecimateRun(o), &stats);
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

TEST(DecimateDistributed, LevelsOfDetailByTheBoundAlone)
{
  // Levels spaced by the bound (level i of K stops at maximumError / 2^(K-1-i)): the pieces stop
  // at the first level's bound, rank 0 makes every level; each is coarser than the one before,
  // seamless, and within its bound.
  const Mesh m = sipmss::testing::BumpyUVSphere(50);
  const int K = 3;
  DecimateOptions o;
  o.maximumError = 4e-3;
  o.levelsOfDetail = K;
  std::vector<std::vector<Mesh>> levels(3);
  std::vector<RunStats> stats;
  RunDistributed(m, 3, Cut::Slabs,
    [&](const MeshSource& source, io::MeshSink& out, Communicator* comm) {
      DecimateOptions mine = o;
      mine.communicator = comm;
      NullProgress progress;
      std::vector<Mesh>& mineLevels = levels[std::size_t(comm->Rank())];
      return Decimate(source, out, mine, progress,
        [&](int, const std::function<void(io::MeshSink&)>& emit) {
          Collect level;
          emit(level);
          mineLevels.push_back(std::move(level.m));
        });
    },
    &stats);
  ASSERT_EQ(levels[0].size(), std::size_t(K));
  std::size_t before = m.t.size();
  for (int i = 0; i < K; ++i)
  {
    const Mesh& level = levels[0][std::size_t(i)];
    EXPECT_LT(level.t.size(), before) << "level " << i;
    before = level.t.size();
    EXPECT_EQ(BoundaryEdges(level), 0u) << "level " << i;
    EXPECT_EQ(DuplicateFaces(level), 0u) << "level " << i;
    EXPECT_LE(Rms(m, level), o.maximumError * LevelBoundFraction(i, K)) << "level " << i;
  }
  EXPECT_LE(stats[0].achievedError, o.maximumError * (1 + 1e-6));
}

TEST(DecimateDistributed, AFailureOnOneRankReachesEveryRank)
{
  // Rank 1's progress aborts at some point of the run, or its piece has a face that names a
  // vertex it does not have: every rank fails, none waits.
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
  const std::vector<Collect> outs = RunDistributed(m, 1, Cut::Blocks, DecimateRun(o));
  EXPECT_EQ(outs[0].m.p, serial.m.p);
  EXPECT_EQ(outs[0].m.t, serial.m.t);
}

TEST(TwoStageDistributed, NoSeamsNoDuplicates)
{
  // Stage 1 is the distributed clustering (the exact serial clustering, cut into the ranks'
  // pieces), stage 2 the distributed decimation of those pieces: the same checks against the
  // serial two-stage run. (The serial stage 1 sums in doubles, the distributed one exactly: the
  // clustered meshes differ in the last bits.)
  const Mesh m = sipmss::testing::BumpyUVSphere(80, { 3, -2, 5 }); // 25,600 triangles
  TwoStageOptions o;
  o.gridDimension = 60;
  o.threads = 1;
  o.decimate.targetTriangles = 1500;
  o.decimate.threads = 1;
  for (int ranks = 1; ranks <= 4; ++ranks)
  {
    for (Cut cut : { Cut::Blocks, Cut::Interleaved, Cut::LastEmpty })
    {
      SCOPED_TRACE(std::to_string(ranks) + " ranks, cut " + std::to_string(int(cut)));
      ExpectSeamless(m, TwoStageRun(o), o.decimate.targetTriangles, ranks, cut);
    }
  }
}

TEST(TwoStageDistributed, OutOfCoreWithAttributesAndAnOpenBoundary)
{
  // Out of core in one DML for both stages (a budget that needs it), with the scalar as an
  // attribute and the sheet's boundary locked: the same checks.
  const Mesh m = Sheet(90); // 16,200 triangles
  TwoStageOptions o;
  o.gridDimension = 70;
  o.threads = 1;
  o.decimate.targetTriangles = 1200;
  o.decimate.lockBoundary = true;
  o.decimate.threads = 1;
  o.decimate.storage.policy = storage::ModePolicy::OutOfCore;
  o.decimate.storage.memoryBudget = 1u << 20;
  ParseAttributeWeights("s:0.5", o.decimate.attributes);
  std::vector<RunStats> stats;
  ExpectSeamless(m, TwoStageRun(o), o.decimate.targetTriangles, 3, Cut::Slabs);
  RunDistributed(m, 3, Cut::Slabs, TwoStageRun(o), &stats);
  for (const RunStats& s : stats)
  {
    EXPECT_TRUE(s.storage.usedOutOfCore);
    EXPECT_LE(s.storage.peakBytes, o.decimate.storage.memoryBudget);
    // (both stages' traffic: the clustering's exchanges and the gather)
    EXPECT_EQ(s.communication.perRank.size(), 12u);
  }
}

TEST(TwoStageDistributed, CarriedQuadricsAreRefusedOnSeveralRanks)
{
  const Mesh m = sipmss::testing::BumpyUVSphere(20);
  TwoStageOptions o;
  o.carryQuadrics = true;
  o.decimate.targetTriangles = 100;
  std::mutex mutex;
  std::vector<std::string> errors;
  RunRanks(2, [&](Communicator& comm) {
    try
    {
      Collect out;
      TwoStageRun(o)(MemorySource(Piece(m, 2, comm.Rank(), Cut::Slabs)), out, &comm);
    }
    catch (const std::invalid_argument& e)
    {
      std::lock_guard<std::mutex> lock(mutex);
      errors.emplace_back(e.what());
    }
  });
  ASSERT_EQ(errors.size(), 2u);
  EXPECT_NE(errors[0].find("cell quadrics"), std::string::npos) << errors[0];
}
