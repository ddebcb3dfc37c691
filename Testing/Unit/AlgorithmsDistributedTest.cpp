// The clustering across ranks (ClusterOptions::communicator), on ranks that are threads of this
// process: for 1 to 4 ranks and pieces cut in several ways, the union of the ranks' outputs is
// the serial output (the same triangles at the same coordinates, bit for bit), no triangle comes
// out twice, and the bytes exchanged are counted.
#include "sipmss/algorithms/Cluster.h"

#include "AlgorithmsTestUtil.h"
#include "sipmss/algorithms/ThreadCommunicator.h"

#include <gtest/gtest.h>

#include <functional>
#include <map>
#include <mutex>

using namespace sipmss;
using namespace sipmss::algorithms;
using sipmss::testing::AbortLater;
using sipmss::testing::Collect;
using sipmss::testing::Cut;
using sipmss::testing::Piece;
using sipmss::testing::MemorySource;
using sipmss::testing::Mesh;

namespace
{
struct Distributed
{
  std::vector<Collect> outputs;
  std::vector<RunStats> stats;
};

Distributed RunDistributed(const Mesh& m, int ranks, Cut cut, const ClusterOptions& options)
{
  Distributed d;
  d.outputs.resize(std::size_t(ranks));
  d.stats.resize(std::size_t(ranks));
  std::vector<Mesh> pieces;
  for (int r = 0; r < ranks; ++r)
  {
    pieces.push_back(Piece(m, ranks, r, cut));
  }
  RunRanks(ranks, [&](Communicator& comm) {
    const std::size_t r = std::size_t(comm.Rank());
    ClusterOptions o = options;
    o.communicator = &comm;
    NullProgress progress;
    d.stats[r] = Cluster(MemorySource(pieces[r]), d.outputs[r], o, progress);
  });
  return d;
}

// Clusters the pieces on their ranks with options o (rank r's progress from
// progressOf(r)) and returns how many ranks failed.
int FailedRanks(const std::vector<Mesh>& pieces, ClusterOptions o,
  const std::function<Progress&(int rank)>& progressOf)
{
  std::mutex mutex;
  int failed = 0;
  RunRanks(int(pieces.size()), [&](Communicator& comm) {
    ClusterOptions mine = o;
    mine.communicator = &comm;
    Collect out;
    try
    {
      Cluster(MemorySource(pieces[std::size_t(comm.Rank())]), out, mine, progressOf(comm.Rank()));
    }
    catch (const std::exception&)
    {
      std::lock_guard<std::mutex> lock(mutex);
      ++failed;
    }
  });
  return failed;
}

// A mesh with a scalar that varies over it: a bumpy sphere far from the origin.
Mesh Input() { return sipmss::testing::BumpyUVSphere(40, { 3.0, -2.0, 5.0 }); }

void ExpectUnionIsSerial(const Mesh& m, const ClusterOptions& options, int ranks, Cut cut)
{
  NullProgress progress;
  Collect serial;
  const RunStats serialStats = Cluster(MemorySource(m), serial, options, progress);
  const auto expected = sipmss::testing::TrianglesByCoordinates(serial.m);
  ASSERT_GT(expected.size(), 100u);
  const Distributed d = RunDistributed(m, ranks, cut, options);
  std::multiset<std::array<float, 9>> all;
  std::uint64_t triangles = 0;
  for (int r = 0; r < ranks; ++r)
  {
    const Collect& out = d.outputs[std::size_t(r)];
    const auto mine = sipmss::testing::TrianglesByCoordinates(out.m);
    all.insert(mine.begin(), mine.end());
    triangles += d.stats[std::size_t(r)].outputTriangles;
    EXPECT_EQ(d.stats[std::size_t(r)].communication.ranks, ranks);
    EXPECT_EQ(d.stats[std::size_t(r)].communication.rank, r);
    if (ranks > 1 && cut != Cut::LastEmpty)
    {
      EXPECT_GT(d.stats[std::size_t(r)].communication.bytesSent, 0u) << "rank " << r;
    }
  }
  EXPECT_EQ(triangles, expected.size());
  EXPECT_TRUE(all == expected) << ranks << " ranks, cut " << int(cut) << ": " << all.size()
                               << " triangles against " << expected.size() << " serial";
  EXPECT_NEAR(d.stats[0].achievedError, serialStats.achievedError,
    1e-12 + 1e-9 * serialStats.achievedError);
  EXPECT_DOUBLE_EQ(d.stats[0].errorDiagonal, serialStats.errorDiagonal);
}
} // namespace

