// Algorithm II across ranks (ClusterOptions::communicator). Each rank reads its own piece of the
// mesh onto the one global grid; the cells' exact sums (Structures.inl, "Exact cell sums") go to
// the cell's owner rank (a hash of its grid key), which adds them; the triangles, named by their
// cells' keys, go to an owner too, which keeps one copy of each (the lowest rank's); the owners
// compute the representatives of the cells the kept triangles use and send them back. Every rank
// then writes its piece: its kept triangles and their vertices. The union of the pieces is the
// serial result, triangle for triangle and bit for bit: the sums are exact, so their order and
// split do not matter. Everything that grows with the mesh stays in the rank's DML; the
// exchanges go in rounds of a bounded size. (Part of Cluster.cpp's translation unit.)
namespace sipmss::algorithms
{
namespace
{
using detail::AgreeOnLayout;
using detail::LayoutSink;
using detail::RoundBytes;
using detail::Rounds;

// The cells a rank owns: their merged records, point data sums and attribute extensions.
struct OwnedCells
{
  OwnedCells(DML& dml, Progress& progress)
    : map(dml, progress)
    , cells(dml, 1024)
  {
  }
  CellMap map;
  Array<CellRec> cells;
  storage::BlockId attr = -1, ext = -1;
  std::uint32_t count = 0;
};

// A triangle at its owner: its cells' keys (the smallest first, orientation kept), the rank that
// sent it and its index there.
struct TriMsg
{
  std::uint64_t k[3];
  std::uint32_t rank;
  std::uint32_t pad;
  std::uint64_t index;
};

void MergeCell(CellRec& dst, const CellRec& src)
{
  AddTo(dst.q, src.q);
  for (int k = 0; k < 3; ++k)
  {
    dst.sum[k] += src.sum[k];
  }
  dst.corners += src.corners;
  dst.vertices += src.vertices;
  if (std::tie(src.first[0], src.first[1], src.first[2]) <
    std::tie(dst.first[0], dst.first[1], dst.first[2]))
  {
    std::copy_n(src.first, 3, dst.first);
  }
}

// Step 1: every cell with content goes to its owner, which adds it to its own.
void SendCellsToOwners(ClusterState& cluster, const Array<std::uint64_t>& keys, OwnedCells& owned,
  Rounds& rounds)
{
  DML& dml = cluster.dml;
  const std::size_t as = cluster.attrStride, xs = cluster.xSize;
  rounds.Local([&] {
    if (as)
    {
      owned.attr = dml.OpenBlock(as * sizeof(float), 1024);
    }
    if (xs)
    {
      owned.ext = dml.OpenBlock(xs * sizeof(double), 1024);
    }
  });
  const std::size_t recordSize = sizeof(std::uint64_t) + sizeof(CellRec) + as * sizeof(float) +
    xs * sizeof(double);
  std::vector<float> attr(as), attrSum(as);
  std::vector<double> ext(xs), extSum(xs);
  std::uint32_t next = 0;
  bool more = true;
  do
  {
    rounds.Local([&] {
      for (; next < cluster.numCells && rounds.Pending() < rounds.Limit(); ++next)
      {
        const CellRec rec = cluster.cells.Get(next);
        if (!rec.corners && !rec.vertices)
        {
          continue;
        }
        const std::uint64_t key = keys.Get(next);
        auto& b = rounds.send[rounds.Owner(key)];
        Rounds::Put(b, key);
        Rounds::Put(b, rec);
        if (as)
        {
          dml.Read(cluster.attrBlock, as * sizeof(float), next, attr.data());
          const std::size_t at = b.size();
          b.resize(at + as * sizeof(float));
          std::memcpy(b.data() + at, attr.data(), as * sizeof(float));
        }
        if (xs)
        {
          dml.Read(cluster.extBlock, xs * sizeof(double), next, ext.data());
          const std::size_t at = b.size();
          b.resize(at + xs * sizeof(double));
          std::memcpy(b.data() + at, ext.data(), xs * sizeof(double));
        }
      }
    });
    rounds.Exchange();
    rounds.Local([&] {
      for (const auto& from : rounds.received)
      {
        if (from.size() % recordSize)
        {
          throw std::logic_error("a rank sent " + std::to_string(from.size()) +
            " bytes of cells of " + std::to_string(recordSize) + " bytes each");
        }
        for (const std::uint8_t* p = from.data(); p < from.data() + from.size();)
        {
          const std::uint64_t key = Rounds::Take<std::uint64_t>(p);
          const CellRec rec = Rounds::Take<CellRec>(p);
          bool inserted = false;
          const std::uint32_t c = owned.map.FindOrInsert(key, owned.count, &inserted);
          if (inserted)
          {
            if (owned.count == owned.cells.Size())
            {
              owned.cells.Resize(2 * owned.cells.Size());
            }
            if (as && owned.count >= dml.Count(owned.attr))
            {
              dml.Resize(owned.attr, owned.cells.Size());
            }
            if (xs && owned.count >= dml.Count(owned.ext))
            {
              dml.Resize(owned.ext, owned.cells.Size());
            }
            ++owned.count;
            CellRec empty{};
            std::fill_n(empty.first, 3, std::numeric_limits<float>::infinity());
            owned.cells.Set(c, empty);
            std::fill(attrSum.begin(), attrSum.end(), 0.f);
            std::fill(extSum.begin(), extSum.end(), 0.0);
            if (as)
            {
              dml.Write(owned.attr, as * sizeof(float), c, attrSum.data());
            }
            if (xs)
            {
              dml.Write(owned.ext, xs * sizeof(double), c, extSum.data());
            }
          }
          CellRec sum = owned.cells.Get(c);
          MergeCell(sum, rec);
          owned.cells.Set(c, sum);
          if (as)
          {
            dml.Read(owned.attr, as * sizeof(float), c, attrSum.data());
            for (std::size_t i = 0; i < as; ++i)
            {
              attrSum[i] += Rounds::Take<float>(p);
            }
            dml.Write(owned.attr, as * sizeof(float), c, attrSum.data());
          }
          if (xs)
          {
            dml.Read(owned.ext, xs * sizeof(double), c, extSum.data());
            for (std::size_t i = 0; i < xs; ++i)
            {
              extSum[i] += Rounds::Take<double>(p);
            }
            dml.Write(owned.ext, xs * sizeof(double), c, extSum.data());
          }
        }
        cluster.progress.Poll();
      }
    });
    more = rounds.Continue(next < cluster.numCells);
  } while (more);
}

// Step 2: every triangle (by its cells' keys) goes to its owner; of the copies that several ranks
// made (faces on both sides of a seam between pieces that fall into the same three cells), the
// lowest rank's is kept and the others are told to drop theirs.
void KeepOneCopyOfEachTriangle(ClusterState& cluster, const Array<std::uint64_t>& keys,
  Array<std::uint8_t>& keep, Rounds& rounds)
{
  DML& dml = cluster.dml;
  auto& order = cluster.triangles.Order();
  const std::uint64_t numTris = cluster.triangles.Size();
  rounds.Local([&] {
    keep = Array<std::uint8_t>(dml, std::max<std::uint64_t>(numTris, 1));
    const std::uint8_t one = 1;
    dml.Fill(keep.Id(), &one);
  });
  Array<TriMsg> got(dml, 1024);
  std::uint64_t numGot = 0;
  std::uint64_t next = 0;
  constexpr std::size_t kTriBytes = 4 * sizeof(std::uint64_t);
  bool more = true;
  do
  {
    rounds.Local([&] {
      for (; next < numTris && rounds.Pending() < rounds.Limit(); ++next)
      {
        const TriSlot t = order.Get(next);
        std::uint64_t k[3] = { keys.Get(t.v[0]), keys.Get(t.v[1]), keys.Get(t.v[2]) };
        const int m = k[0] < k[1] ? (k[0] < k[2] ? 0 : 2) : (k[1] < k[2] ? 1 : 2);
        std::rotate(k, k + m, k + 3);
        auto& b = rounds.send[rounds.Owner(k[0] ^ Mix(k[1] ^ Mix(k[2])))];
        for (std::uint64_t key : k)
        {
          Rounds::Put(b, key);
        }
        Rounds::Put(b, next);
      }
    });
    rounds.Exchange();
    rounds.Local([&] {
      for (std::size_t from = 0; from < rounds.received.size(); ++from)
      {
        const auto& data = rounds.received[from];
        if (data.size() % kTriBytes)
        {
          throw std::logic_error("a rank sent a partial triangle");
        }
        for (const std::uint8_t* p = data.data(); p < data.data() + data.size();)
        {
          TriMsg msg{};
          for (auto& key : msg.k)
          {
            key = Rounds::Take<std::uint64_t>(p);
          }
          msg.rank = std::uint32_t(from);
          msg.index = Rounds::Take<std::uint64_t>(p);
          if (numGot == got.Size())
          {
            got.Resize(2 * got.Size());
          }
          got.Set(numGot++, msg);
        }
      }
      cluster.progress.Poll();
    });
    more = rounds.Continue(next < numTris);
  } while (more);
  rounds.Local([&] {
    got.Resize(std::max<std::uint64_t>(numGot, 1));
    if (numGot)
    {
      storage::Sort(dml, got, [](const TriMsg& a, const TriMsg& b) {
        return std::tie(a.k[0], a.k[1], a.k[2], a.rank, a.index) <
          std::tie(b.k[0], b.k[1], b.k[2], b.rank, b.index);
      });
    }
  });
  rounds.Agree();
  // The copies after the first of each run of equal keys are dropped by their ranks.
  std::uint64_t at = 0;
  TriMsg previous{};
  do
  {
    rounds.Local([&] {
      for (; at < numGot && rounds.Pending() < rounds.Limit(); ++at)
      {
        const TriMsg msg = got.Get(at);
        if (at > 0 && std::equal(msg.k, msg.k + 3, previous.k))
        {
          Rounds::Put(rounds.send[msg.rank], msg.index);
        }
        previous = msg;
      }
    });
    rounds.Exchange();
    rounds.Local([&] {
      for (const auto& data : rounds.received)
      {
        if (data.size() % sizeof(std::uint64_t))
        {
          throw std::logic_error("a rank sent a partial triangle index");
        }
        for (const std::uint8_t* p = data.data(); p < data.data() + data.size();)
        {
          const std::uint64_t t = Rounds::Take<std::uint64_t>(p);
          if (t >= numTris)
          {
            throw std::logic_error("a rank named triangle " + std::to_string(t) + " of " +
              std::to_string(numTris));
          }
          keep.Set(t, 0);
        }
      }
    });
    more = rounds.Continue(at < numGot);
  } while (more);
  got.Close();
}

// Step 3: the owners compute the vertices of the cells the kept triangles use. A request is a
// key (8 bytes) and its answer a vertex record, so a round asks for at most as many as make a
// round's worth of answers.
void FetchVertices(ClusterState& cluster, const Array<std::uint64_t>& keys,
  const Array<std::uint8_t>& keep, OwnedCells& owned, DistributedOutput& out, Rounds& rounds)
{
  DML& dml = cluster.dml;
  out.recordSize = VertexRecordSize(cluster.layout);
  // The cells used here, numbered as Emit writes them.
  Array<std::uint32_t>& index = out.index;
  rounds.Local([&] {
    out.numOut = NumberUsedCells(
      cluster, &keep, index, out.outTris, [&cluster](std::uint64_t) { cluster.progress.Poll(); });
    out.vertices = dml.OpenBlock(out.recordSize, std::max<std::uint32_t>(out.numOut, 1));
  });
  const int ranks = int(rounds.send.size());
  const std::size_t maxAsked =
    std::max<std::size_t>(1, rounds.Limit() / out.recordSize) * sizeof(std::uint64_t);
  std::vector<std::vector<std::uint32_t>> asked(std::size_t(ranks), std::vector<std::uint32_t>{});
  std::vector<std::uint8_t> record(out.recordSize);
  std::vector<float> attr(cluster.attrStride);
  std::uint32_t next = 0;
  bool more = true;
  do
  {
    for (auto& a : asked)
    {
      a.clear();
    }
    rounds.Local([&] {
      for (; next < cluster.numCells && rounds.Pending() < maxAsked; ++next)
      {
        const std::uint32_t i = index.Get(next);
        if (i == kNoCell)
        {
          continue;
        }
        const std::uint64_t key = keys.Get(next);
        const int owner = rounds.Owner(key);
        Rounds::Put(rounds.send[owner], key);
        asked[owner].push_back(i);
      }
    });
    rounds.Exchange();
    // (the owners answer in the order asked)
    rounds.Local([&] {
      for (int from = 0; from < ranks; ++from)
      {
        const auto& data = rounds.received[from];
        if (data.size() % sizeof(std::uint64_t))
        {
          throw std::logic_error("a rank sent a partial request");
        }
        for (const std::uint8_t* p = data.data(); p < data.data() + data.size();)
        {
          const std::uint32_t c = owned.map.Find(Rounds::Take<std::uint64_t>(p));
          if (c == kNoCell)
          {
            throw std::logic_error("a rank asked for a cell that no rank sent");
          }
          if (cluster.xSize)
          {
            dml.Read(owned.ext, cluster.xSize * sizeof(double), c, cluster.extBuf.data());
          }
          if (cluster.attrStride)
          {
            dml.Read(owned.attr, cluster.attrStride * sizeof(float), c, attr.data());
          }
          VertexBuffers v;
          AppendVertex(cluster, owned.cells.Get(c), attr.data(), v, 0);
          PackVertex(cluster.layout, v, 0, record.data());
          auto& b = rounds.send[from];
          b.insert(b.end(), record.begin(), record.end());
        }
      }
    });
    rounds.Exchange();
    rounds.Local([&] {
      for (int from = 0; from < ranks; ++from)
      {
        const auto& data = rounds.received[from];
        if (data.size() != asked[from].size() * out.recordSize)
        {
          throw std::logic_error("an owner rank answered " + std::to_string(data.size()) +
            " bytes for " + std::to_string(asked[from].size()) + " vertices");
        }
        for (std::size_t j = 0; j < asked[from].size(); ++j)
        {
          dml.Write(out.vertices, out.recordSize, asked[from][j], data.data() + j * out.recordSize);
        }
      }
      cluster.progress.Poll();
    });
    more = rounds.Continue(next < cluster.numCells);
  } while (more);
}


RunStats ClusterDistributed(const MeshSource& source, io::MeshSink& output,
  const ClusterOptions& given, Progress& progress)
{
  Communicator& comm = *given.communicator;
  RunStats stats;
  Rounds rounds(comm, RoundBytes(given.storage), stats.communication);
  if (given.boundaryQuadrics && comm.Size() > 1)
  {
    throw std::invalid_argument("boundary planes are not available on more than one rank yet");
  }
  ClusterOptions options = given; // (with the attribute list the ranks agree on)
  const int threads = storage::ResolveThreads(options.threads);
  const MeshSource input =
    threads > 1 ? Prefetched(source, PrefetchDepth(options.storage.memoryBudget)) : source;
  std::optional<DML> own; // (or the caller's: two-stage's stage 1)
  DML& dml = options.dml ? *options.dml : own.emplace();
  if (own)
  {
    dml.Config(options.storage);
  }

  // A vertices-only pass over the piece: its bounds, its size and its point data, which the
  // ranks agree on (a rank with an empty piece may have none). A failure on one rank reaches
  // the others at the next agreement (Rounds::Local, Agree, Continue): every rank then throws.
  std::array<double, 6> bounds = options.bounds;
  io::VertexLayout layout;
  std::uint64_t vertices = 0;
  {
    rounds.Local([&] { progress.BeginPhase("bounds", 0.0, 1.0); }); // (it polls)
    PhaseTimer timer(stats, dml, "bounds");
    rounds.Local([&] {
      BoundsSink bs(progress, [&options](std::uint64_t v, std::uint64_t f) {
        return kWork::kCluster * double(v + f) +
          ClusterWorkAfterRead(v, f, options.maximumGridDimension, options);
      });
      LayoutSink ls(bs, nullptr);
      io::ReadOptions ro;
      ro.verticesOnly = true;
      input(ls, ro);
      layout = ls.Seen();
      vertices = bs.VerticesSeen();
      if (!options.useBounds)
      {
        bounds = bs.b;
      }
    });
    rounds.Agree();
    std::string attributes = FormatAttributeWeights(options.attributes);
    layout = AgreeOnLayout(layout, vertices, attributes, rounds);
    options.attributes.clear();
    ParseAttributeWeights(attributes, options.attributes);
    if (!options.useBounds)
    {
      double lo[3] = { bounds[0], bounds[2], bounds[4] },
             hi[3] = { bounds[1], bounds[3], bounds[5] };
      rounds.Min(lo, 3);
      rounds.Max(hi, 3);
      bounds = { lo[0], hi[0], lo[1], hi[1], lo[2], hi[2] };
    }
  }
  const ClusterGrid grid = ClusterGrid::Make(bounds, options.maximumGridDimension);

  ClusterState cluster(dml, grid, options, own.has_value(), progress);
  ClusterSink clusterSink(cluster);
  LayoutSink sink(clusterSink, vertices ? nullptr : &layout);
  Array<std::uint64_t> keys;
  {
    rounds.Local([&] { progress.BeginPhase("cluster", 1.0, 1.0); }); // (it polls)
    PhaseTimer timer(stats, dml, "cluster");
    rounds.Local([&] {
      const io::ReadStats read = input(sink, io::ReadOptions{});
      stats.inputVertices = read.vertices;
      stats.inputTriangles = read.triangles;
      stats.droppedInputFaces = read.droppedFaces;
      if (options.sourceConsumed)
      {
        options.sourceConsumed();
      }
      if (options.boundaryQuadrics)
      {
        FinishBoundaries(cluster); // (one rank: the serial run's boundary planes)
      }
      // Each local cell's grid key (the map goes with the input's blocks).
      keys = Array<std::uint64_t>(dml, std::max<std::uint32_t>(cluster.numCells, 1));
      cluster.cellWindow.Release();
      cluster.cellMap.ForEach(
        [&keys](std::uint64_t key, std::uint32_t cell) { keys.Set(cell, key); });
      ReleaseInputBlocks(cluster);
      FinishTriangles(cluster);
    });
    rounds.Agree();
  }
  DistributedOutput out;
  {
    rounds.Local([&] { progress.BeginPhase("exchange", 1.0, 1.0); }); // (it polls)
    PhaseTimer timer(stats, dml, "exchange");
    OwnedCells owned(dml, progress);
    SendCellsToOwners(cluster, keys, owned, rounds);
    KeepOneCopyOfEachTriangle(cluster, keys, out.keep, rounds);
    FetchVertices(cluster, keys, out.keep, owned, out, rounds);
    if (owned.attr >= 0)
    {
      dml.CloseBlock(owned.attr);
    }
    if (owned.ext >= 0)
    {
      dml.CloseBlock(owned.ext);
    }
  }
  keys.Close();
  // The last collectives: the error and every rank's traffic (nothing waits on the writes).
  double err2 = cluster.achievedErr2;
  rounds.Max(&err2, 1);
  {
    CommunicationStats& c = stats.communication;
    std::vector<double> mine = { double(c.bytesSent), double(c.bytesReceived), c.seconds,
      double(c.rounds) };
    std::vector<double> all(4 * std::size_t(comm.Size()), 0.0);
    std::copy(mine.begin(), mine.end(), all.begin() + 4 * comm.Rank());
    rounds.Max(all.data(), all.size());
    c.perRank = all;
  }
  {
    progress.BeginPhase("output", 1.0, 0.0);
    PhaseTimer timer(stats, dml, "output");
    Emit(cluster, output, stats, &out);
  }
  dml.CloseBlock(out.vertices);
  out.keep.Close();
  stats.errorDiagonal = std::sqrt((bounds[1] - bounds[0]) * (bounds[1] - bounds[0]) +
    (bounds[3] - bounds[2]) * (bounds[3] - bounds[2]) +
    (bounds[5] - bounds[4]) * (bounds[5] - bounds[4]));
  stats.achievedError = RelativeError(err2, stats.errorDiagonal);
  progress.Finish();
  stats.storage = dml.GetStats();
  return stats;
}
} // namespace
} // namespace sipmss::algorithms
