// Reader tests: every PLY encoding x count type x index type (plain, gzip, CRLF), attributes,
// unknown elements, polygons, STL ASCII/binary, OBJ, detection, headers, chunking, aborts and the
// shared real scans.
#include "IOTestUtil.h"

#include <chrono>
#include <cmath>
#include <random>
#include <thread>
#include <tuple>

#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

namespace sipmss::io::test
{
namespace
{

// ---------------------------------------------------------------------------------------------
// The reference mesh of the PLY matrix.
struct RefVertex
{
  float x, y, z, nx, ny, nz;
  std::uint8_t r, g, b, a;
  float u, v, quality;
  double intensity;
};

std::vector<RefVertex> RefVertices()
{
  std::vector<RefVertex> v;
  const float pos[6][3] = { { 0, 0, 0 }, { 1, 0, 0 }, { 1, 1, 0 }, { 0, 1, 0 }, { 0.5f, 1.5f, 0.25f },
    { -1.25f, 0.75f, 2 } };
  for (int i = 0; i < 6; ++i)
  {
    RefVertex r{};
    r.x = pos[i][0];
    r.y = pos[i][1];
    r.z = pos[i][2];
    r.nx = i == 4 ? 0.6f : 0.f;
    r.ny = 0.f;
    r.nz = i == 4 ? 0.8f : 1.f;
    r.r = std::uint8_t(10 * i);
    r.g = std::uint8_t(20 * i);
    r.b = std::uint8_t(30 * i);
    r.a = std::uint8_t(255 - i);
    r.u = 0.25f * float(i);
    r.v = 1.f - 0.125f * float(i);
    r.quality = 1.5f * float(i);
    r.intensity = 0.1 * i;
    v.push_back(r);
  }
  return v;
}

const std::vector<std::vector<int>> kFaces = { { 0, 1, 2 }, { 0, 2, 3, 4 }, { 1, 2, 3, 4, 5 } };
const std::vector<std::uint32_t> kFaceTriangles = { 0, 1, 2, 0, 2, 3, 0, 3, 4, 1, 2, 3, 1, 3, 4, 1, 4, 5 };

const char* const kIntTypes[6][2] = { { "char", "int8" }, { "uchar", "uint8" }, { "short", "int16" },
  { "ushort", "uint16" }, { "int", "int32" }, { "uint", "uint32" } };

// A PLY with every kind of vertex attribute, a vertex list property, unknown elements (with list
// properties) before, between and after, and faces with extra properties around vertex_indices.
std::string MatrixPly(Enc enc, bool crlf, const std::string& countType, const std::string& indexType)
{
  PlyBuilder b(enc, crlf);
  b.H("comment matrix test").H("obj_info generated");
  b.H("element multi_texture_vertex 3").H("property uchar tx").H("property float u").H("property float v");
  b.H("element vertex 6")
    .H("property float x")
    .H("property float32 y")
    .H("property float quality")
    .H("property float z")
    .H("property float nx")
    .H("property float ny")
    .H("property float nz")
    .H("property uchar red")
    .H("property uint8 green")
    .H("property uchar blue")
    .H("property uchar alpha")
    .H("property list uchar int vertex_junk")
    .H("property float u")
    .H("property float v")
    .H("property double intensity");
  b.H("element material 2").H("property list uchar uchar name").H("property float shininess");
  b.H("element face 3")
    .H("property int flags")
    .H("property list " + countType + " " + indexType + " vertex_indices")
    .H("property list uchar float texcoord");
  b.H("element multi_texture_face 2").H("property uchar tx").H("property uint tn").H(
    "property list uchar int texture_vertex_indices");
  for (int i = 0; i < 3; ++i)
    b.V("uchar", i).V("float", 0.5 * i).V("float", 0.25).EndRecord();
  for (const RefVertex& r : RefVertices())
  {
    b.V("float", r.x).V("float", r.y).V("float", r.quality).V("float", r.z);
    b.V("float", r.nx).V("float", r.ny).V("float", r.nz);
    b.V("uchar", r.r).V("uchar", r.g).V("uchar", r.b).V("uchar", r.a);
    const int junk = int(r.r / 10) % 3;
    b.V("uchar", junk);
    for (int k = 0; k < junk; ++k)
      b.V("int", -k);
    b.V("float", r.u).V("float", r.v).V("double", r.intensity).EndRecord();
  }
  for (int m = 0; m < 2; ++m)
  {
    b.V("uchar", 3 + m);
    for (int k = 0; k < 3 + m; ++k)
      b.V("uchar", 'a' + k);
    b.V("float", 0.5).EndRecord();
  }
  for (std::size_t f = 0; f < kFaces.size(); ++f)
  {
    b.V("int", 7 * int(f));
    b.V(countType, double(kFaces[f].size()));
    for (int i : kFaces[f])
      b.V(indexType, i);
    b.V("uchar", f);
    for (std::size_t k = 0; k < f; ++k)
      b.V("float", 0.5);
    b.EndRecord();
  }
  for (int m = 0; m < 2; ++m)
  {
    b.V("uchar", m).V("uint", 12345).V("uchar", 3);
    for (int k = 0; k < 3; ++k)
      b.V("int", k + m);
    b.EndRecord();
  }
  return b.Bytes();
}

void ExpectMatrixMesh(const CollectSink& s, const std::string& what)
{
  SCOPED_TRACE(what);
  const std::vector<RefVertex> ref = RefVertices();
  ASSERT_EQ(s.Vertices(), ref.size());
  EXPECT_TRUE(s.header.layout.normals);
  EXPECT_TRUE(s.header.layout.colors);
  EXPECT_TRUE(s.header.layout.texcoords);
  ASSERT_EQ(s.header.layout.scalars, (std::vector<std::string>{ "quality", "intensity" }));
  for (std::size_t i = 0; i < ref.size(); ++i)
  {
    const RefVertex& r = ref[i];
    EXPECT_EQ(s.xyz[3 * i], r.x);
    EXPECT_EQ(s.xyz[3 * i + 1], r.y);
    EXPECT_EQ(s.xyz[3 * i + 2], r.z);
    EXPECT_EQ(s.normals[3 * i], r.nx);
    EXPECT_EQ(s.normals[3 * i + 1], r.ny);
    EXPECT_EQ(s.normals[3 * i + 2], r.nz);
    EXPECT_EQ(s.rgba[4 * i], r.r);
    EXPECT_EQ(s.rgba[4 * i + 1], r.g);
    EXPECT_EQ(s.rgba[4 * i + 2], r.b);
    EXPECT_EQ(s.rgba[4 * i + 3], r.a);
    EXPECT_EQ(s.texcoords[2 * i], r.u);
    EXPECT_EQ(s.texcoords[2 * i + 1], r.v);
    EXPECT_EQ(s.scalars[2 * i], r.quality);
    EXPECT_EQ(s.scalars[2 * i + 1], float(r.intensity));
  }
  EXPECT_EQ(s.tris, kFaceTriangles);
  EXPECT_EQ(s.stats.polygons, 3u);
  EXPECT_EQ(s.stats.triangles, 6u);
  EXPECT_EQ(s.stats.droppedFaces, 0u);
}

class IOPlyMatrix : public ::testing::TestWithParam<std::tuple<Enc, bool, bool>>
{
};

TEST_P(IOPlyMatrix, AllCountAndIndexTypes)
{
  const auto [enc, gz, crlf] = GetParam();
  TempDir dir;
  const Format expected =
    enc == Enc::Ascii ? Format::PlyAscii : enc == Enc::LE ? Format::PlyBinaryLE : Format::PlyBinaryBE;
  for (int ci = 0; ci < 6; ++ci)
    for (int ii = 0; ii < 6; ++ii)
    {
      const std::string ct = kIntTypes[ci][(ci + ii) % 2], it = kIntTypes[ii][(ci + ii + 1) % 2];
      const std::string name = "m_" + ct + "_" + it + (gz ? ".ply.gz" : ".ply");
      const std::string bytes = MatrixPly(enc, crlf, ct, it);
      const std::string path = dir.File(name);
      if (gz)
        WriteGzip(path, bytes);
      else
        WriteFile(path, bytes);
      EXPECT_EQ(DetectFormat(path), expected);
      CollectSink s = ReadAll(path);
      ExpectMatrixMesh(s, name);
      EXPECT_EQ(s.header.format, expected);
      EXPECT_EQ(s.header.vertexCount, gz ? 0u : 6u) << "gzip counts are unknown up front";
      EXPECT_EQ(s.header.faceCount, gz ? 0u : 3u);
      EXPECT_EQ(s.stats.bytes, bytes.size());
      // Tiny chunks and a tiny buffer (from memory) exercise every boundary.
      ReadOptions o;
      o.chunkElements = 1;
      CollectSink s1 = ReadAll(path, o);
      ExpectMatrixMesh(s1, name + " chunk 1");
      EXPECT_EQ(s1.maxVertexChunk, 1u);
      CollectSink s2;
      MemoryReadOptions mo;
      mo.bufferBytes = 1024;
      const std::string fileBytes = ReadFileBytes(path);
      ReadMeshFromMemory(fileBytes.data(), fileBytes.size(), s2, ReadOptions{}, mo);
      ExpectMatrixMesh(s2, name + " memory");
      const MeshHeader h = ReadHeader(path);
      EXPECT_EQ(h.vertexCount, 6u);
      EXPECT_EQ(h.faceCount, 3u);
      EXPECT_EQ(h.layout.scalars.size(), 2u);
    }
}

INSTANTIATE_TEST_SUITE_P(IO, IOPlyMatrix,
  ::testing::Combine(::testing::Values(Enc::Ascii, Enc::LE, Enc::BE), ::testing::Bool(), ::testing::Bool()),
  [](const ::testing::TestParamInfo<IOPlyMatrix::ParamType>& info) {
    const Enc e = std::get<0>(info.param);
    return std::string(e == Enc::Ascii ? "Ascii" : e == Enc::LE ? "BinaryLE" : "BinaryBE") +
      (std::get<1>(info.param) ? "Gzip" : "Plain") + (std::get<2>(info.param) ? "CRLF" : "LF");
  });

// ---------------------------------------------------------------------------------------------
std::string SimplePly(Enc enc, const std::string& extraVertexProps = "")
{
  (void)extraVertexProps;
  PlyBuilder b(enc);
  b.H("element vertex 4").H("property float x").H("property float y").H("property float z");
  b.H("element face 2").H("property list uchar int vertex_indices");
  for (int i = 0; i < 4; ++i)
    b.V("float", i).V("float", i * 2).V("float", -i).EndRecord();
  b.V("uchar", 3).V("int", 0).V("int", 1).V("int", 2).EndRecord();
  b.V("uchar", 3).V("int", 1).V("int", 2).V("int", 3).EndRecord();
  return b.Bytes();
}

TEST(IOPly, AllVertexScalarTypesBecomeScalarsAndAttributes)
{
  TempDir dir;
  const char* types[] = { "char", "uchar", "short", "ushort", "int", "uint", "float", "double",
    "int8", "uint8", "int16", "uint16", "int32", "uint32", "float32", "float64" };
  for (Enc enc : { Enc::Ascii, Enc::LE, Enc::BE })
  {
    PlyBuilder b(enc);
    b.H("element vertex 3").H("property double x").H("property int16 y").H("property uint z");
    for (const char* t : types)
      b.H(std::string("property ") + t + " p_" + t);
    b.H("property float nx").H("property double ny").H("property short nz");
    for (int i = 0; i < 3; ++i)
    {
      b.V("double", 0.5 + i).V("int16", -i).V("uint", 3 * i);
      for (const char* t : types)
        b.V(t, (PlyBuilder::Canon(t)[0] == 'u' ? 1 : -1) * (i + 1));
      b.V("float", 1).V("double", 0).V("short", 0).EndRecord();
    }
    const std::string path = dir.File(std::string("types_") + EncName(enc) + ".ply");
    WriteFile(path, b.Bytes());
    CollectSink s = ReadAll(path);
    ASSERT_EQ(s.Vertices(), 3u);
    ASSERT_EQ(s.header.layout.scalars.size(), 16u);
    EXPECT_TRUE(s.header.layout.normals);
    for (int i = 0; i < 3; ++i)
    {
      EXPECT_EQ(s.xyz[3 * i], 0.5f + float(i));
      EXPECT_EQ(s.xyz[3 * i + 1], float(-i));
      EXPECT_EQ(s.xyz[3 * i + 2], float(3 * i));
      for (int k = 0; k < 16; ++k)
        EXPECT_EQ(s.scalars[16 * i + k], float((PlyBuilder::Canon(types[k])[0] == 'u' ? 1 : -1) * (i + 1)))
          << types[k];
      EXPECT_EQ(s.normals[3 * i], 1.f);
    }
  }
}

TEST(IOPly, BinaryVertexBlockPathsAndEndianness)
{
  // Fixed-size records (no lists) go through the block path: xyz-first float LE (memcpy),
  // other orders and big-endian (per property). Enough vertices to cross buffer refills.
  TempDir dir;
  const int n = 5000;
  for (Enc enc : { Enc::LE, Enc::BE })
    for (int layout = 0; layout < 3; ++layout)
    {
      PlyBuilder b(enc);
      b.H("element vertex " + std::to_string(n));
      if (layout == 0)
        b.H("property float x").H("property float y").H("property float z");
      else if (layout == 1)
        b.H("property float x").H("property float y").H("property float z").H("property uchar red").H(
          "property uchar green").H("property uchar blue").H("property ushort flags");
      else
        b.H("property double z").H("property float s").H("property float x").H("property float t").H(
          "property float y");
      for (int i = 0; i < n; ++i)
      {
        const float x = float(i) * 0.5f, y = float(-i), z = float(i % 17) * 0.25f;
        if (layout == 0)
          b.V("float", x).V("float", y).V("float", z);
        else if (layout == 1)
          b.V("float", x).V("float", y).V("float", z).V("uchar", i % 256).V("uchar", 1).V("uchar", 2).V("ushort", i);
        else
          b.V("double", z).V("float", 0.5).V("float", x).V("float", 0.75).V("float", y);
      }
      const std::string bytes = b.Bytes();
      for (std::size_t buffer : { std::size_t(0), std::size_t(1024), std::size_t(1500) })
      {
        CollectSink s;
        MemoryReadOptions mo;
        mo.bufferBytes = buffer;
        ReadOptions o;
        o.chunkElements = 333;
        ReadMeshFromMemory(bytes.data(), bytes.size(), s, o, mo);
        ASSERT_EQ(s.Vertices(), std::uint64_t(n));
        EXPECT_LE(s.maxVertexChunk, 333u);
        for (int i = 0; i < n; ++i)
        {
          ASSERT_EQ(s.xyz[3 * i], float(i) * 0.5f) << i;
          ASSERT_EQ(s.xyz[3 * i + 1], float(-i));
          ASSERT_EQ(s.xyz[3 * i + 2], float(i % 17) * 0.25f);
        }
        if (layout == 1)
        {
          ASSERT_TRUE(s.header.layout.colors);
          EXPECT_EQ(s.rgba[4 * 300], 300 % 256);
          EXPECT_EQ(s.rgba[4 * 300 + 3], 255) << "alpha defaults to 255";
          EXPECT_EQ(s.scalars[300], 300.f);
        }
        if (layout == 2)
        {
          ASSERT_TRUE(s.header.layout.texcoords);
          EXPECT_EQ(s.texcoords[2 * 7], 0.5f);
          EXPECT_EQ(s.texcoords[2 * 7 + 1], 0.75f);
        }
      }
    }
}

TEST(IOPly, BinaryFacesFastPathMixedPolygonsAcrossBuffers)
{
  // Many triangles with a quad, a pentagon, a 2-gon and a degenerate triangle sprinkled in, big
  // enough to cross 1 KiB and 1 MiB buffers at odd offsets.
  const int nv = 1000, nf = 120000;
  std::vector<std::uint32_t> expected;
  std::uint64_t dropped = 0;
  for (Enc enc : { Enc::LE, Enc::BE })
    for (const char* it : { "int", "uint" })
    {
      PlyBuilder b(enc);
      b.H("element vertex " + std::to_string(nv)).H("property float x").H("property float y").H("property float z");
      b.H("element face " + std::to_string(nf)).H(std::string("property list uchar ") + it + " vertex_indices");
      for (int i = 0; i < nv; ++i)
        b.V("float", i).V("float", 0).V("float", 0);
      expected.clear();
      dropped = 0;
      for (int f = 0; f < nf; ++f)
      {
        const std::uint32_t a = std::uint32_t(f % nv), c1 = std::uint32_t((f + 1) % nv),
                            c2 = std::uint32_t((f + 2) % nv), c3 = std::uint32_t((f + 3) % nv),
                            c4 = std::uint32_t((f + 4) % nv);
        if (f % 997 == 5)
        {
          b.V("uchar", 4).V(it, a).V(it, c1).V(it, c2).V(it, c3);
          expected.insert(expected.end(), { a, c1, c2, a, c2, c3 });
        }
        else if (f % 1999 == 7)
        {
          b.V("uchar", 5).V(it, a).V(it, c1).V(it, c2).V(it, c3).V(it, c4);
          expected.insert(expected.end(), { a, c1, c2, a, c2, c3, a, c3, c4 });
        }
        else if (f % 3001 == 11)
        {
          b.V("uchar", 2).V(it, a).V(it, c1);
          ++dropped;
        }
        else if (f % 4001 == 13)
        {
          b.V("uchar", 3).V(it, a).V(it, c1).V(it, a);
          ++dropped;
        }
        else
        {
          b.V("uchar", 3).V(it, a).V(it, c1).V(it, c2);
          expected.insert(expected.end(), { a, c1, c2 });
        }
      }
      const std::string bytes = b.Bytes();
      for (std::size_t buffer : { std::size_t(0), std::size_t(1024), std::size_t(4099) })
      {
        SCOPED_TRACE(std::string(EncName(enc)) + " " + it + " buffer " + std::to_string(buffer));
        CollectSink s;
        MemoryReadOptions mo;
        mo.bufferBytes = buffer;
        ReadMeshFromMemory(bytes.data(), bytes.size(), s, ReadOptions{}, mo);
        EXPECT_EQ(s.stats.polygons, std::uint64_t(nf));
        EXPECT_EQ(s.stats.droppedFaces, dropped);
        ASSERT_EQ(s.tris.size(), expected.size());
        EXPECT_TRUE(s.tris == expected);
      }
    }
}

// A face property as TriangleFlags (ReadOptions::faceFlag): before or after the index list, in
// every encoding, on polygons (each of its triangles) and across small buffers; the header lists
// the face scalars; nothing is delivered without the option or for a name the file lacks.
TEST(IOPly, FaceScalarBecomesTriangleFlags)
{
  const int nv = 50, nf = 3000;
  for (Enc enc : { Enc::Ascii, Enc::LE, Enc::BE })
    for (bool before : { true, false })
    {
      PlyBuilder b(enc);
      b.H("element vertex " + std::to_string(nv)).H("property float x").H("property float y").H("property float z");
      b.H("element face " + std::to_string(nf));
      if (before)
        b.H("property float sel");
      b.H("property list uchar int vertex_indices");
      if (!before)
        b.H("property uchar sel");
      b.H("property short other");
      for (int i = 0; i < nv; ++i)
        b.V("float", i).V("float", i % 7).V("float", 0).EndRecord();
      std::vector<std::uint8_t> expected;
      for (int f = 0; f < nf; ++f)
      {
        const int flag = (f / 3) % 2;
        const int n = f % 11 == 0 ? 5 : 3; // pentagons: three triangles each
        if (before)
          b.V("float", flag ? 0.5 : 0.0);
        b.V("uchar", n);
        for (int k = 0; k < n; ++k)
          b.V("int", (f + k) % nv);
        if (!before)
          b.V("uchar", flag);
        b.V("short", -f % 100).EndRecord();
        expected.insert(expected.end(), std::size_t(n - 2), std::uint8_t(flag));
      }
      const std::string bytes = b.Bytes();
      for (std::size_t buffer : { std::size_t(0), std::size_t(1024) })
      {
        SCOPED_TRACE(std::string(EncName(enc)) + (before ? " before" : " after") + " buffer " +
          std::to_string(buffer));
        ReadOptions o;
        o.faceFlag = "sel";
        o.chunkElements = 100; // (a polygon may not fit what is left of the buffer)
        CollectSink s;
        MemoryReadOptions mo;
        mo.bufferBytes = buffer;
        ReadMeshFromMemory(bytes.data(), bytes.size(), s, o, mo);
        EXPECT_EQ(s.header.faceScalars, (std::vector<std::string>{ "sel", "other" }));
        ASSERT_EQ(s.flags.size(), s.TriangleCount());
        EXPECT_TRUE(s.flags == expected);
        CollectSink none;
        ReadMeshFromMemory(bytes.data(), bytes.size(), none, ReadOptions{}, mo);
        EXPECT_TRUE(none.flags.empty());
        EXPECT_TRUE(none.tris == s.tris);
        o.faceFlag = "missing";
        CollectSink missing;
        ReadMeshFromMemory(bytes.data(), bytes.size(), missing, o, mo);
        EXPECT_TRUE(missing.flags.empty());
      }
    }
}

TEST(IOPly, FloatColorsAreScaledAndTexcoordAliases)
{
  TempDir dir;
  for (Enc enc : { Enc::Ascii, Enc::LE })
  {
    PlyBuilder b(enc);
    b.H("element vertex 2")
      .H("property float x")
      .H("property float y")
      .H("property float z")
      .H("property float red")
      .H("property float green")
      .H("property double blue")
      .H("property float texture_u")
      .H("property float texture_v")
      .H("property float s");
    b.V("float", 0).V("float", 0).V("float", 0).V("float", 1).V("float", 0.5).V("double", 0).V("float", 0.25).V("float", 0.75).V("float", 9).EndRecord();
    b.V("float", 1).V("float", 1).V("float", 1).V("float", 2).V("float", -1).V("double", 0.2).V("float", 1).V("float", 0).V("float", 8).EndRecord();
    const std::string path = dir.File(std::string("colors_") + EncName(enc) + ".ply");
    WriteFile(path, b.Bytes());
    CollectSink s = ReadAll(path);
    ASSERT_TRUE(s.header.layout.colors);
    ASSERT_TRUE(s.header.layout.texcoords);
    EXPECT_EQ(s.header.layout.scalars, std::vector<std::string>{ "s" }) << "s without t is a scalar";
    EXPECT_EQ(std::vector<int>(s.rgba.begin(), s.rgba.end()),
      (std::vector<int>{ 255, 128, 0, 255, 255, 0, 51, 255 }));
    EXPECT_EQ(s.texcoords, (std::vector<float>{ 0.25f, 0.75f, 1.f, 0.f }));
    EXPECT_EQ(s.scalars, (std::vector<float>{ 9.f, 8.f }));
  }
}

TEST(IOPly, PartialNormalsAreScalarsAndStAliases)
{
  TempDir dir;
  PlyBuilder b(Enc::Ascii);
  b.H("element vertex 1").H("property float x").H("property float y").H("property float z").H(
    "property float nx").H("property float ny").H("property float s").H("property float t");
  b.V("float", 1).V("float", 2).V("float", 3).V("float", 4).V("float", 5).V("float", 6).V("float", 7).EndRecord();
  const std::string path = dir.File("partial.ply");
  WriteFile(path, b.Bytes());
  CollectSink s = ReadAll(path);
  EXPECT_FALSE(s.header.layout.normals);
  EXPECT_TRUE(s.header.layout.texcoords);
  EXPECT_EQ(s.header.layout.scalars, (std::vector<std::string>{ "nx", "ny" }));
  EXPECT_EQ(s.scalars, (std::vector<float>{ 4, 5 }));
  EXPECT_EQ(s.texcoords, (std::vector<float>{ 6, 7 }));
}

TEST(IOPly, FacesBeforeVerticesAndVertexIndexName)
{
  TempDir dir;
  for (Enc enc : { Enc::Ascii, Enc::LE, Enc::BE })
  {
    PlyBuilder b(enc);
    b.H("element face 2").H("property list int short vertex_index");
    b.H("element vertex 4").H("property float x").H("property float y").H("property float z");
    b.V("int", 3).V("short", 0).V("short", 1).V("short", 2).EndRecord();
    b.V("int", 3).V("short", 3).V("short", 2).V("short", 1).EndRecord();
    for (int i = 0; i < 4; ++i)
      b.V("float", i).V("float", 0).V("float", 1).EndRecord();
    const std::string path = dir.File(std::string("fbv_") + EncName(enc) + ".ply");
    WriteFile(path, b.Bytes());
    CollectSink s = ReadAll(path);
    EXPECT_EQ(s.Vertices(), 4u);
    EXPECT_EQ(s.tris, (std::vector<std::uint32_t>{ 0, 1, 2, 3, 2, 1 }));
    ReadOptions o;
    o.verticesOnly = true;
    CollectSink v = ReadAll(path, o);
    EXPECT_EQ(v.Vertices(), 4u);
    EXPECT_TRUE(v.tris.empty());
  }
}

TEST(IOPly, VerticesOnlyStopsAfterTheVertexElement)
{
  TempDir dir;
  for (Enc enc : { Enc::Ascii, Enc::LE })
  {
    const std::string bytes = SimplePly(enc);
    const std::string path = dir.File(std::string("vo_") + EncName(enc) + ".ply");
    WriteFile(path, bytes);
    ReadOptions o;
    o.verticesOnly = true;
    CollectSink s = ReadAll(path, o);
    EXPECT_EQ(s.Vertices(), 4u);
    EXPECT_EQ(s.triangleCalls, 0u);
    EXPECT_EQ(s.stats.triangles, 0u);
    EXPECT_LT(s.stats.bytes, bytes.size()) << "the faces were not read";
  }
  // Stopping early also means garbage after the vertices is never seen.
  PlyBuilder b(Enc::LE);
  b.H("element vertex 1").H("property float x").H("property float y").H("property float z");
  b.H("element face 1").H("property list uchar int vertex_indices");
  b.V("float", 1).V("float", 2).V("float", 3).V("uchar", 3).V("int", 0).V("int", 0).V("int", 99);
  const std::string path = dir.File("vo_bad_faces.ply");
  WriteFile(path, b.Bytes());
  ReadOptions o;
  o.verticesOnly = true;
  EXPECT_EQ(ReadAll(path, o).Vertices(), 1u);
  EXPECT_NE(ReadError(path).find("out of range"), std::string::npos);
}

TEST(IOPly, ShortFacesAreDroppedAndDegenerateOnesOptionally)
{
  TempDir dir;
  for (Enc enc : { Enc::Ascii, Enc::LE, Enc::BE })
  {
    PlyBuilder b(enc);
    b.H("element vertex 4").H("property float x").H("property float y").H("property float z");
    b.H("element face 6").H("property list uchar uint vertex_indices");
    for (int i = 0; i < 4; ++i)
      b.V("float", i).V("float", 1).V("float", 2).EndRecord();
    b.V("uchar", 0).EndRecord();
    b.V("uchar", 1).V("uint", 2).EndRecord();
    b.V("uchar", 2).V("uint", 2).V("uint", 3).EndRecord();
    b.V("uchar", 3).V("uint", 1).V("uint", 1).V("uint", 2).EndRecord(); // degenerate
    b.V("uchar", 4).V("uint", 0).V("uint", 1).V("uint", 1).V("uint", 2).EndRecord(); // one of two
    b.V("uchar", 3).V("uint", 0).V("uint", 1).V("uint", 2).EndRecord();
    const std::string path = dir.File(std::string("short_") + EncName(enc) + ".ply");
    WriteFile(path, b.Bytes());
    CollectSink s = ReadAll(path);
    EXPECT_EQ(s.stats.polygons, 6u);
    EXPECT_EQ(s.stats.droppedFaces, 5u) << "3 short faces + 2 degenerate triangles";
    EXPECT_EQ(s.tris, (std::vector<std::uint32_t>{ 0, 1, 2, 0, 1, 2 }));
    ReadOptions keep;
    keep.dropDegenerateFaces = false;
    CollectSink k = ReadAll(path, keep);
    EXPECT_EQ(k.stats.droppedFaces, 3u);
    EXPECT_EQ(k.tris, (std::vector<std::uint32_t>{ 1, 1, 2, 0, 1, 1, 0, 1, 2, 0, 1, 2 }));
  }
}

TEST(IOPly, PointCloudWithoutFacesAndEmptyElements)
{
  TempDir dir;
  PlyBuilder b(Enc::Ascii);
  b.H("element vertex 2").H("property float x").H("property float y").H("property float z");
  b.H("element nothing 5");
  b.H("element face 0").H("property list uchar int vertex_indices");
  b.V("float", 1).V("float", 2).V("float", 3).EndRecord().EndRecord(); // a blank line
  b.V("float", 4).V("float", 5).V("float", 6);                          // no final newline
  const std::string path = dir.File("cloud.ply");
  WriteFile(path, b.Bytes());
  CollectSink s = ReadAll(path);
  EXPECT_EQ(s.xyz, (std::vector<float>{ 1, 2, 3, 4, 5, 6 }));
  EXPECT_TRUE(s.tris.empty());
}

TEST(IOPly, AbortBetweenChunks)
{
  TempDir dir;
  const std::string path = dir.File("abort.ply");
  WriteFile(path, SimplePly(Enc::LE));
  CollectSink s;
  s.abortAfterCalls = 1;
  ReadOptions o;
  o.chunkElements = 1;
  try
  {
    ReadMesh(path, s, o);
    FAIL() << "no abort";
  }
  catch (const MeshIOError& e)
  {
    EXPECT_NE(std::string(e.what()).find("aborted"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find(path), std::string::npos) << e.what();
  }
  EXPECT_EQ(s.vertexCalls, 1u);
  EXPECT_FALSE(s.ended);
}

// ---------------------------------------------------------------------------------------------
std::string BinaryStl(const std::vector<float>& tris9, const std::string& header80 = "binary")
{
  std::string h = header80;
  h.resize(80, ' ');
  const std::uint32_t n = std::uint32_t(tris9.size() / 9);
  h.append(reinterpret_cast<const char*>(&n), 4); // the test host is little-endian (x86/ARM)
  for (std::uint32_t t = 0; t < n; ++t)
  {
    const float nrm[3] = { 0, 0, 1 };
    h.append(reinterpret_cast<const char*>(nrm), 12);
    h.append(reinterpret_cast<const char*>(&tris9[9 * t]), 36);
    h.append("\0\0", 2);
  }
  return h;
}

const std::vector<float> kStlTris = { 0, 0, 0, 1, 0, 0, 0, 1, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 0.5f, -2.25f,
  3, 1e-3f, 7, -8, 100, 200, 300 };

void ExpectStlMesh(const CollectSink& s)
{
  ASSERT_EQ(s.Vertices(), 9u);
  EXPECT_EQ(s.xyz, kStlTris);
  EXPECT_EQ(s.tris, (std::vector<std::uint32_t>{ 0, 1, 2, 3, 4, 5, 6, 7, 8 }));
  EXPECT_FALSE(s.header.layout.normals);
}

TEST(IOStl, BinaryIncludingOneStartingWithSolid)
{
  TempDir dir;
  for (const char* header : { "binary", "solid pretending to be ascii", "solid" })
    for (bool gz : { false, true })
    {
      const std::string path = dir.File(std::string("b_") + (header[0] == 's' ? "solid" : "plain") +
        std::to_string(std::strlen(header)) + (gz ? ".stl.gz" : ".stl"));
      const std::string bytes = BinaryStl(kStlTris, header);
      if (gz)
        WriteGzip(path, bytes);
      else
        WriteFile(path, bytes);
      EXPECT_EQ(DetectFormat(path), Format::StlBinary) << header;
      CollectSink s = ReadAll(path);
      ExpectStlMesh(s);
      EXPECT_EQ(s.header.format, Format::StlBinary);
      const MeshHeader h = ReadHeader(path);
      EXPECT_EQ(h.vertexCount, 9u);
      EXPECT_EQ(h.faceCount, 3u);
    }
  // Chunks: facets per call bounded by chunkElements / 3
  const std::string path = dir.File("chunks.stl");
  WriteFile(path, BinaryStl(kStlTris));
  ReadOptions o;
  o.chunkElements = 3;
  CollectSink s = ReadAll(path, o);
  ExpectStlMesh(s);
  EXPECT_EQ(s.maxVertexChunk, 3u);
  EXPECT_EQ(s.vertexCalls, 3u);
}

std::string AsciiStl(const std::string& nl)
{
  std::string s = "solid test" + nl;
  for (std::size_t t = 0; t < kStlTris.size() / 9; ++t)
  {
    s += "  facet normal 0 0 1" + nl + "    outer loop" + nl;
    for (int v = 0; v < 3; ++v)
    {
      char buf[128];
      std::snprintf(buf, sizeof buf, "      vertex %.9g %.9g %.9g", kStlTris[9 * t + 3 * v],
        kStlTris[9 * t + 3 * v + 1], kStlTris[9 * t + 3 * v + 2]);
      s += buf + nl;
    }
    s += "    endloop" + nl + "  endfacet" + nl;
  }
  return s + "endsolid test" + nl;
}

TEST(IOStl, AsciiPlainCrlfGzipUppercase)
{
  TempDir dir;
  for (const std::string nl : { "\n", "\r\n" })
    for (bool gz : { false, true })
    {
      const std::string path = dir.File(std::string("a") + (nl.size() == 2 ? "_crlf" : "") + (gz ? ".stl.gz" : ".stl"));
      if (gz)
        WriteGzip(path, AsciiStl(nl));
      else
        WriteFile(path, AsciiStl(nl));
      EXPECT_EQ(DetectFormat(path), Format::StlAscii);
      CollectSink s = ReadAll(path);
      ExpectStlMesh(s);
      const MeshHeader h = ReadHeader(path);
      EXPECT_EQ(h.vertexCount, 9u);
      EXPECT_EQ(h.faceCount, 3u);
    }
  std::string upper = AsciiStl("\n");
  for (char& c : upper)
    if (c >= 'a' && c <= 'z')
      c = char(c - 'a' + 'A');
  const std::string path = dir.File("upper.stl");
  WriteFile(path, upper);
  ExpectStlMesh(ReadAll(path));
}

TEST(IOStl, AsciiPolygonFacetsMultipleSolidsAndShortFacets)
{
  TempDir dir;
  const std::string text =
    "solid a\nfacet normal 0 0 0\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 1 1 0\nvertex 0 1 0\n"
    "endloop\nendfacet\nendsolid a\nsolid b\nfacet normal 0 0 0\nouter loop\nvertex 5 5 5\nvertex 6 6 6\n"
    "endloop\nendfacet\nfacet normal 0 0 0\nouter loop\nvertex 1 2 3\nvertex 4 5 6\nvertex 7 8 9\nendloop\n"
    "endfacet\nendsolid b\n";
  const std::string path = dir.File("poly.stl");
  WriteFile(path, text);
  CollectSink s = ReadAll(path);
  EXPECT_EQ(s.Vertices(), 7u) << "the 2-vertex facet delivers no vertices";
  EXPECT_EQ(s.tris, (std::vector<std::uint32_t>{ 0, 1, 2, 0, 2, 3, 4, 5, 6 }));
  EXPECT_EQ(s.stats.droppedFaces, 1u);
  EXPECT_EQ(s.stats.polygons, 3u);
}

// ---------------------------------------------------------------------------------------------
TEST(IOObj, AllFaceFormsNegativeIndicesAndInterleaving)
{
  TempDir dir;
  for (const std::string nl : { "\n", "\r\n" })
    for (bool gz : { false, true })
    {
      std::string t = "# comment" + nl + "mtllib x.mtl" + nl + "o thing" + nl;
      t += "v 0 0 0" + nl + "v 1 0 0" + nl + "v 1 1 0 1.0" + nl + "vt 0 0" + nl + "vn 0 0 1" + nl;
      t += "f 1 2 3" + nl;                 // i
      t += "v 0 1 0 0.5 0.5 0.5" + nl;     // w + colour extension: ignored
      t += "f 1/1 3/1 4/1" + nl;           // i/t
      t += "g group" + nl + "s off" + nl + "usemtl m" + nl;
      t += "f\t1//1  2//1 3//1   " + nl;   // i//n, blanks
      t += "v -1 -1 -1" + nl + "v 2 2 2" + nl;
      t += "f -2/1/1 -1/1/1 -6/1/1" + nl; // i/t/n, relative
      t += "f 1 2 3 4 5" + nl;             // pentagon
      t += "f 1 2" + nl;                   // dropped
      t += "f 2 2 3" + nl;                 // degenerate: dropped
      t += "l 1 2" + nl + "# end";
      const std::string path = dir.File(std::string("m") + (nl.size() == 2 ? "_crlf" : "") + (gz ? ".obj.gz" : ".obj"));
      if (gz)
        WriteGzip(path, t);
      else
        WriteFile(path, t);
      EXPECT_EQ(DetectFormat(path), Format::Obj);
      CollectSink s;
      s.checkOrder = true;
      ReadOptions o;
      o.chunkElements = 2;
      ReadMesh(path, s, o);
      EXPECT_EQ(s.xyz, (std::vector<float>{ 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, -1, -1, -1, 2, 2, 2 }));
      EXPECT_EQ(s.tris, (std::vector<std::uint32_t>{ 0, 1, 2, 0, 2, 3, 0, 1, 2, 4, 5, 0, 0, 1, 2, 0, 2, 3, 0, 3, 4 }));
      EXPECT_EQ(s.stats.polygons, 7u);
      EXPECT_EQ(s.stats.droppedFaces, 2u);
      EXPECT_EQ(s.header.vertexCount, 0u) << "unknown up front";
      const MeshHeader h = ReadHeader(path);
      EXPECT_EQ(h.vertexCount, 6u);
      EXPECT_EQ(h.faceCount, 7u);
      o.verticesOnly = true;
      CollectSink v = ReadAll(path, o);
      EXPECT_EQ(v.Vertices(), 6u);
      EXPECT_TRUE(v.tris.empty());
    }
}

TEST(IOObj, LargeInterleavedFileInOrder)
{
  // A strip of quads written v,v,f,...: every triangle only references vertices delivered
  // before it, whatever the chunk size.
  std::string t;
  const int n = 20000;
  for (int i = 0; i < n; ++i)
  {
    t += "v " + std::to_string(i) + " 0 0\nv " + std::to_string(i) + " 1 0\n";
    if (i > 0)
      t += "f -4 -3 -1 -2\n";
  }
  for (std::size_t chunk : { std::size_t(1), std::size_t(7), std::size_t(1 << 14) })
  {
    CollectSink s;
    s.checkOrder = true;
    ReadOptions o;
    o.chunkElements = chunk;
    MemoryReadOptions mo;
    mo.bufferBytes = 1024;
    ReadMeshFromMemory(t.data(), t.size(), s, o, mo);
    EXPECT_EQ(s.Vertices(), std::uint64_t(2 * n));
    EXPECT_EQ(s.TriangleCount(), std::uint64_t(2 * (n - 1)));
    EXPECT_EQ(s.tris[0], 0u);
    EXPECT_EQ(s.tris.back(), std::uint32_t(2 * n - 2));
  }
}

// ---------------------------------------------------------------------------------------------
TEST(IODetect, ByContent)
{
  TempDir dir;
  struct Case
  {
    std::string name, bytes;
    Format format;
  } cases[] = {
    { "a.dat", SimplePly(Enc::Ascii), Format::PlyAscii },
    { "b.dat", SimplePly(Enc::LE), Format::PlyBinaryLE },
    { "c.dat", SimplePly(Enc::BE), Format::PlyBinaryBE },
    { "d.dat", BinaryStl(kStlTris, "solid x"), Format::StlBinary },
    { "e.dat", AsciiStl("\n"), Format::StlAscii },
    { "f.dat", "# just comments\n\nv 1 2 3\n", Format::Obj },
    { "g.dat", "hello world\n", Format::Unknown },
    { "h.dat", "", Format::Unknown },
    { "i.dat", std::string("\x89PNG\r\n\x1a\n", 8) + std::string(200, '\0'), Format::Unknown },
  };
  for (const Case& c : cases)
  {
    WriteFile(dir.File(c.name), c.bytes);
    EXPECT_EQ(DetectFormat(dir.File(c.name)), c.format) << c.name;
    EXPECT_EQ(DetectFormatFromMemory(c.bytes.data(), c.bytes.size()), c.format) << c.name;
    WriteGzip(dir.File(c.name + ".gz"), c.bytes);
    if (c.format != Format::Unknown)
    {
      EXPECT_EQ(DetectFormat(dir.File(c.name + ".gz")), c.format) << c.name;
    }
  }
  EXPECT_STREQ(ToString(Format::PlyBinaryBE), "PLY (binary big-endian)");
}

TEST(IOHeader, PlyFromHeaderOthersByScan)
{
  TempDir dir;
  const std::string ply = dir.File("h.ply");
  WriteFile(ply, SimplePly(Enc::LE));
  MeshHeader h = ReadHeader(ply);
  EXPECT_EQ(h.format, Format::PlyBinaryLE);
  EXPECT_EQ(h.vertexCount, 4u);
  EXPECT_EQ(h.faceCount, 2u);
  const std::string gz = dir.File("h.ply.gz");
  WriteGzip(gz, SimplePly(Enc::BE));
  h = ReadHeader(gz);
  EXPECT_EQ(h.format, Format::PlyBinaryBE);
  EXPECT_EQ(h.vertexCount, 4u);
  EXPECT_EQ(h.faceCount, 2u);
}

TEST(IOHeader, PropertiesFromTheHeaderAlone)
{
  TempDir dir;
  PlyBuilder b(Enc::LE);
  b.H("element vertex 3").H("property float x").H("property float y").H("property float z");
  b.H("property float nx").H("property float ny").H("property float nz");
  b.H("property uchar red").H("property uchar green").H("property uchar blue");
  b.H("property float quality").H("property int mask");
  b.H("element face 1").H("property list uchar int vertex_indices").H("property uchar sel");
  for (int i = 0; i < 3; ++i)
  {
    b.V("float", i).V("float", 0).V("float", 0).V("float", 0).V("float", 0).V("float", 1);
    b.V("uchar", 1).V("uchar", 2).V("uchar", 3).V("float", 0.5).V("int", i).EndRecord();
  }
  b.V("uchar", 3).V("int", 0).V("int", 1).V("int", 2).V("uchar", 1).EndRecord();
  const std::string bytes = b.Bytes();
  const std::string ply = dir.File("p.ply");
  WriteFile(ply, bytes);
  const std::vector<std::string> points{ "quality", "mask" }, cells{ "sel" };
  MeshHeader h = ReadProperties(ply);
  EXPECT_EQ(h.format, Format::PlyBinaryLE);
  EXPECT_EQ(h.layout.scalars, points);
  EXPECT_EQ(h.faceScalars, cells);
  EXPECT_EQ(h.vertexCount, 0u);
  EXPECT_EQ(h.faceCount, 0u);
  // the names are those a run reads (ReadHeader's)
  EXPECT_EQ(ReadHeader(ply).layout.scalars, points);
  const std::string gz = dir.File("p.ply.gz");
  WriteGzip(gz, bytes);
  h = ReadProperties(gz);
  EXPECT_EQ(h.layout.scalars, points);
  EXPECT_EQ(h.faceScalars, cells);
  // the header alone: a body cut short still names its properties (ReadHeader refuses it)
  const std::string cut = dir.File("cut.ply");
  WriteFile(cut, bytes.substr(0, bytes.size() - 20));
  EXPECT_EQ(ReadProperties(cut).layout.scalars, points);
  EXPECT_THROW(ReadHeader(cut), MeshIOError);
  // STL and OBJ name none
  const std::string obj = dir.File("t.obj");
  WriteFile(obj, "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n");
  h = ReadProperties(obj);
  EXPECT_EQ(h.format, Format::Obj);
  EXPECT_TRUE(h.layout.scalars.empty());
  EXPECT_TRUE(h.faceScalars.empty());
  const std::string stl = dir.File("t.stl");
  WriteFile(stl, BinaryStl(kStlTris));
  EXPECT_EQ(ReadProperties(stl).format, Format::StlBinary);
  EXPECT_TRUE(ReadProperties(stl).layout.scalars.empty());
  // errors name the file
  WriteFile(dir.File("bad.ply"), "ply\nformat ascii 1.0\nelement vertex x\nend_header\n");
  try
  {
    ReadProperties(dir.File("bad.ply"));
    ADD_FAILURE() << "a malformed header was accepted";
  }
  catch (const MeshIOError& e)
  {
    EXPECT_NE(std::string(e.what()).find("bad.ply"), std::string::npos) << e.what();
  }
  EXPECT_THROW(ReadProperties(dir.File("missing.ply")), MeshIOError);
}

// ---------------------------------------------------------------------------------------------
struct SharedCase
{
  const char* file;
  std::uint64_t vertices, faces;
  Format format;
};

class IOSharedData : public ::testing::TestWithParam<SharedCase>
{
};

TEST_P(IOSharedData, Counts)
{
  const SharedCase& c = GetParam();
  const std::string path = DataDir() + "/" + c.file;
  if (!std::filesystem::exists(path))
    GTEST_SKIP() << "shared test data not found: " << path << " (set SIPMSS_SHARED_DATA_DIR)";
  EXPECT_EQ(DetectFormat(path), c.format);
  CollectSink s = ReadAll(path);
  EXPECT_EQ(s.stats.vertices, c.vertices);
  EXPECT_EQ(s.stats.polygons, c.faces);
  EXPECT_EQ(s.stats.triangles + s.stats.droppedFaces, c.faces) << "all triangles";
  const MeshHeader h = ReadHeader(path);
  EXPECT_EQ(h.vertexCount, c.vertices);
  EXPECT_EQ(h.faceCount, c.faces);
  ReadOptions o;
  o.verticesOnly = true;
  CollectSink v = ReadAll(path, o);
  EXPECT_EQ(v.xyz, s.xyz);
  if (std::string(c.file) == "bunny.ply")
  {
    EXPECT_EQ(s.header.layout.scalars, (std::vector<std::string>{ "confidence", "intensity" }));
  }
  if (std::string(c.file) == "horse.ply")
  {
    EXPECT_TRUE(s.header.layout.colors);
    EXPECT_EQ(s.header.layout.scalars, std::vector<std::string>{ "confidence" });
  }
  // Plausible coordinates: finite and not all zero.
  float extent = 0;
  for (float x : s.xyz)
    extent = std::max(extent, std::fabs(x));
  EXPECT_GT(extent, 0.f);
  EXPECT_LT(extent, 1e6f);
}

INSTANTIATE_TEST_SUITE_P(IO, IOSharedData,
  ::testing::Values(SharedCase{ "bunny.ply", 35947, 69451, Format::PlyAscii },
    SharedCase{ "horse.ply", 48485, 96966, Format::PlyBinaryBE },
    SharedCase{ "pepper.ply", 14980, 29956, Format::PlyBinaryLE },
    SharedCase{ "dragon_vrip_res4.ply.gz", 5205, 11102, Format::PlyAscii }),
  [](const ::testing::TestParamInfo<SharedCase>& info) {
    std::string n = info.param.file;
    return n.substr(0, n.find_first_of('.'));
  });

// ---------------------------------------------------------------------------------------------
// Issue 20 item 4: an abort reaches the reader inside a chunk, however long a line, a run of
// skipped records or of dropped faces is (before, only a chunk flush asked, so none of these
// inputs, which never fill a chunk, could be stopped).
class AbortAlways : public MeshSink
{
public:
  void Begin(const MeshHeader&) override {}
  void Vertices(const VertexChunk&) override {}
  void Triangles(const std::uint32_t*, std::size_t) override {}
  void End(const ReadStats&) override { ended = true; }
  bool AbortRequested() override
  {
    // not at the first ask (format detection's first buffer): inside the long loop
    return ++asked >= 3;
  }
  bool ended = false;
  std::uint64_t asked = 0;
};

TEST(IOAbort, InsideLongLinesSkippedRecordsAndDroppedFaces)
{
  const std::size_t big = std::size_t(6) << 20; // several buffer refills
  std::string comment = "# " + std::string(big, 'x') + "\nv 0 0 0\n";
  std::string emptyFaces = "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                           "property float y\nproperty float z\nelement face " +
    std::to_string(big / 2) + "\nproperty list uchar int vertex_indices\nend_header\n";
  for (std::size_t i = 0; i < big / 2; ++i)
    emptyFaces += "0\n";
  std::string skipped = "ply\nformat ascii 1.0\nelement junk " + std::to_string(big / 4) +
    "\nproperty int a\nelement vertex 0\nproperty float x\nproperty float y\nproperty float z\n"
    "end_header\n";
  for (std::size_t i = 0; i < big / 4; ++i)
    skipped += "123\n";
  std::string stlLine = "solid " + std::string(big, 'n') + "\nendsolid\n";
  const std::pair<const char*, std::string*> cases[] = { { "comment.obj", &comment },
    { "emptyfaces.ply", &emptyFaces }, { "skipped.ply", &skipped }, { "name.stl", &stlLine } };
  TempDir dir;
  for (const auto& [name, bytes] : cases)
    for (const bool gz : { false, true })
    {
      const std::string path = dir.File(std::string(name) + (gz ? ".gz" : ""));
      if (gz)
        WriteGzip(path, *bytes);
      else
        WriteFile(path, *bytes);
      AbortAlways sink;
      try
      {
        ReadMesh(path, sink);
        ADD_FAILURE() << path << ": read to the end despite the abort";
      }
      catch (const ReadAbortedError& e)
      {
        EXPECT_NE(std::string(e.what()).find(path + ": "), std::string::npos) << e.what();
        EXPECT_NE(std::string(e.what()).find("read aborted"), std::string::npos) << e.what();
      }
      EXPECT_FALSE(sink.ended) << path;
      EXPECT_EQ(sink.asked, 3u) << path;
    }
}

TEST(IOAbort, PollsCostNothingPerByte)
{
  // One poll per buffer refill: a 6 MiB read asks a handful of times, not per line or byte.
  class Counting : public AbortAlways
  {
  public:
    bool AbortRequested() override
    {
      ++asked;
      return false;
    }
  };
  std::string obj;
  for (int i = 0; i < 200000; ++i)
    obj += "v " + std::to_string(i) + " 1 2\n# a comment line\n";
  TempDir dir;
  WriteFile(dir.File("m.obj"), obj);
  Counting sink;
  ReadMesh(dir.File("m.obj"), sink);
  EXPECT_TRUE(sink.ended);
  EXPECT_GE(sink.asked, obj.size() >> 20); // at least one per MiB
  EXPECT_LE(sink.asked, (obj.size() >> 20) + 20 + 200000 / (1 << 14) * 2);
}

// Issue 20 item 5: a FIFO (or /dev/stdin) opens without blocking, stops on an abort while no
// writer comes, and MeshInputFile copies it once (unlinked) so it can be read several times.
TEST(IOFifo, OpenWithoutWriterAbortsInsteadOfBlocking)
{
  TempDir dir;
  const std::string fifo = dir.File("in.obj");
  ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
  // Rescue for a reader that blocks in open(2) (the old behaviour): a writer comes after 5 s and
  // leaves at once, so the test fails instead of hanging.
  std::thread rescue([&] {
    std::this_thread::sleep_for(std::chrono::seconds(5));
    const int fd = ::open(fifo.c_str(), O_RDWR | O_NONBLOCK);
    if (fd >= 0)
      ::close(fd);
  });
  class AbortLater : public AbortAlways
  {
  public:
    std::chrono::steady_clock::time_point at = std::chrono::steady_clock::now() +
      std::chrono::milliseconds(300);
    bool AbortRequested() override { return std::chrono::steady_clock::now() >= at; }
  };
  AbortLater sink;
  const auto t0 = std::chrono::steady_clock::now();
  std::string error;
  bool aborted = false;
  try
  {
    ReadMesh(fifo, sink);
  }
  catch (const ReadAbortedError& e)
  {
    aborted = true;
    error = e.what();
  }
  catch (const MeshIOError& e)
  {
    error = e.what();
  }
  const double seconds =
    std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  rescue.join();
  EXPECT_TRUE(aborted) << error;
  EXPECT_LT(seconds, 2.0);
}

TEST(IOFifo, MeshInputFileCopiesAFifoOnceAndReplaysIt)
{
  TempDir dir, spool;
  std::string obj = "# fifo\n";
  for (int i = 0; i < 30000; ++i)
    obj += "v " + std::to_string(i % 97) + " " + std::to_string(i / 97) + " " +
      std::to_string(i % 13) + "\n";
  for (int i = 0; i + 2 < 30000; i += 3)
    obj += "f " + std::to_string(i + 1) + " " + std::to_string(i + 2) + " " +
      std::to_string(i + 3) + "\n";
  WriteFile(dir.File("ref.obj"), obj);
  WriteGzip(dir.File("ref.obj.gz"), obj);
  const CollectSink ref = ReadAll(dir.File("ref.obj"));
  for (const char* source : { "ref.obj", "ref.obj.gz" })
  {
    const std::string fifo = dir.File("fifo");
    std::filesystem::remove(fifo);
    ASSERT_EQ(::mkfifo(fifo.c_str(), 0600), 0);
    const std::string bytes = ReadFileBytes(dir.File(source));
    std::thread writer([&] {
      const int fd = ::open(fifo.c_str(), O_WRONLY);
      std::size_t off = 0;
      while (fd >= 0 && off < bytes.size())
      {
        const ssize_t w = ::write(fd, bytes.data() + off, std::min<std::size_t>(bytes.size() - off, 4096));
        if (w <= 0)
          break;
        off += std::size_t(w);
      }
      if (fd >= 0)
        ::close(fd);
    });
    {
      MeshInputFile input(fifo, spool.Path());
      ReadOptions verticesOnly;
      verticesOnly.verticesOnly = true;
      CollectSink first, second, third;
      input.Read(first, verticesOnly); // the first pass stops early; the rest is still copied
      writer.join();
      input.Read(second);
      input.Read(third);
      EXPECT_TRUE(input.Spooled());
      EXPECT_EQ(first.xyz, ref.xyz) << source;
      EXPECT_EQ(second.xyz, ref.xyz) << source;
      EXPECT_EQ(second.tris, ref.tris) << source;
      EXPECT_EQ(third.tris, ref.tris) << source;
      // The copy is unlinked from the start: nothing in the spool directory, even now.
      EXPECT_TRUE(std::filesystem::is_empty(spool.Path())) << source;
    }
  }
  // A regular file is read in place, never copied.
  MeshInputFile regular(dir.File("ref.obj"), spool.Path());
  CollectSink s;
  regular.Read(s);
  EXPECT_FALSE(regular.Spooled());
  EXPECT_EQ(s.tris, ref.tris);
}

} // namespace
} // namespace sipmss::io::test
