// A file read in pieces by byte ranges (FilePiece, io/MeshPiece.h), on ranks that are threads:
// the pieces together are the whole file (the same triangles at the same coordinates, with
// their point data), each rank reads about 1/N of the file, files that cannot be split are read
// whole by rank 0 by agreement of all ranks and scattered (the same pieces), a bad file fails
// every rank, and the distributed clustering of a file's pieces is the serial clustering of the
// file.
#include "sipmss/algorithms/Cluster.h"
#include "sipmss/algorithms/FilePiece.h"
#include "sipmss/algorithms/ThreadCommunicator.h"
#include "sipmss/io/MeshPiece.h"

#include "AlgorithmsTestUtil.h"
#include "IOTestUtil.h"

#include <gtest/gtest.h>

#include <mutex>

using namespace sipmss;
using namespace sipmss::algorithms;
using sipmss::io::test::PlyBuilder;
using sipmss::io::test::TempDir;
using sipmss::testing::AbortLater;
using sipmss::testing::Collect;
using sipmss::testing::Mesh;

namespace
{
// A triangle by its corners' coordinates (and scalar), rotated to start at the smallest corner.
using Corner = std::array<float, 4>;
using Tri = std::array<Corner, 3>;

std::vector<Tri> Triangles(const Mesh& m)
{
  const std::size_t ns = m.p.empty() ? 0 : m.scalar.size() / (m.p.size() / 3);
  std::vector<Tri> out;
  for (std::size_t f = 0; f < m.t.size(); f += 3)
  {
    Tri t;
    for (int k = 0; k < 3; ++k)
    {
      const std::uint32_t v = m.t[f + std::size_t(k)];
      t[std::size_t(k)] = { m.p[3 * v], m.p[3 * v + 1], m.p[3 * v + 2], ns ? m.scalar[ns * v] : 0.f };
    }
    std::rotate(t.begin(), std::min_element(t.begin(), t.end()), t.end());
    out.push_back(t);
  }
  std::sort(out.begin(), out.end());
  return out;
}

void Write(const Mesh& m, const std::string& path, bool ascii = false)
{
  auto w = io::MeshWriter::Create(path, ascii);
  io::VertexLayout layout;
  layout.scalars = m.Names();
  w->Begin(m.p.size() / 3, m.t.size() / 3, layout);
  io::VertexChunk c;
  c.count = m.p.size() / 3;
  c.xyz = m.p.data();
  c.scalars = m.scalar.empty() ? nullptr : m.scalar.data();
  w->Vertices(c);
  w->Triangles(m.t.data(), m.t.size() / 3);
  w->End();
}

Mesh ReadWhole(const std::string& path)
{
  Collect c;
  FileSource(path)(c, io::ReadOptions{});
  return c.m;
}

struct PieceRun
{
  std::vector<Mesh> pieces;
  // (char, not bool: the ranks are threads that write their entries at the same time, and
  // std::vector<bool> packs its entries into shared words)
  std::vector<char> split, scattered;
  std::vector<std::string> whyNot, errors;
  std::vector<std::uint64_t> bytes, faces, sent, received;
};

// Every rank builds its piece and replays it once (when split).
PieceRun ReadPieces(const std::string& path, int ranks, storage::Profile profile = {})
{
  PieceRun run;
  const std::size_t n = std::size_t(ranks);
  run.pieces.resize(n);
  run.split.resize(n);
  run.scattered.resize(n);
  run.sent.resize(n);
  run.received.resize(n);
  run.whyNot.resize(n);
  run.errors.resize(n);
  run.bytes.resize(n);
  run.faces.resize(n);
  RunRanks(ranks, [&](Communicator& comm) {
    const std::size_t r = std::size_t(comm.Rank());
    NullProgress progress;
    try
    {
      FilePiece piece(path, comm, profile, progress);
      run.split[r] = piece.Split();
      run.scattered[r] = piece.Scattered();
      run.whyNot[r] = piece.WhyNot();
      run.sent[r] = piece.Traffic().bytesSent;
      run.received[r] = piece.Traffic().bytesReceived;
      {
        Collect c;
        piece.Source()(c, io::ReadOptions{});
        run.pieces[r] = c.m;
        run.bytes[r] = piece.BytesRead();
        run.faces[r] = piece.Faces();
      }
    }
    catch (const std::exception& e)
    {
      run.errors[r] = e.what();
    }
  });
  return run;
}

// The pieces, by byte ranges (or scattered by rank 0), hold the file's triangles once each.
void ExpectPiecesAreTheWhole(
  const std::string& path, int ranks, storage::Profile profile = {}, bool scattered = false)
{
  const Mesh whole = ReadWhole(path);
  const PieceRun run = ReadPieces(path, ranks, profile);
  std::vector<Tri> all;
  std::uint64_t faces = 0;
  const std::uint64_t fileBytes = std::filesystem::file_size(path);
  for (int r = 0; r < ranks; ++r)
  {
    const std::size_t k = std::size_t(r);
    ASSERT_TRUE(run.errors[k].empty()) << run.errors[k];
    ASSERT_EQ(run.split[k] != 0, !scattered) << run.whyNot[k];
    ASSERT_EQ(run.scattered[k] != 0, scattered);
    const std::vector<Tri> t = Triangles(run.pieces[k]);
    all.insert(all.end(), t.begin(), t.end());
    faces += run.faces[k];
    // Every vertex of a piece is used by its faces (no vertex read for nothing) ...
    std::vector<bool> used(run.pieces[k].p.size() / 3, false);
    for (std::uint32_t v : run.pieces[k].t)
    {
      used[v] = true;
    }
    EXPECT_EQ(std::count(used.begin(), used.end(), false), 0) << "rank " << r;
    if (scattered)
    {
      // Rank 0 reads the file (uncompressed, once), the others at most what they read of their
      // share before they found that it cannot be read in pieces; rank 0 sends each of them
      // its piece.
      if (r == 0)
      {
        EXPECT_GT(run.bytes[k], 0u);
      }
      else
      {
        EXPECT_LE(double(run.bytes[k]), 1.25 * double(fileBytes) / ranks + 2048) << "rank " << r;
      }
      EXPECT_EQ(run.received[k] > 0, r != 0) << "rank " << r; // (a header, at least)
      EXPECT_EQ(run.sent[k] > 0, r == 0 && ranks > 1) << "rank " << r;
      continue;
    }
    // ... and a rank reads about 1/N of the file (its faces, and their vertices: a little more
    // than its share where its faces use vertices of the next piece's).
    EXPECT_LE(double(run.bytes[k]), 1.25 * double(fileBytes) / ranks + 2048)
      << "rank " << r << " of " << ranks;
    EXPECT_EQ(run.bytes[k] > 0, run.faces[k] > 0);
  }
  EXPECT_EQ(faces, whole.t.size() / 3);
  std::sort(all.begin(), all.end());
  EXPECT_EQ(all, Triangles(whole)) << ranks << " ranks";
}
} // namespace

