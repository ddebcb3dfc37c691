// The one request of every front end (Simplify.h): the algorithms' defaults, the rules and their
// words, and that Simplify() runs what the request asks (the same mesh as the core called
// directly with the same options).
#include "sipmss/algorithms/Simplify.h"

#include "AlgorithmsTestUtil.h"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>

using namespace sipmss;
using namespace sipmss::algorithms;
using sipmss::testing::Collect;
using sipmss::testing::MemorySource;
using sipmss::testing::Mesh;

namespace
{
// An open, bumpy n x n grid: boundaries all round.
Mesh Sheet(int n)
{
  Mesh m;
  for (int j = 0; j < n; ++j)
  {
    for (int i = 0; i < n; ++i)
    {
      m.p.insert(m.p.end(), { float(i) / float(n - 1), float(j) / float(n - 1),
                              0.05f * float((i * 7 + j * 13) % 5) / 5.0f });
    }
  }
  for (int j = 0; j + 1 < n; ++j)
  {
    for (int i = 0; i + 1 < n; ++i)
    {
      const std::uint32_t a = std::uint32_t(j * n + i), b = a + 1, c = a + 1 + std::uint32_t(n),
                          d = a + std::uint32_t(n);
      m.t.insert(m.t.end(), { a, b, c, a, c, d });
    }
  }
  return m;
}

std::vector<Parameter> ProblemParameters(const SimplifyRequest& r)
{
  std::vector<Parameter> out;
  for (const auto& p : Problems(r))
  {
    out.push_back(p.parameter);
  }
  return out;
}

void ExpectSameMesh(const Mesh& a, const Mesh& b)
{
  ASSERT_EQ(a.p.size(), b.p.size());
  ASSERT_EQ(a.t, b.t);
  for (std::size_t i = 0; i < a.p.size(); ++i)
  {
    ASSERT_EQ(a.p[i], b.p[i]) << i;
  }
}
} // namespace

TEST(Simplify, EachAlgorithmHasItsDefaults)
{
  SimplifyRequest r;
  EXPECT_EQ(r.algorithm, Algorithm::Cluster);
  EXPECT_EQ(r.EffectiveGrid(), kDefaultClusterGrid);
  EXPECT_EQ(r.EffectiveBoundaryWeight(), kDefaultClusterBoundaryWeight);
  r.algorithm = Algorithm::TwoStage;
  EXPECT_EQ(r.EffectiveGrid(), kDefaultTwoStageGrid); // (no triangle target)
  EXPECT_EQ(r.EffectiveBoundaryWeight(), kDefaultDecimateBoundaryWeight);
  // With a triangle target: the grid whose clustered mesh has about 16 times its triangles,
  // never coarser than 300.
  r.targetTriangles = 10000;
  EXPECT_EQ(r.EffectiveGrid(), kDefaultTwoStageGrid); // (ceil(sqrt(160000 / 3.4)) = 217)
  r.targetTriangles = 19000;
  EXPECT_EQ(r.EffectiveGrid(), 300); // (298.9)
  r.targetTriangles = 19126;
  EXPECT_EQ(r.EffectiveGrid(), 301);
  r.targetTriangles = 100000;
  EXPECT_EQ(r.EffectiveGrid(), 686); // ceil(685.99)
  r.targetTriangles = std::uint64_t(1) << 40;
  EXPECT_EQ(r.EffectiveGrid(), kMaximumGrid);
  r.targetTriangles = 0;
  r.algorithm = Algorithm::Decimate;
  EXPECT_EQ(r.EffectiveBoundaryWeight(), kDefaultDecimateBoundaryWeight);
  r.grid = 77;
  r.boundaryWeight = 3.0;
  EXPECT_EQ(r.EffectiveGrid(), 77);
  EXPECT_EQ(r.EffectiveBoundaryWeight(), 3.0);
  EXPECT_STREQ(ToString(Algorithm::TwoStage), "two-stage");
  EXPECT_STREQ(CliOption(Parameter::WeldDistance), "--weld");
}

