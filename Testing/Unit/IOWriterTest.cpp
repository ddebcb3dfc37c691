// Writer tests: round trips through every writer and reader with exact equality, chunked
// writes, count checks, I/O failures, the STL vertex spool.
#include "IOTestUtil.h"

#include <cmath>
#include <functional>
#include <random>

namespace sipmss::io::test
{
namespace
{

struct Mesh
{
  VertexLayout layout;
  std::vector<float> xyz, normals, texcoords, scalars;
  std::vector<std::uint8_t> rgba;
  std::vector<std::uint32_t> tris;
  std::size_t Vertices() const { return xyz.size() / 3; }
};

Mesh MakeMesh(std::size_t nv, std::size_t nt, bool attributes, unsigned seed = 7)
{
  Mesh m;
  std::mt19937 rng(seed);
  std::uniform_real_distribution<float> u(-100.f, 100.f);
  if (attributes)
  {
    m.layout.normals = m.layout.colors = m.layout.texcoords = true;
    m.layout.scalars = { "quality", "curvature" };
  }
  for (std::size_t i = 0; i < nv; ++i)
  {
    for (int k = 0; k < 3; ++k)
      m.xyz.push_back(u(rng) * (k == 2 ? 1e-7f : 1.f)); // tiny and odd values too
    if (!attributes)
      continue;
    for (int k = 0; k < 3; ++k)
      m.normals.push_back(u(rng) / 100.f);
    for (int k = 0; k < 4; ++k)
      m.rgba.push_back(std::uint8_t(rng()));
    m.texcoords.push_back(u(rng) / 200.f + 0.5f);
    m.texcoords.push_back(1.f / 3.f);
    m.scalars.push_back(u(rng));
    m.scalars.push_back(-0.0f);
  }
  for (std::size_t t = 0; t < nt; ++t)
  {
    const std::uint32_t a = std::uint32_t(rng() % nv);
    std::uint32_t b = std::uint32_t(rng() % nv), c = std::uint32_t(rng() % nv);
    while (b == a)
      b = std::uint32_t((b + 1) % nv);
    while (c == a || c == b)
      c = std::uint32_t((c + 1) % nv);
    m.tris.insert(m.tris.end(), { a, b, c });
  }
  return m;
}

void WriteMesh(const Mesh& m, const std::string& path, bool ascii, std::size_t chunk = 1000)
{
  auto w = MeshWriter::Create(path, ascii);
  w->Begin(m.Vertices(), m.tris.size() / 3, m.layout);
  const std::size_t ns = m.layout.scalars.size();
  for (std::size_t first = 0; first < m.Vertices(); first += chunk)
  {
    VertexChunk c;
    c.first = first;
    c.count = std::min(chunk, m.Vertices() - first);
    c.xyz = m.xyz.data() + 3 * first;
    if (m.layout.normals)
      c.normals = m.normals.data() + 3 * first;
    if (m.layout.colors)
      c.rgba = m.rgba.data() + 4 * first;
    if (m.layout.texcoords)
      c.texcoords = m.texcoords.data() + 2 * first;
    if (ns)
      c.scalars = m.scalars.data() + ns * first;
    w->Vertices(c);
  }
  const std::size_t nt = m.tris.size() / 3;
  for (std::size_t first = 0; first < nt; first += chunk)
    w->Triangles(m.tris.data() + 3 * first, std::min(chunk, nt - first));
  w->End();
}

// Bitwise float equality (-0.0 vs 0.0 matters).
bool SameBits(const std::vector<float>& a, const std::vector<float>& b)
{
  return a.size() == b.size() && (a.empty() || std::memcmp(a.data(), b.data(), 4 * a.size()) == 0);
}

struct WriterCase
{
  const char* name;
  const char* ext;
  bool ascii;
  Format format;
  bool attributes; // the format carries the layout
  bool soup;       // STL: 3 fresh vertices per triangle
};

class IORoundTrip : public ::testing::TestWithParam<WriterCase>
{
};

TEST_P(IORoundTrip, ExactThroughWriterAndReader)
{
  const WriterCase& wc = GetParam();
  TempDir dir;
  for (bool attributes : { false, true })
  {
    const Mesh m = MakeMesh(2500, 4000, attributes);
    const std::string path = dir.File(std::string("rt") + (attributes ? "_attr" : "") + wc.ext);
    WriteMesh(m, path, wc.ascii, 777);
    EXPECT_EQ(DetectFormat(path), wc.format);
    for (bool memory : { false, true })
    {
      CollectSink s;
      if (memory)
      {
        const std::string bytes = ReadFileBytes(path);
        MemoryReadOptions mo;
        mo.bufferBytes = 2048;
        ReadMeshFromMemory(bytes.data(), bytes.size(), s, ReadOptions{}, mo);
      }
      else
        s = ReadAll(path);
      EXPECT_EQ(s.header.format, wc.format);
      if (wc.soup)
      {
        ASSERT_EQ(s.Vertices(), m.tris.size());
        for (std::size_t i = 0; i < m.tris.size(); ++i)
          for (int k = 0; k < 3; ++k)
            ASSERT_EQ(std::memcmp(&s.xyz[3 * i + k], &m.xyz[3 * m.tris[i] + k], 4), 0) << i;
        for (std::size_t i = 0; i < s.tris.size(); ++i)
          ASSERT_EQ(s.tris[i], i);
        continue;
      }
      EXPECT_TRUE(SameBits(s.xyz, m.xyz));
      EXPECT_EQ(s.tris, m.tris);
      if (wc.attributes)
      {
        EXPECT_EQ(s.header.layout.normals, m.layout.normals);
        EXPECT_EQ(s.header.layout.colors, m.layout.colors);
        EXPECT_EQ(s.header.layout.texcoords, m.layout.texcoords);
        EXPECT_EQ(s.header.layout.scalars, m.layout.scalars);
        EXPECT_TRUE(SameBits(s.normals, m.normals));
        EXPECT_EQ(s.rgba, m.rgba);
        EXPECT_TRUE(SameBits(s.texcoords, m.texcoords));
        EXPECT_TRUE(SameBits(s.scalars, m.scalars));
      }
    }
  }
}

INSTANTIATE_TEST_SUITE_P(IO, IORoundTrip,
  ::testing::Values(WriterCase{ "PlyBinary", ".ply", false, Format::PlyBinaryLE, true, false },
    WriterCase{ "PlyAscii", ".ply", true, Format::PlyAscii, true, false },
    WriterCase{ "StlBinary", ".stl", false, Format::StlBinary, false, true },
    WriterCase{ "StlAscii", ".stl", true, Format::StlAscii, false, true },
    WriterCase{ "Obj", ".obj", false, Format::Obj, false, false }),
  [](const ::testing::TestParamInfo<WriterCase>& info) { return std::string(info.param.name); });

TEST(IOWriter, CreateByExtensionCaseInsensitive)
{
  TempDir dir;
  const Mesh m = MakeMesh(10, 5, false);
  const std::pair<const char*, Format> cases[] = { { "a.PLY", Format::PlyBinaryLE },
    { "b.Stl", Format::StlBinary }, { "c.OBJ", Format::Obj } };
  for (const auto& [name, format] : cases)
  {
    WriteMesh(m, dir.File(name), false);
    EXPECT_EQ(DetectFormat(dir.File(name)), format) << name;
  }
  EXPECT_THROW(MeshWriter::Create(dir.File("x.vtk")), MeshIOError);
  EXPECT_THROW(MeshWriter::Create(dir.File("noext")), MeshIOError);
}

TEST(IOWriter, StlSpoolsVerticesToATemporaryFile)
{
  TempDir dir;
  const Mesh m = MakeMesh(3000, 5000, false);
  const std::size_t old = detail::SetStlWriterMemoryLimit(0);
  for (bool ascii : { false, true })
  {
    const std::string spooled = dir.File(ascii ? "s_a.stl" : "s_b.stl");
    WriteMesh(m, spooled, ascii, 500);
    detail::SetStlWriterMemoryLimit(old);
    const std::string memory = dir.File(ascii ? "m_a.stl" : "m_b.stl");
    WriteMesh(m, memory, ascii, 500);
    detail::SetStlWriterMemoryLimit(0);
    EXPECT_EQ(ReadFileBytes(spooled), ReadFileBytes(memory));
  }
  // Interleaved (triangles before all vertices): the spool is read back with pread.
  {
    auto w = MeshWriter::Create(dir.File("inter.stl"));
    w->Begin(6, 2, VertexLayout{});
    const float xyz[18] = { 0, 0, 0, 1, 0, 0, 0, 1, 0, 5, 5, 5, 6, 5, 5, 5, 6, 5 };
    const std::uint32_t t0[3] = { 0, 1, 2 }, t1[3] = { 3, 4, 5 };
    VertexChunk c;
    c.count = 3;
    c.xyz = xyz;
    w->Vertices(c);
    w->Triangles(t0, 1);
    c.first = 3;
    c.xyz = xyz + 9;
    w->Vertices(c);
    w->Triangles(t1, 1);
    w->End();
    CollectSink s = ReadAll(dir.File("inter.stl"));
    EXPECT_EQ(s.xyz, std::vector<float>(xyz, xyz + 18));
  }
  detail::SetStlWriterMemoryLimit(old);
  // Nothing left next to the outputs (the spool is unlinked at creation).
  int files = 0;
  for (const auto& entry : std::filesystem::directory_iterator(dir.Path()))
  {
    (void)entry;
    ++files;
  }
  EXPECT_EQ(files, 5);
}

std::string WriterError(const std::function<void()>& f)
{
  try
  {
    f();
  }
  catch (const MeshIOError& e)
  {
    return e.what();
  }
  return {};
}

TEST(IOWriter, CountsAndIndicesAreChecked)
{
  TempDir dir;
  const float xyz[9] = { 0, 0, 0, 1, 0, 0, 0, 1, 0 };
  const std::uint32_t tri[3] = { 0, 1, 2 }, bad[3] = { 0, 1, 3 };
  for (const char* ext : { ".ply", ".stl", ".obj" })
  {
    const std::string path = dir.File(std::string("c") + ext);
    VertexChunk c;
    c.count = 3;
    c.xyz = xyz;
    // too few vertices
    std::string e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      w->Begin(4, 1, VertexLayout{});
      w->Vertices(c);
      w->End();
    });
    EXPECT_NE(e.find("declared"), std::string::npos) << e;
    EXPECT_NE(e.find(path), std::string::npos) << e;
    // too many vertices
    e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      w->Begin(2, 1, VertexLayout{});
      w->Vertices(c);
    });
    EXPECT_NE(e.find("declared"), std::string::npos) << e;
    // too many triangles, and too few
    e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      w->Begin(3, 0, VertexLayout{});
      w->Vertices(c);
      w->Triangles(tri, 1);
    });
    EXPECT_NE(e.find("declared"), std::string::npos) << e;
    e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      w->Begin(3, 2, VertexLayout{});
      w->Vertices(c);
      w->Triangles(tri, 1);
      w->End();
    });
    EXPECT_NE(e.find("declared"), std::string::npos) << e;
    // out-of-range index
    e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      w->Begin(3, 1, VertexLayout{});
      w->Vertices(c);
      w->Triangles(bad, 1);
    });
    EXPECT_NE(e.find("out of range"), std::string::npos) << e;
    // layout declared but chunk lacks it
    e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      VertexLayout l;
      l.normals = true;
      w->Begin(3, 1, l);
      w->Vertices(c);
    });
    EXPECT_NE(e.find("lacks"), std::string::npos) << e;
    // non-consecutive chunks
    e = WriterError([&] {
      auto w = MeshWriter::Create(path);
      w->Begin(3, 1, VertexLayout{});
      VertexChunk d = c;
      d.first = 1;
      w->Vertices(d);
    });
    EXPECT_NE(e.find("expected 0"), std::string::npos) << e;
  }
  // PLY property names must be unique and blank-free.
  for (const char* name : { "x", "quality two", "" })
  {
    const std::string e = WriterError([&] {
      VertexLayout l;
      l.scalars = { name };
      MeshWriter::Create(dir.File("names.ply"))->Begin(1, 0, l);
    });
    EXPECT_NE(e.find("cannot be a PLY property name"), std::string::npos) << e;
  }
  // PLY stores vertices first.
  const std::string e = WriterError([&] {
    auto w = MeshWriter::Create(dir.File("order.ply"));
    w->Begin(6, 1, VertexLayout{});
    VertexChunk c;
    c.count = 3;
    c.xyz = xyz;
    w->Vertices(c);
    w->Triangles(tri, 1);
  });
  EXPECT_NE(e.find("vertices first"), std::string::npos) << e;
}