TEST(FilePiece, ThePiecesOfABinaryPlyAreTheWholeFile)
{
  TempDir dir;
  const std::string path = dir.File("sphere.ply");
  Write(sipmss::testing::BumpyUVSphere(40, { 1, 2, 3 }), path); // 6,400 triangles, scalar s
  for (int ranks = 1; ranks <= 4; ++ranks)
  {
    SCOPED_TRACE(std::to_string(ranks) + " ranks");
    ExpectPiecesAreTheWhole(path, ranks);
  }
  // Out of core (the piece's faces, map and vertex numbers in block files): the same.
  storage::Profile tiny;
  tiny.memoryBudget = 64u << 10;
  tiny.policy = storage::ModePolicy::OutOfCore;
  ExpectPiecesAreTheWhole(path, 3, tiny);
  // More ranks than faces would leave some empty: they take part with nothing.
  Mesh one;
  one.p = { 0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 1, 0 };
  one.t = { 0, 1, 2, 1, 3, 2 };
  Write(one, dir.File("two.ply"));
  ExpectPiecesAreTheWhole(dir.File("two.ply"), 3);
}

TEST(FilePiece, BigEndianShortIndicesAndOtherFaceProperties)
{
  // A face record with a property before and after the list, 16-bit signed indices, big-endian:
  // the records' places come from the header.
  TempDir dir;
  PlyBuilder b(io::test::Enc::BE);
  const int n = 6;
  b.H("element vertex " + std::to_string((n + 1) * (n + 1)))
    .H("property float x")
    .H("property float y")
    .H("property float z")
    .H("property uchar red")
    .H("element face " + std::to_string(2 * n * n))
    .H("property ushort material")
    .H("property list uchar short vertex_indices")
    .H("property float quality");
  for (int j = 0; j <= n; ++j)
  {
    for (int i = 0; i <= n; ++i)
    {
      b.V("float", i).V("float", j).V("float", 0.1 * i * j).V("uchar", 10 * i).EndRecord();
    }
  }
  std::vector<std::uint32_t> t;
  sipmss::testing::GridTriangles(n, t);
  for (std::size_t f = 0; f < t.size(); f += 3)
  {
    b.V("ushort", double(f)).V("uchar", 3);
    for (int k = 0; k < 3; ++k)
    {
      b.V("short", t[f + std::size_t(k)]);
    }
    b.V("float", 0.5).EndRecord();
  }
  const std::string path = dir.File("be.ply");
  io::test::WriteFile(path, b.Bytes());
  const io::SplitLayout layout = io::ProbeSplit(path);
  ASSERT_EQ(layout.whyNot, "");
  EXPECT_TRUE(layout.bigEndian);
  EXPECT_EQ(layout.countOffset, 2u);
  EXPECT_EQ(layout.faceStride, 2u + 1 + 6 + 4);
  for (int ranks : { 2, 3 })
  {
    ExpectPiecesAreTheWhole(path, ranks);
  }
  // (the colour comes along)
  const PieceRun run = ReadPieces(path, 2);
  EXPECT_TRUE(run.pieces[1].p.size() > 0);
}