TEST(Simplify, TheRulesNameEachParameterAndItsValue)
{
  EXPECT_TRUE(Problems(SimplifyRequest{}).empty());
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  struct Case
  {
    void (*set)(SimplifyRequest&);
    Parameter parameter;
    const char* words;
  };
  const Case cases[] = {
    { [](SimplifyRequest& r) { r.targetReduction = std::nan(""); }, Parameter::TargetReduction,
      "must be a finite number, not nan" },
    { [](SimplifyRequest& r) { r.targetReduction = 1.5; }, Parameter::TargetReduction,
      "must be between 0 and 1, not 1.5" },
    { [](SimplifyRequest& r) { r.maximumError = -1; }, Parameter::MaximumError,
      "must be a number of at least 0 (infinite: no bound), not -1" },
    { [](SimplifyRequest& r) { r.levelsOfDetail = 65; }, Parameter::LevelsOfDetail,
      "must be between 1 and 64, not 65" },
    { [](SimplifyRequest& r) { r.grid = 65536; }, Parameter::Grid,
      "must be between 0 and 65535, not 65536" },
    { [](SimplifyRequest& r) { r.bounds = std::array<double, 6>{ 0, 1, 0, std::nan(""), 0, 1 }; },
      Parameter::Bounds, "must be finite numbers, not nan" },
    { [](SimplifyRequest& r) { r.boundaryWeight = 2e9; }, Parameter::BoundaryWeight,
      "must be between 0 and 1e+09, not 2e+09" },
    { [](SimplifyRequest& r) { r.weldDistance = std::numeric_limits<double>::infinity(); },
      Parameter::WeldDistance, "must be a finite number (negative: no welding), not inf" },
    { [](SimplifyRequest& r) { r.memoryBudgetMB = 0.01; }, Parameter::MemoryBudget,
      "must be 0 (automatic), -1 (unbounded) or between 0.0625 (64 KiB) and 1e9 MiB, not 0.01" },
    { [](SimplifyRequest& r) { r.threads = 257; }, Parameter::Threads,
      "must be between 0 and 256, not 257" },
    { [](SimplifyRequest& r) { r.pruneSize = 1.5; }, Parameter::PruneSize,
      "must be between 0 and 1, not 1.5" },
  };
  for (const Case& c : cases)
  {
    SimplifyRequest r;
    c.set(r);
    const auto problems = Problems(r);
    ASSERT_EQ(problems.size(), 1u) << c.words;
    EXPECT_EQ(problems[0].parameter, c.parameter) << c.words;
    EXPECT_EQ(problems[0].problem, c.words);
  }
  // what is meaningful has no problem: no bound, no welding, unbounded memory, every core
  SimplifyRequest ok;
  ok.maximumError = inf;
  ok.weldDistance = -1;
  ok.memoryBudgetMB = kUnboundedMemoryBudget;
  ok.threads = 0;
  ok.targetReduction = 0;
  EXPECT_TRUE(Problems(ok).empty());
  // several at once: each is named
  SimplifyRequest bad;
  bad.targetReduction = nan;
  bad.threads = -1;
  EXPECT_EQ(ProblemParameters(bad), (std::vector<Parameter>{ Parameter::TargetReduction, Parameter::Threads }));
}

TEST(Simplify, RunsWhatTheRequestAsks)
{
  const Mesh in = Sheet(40);
  NullProgress none;
  {
    SimplifyRequest r;
    r.algorithm = Algorithm::Cluster;
    r.grid = 12;
    r.boundaryWeight = 1.0;
    r.memoryBudgetMB = 1;
    Collect viaRequest, direct;
    const RunStats s = Simplify(r, MemorySource(in), viaRequest, none);
    ClusterOptions o;
    o.maximumGridDimension = 12;
    o.boundaryQuadrics = true;
    o.boundaryWeight = 1.0;
    ApplyMemoryBudget(1, o.storage);
    Cluster(MemorySource(in), direct, o, none);
    ExpectSameMesh(viaRequest.m, direct.m);
    EXPECT_EQ(s.memoryBudgetBytes, std::uint64_t(1) << 20);
    EXPECT_TRUE(s.memoryBudgetOrigin.empty()); // given
  }
  {
    SimplifyRequest r;
    r.algorithm = Algorithm::Decimate;
    r.targetTriangles = 300;
    r.lockBoundary = true;
    r.weldDistance = 0;
    r.mode = storage::ModePolicy::OutOfCore;
    r.memoryBudgetMB = 1;
    Collect viaRequest, direct;
    const RunStats s = Simplify(r, MemorySource(in), viaRequest, none);
    EXPECT_TRUE(s.storage.usedOutOfCore);
    DecimateOptions o;
    o.targetTriangles = 300;
    o.lockBoundary = true;
    o.weldDistance = 0;
    Decimate(MemorySource(in), direct, o, none);
    ExpectSameMesh(viaRequest.m, direct.m); // (the storage mode does not change the result)
    EXPECT_LE(s.outputTriangles, 300u);
  }
  {
    SimplifyRequest r;
    r.algorithm = Algorithm::TwoStage; // grid: the automatic one for 200 triangles (300)
    r.targetTriangles = 200;
    Collect viaRequest, direct;
    Simplify(r, MemorySource(in), viaRequest, none);
    TwoStageOptions o;
    o.gridDimension = AutomaticTwoStageGrid(200);
    o.decimate.targetTriangles = 200;
    TwoStage(MemorySource(in), direct, o, none);
    ExpectSameMesh(viaRequest.m, direct.m);
  }
}