TEST(IOWriter, IoFailuresNameThePathAndTheReason)
{
  TempDir dir;
  const std::string missing = dir.File("no/such/dir/x.ply");
  const std::string e = WriterError([&] { MeshWriter::Create(missing); });
  EXPECT_NE(e.find(missing), std::string::npos) << e;
  EXPECT_NE(e.find("No such file or directory"), std::string::npos) << e;

  if (!std::filesystem::exists("/dev/full"))
    GTEST_SKIP() << "/dev/full not available";
  const std::string full = dir.File("full.ply");
  std::filesystem::create_symlink("/dev/full", full);
  const Mesh m = MakeMesh(100000, 10, false); // > 1 MiB: the buffer overflows into write(2)
  const std::string e2 = WriterError([&] { WriteMesh(m, full, false, 100000); });
  EXPECT_NE(e2.find(full), std::string::npos) << e2;
  EXPECT_NE(e2.find("No space left on device"), std::string::npos) << e2;
  const std::string e3 = WriterError([&] { WriteMesh(MakeMesh(3, 1, false), full, true); });
  EXPECT_NE(e3.find("No space left on device"), std::string::npos) << "flushed in End: " << e3;
}

TEST(IOWriter, EmptyMeshAndPointCloud)
{
  TempDir dir;
  for (const char* name : { "e.ply", "e.obj" })
  {
    auto w = MeshWriter::Create(dir.File(name));
    w->Begin(0, 0, VertexLayout{});
    w->End();
    CollectSink s = ReadAll(dir.File(name));
    EXPECT_EQ(s.Vertices(), 0u);
  }
  auto w = MeshWriter::Create(dir.File("e.stl"));
  w->Begin(0, 0, VertexLayout{});
  w->End();
  EXPECT_EQ(ReadFileBytes(dir.File("e.stl")).size(), 84u);
  EXPECT_EQ(ReadAll(dir.File("e.stl")).Vertices(), 0u);
}

} // namespace
} // namespace sipmss::io::test