TEST(FilePiece, BinaryStlPieces)
{
  TempDir dir;
  const std::string path = dir.File("sphere.stl");
  Mesh m = sipmss::testing::BumpyUVSphere(20);
  m.scalar.clear();
  Write(m, path);
  const io::SplitLayout layout = io::ProbeSplit(path);
  ASSERT_EQ(layout.whyNot, "");
  EXPECT_EQ(layout.faceCount, m.t.size() / 3);
  for (int ranks = 1; ranks <= 4; ++ranks)
  {
    SCOPED_TRACE(std::to_string(ranks) + " ranks");
    ExpectPiecesAreTheWhole(path, ranks);
    const PieceRun run = ReadPieces(path, ranks);
    for (int r = 0; r < ranks; ++r)
    {
      EXPECT_EQ(run.bytes[std::size_t(r)], 50 * run.faces[std::size_t(r)]); // (facets only)
    }
  }
}

TEST(FilePiece, FilesThatCannotBeSplitAreScatteredByRankZero)
{
  // Every rank agrees, and says why; rank 0 reads the file and sends every rank its piece.
  TempDir dir;
  const Mesh m = sipmss::testing::BumpyUVSphere(8);
  Write(m, dir.File("a.obj"));
  Write(m, dir.File("b.ply.gz"));
  PlyBuilder ascii(io::test::Enc::Ascii);
  ascii.H("element vertex 3").H("property float x").H("property float y").H("property float z");
  ascii.H("element face 1").H("property list uchar int vertex_indices");
  ascii.V("float", 0).V("float", 0).V("float", 0).EndRecord();
  ascii.V("float", 1).V("float", 0).V("float", 0).EndRecord();
  ascii.V("float", 0).V("float", 1).V("float", 0).EndRecord();
  ascii.V("uchar", 3).V("int", 0).V("int", 1).V("int", 2).EndRecord();
  io::test::WriteFile(dir.File("c.ply"), ascii.Bytes());
  // A quad among triangles: the sizes do not add up to fixed records.
  auto quads = [](std::initializer_list<int> counts) {
    PlyBuilder b(io::test::Enc::LE);
    b.H("element vertex 4").H("property float x").H("property float y").H("property float z");
    b.H("element face " + std::to_string(counts.size())).H("property list uchar int vertex_indices");
    for (int v = 0; v < 4; ++v)
    {
      b.V("float", v & 1).V("float", v >> 1).V("float", 0).EndRecord();
    }
    for (int c : counts)
    {
      b.V("uchar", c);
      for (int k = 0; k < c; ++k)
      {
        b.V("int", k);
      }
      b.EndRecord();
    }
    return b.Bytes();
  };
  io::test::WriteFile(dir.File("d.ply"), quads({ 3, 4 }));
  // A quad and a 2-gon: 6 indices in 2 faces, as if two triangles. Only reading finds out.
  io::test::WriteFile(dir.File("e.ply"), quads({ 3, 4, 2 }));
  const std::pair<const char*, const char*> cases[] = { { "a.obj", "OBJ" },
    { "b.ply.gz", "gzip" }, { "c.ply", "ASCII PLY" }, { "d.ply", "not all triangles" },
    { "e.ply", "vertices: the file cannot be read in pieces" } };
  for (const auto& c : cases)
  {
    SCOPED_TRACE(c.first);
    const PieceRun run = ReadPieces(dir.File(c.first), 3);
    bool named = false;
    for (int r = 0; r < 3; ++r)
    {
      EXPECT_EQ(run.errors[std::size_t(r)], "");
      EXPECT_FALSE(run.split[std::size_t(r)]);
      EXPECT_TRUE(run.scattered[std::size_t(r)]);
      EXPECT_FALSE(run.whyNot[std::size_t(r)].empty());
      named = named || run.whyNot[std::size_t(r)].find(c.second) != std::string::npos;
    }
    EXPECT_TRUE(named) << run.whyNot[0] << " | " << run.whyNot[1] << " | " << run.whyNot[2];
    for (int ranks = 1; ranks <= 4; ++ranks)
    {
      SCOPED_TRACE(std::to_string(ranks) + " ranks");
      ExpectPiecesAreTheWhole(dir.File(c.first), ranks, {}, true);
    }
  }
}