TEST(ClusterDistributed, TheUnionOfThePiecesIsTheSerialResult)
{
  const Mesh m = Input();
  for (int grid : { 8, 30 })
  {
    ClusterOptions o;
    o.maximumGridDimension = grid;
    for (int ranks = 1; ranks <= 4; ++ranks)
    {
      for (Cut cut : { Cut::Blocks, Cut::Slabs, Cut::Interleaved, Cut::LastEmpty })
      {
        SCOPED_TRACE("grid " + std::to_string(grid) + ", " + std::to_string(ranks) + " ranks");
        ExpectUnionIsSerial(m, o, ranks, cut);
      }
    }
  }
}

TEST(ClusterDistributed, SampledVertexGivenBoundsAndPointData)
{
  const Mesh m = Input();
  ClusterOptions o;
  o.maximumGridDimension = 17;
  o.fallback = ClusterFallback::SampledVertex;
  o.placementSlack = 0; // (the fallback at work)
  ExpectUnionIsSerial(m, o, 3, Cut::Slabs);
  o = ClusterOptions{};
  o.useBounds = true;
  o.bounds = { 1.5, 4.5, -3.5, -0.5, 3.5, 6.5 };
  ExpectUnionIsSerial(m, o, 4, Cut::Interleaved);
  // The point data of a vertex is the mean over the cell's vertices in every piece: a vertex
  // on a seam counts once per piece, so it is close to, not the same as, the serial mean.
  o = ClusterOptions{};
  o.maximumGridDimension = 12;
  NullProgress progress;
  Collect serial;
  Cluster(MemorySource(m), serial, o, progress);
  const Distributed d = RunDistributed(m, 2, Cut::Slabs, o);
  std::map<std::array<float, 3>, float> scalar;
  for (std::size_t v = 0; v < serial.m.p.size() / 3; ++v)
  {
    scalar[{ serial.m.p[3 * v], serial.m.p[3 * v + 1], serial.m.p[3 * v + 2] }] = serial.m.scalar[v];
  }
  std::size_t checked = 0;
  for (const Collect& out : d.outputs)
  {
    ASSERT_EQ(out.m.scalar.size(), out.m.p.size() / 3);
    for (std::size_t v = 0; v < out.m.p.size() / 3; ++v)
    {
      const auto it = scalar.find({ out.m.p[3 * v], out.m.p[3 * v + 1], out.m.p[3 * v + 2] });
      ASSERT_NE(it, scalar.end());
      EXPECT_NEAR(out.m.scalar[v], it->second, 0.05);
      ++checked;
    }
  }
  EXPECT_GT(checked, 50u);
}

TEST(ClusterDistributed, OutOfCoreRanksGiveTheSameResult)
{
  // A small budget per rank: the blocks go to files, the exchanges go in many small rounds.
  const Mesh m = sipmss::testing::BumpyUVSphere(120);
  ClusterOptions o;
  o.maximumGridDimension = 60;
  o.storage.policy = storage::ModePolicy::OutOfCore;
  o.storage.memoryBudget = 2u << 20;
  ExpectUnionIsSerial(m, o, 3, Cut::Slabs);
  const Distributed d = RunDistributed(m, 3, Cut::Slabs, o);
  for (const RunStats& s : d.stats)
  {
    EXPECT_TRUE(s.storage.usedOutOfCore);
    EXPECT_GT(s.communication.rounds, 6u); // (three exchanges and their rounds)
  }
}

