// Algorithm I across ranks (DecimateOptions::communicator). Partition, lock the borders, then
// simplify the borders again:
// 1. Each rank counts its piece (triangles, bounds, point data); the ranks agree on the point
//    data and sum the counts, so that every rank knows the whole input's size and diagonal.
// 2. Each rank decimates its piece alone with the piece's boundary locked (lockBoundary) and no
//    boundary planes, to kPieceSlack times its share of the target (its share of the first
//    level's) plus kTrianglesPerBorderVertex per locked vertex. A piece's border is where it
//    meets the others: those vertices stay where they are and their border edges stay as they
//    are, on both sides. The run keeps each output vertex's accumulated quadric (finalQuadric).
// 3. Rank 0 gathers the pieces' outputs with their quadrics, in rounds of a bounded size, into a
//    mesh in its DML, numbered piece after piece (the same numbers whatever the round size).
// 4. The borders are joined: the gathered vertices are sorted by position (storage::Sort, within
//    the budget), and a vertex at the same position as one of another piece becomes that vertex
//    (the first piece's), its quadric added to it: the planes of the faces on both sides, as the
//    serial run's vertex has them.
// 5. Rank 0 decimates the joined mesh with the user's options to the target, each vertex
//    starting from its accumulated quadric (initialQuadric with initialQuadricReplacesFaces), so
//    that the error and the bound measure the distance to the input's faces as in one run, and
//    fits the result to the samples of the input the pieces took (finalSamples in step 2, sent
//    with the gather, initialSamples here). The output is on rank 0; the other ranks' outputs
//    are empty.
// The result has no seams (no border edge is left open: the joined mesh is the input's surface)
// and no face twice. It is not the serial result: the first pass's choices are local. Rank 0
// holds the gathered mesh: about kPieceSlack times the target plus the pieces' border strips.
// (Part of Decimate.cpp's translation unit.)
namespace sipmss::algorithms
{
namespace
{
using detail::AgreeOnLayout;
using detail::RoundBytes;
using detail::Rounds;
using detail::StageProgress;
using detail::StoredMesh;

// Each piece stops at this multiple of its share of the target; the gathered pass makes the
// last choices over the whole mesh (docs/benchmarks.md: RMS against the serial run).
constexpr double kPieceSlack = 2.0;
// ... plus this many triangles for each vertex of its locked border: a long border (a cut across
// a 25M-triangle scan has thousands of vertices) would otherwise take the piece's share, and the
// rest of the piece would be decimated far below it, which the gathered pass cannot undo
// (docs/benchmarks.md: Lucy-size on 4 ranks).
constexpr double kTrianglesPerBorderVertex = 2.0;

// Step 1: a piece's size, bounds and point data.
class CountSink final : public io::MeshSink
{
public:
  explicit CountSink(Progress& progress)
    : progress_(progress)
  {
  }
  void Begin(const io::MeshHeader& h) override
  {
    this->layout = h.layout;
    this->faceScalars = h.faceScalars;
  }
  void Vertices(const io::VertexChunk& c) override
  {
    if (c.first == 0 && c.count > 0)
    {
      this->first = { double(c.xyz[0]), double(c.xyz[1]), double(c.xyz[2]) };
    }
    this->vertices = std::max<std::uint64_t>(this->vertices, c.first + c.count);
    detail::ExtendBounds(this->bounds, c.xyz, c.count);
    this->progress_.Poll();
  }
  void Triangles(const std::uint32_t*, std::size_t n) override
  {
    this->triangles += n;
    this->progress_.Poll();
  }
  void End(const io::ReadStats&) override {}
  bool AbortRequested() override { return this->progress_.Aborted(); }