TEST(FilePiece, ScatteredPiecesCarryThePointDataWithinABudget)
{
  // An ASCII PLY with a scalar, an OBJ: the pieces are the whole file with its point data, also
  // when the whole mesh (rank 0) and the pieces are in block files, in rounds of 256 KiB.
  TempDir dir;
  const Mesh m = sipmss::testing::BumpyUVSphere(60, { 1, 2, 3 }); // 14,400 triangles, scalar s
  Write(m, dir.File("sphere.ply"), true);
  Write(m, dir.File("sphere.obj"));
  storage::Profile tiny;
  tiny.memoryBudget = 64u << 10;
  tiny.policy = storage::ModePolicy::OutOfCore;
  for (const char* name : { "sphere.ply", "sphere.obj" })
  {
    SCOPED_TRACE(name);
    for (int ranks : { 2, 3 })
    {
      ExpectPiecesAreTheWhole(dir.File(name), ranks, {}, true);
      ExpectPiecesAreTheWhole(dir.File(name), ranks, tiny, true);
    }
  }
  // Several rounds: rank 0 sends more than a round's bytes (256 KiB at this budget).
  Write(sipmss::testing::BumpyUVSphere(120, { 1, 2, 3 }), dir.File("big.ply"), true);
  ExpectPiecesAreTheWhole(dir.File("big.ply"), 2, tiny, true);
  const PieceRun run = ReadPieces(dir.File("big.ply"), 2, tiny);
  EXPECT_GT(run.sent[0], std::uint64_t(256) << 10);
}