TEST(ClusterDistributed, BoundaryPlanesAcrossRanksAreRefused)
{
  // An open surface (a half sphere): its boundary planes change the result.
  const Mesh m = Input();
  Mesh upper;
  upper.p = m.p;
  upper.scalar = m.scalar;
  for (std::size_t f = 0; f < m.t.size(); f += 3)
  {
    if (m.p[3 * m.t[f] + 2] > 5.0f && m.p[3 * m.t[f + 1] + 2] > 5.0f && m.p[3 * m.t[f + 2] + 2] > 5.0f)
    {
      upper.t.insert(upper.t.end(), m.t.begin() + f, m.t.begin() + f + 3);
    }
  }
  const Mesh half = Piece(upper, 1, 0, Cut::Blocks); // (only the vertices its faces use)
  ClusterOptions o;
  o.maximumGridDimension = 16;
  o.boundaryQuadrics = true;
  EXPECT_THROW(RunDistributed(half, 2, Cut::Slabs, o), std::invalid_argument);
  // one rank is the serial run, boundary planes and all
  ExpectUnionIsSerial(half, o, 1, Cut::Blocks);
  NullProgress progress;
  Collect with, without;
  Cluster(MemorySource(half), with, o, progress);
  o.boundaryQuadrics = false;
  Cluster(MemorySource(half), without, o, progress);
  EXPECT_NE(with.m.p, without.m.p); // (the planes matter here)
}

TEST(ClusterDistributed, AttributesAcrossRanks)
{
  // With attributes the extensions are doubles added in arrival order: the same triangles, the
  // positions equal to rounding. An empty piece takes the others' attribute list.
  const Mesh m = Input();
  ClusterOptions o;
  o.maximumGridDimension = 14;
  ParseAttributeWeights("s:2", o.attributes);
  NullProgress progress;
  Collect serial;
  Cluster(MemorySource(m), serial, o, progress);
  for (Cut cut : { Cut::Slabs, Cut::LastEmpty })
  {
    const Distributed d = RunDistributed(m, 3, cut, o);
    std::size_t triangles = 0, vertices = 0;
    for (const Collect& out : d.outputs)
    {
      triangles += out.m.t.size() / 3;
      vertices += out.m.p.size() / 3;
    }
    EXPECT_EQ(triangles, serial.m.t.size() / 3) << int(cut);
    EXPECT_GE(vertices, serial.m.p.size() / 3) << int(cut); // (shared vertices in several pieces)
  }
}

TEST(ClusterDistributed, AnAbortDuringTheExchangesReachesEveryRank)
{
  // Rank 1 is aborted after a few polls (inside the exchanges): every rank stops, none waits.
  const Mesh m = Input();
  const std::vector<Mesh> pieces = { Piece(m, 3, 0, Cut::Slabs), Piece(m, 3, 1, Cut::Slabs),
    Piece(m, 3, 2, Cut::Slabs) };
  for (int limit : { 0, 3, 20, 60, 1000000 })
  {
    ClusterOptions o;
    o.maximumGridDimension = 12;
    NullProgress quiet0, quiet2;
    AbortLater aborting(limit);
    const int failed = FailedRanks(pieces, o, [&](int rank) -> Progress& {
      return rank == 1 ? static_cast<Progress&>(aborting) : rank == 0 ? quiet0 : quiet2;
    });
    EXPECT_TRUE(failed == 0 || failed == 3) << "abort after " << limit << " polls: " << failed;
    EXPECT_EQ(failed, limit == 0 ? 3 : limit == 1000000 ? 0 : failed) << limit;
  }
}

TEST(ClusterDistributed, AFailureOnOneRankReachesEveryRank)
{
  // Rank 1's piece has a face that names a vertex it does not have: every rank fails (none
  // waits for it in an exchange).
  const Mesh m = Input();
  std::vector<Mesh> pieces = { Piece(m, 2, 0, Cut::Slabs), Piece(m, 2, 1, Cut::Slabs) };
  pieces[1].t.push_back(std::uint32_t(pieces[1].p.size() / 3 + 5));
  pieces[1].t.push_back(0);
  pieces[1].t.push_back(1);
  NullProgress progress0, progress1;
  EXPECT_EQ(FailedRanks(pieces, ClusterOptions{},
              [&](int rank) -> Progress& { return rank == 0 ? progress0 : progress1; }),
    2);
}