  io::VertexLayout layout;
  std::vector<std::string> faceScalars;
  std::uint64_t vertices = 0, triangles = 0;
  std::array<double, 6> bounds = { kInf, -kInf, kInf, -kInf, kInf, -kInf };
  std::array<double, 3> first = { 0, 0, 0 }; // the first vertex

private:
  static constexpr double kInf = std::numeric_limits<double>::infinity();
  Progress& progress_;
};

// A gathered vertex by position (for step 4): its coordinates' bits (-0 as +0), its piece and
// its number in the gathered mesh.
struct JoinKey
{
  std::uint32_t x, y, z;
  std::uint32_t rank;
  std::uint64_t vertex;
};

std::uint32_t PositionBits(float f)
{
  if (f == 0.0f)
  {
    f = 0.0f;
  }
  std::uint32_t b;
  std::memcpy(&b, &f, 4);
  return b;
}

// The vertex that vertex v of the gathered mesh joins (v itself when it joins none).
std::uint32_t Joined(const std::unordered_map<std::uint32_t, std::uint32_t>& join, std::uint32_t v)
{
  const auto it = join.find(v);
  return it == join.end() ? v : it->second;
}

// Forwards a replay with the joined vertices replaced by the vertex they join.
class JoinSink final : public io::MeshSink
{
public:
  JoinSink(io::MeshSink& inner, const std::unordered_map<std::uint32_t, std::uint32_t>& join)
    : inner_(inner)
    , join_(join)
  {
  }
  void Begin(const io::MeshHeader& h) override { this->inner_.Begin(h); }
  void Vertices(const io::VertexChunk& c) override { this->inner_.Vertices(c); }
  void Triangles(const std::uint32_t* idx, std::size_t n) override
  {
    this->buffer_.assign(idx, idx + 3 * n);
    for (std::uint32_t& v : this->buffer_)
    {
      v = Joined(this->join_, v);
    }
    this->inner_.Triangles(this->buffer_.data(), n);
  }
  void End(const io::ReadStats& s) override { this->inner_.End(s); }
  bool AbortRequested() override { return this->inner_.AbortRequested(); }

private:
  io::MeshSink& inner_;
  const std::unordered_map<std::uint32_t, std::uint32_t>& join_;
  std::vector<std::uint32_t> buffer_;
};

// The message sections of the gather (step 3).
enum : std::uint8_t
{
  kVertexSection = 0,
  kTriangleSection = 1,
  kSampleSection = 2
};

// A sample of the final fit between the passes: a position of the input (input coordinates)
// and the vertex that stands for it (of the piece's output; on rank 0, of the gathered mesh).
struct PieceSample
{
  double p[3];
  std::uint64_t vertex;
};

RunStats DecimateDistributed(const MeshSource& input, io::MeshSink& output,
  const DecimateOptions& given, Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  Communicator& comm = *given.communicator;
  const int N = comm.Size(), rank = comm.Rank();
  RunStats stats;
  Rounds rounds(comm, RoundBytes(given.storage), stats.communication);
  DecimateOptions options = given; // (with the attribute list the ranks agree on)
  std::optional<DML> own; // (or the caller's: two-stage's stage 2, its input in it)
  DML& dml = given.dml ? *given.dml : own.emplace();

  // 1. The piece's size, bounds and point data; the ranks agree on the point data and sum the
  // sizes. A failure on one rank reaches the others at the next agreement.
  CountSink count(progress);
  {
    rounds.Local([&] { progress.BeginPhase("count", 1.0, 20.0); });
    PhaseTimer timer(stats, dml, "count");
    rounds.Local([&] { input(count, io::ReadOptions{}); });
    rounds.Agree();
  }
  std::string attributes = FormatAttributeWeights(options.attributes);
  const io::VertexLayout layout = AgreeOnLayout(count.layout, count.vertices, attributes, rounds);
  options.attributes.clear();
  ParseAttributeWeights(attributes, options.attributes);
  if (!options.selectionArray.empty() &&
    std::find(layout.scalars.begin(), layout.scalars.end(), options.selectionArray) ==
      layout.scalars.end())
  {
    // (the gathered mesh carries point data only; the same words on every rank)
    throw std::invalid_argument("the selection array \"" + options.selectionArray +
      "\" must be point data on more than one rank (a face selection is not carried across "
      "ranks)");
  }
  double lo[3] = { count.bounds[0], count.bounds[2], count.bounds[4] };
  double hi[3] = { count.bounds[1], count.bounds[3], count.bounds[5] };
  rounds.Min(lo, 3);
  rounds.Max(hi, 3);
  std::uint64_t totals[2] = { count.vertices, count.triangles };
  rounds.Sum(totals, 2);
  const std::uint64_t F = totals[1];
  const double diagonal = lo[0] <= hi[0]
    ? std::sqrt((hi[0] - lo[0]) * (hi[0] - lo[0]) + (hi[1] - lo[1]) * (hi[1] - lo[1]) +
        (hi[2] - lo[2]) * (hi[2] - lo[2]))
    : 0.0;
  // One origin for both passes on every rank: rank 0's first vertex, as a serial run on the
  // pieces one after the other has it (the lowest corner when rank 0's piece is empty). A
  // coordinate far smaller than its distance from the origin rounds (DecimateOptions::origin):
  // the same origin rounds it the same way everywhere.
  std::array<double, 3> origin;
  {
    constexpr double inf = std::numeric_limits<double>::infinity();
    double o[4] = { -inf, -inf, -inf, -inf };
    if (rank == 0 && count.vertices > 0)
    {
      o[0] = 1;
      std::copy(count.first.begin(), count.first.end(), o + 1);
    }
    rounds.Max(o, 4);
    origin = o[0] > 0 ? std::array<double, 3>{ o[1], o[2], o[3] }
      : std::array<double, 3>{ lo[0] <= hi[0] ? lo[0] : 0.0, lo[1] <= hi[1] ? lo[1] : 0.0,
          lo[2] <= hi[2] ? lo[2] : 0.0 };
  }
  if (options.errorDiagonal <= 0)
  {
    options.errorDiagonal = diagonal;
  }

  // The target and the first level, on the whole input's count (as one run's Levels).
  const bool boundOnly = BoundIsTheOnlyStop(options);
  std::uint64_t target = options.targetTriangles;
  if (target == 0 && !boundOnly)
  {
    const double r = std::min(1.0, std::max(0.0, options.targetReduction));
    target = std::uint64_t(std::llround(double(F) * (1.0 - r)));
  }
  const int K = std::max(1, options.levelsOfDetail);
  double firstLevel = double(target);
  if (K > 1 && F > target && target > 0)
  {
    firstLevel = std::max(double(target),
      std::round(double(F) * std::pow(double(target) / double(F), 1.0 / double(K))));
  }
  if (own)
  {
    storage::Profile p = options.storage;
    p.structures.push_back({ "decimate", 1,
      std::uint64_t(DecimateBytes(count.vertices, count.triangles, 4 * options.attributes.size())),
      0.0 });
    dml.Config(p);
  }

  // 2. The piece alone, its border locked, into `mine` with its quadrics.
  StoredMesh mine(dml);
  Array<Quadric> quadrics(dml, 1);
  Array<PieceSample> samples(dml, 1); // (the final fit's, for rank 0's pass)
  std::uint64_t nSamples = 0;
  double err = -1; // (relative to the whole input's diagonal, as each pass measures it)
  {
    PhaseTimer timer(stats, dml, "piece");
    rounds.Local([&] {
      if (count.triangles == 0)
      {
        return;
      }
      DecimateOptions o = options;
      o.communicator = nullptr;
      o.dml = &dml;
      o.layout = LayoutPolicy::Keep;
      o.lockBoundary = true;
      o.origin = origin;
      o.boundaryWeight = 0;
      o.pruneSize = 0;
      o.levelsOfDetail = 1;
      o.fitSurface = false; // (an intermediate: rank 0 fits the result to the pieces' samples)
      if (options.fitSurface)
      {
        o.finalSamples = [&samples, &nSamples](const double p[3], std::uint64_t v) {
          if (nSamples == samples.Size())
          {
            samples.Resize(2 * nSamples);
          }
          samples.Set(nSamples++, PieceSample{ { p[0], p[1], p[2] }, v });
        };
        // (as many as the piece's share of the result needs, not its slack's; with a bound
        // alone, as the serial run: SampleInput's default)
        o.fitSampleTriangles = boundOnly ? 0
                                         : std::max<std::uint64_t>(1,
                                             std::uint64_t(std::ceil(firstLevel * double(count.triangles) /
                                               double(std::max<std::uint64_t>(F, 1)))));
      }
      o.maximumError = LevelBound(options, 0); // (the first level's, when it spaces them)
      o.trianglesPerFixedVertex = kTrianglesPerBorderVertex;
      o.targetTriangles = boundOnly ? 0
                                    : std::max<std::uint64_t>(1,
                                        std::uint64_t(std::ceil(kPieceSlack * firstLevel *
                                          double(count.triangles) / double(std::max<std::uint64_t>(F, 1)))));
      o.finalQuadric = [&quadrics](std::uint64_t v, const double q[10]) {
        if (v >= quadrics.Size())
        {
          quadrics.Resize(std::max<std::uint64_t>(v + 1, 2 * quadrics.Size()));
        }
        Quadric Q;
        std::copy(q, q + 10, Q.q);
        quadrics.Set(v, Q);
      };
      StageProgress p1(progress, "piece: ", [](std::uint64_t, std::uint64_t) { return 0.6; });
      RunStats s1;
      RunOnOwnState(o, p1, s1, input, mine, nullptr);
      detail::AddNestedRun(stats, s1, "piece ");
      stats.droppedInputFaces = s1.droppedInputFaces;
      err = s1.achievedError;
    });
    rounds.Agree();
  }
  stats.inputVertices = count.vertices;
  stats.inputTriangles = count.triangles;

  // 3. The gather: every piece's vertices (position, point data, quadric) and triangles go to
  // rank 0, each at its place in the gathered mesh (the pieces one after the other).
  // (per rank: vertices, triangles, the final fit's samples)
  std::vector<std::uint64_t> sizes(3 * std::size_t(N), 0);
  sizes[3 * std::size_t(rank)] = mine.VertexCount();
  sizes[3 * std::size_t(rank) + 1] = mine.TriangleCount();
  sizes[3 * std::size_t(rank) + 2] = nSamples;
  rounds.Sum(sizes.data(), sizes.size());
  std::vector<std::uint64_t> vFirst(std::size_t(N) + 1, 0), tFirst(std::size_t(N) + 1, 0),
    sFirst(std::size_t(N) + 1, 0);
  for (int r = 0; r < N; ++r)
  {
    vFirst[r + 1] = vFirst[r] + sizes[3 * std::size_t(r)];
    tFirst[r + 1] = tFirst[r] + sizes[3 * std::size_t(r) + 1];
    sFirst[r + 1] = sFirst[r] + sizes[3 * std::size_t(r) + 2];
  }
  const std::uint64_t gatheredV = vFirst[N], gatheredT = tFirst[N], gatheredS = sFirst[N];
  if (gatheredV > std::numeric_limits<std::uint32_t>::max() ||
    gatheredT > std::numeric_limits<std::uint32_t>::max())
  {
    throw std::length_error("the gathered mesh has " + std::to_string(gatheredV) +
      " vertices and " + std::to_string(gatheredT) +
      " triangles: more than 32-bit numbers hold (set a smaller target)");
  }
  std::optional<StoredMesh> gathered;
  Array<Quadric> gatheredQuadrics;
  Array<PieceSample> gatheredSamples;
  Array<JoinKey> keys;
  const std::size_t stride = detail::PointDataWords(layout);
  {
    rounds.Local([&] { progress.BeginPhase("gather", 1.0, 1.0); });
    PhaseTimer timer(stats, dml, "gather");
    rounds.Local([&] {
      if (rank == 0)
      {
        gathered.emplace(dml);
        io::MeshHeader h;
        h.vertexCount = gatheredV;
        h.faceCount = gatheredT;
        h.layout = layout;
        gathered->Begin(h);
        gatheredQuadrics = Array<Quadric>(dml, std::max<std::uint64_t>(gatheredV, 1));
        gatheredSamples = Array<PieceSample>(dml, std::max<std::uint64_t>(gatheredS, 1));
        keys = Array<JoinKey>(dml, std::max<std::uint64_t>(gatheredV, 1));
      }
    });
    // (what each rank sends in a round: a share of the round's size, which rank 0 receives)
    const std::size_t share = std::max<std::size_t>(64 << 10, rounds.Limit() / std::size_t(N));
    const std::size_t vertexBytes = 12 + 4 * stride + sizeof(Quadric);
    const std::size_t sectionBytes = 1 + 2 * sizeof(std::uint64_t);
    std::uint64_t nextV = 0, nextT = 0, nextS = 0;
    const std::uint64_t myV = mine.VertexCount(), myT = mine.TriangleCount(), myS = nSamples;
    std::vector<float> xyz;
    std::vector<std::uint32_t> words;
    std::vector<Quadric> q;
    std::vector<JoinKey> k;
    std::vector<PieceSample> s;
    std::uint64_t samplesIn = 0; // (the progress counts them with the triangles)
    detail::PointDataBuffers buffers;
    bool more = true;
    do
    {
      rounds.Local([&] {
        std::vector<std::uint8_t>& b = rounds.send[0];
        auto section = [&](std::uint8_t kind, std::uint64_t first, std::uint64_t n) {
          Rounds::Put(b, kind);
          Rounds::Put(b, first);
          Rounds::Put(b, n);
        };
        if (nextV < myV)
        {
          const std::size_t n = std::size_t(std::min<std::uint64_t>(
            myV - nextV, std::max<std::size_t>(1, (share - sectionBytes) / vertexBytes)));
          mine.ReadVertices(nextV, n, xyz, words);
          q.resize(n);
          quadrics.Read(nextV, n, q.data());
          section(kVertexSection, nextV, n);
          const std::size_t at = b.size();
          b.resize(at + n * vertexBytes);
          std::memcpy(b.data() + at, xyz.data(), 12 * n);
          std::memcpy(b.data() + at + 12 * n, words.data(), 4 * stride * n);
          std::memcpy(b.data() + at + (12 + 4 * stride) * n, q.data(), sizeof(Quadric) * n);
          nextV += n;
        }
        if (nextV == myV && nextT < myT && b.size() + sectionBytes + 12 <= share)
        {
          const std::size_t n = std::size_t(
            std::min<std::uint64_t>(myT - nextT, (share - b.size() - sectionBytes) / 12));
          section(kTriangleSection, nextT, n);
          const std::size_t at = b.size();
          b.resize(at + 12 * n);
          mine.ReadTriangles(nextT, n, reinterpret_cast<std::uint32_t*>(b.data() + at));
          nextT += n;
        }
        if (nextV == myV && nextT == myT && nextS < myS &&
          b.size() + sectionBytes + sizeof(PieceSample) <= share)
        {
          const std::size_t n = std::size_t(std::min<std::uint64_t>(
            myS - nextS, (share - b.size() - sectionBytes) / sizeof(PieceSample)));
          section(kSampleSection, nextS, n);
          const std::size_t at = b.size();
          b.resize(at + sizeof(PieceSample) * n);
          samples.Read(nextS, n, reinterpret_cast<PieceSample*>(b.data() + at));
          nextS += n;
        }
      });
      rounds.Exchange();
      rounds.Local([&] {
        if (rank != 0)
        {
          return;
        }
        for (int r = 0; r < N; ++r)
        {
          const std::vector<std::uint8_t>& m = rounds.received[std::size_t(r)];
          const std::uint8_t* p = m.data();
          const std::uint8_t* end = m.data() + m.size();
          while (p < end)
          {
            if (std::size_t(end - p) < sectionBytes)
            {
              throw std::runtime_error("a malformed gather message from rank " + std::to_string(r));
            }
            const auto kind = Rounds::Take<std::uint8_t>(p);
            const auto first = Rounds::Take<std::uint64_t>(p);
            const auto n = Rounds::Take<std::uint64_t>(p);
            if (kind > kSampleSection)
            {
              throw std::runtime_error("a malformed gather message from rank " + std::to_string(r));
            }
            const std::uint64_t limit = sizes[3 * std::size_t(r) + kind];
            const std::size_t bytes = std::size_t(n) *
              (kind == kVertexSection ? vertexBytes
                                      : (kind == kTriangleSection ? 12 : sizeof(PieceSample)));
            if (first > limit || n > limit - first || std::size_t(end - p) < bytes)
            {
              throw std::runtime_error("a malformed gather message from rank " + std::to_string(r));
            }
            const std::uint64_t to =
              (kind == kVertexSection ? vFirst : (kind == kTriangleSection ? tFirst : sFirst))
                [std::size_t(r)] +
              first;
            if (kind == kSampleSection)
            {
              s.resize(std::size_t(n));
              std::memcpy(s.data(), p, bytes);
              for (PieceSample& x : s)
              {
                if (x.vertex >= sizes[3 * std::size_t(r)])
                {
                  throw std::runtime_error(
                    "a malformed gather message from rank " + std::to_string(r));
                }
                x.vertex += vFirst[std::size_t(r)];
              }
              gatheredSamples.Write(to, std::size_t(n), s.data());
              samplesIn += n;
            }
            else if (kind == kVertexSection)
            {
              xyz.resize(3 * n);
              words.resize(stride * n);
              q.resize(n);
              std::memcpy(xyz.data(), p, 12 * n);
              std::memcpy(words.data(), p + 12 * n, 4 * stride * n);
              std::memcpy(q.data(), p + (12 + 4 * stride) * n, sizeof(Quadric) * n);
              io::VertexChunk c;
              c.first = to;
              c.count = std::size_t(n);
              c.xyz = xyz.data();
              if (stride)
              {
                buffers.Unpack(words.data(), std::size_t(n), layout, stride, c);
              }
              gathered->Vertices(c);
              gatheredQuadrics.Write(to, std::size_t(n), q.data());
              k.resize(std::size_t(n));
              for (std::size_t i = 0; i < n; ++i)
              {
                k[i] = { PositionBits(xyz[3 * i]), PositionBits(xyz[3 * i + 1]),
                  PositionBits(xyz[3 * i + 2]), std::uint32_t(r), to + i };
              }
              keys.Write(to, std::size_t(n), k.data());
            }
            else
            {
              words.assign(reinterpret_cast<const std::uint32_t*>(p),
                reinterpret_cast<const std::uint32_t*>(p) + 3 * n);
              for (std::uint32_t& v : words)
              {
                if (v >= sizes[3 * std::size_t(r)])
                {
                  throw std::runtime_error(
                    "a malformed gather message from rank " + std::to_string(r));
                }
                v += std::uint32_t(vFirst[std::size_t(r)]);
              }
              gathered->TrianglesAt(to, words.data(), std::size_t(n));
            }
            p += bytes;
          }
        }
        progress.Tick(double(gathered->TriangleCount() + samplesIn) /
          double(std::max<std::uint64_t>(gatheredT + gatheredS, 1)));
      });
      more = rounds.Continue(nextV < myV || nextT < myT || nextS < myS);
    } while (more);
    mine.Release();
    quadrics.Close();
    samples.Close();
  }

  // 4. The join: vertices at one position from different pieces become the first piece's.
  std::unordered_map<std::uint32_t, std::uint32_t> join;
  RunStats s2;
  {
    PhaseTimer timer(stats, dml, "join");
    rounds.Local([&] {
      if (rank != 0)
      {
        return;
      }
      progress.BeginPhase("join", 1.0, 10.0);
      gathered->End(io::ReadStats{});
      storage::Sort(dml, keys, [](const JoinKey& a, const JoinKey& b) {
        return std::tie(a.x, a.y, a.z, a.rank, a.vertex) < std::tie(b.x, b.y, b.z, b.rank, b.vertex);
      }, [&progress](double) { progress.Poll(); });
      constexpr std::size_t kRun = 1 << 14;
      std::vector<JoinKey> k(kRun);
      JoinKey head{};
      bool haveHead = false;
      for (std::uint64_t first = 0; first < gatheredV; first += kRun)
      {
        const std::size_t n = std::size_t(std::min<std::uint64_t>(kRun, gatheredV - first));
        keys.Read(first, n, k.data());
        for (std::size_t i = 0; i < n; ++i)
        {
          const JoinKey& e = k[i];
          if (!haveHead || e.x != head.x || e.y != head.y || e.z != head.z)
          {
            head = e;
            haveHead = true;
          }
          else if (e.rank != head.rank)
          {
            join[std::uint32_t(e.vertex)] = std::uint32_t(head.vertex);
            Quadric sum = gatheredQuadrics.Get(head.vertex);
            AddTo(sum, gatheredQuadrics.Get(e.vertex));
            gatheredQuadrics.Set(head.vertex, sum);
          }
        }
        progress.Tick(double(first + n) / double(gatheredV));
      }
      keys.Close();
    });
    rounds.Agree();
  }

  // 5. Rank 0 decimates the joined mesh to the target with the user's options.
  rounds.Local([&] {
    if (rank != 0)
    {
      return;
    }
    DecimateOptions o = options;
    o.communicator = nullptr;
    o.dml = &dml;
    o.layout = LayoutPolicy::Keep;
    o.origin = origin;
    o.targetTriangles = boundOnly ? 0 : target;
    o.levelsFrom = F;
    // The final fit to the pieces' samples of the input, each with the gathered vertex that
    // stands for it (a vertex joined to another piece's: that one).
    if (options.fitSurface)
    {
      o.initialSamples = [&gatheredSamples, gatheredS, &join](
                           const DecimateOptions::SampleCallback& emit) {
        constexpr std::size_t kRun = 1 << 12;
        std::vector<PieceSample> s(kRun);
        for (std::uint64_t first = 0; first < gatheredS; first += kRun)
        {
          const std::size_t n = std::size_t(std::min<std::uint64_t>(kRun, gatheredS - first));
          gatheredSamples.Read(first, n, s.data());
          for (std::size_t i = 0; i < n; ++i)
          {
            emit(s[i].p, Joined(join, std::uint32_t(s[i].vertex)));
          }
        }
      };
    }
    o.initialQuadric = [&gatheredQuadrics](std::uint64_t v, double q[10]) {
      const Quadric Q = gatheredQuadrics.Get(v);
      std::copy(Q.q, Q.q + 10, q);
      return true;
    };
    o.initialQuadricReplacesFaces = true;
    o.sourceConsumed = [&gathered, &gatheredQuadrics, &gatheredSamples] {
      gathered->Release();
      gatheredQuadrics.Close();
      gatheredSamples.Close();
    };
    StageProgress p2(progress, "gathered: ");
    const MeshSource source = [&gathered, &join](io::MeshSink& sink, const io::ReadOptions& ro) {
      JoinSink js(sink, join);
      return gathered->Replay(js, ro);
    };
    RunOnOwnState(o, p2, s2, source, output, onLevel);
    detail::AddNestedRun(stats, s2, "gathered ");
    err = std::max(err, s2.achievedError);
  });
  rounds.Agree();
  // The last collectives: the error and every rank's traffic (nothing waits on the writes).
  rounds.Max(&err, 1);
  {
    CommunicationStats& c = stats.communication;
    std::vector<double> all(4 * std::size_t(N), 0.0);
    all[4 * std::size_t(rank)] = double(c.bytesSent);
    all[4 * std::size_t(rank) + 1] = double(c.bytesReceived);
    all[4 * std::size_t(rank) + 2] = c.seconds;
    all[4 * std::size_t(rank) + 3] = double(c.rounds);
    rounds.Max(all.data(), all.size());
    c.perRank = all;
  }
  if (rank != 0)
  {
    // (an empty piece, with the point data of the others)
    io::MeshHeader h;
    h.layout = layout;
    output.Begin(h);
    output.End(io::ReadStats{});
  }
  else
  {
    stats.outputVertices = s2.outputVertices;
    stats.outputTriangles = s2.outputTriangles;
    stats.prunedComponents = s2.prunedComponents;
    stats.prunedTriangles = s2.prunedTriangles;
  }
  stats.errorDiagonal = options.errorDiagonal;
  stats.achievedError = err;
  progress.Finish();
  stats.storage = dml.GetStats();
  return stats;
}
} // namespace
} // namespace sipmss::algorithms