TEST(FilePiece, ABadFileFailsEveryRank)
{
  // An index out of range in the last face: the rank that reads it names the file, the face and
  // its byte; the others name that rank. Nobody waits.
  TempDir dir;
  const Mesh m = sipmss::testing::BumpyUVSphere(10);
  const std::string path = dir.File("bad.ply");
  Write(m, path);
  {
    // (the writer refuses such an index: the last index of the file, written over)
    std::string bytes = io::test::ReadFileBytes(path);
    ASSERT_EQ(bytes.compare(bytes.size() - 4, 4, reinterpret_cast<const char*>(&m.t.back()), 4), 0);
    const std::uint32_t bad = std::uint32_t(m.p.size() / 3 + 7);
    bytes.replace(bytes.size() - 4, 4, reinterpret_cast<const char*>(&bad), 4);
    io::test::WriteFile(path, bytes);
  }
  const PieceRun run = ReadPieces(path, 3);
  EXPECT_NE(run.errors[2].find("bad.ply: face #" + std::to_string(m.t.size() / 3 - 1) +
              " has vertex index"),
    std::string::npos)
    << run.errors[2];
  EXPECT_NE(run.errors[2].find("at byte"), std::string::npos) << run.errors[2];
  for (int r : { 0, 1 })
  {
    EXPECT_NE(run.errors[std::size_t(r)].find("rank 2 could not read its piece"), std::string::npos)
      << run.errors[std::size_t(r)];
  }
  // A file that is not there: every rank says so.
  const PieceRun missing = ReadPieces(dir.File("missing.ply"), 2);
  for (const std::string& e : missing.errors)
  {
    EXPECT_NE(e.find("cannot be opened"), std::string::npos) << e;
  }
  // A file that only rank 0 can open (on a disk of its own node): rank 0 reads it whole and
  // sends the pieces.
  const std::string good = dir.File("good.ply");
  const Mesh goodMesh = sipmss::testing::BumpyUVSphere(10);
  Write(goodMesh, good);
  std::vector<char> split(3, true); // (char: written by the rank threads at once)
  std::vector<std::string> why(3);
  std::vector<Mesh> pieces(3);
  RunRanks(3, [&](Communicator& comm) {
    NullProgress progress;
    FilePiece piece(comm.Rank() == 0 ? good : dir.File("elsewhere.ply"), comm, {}, progress);
    split[std::size_t(comm.Rank())] = piece.Split();
    why[std::size_t(comm.Rank())] = piece.WhyNot();
    Collect c;
    piece.Source()(c, io::ReadOptions{});
    pieces[std::size_t(comm.Rank())] = c.m;
  });
  std::vector<Tri> all;
  for (int r = 0; r < 3; ++r)
  {
    EXPECT_FALSE(split[std::size_t(r)]);
    EXPECT_NE(why[std::size_t(r)].find("not every rank can open it"), std::string::npos) << why[std::size_t(r)];
    const std::vector<Tri> t = Triangles(pieces[std::size_t(r)]);
    all.insert(all.end(), t.begin(), t.end());
  }
  std::sort(all.begin(), all.end());
  EXPECT_EQ(all, Triangles(ReadWhole(good)));
  // An ASCII file that rank 0 cannot read (an index out of range): rank 0 says where, the
  // others name rank 0.
  {
    Mesh bad = sipmss::testing::BumpyUVSphere(6);
    const std::string path = dir.File("bad-ascii.ply");
    Write(bad, path, true);
    std::string text = io::test::ReadFileBytes(path);
    const std::string last = "3 " + std::to_string(bad.t[bad.t.size() - 3]) + " " +
      std::to_string(bad.t[bad.t.size() - 2]) + " " + std::to_string(bad.t.back());
    const std::size_t at = text.rfind(last);
    ASSERT_NE(at, std::string::npos) << last;
    text.replace(at, last.size(), "3 0 1 " + std::to_string(bad.p.size()));
    io::test::WriteFile(path, text);
    const PieceRun run = ReadPieces(path, 3);
    EXPECT_NE(run.errors[0].find("bad-ascii.ply"), std::string::npos) << run.errors[0];
    EXPECT_NE(run.errors[0].find("index"), std::string::npos) << run.errors[0];
    for (int r : { 1, 2 })
    {
      EXPECT_NE(run.errors[std::size_t(r)].find("rank 0 could not read the file"), std::string::npos)
        << run.errors[std::size_t(r)];
    }
  }
}

TEST(FilePiece, AnAbortDuringTheScatterStopsEveryRank)
{
  // Rank 2 aborts while rank 0 sends: rank 2 stops with AbortedError, the others with an error,
  // and none waits.
  TempDir dir;
  const std::string path = dir.File("sphere.obj");
  Write(sipmss::testing::BumpyUVSphere(40), path);
  std::vector<std::string> outcome(3);
  RunRanks(3, [&](Communicator& comm) {
    AbortLater progress(comm.Rank() == 2 ? 0 : 1000000);
    try
    {
      FilePiece piece(path, comm, {}, progress);
      outcome[std::size_t(comm.Rank())] = "finished";
    }
    catch (const AbortedError&)
    {
      outcome[std::size_t(comm.Rank())] = "aborted";
    }
    catch (const std::exception& e)
    {
      outcome[std::size_t(comm.Rank())] = e.what();
    }
  });
  EXPECT_EQ(outcome[2], "aborted");
  for (int r : { 0, 1 })
  {
    EXPECT_NE(outcome[std::size_t(r)].find("could not keep its piece"), std::string::npos)
      << outcome[std::size_t(r)];
  }
}

TEST(FilePiece, TheClusteringOfAFilesPiecesIsTheSerialClustering)
{
  // The whole chain of a distributed File source: each rank clusters its piece of the file, and
  // the union of the outputs is the serial run's on the file (exact sums: bit for bit).
  TempDir dir;
  const std::string path = dir.File("sphere.ply");
  Write(sipmss::testing::BumpyUVSphere(60, { -4, 1, 2 }), path);
  ClusterOptions o;
  o.maximumGridDimension = 17;
  o.threads = 1;
  Collect serial;
  NullProgress quiet;
  Cluster(FileSource(path), serial, o, quiet);
  for (int ranks = 2; ranks <= 4; ++ranks)
  {
    std::vector<Collect> outs(static_cast<std::size_t>(ranks));
    RunRanks(ranks, [&](Communicator& comm) {
      NullProgress progress;
      FilePiece piece(path, comm, storage::Profile{}, progress);
      ASSERT_TRUE(piece.Split());
      ClusterOptions co = o;
      co.communicator = &comm;
      Cluster(piece.Source(), outs[std::size_t(comm.Rank())], co, progress);
    });
    std::vector<Tri> all;
    for (const Collect& c : outs)
    {
      const std::vector<Tri> t = Triangles(c.m);
      all.insert(all.end(), t.begin(), t.end());
    }
    std::sort(all.begin(), all.end());
    Mesh s = serial.m;
    s.scalar.clear(); // (the scalar's mean is close to the serial one where pieces meet)
    for (Tri& t : all)
    {
      for (Corner& c : t)
      {
        c[3] = 0;
      }
    }
    std::sort(all.begin(), all.end());
    EXPECT_EQ(all, Triangles(s)) << ranks << " ranks";
  }
}
