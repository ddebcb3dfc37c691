// Helpers for the IO tests: temporary directories, a collecting sink that checks the chunk
// protocol, a PLY builder for every encoding and scalar type, gzip.
#pragma once

#include "sipmss/io/MeshIO.h"
#include "sipmss/io/MeshIOInternal.h"

#include <gtest/gtest.h>
#include <zlib.h>

#include <algorithm>
#include <cstdint>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace sipmss::io::test
{

class TempDir
{
public:
  TempDir()
  {
    std::string tmpl = (std::filesystem::temp_directory_path() / "sipmss-io-XXXXXX").string();
    std::vector<char> buf(tmpl.begin(), tmpl.end());
    buf.push_back('\0');
    if (!mkdtemp(buf.data()))
      throw std::runtime_error("mkdtemp failed");
    path_ = buf.data();
  }
  ~TempDir()
  {
    std::error_code ec;
    std::filesystem::remove_all(path_, ec);
  }
  std::string File(const std::string& name) const { return path_ + "/" + name; }
  const std::string& Path() const { return path_; }

private:
  std::string path_;
};

inline void WriteFile(const std::string& path, const std::string& bytes)
{
  std::ofstream f(path, std::ios::binary | std::ios::trunc);
  f.write(bytes.data(), std::streamsize(bytes.size()));
  if (!f)
    throw std::runtime_error("cannot write " + path);
}

inline std::string ReadFileBytes(const std::string& path)
{
  std::ifstream f(path, std::ios::binary);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

inline void WriteGzip(const std::string& path, const std::string& bytes)
{
  gzFile gz = gzopen(path.c_str(), "wb6");
  if (!gz)
    throw std::runtime_error("gzopen failed");
  std::size_t off = 0;
  while (off < bytes.size())
  {
    const unsigned n = unsigned(std::min<std::size_t>(bytes.size() - off, 1 << 20));
    if (gzwrite(gz, bytes.data() + off, n) != int(n))
      throw std::runtime_error("gzwrite failed");
    off += n;
  }
  gzclose(gz);
}

// Collects everything a reader delivers and checks the chunk protocol as it goes.
class CollectSink : public MeshSink
{
public:
  MeshHeader header;
  ReadStats stats;
  bool begun = false, ended = false;
  std::vector<float> xyz, normals, texcoords, scalars;
  std::vector<std::uint8_t> rgba;
  std::vector<std::uint32_t> tris;
  std::size_t vertexCalls = 0, triangleCalls = 0;
  std::size_t maxVertexChunk = 0, maxTriangleChunk = 0;
  bool checkOrder = false; // each triangle only references vertices delivered before it
  std::size_t abortAfterCalls = 0; // AbortRequested true after this many sink calls (0 = never)

  std::uint64_t Vertices() const { return xyz.size() / 3; }
  std::uint64_t TriangleCount() const { return tris.size() / 3; }

  void Begin(const MeshHeader& h) override
  {
    EXPECT_FALSE(begun) << "Begin twice";
    begun = true;
    header = h;
  }
  void Vertices(const VertexChunk& c) override
  {
    EXPECT_TRUE(begun);
    EXPECT_EQ(c.first, Vertices()) << "vertex chunks must be consecutive";
    EXPECT_GT(c.count, 0u);
    ++vertexCalls;
    maxVertexChunk = std::max(maxVertexChunk, c.count);
    xyz.insert(xyz.end(), c.xyz, c.xyz + 3 * c.count);
    EXPECT_EQ(c.normals != nullptr, header.layout.normals);
    EXPECT_EQ(c.rgba != nullptr, header.layout.colors);
    EXPECT_EQ(c.texcoords != nullptr, header.layout.texcoords);
    EXPECT_EQ(c.scalars != nullptr, !header.layout.scalars.empty());
    if (c.normals)
      normals.insert(normals.end(), c.normals, c.normals + 3 * c.count);
    if (c.rgba)
      rgba.insert(rgba.end(), c.rgba, c.rgba + 4 * c.count);
    if (c.texcoords)
      texcoords.insert(texcoords.end(), c.texcoords, c.texcoords + 2 * c.count);
    if (c.scalars)
      scalars.insert(scalars.end(), c.scalars, c.scalars + header.layout.scalars.size() * c.count);
  }
  void Triangles(const std::uint32_t* idx, std::size_t count) override
  {
    EXPECT_TRUE(begun);
    EXPECT_GT(count, 0u);
    ++triangleCalls;
    maxTriangleChunk = std::max(maxTriangleChunk, count);
    for (std::size_t i = 0; i < 3 * count; ++i)
    {
      if (header.vertexCount)
      {
        EXPECT_LT(idx[i], header.vertexCount);
      }
      if (checkOrder)
      {
        EXPECT_LT(idx[i], Vertices()) << "triangle delivered before its vertices";
      }
    }
    tris.insert(tris.end(), idx, idx + 3 * count);
    lastTriangles = count;
  }
  void TriangleFlags(const std::uint8_t* f, std::size_t count) override
  {
    EXPECT_EQ(count, lastTriangles) << "flags for another number of triangles";
    EXPECT_EQ(flags.size() + count, TriangleCount()) << "flags not right after their triangles";
    flags.insert(flags.end(), f, f + count);
  }
  std::vector<std::uint8_t> flags; // TriangleFlags, one per triangle
  std::size_t lastTriangles = 0;
  void End(const ReadStats& s) override
  {
    EXPECT_TRUE(begun);
    EXPECT_FALSE(ended);
    ended = true;
    stats = s;
    EXPECT_EQ(s.vertices, Vertices());
    EXPECT_EQ(s.triangles, TriangleCount());
    for (std::uint32_t i : tris)
      EXPECT_LT(i, Vertices());
  }
  bool AbortRequested() override
  {
    return abortAfterCalls && vertexCalls + triangleCalls >= abortAfterCalls;
  }
};

inline CollectSink ReadAll(const std::string& path, const ReadOptions& options = {})
{
  CollectSink s;
  ReadMesh(path, s, options);
  EXPECT_TRUE(s.ended);
  return s;
}

// The MeshIOError message of reading path (empty when it reads fine).
inline std::string ReadError(const std::string& path, const ReadOptions& options = {})
{
  try
  {
    CollectSink s;
    ReadMesh(path, s, options);
  }
  catch (const MeshIOError& e)
  {
    return e.what();
  }
  return {};
}

// ---------------------------------------------------------------------------------------------
enum class Enc
{
  Ascii,
  LE,
  BE
};

inline const char* EncName(Enc e)
{
  return e == Enc::Ascii ? "ascii" : e == Enc::LE ? "binary_little_endian" : "binary_big_endian";
}

// Builds a PLY file value by value in any encoding.
class PlyBuilder
{
public:
  explicit PlyBuilder(Enc enc, bool crlf = false)
    : enc_(enc)
    , nl_(crlf ? "\r\n" : "\n")
  {
    header_ = "ply" + nl_ + "format " + EncName(enc) + " 1.0" + nl_;
  }
  PlyBuilder& H(const std::string& line)
  {
    header_ += line + nl_;
    return *this;
  }
  // One value of the PLY type `type` (any name or alias).
  PlyBuilder& V(const std::string& type, double v)
  {
    const std::string t = Canon(type);
    if (enc_ == Enc::Ascii)
    {
      if (!atLineStart_)
        body_ += ' ';
      char buf[64];
      if (t == "float32" || t == "float64")
        std::snprintf(buf, sizeof buf, "%.17g", v);
      else
        std::snprintf(buf, sizeof buf, "%lld", static_cast<long long>(v));
      body_ += buf;
      atLineStart_ = false;
      return *this;
    }
    unsigned char b[8];
    std::size_t n = 0;
    auto put = [&](const void* src, std::size_t sz) {
      std::memcpy(b, src, sz);
      n = sz;
    };
    if (t == "int8") { const std::int8_t x = std::int8_t(v); put(&x, 1); }
    else if (t == "uint8") { const std::uint8_t x = std::uint8_t(v); put(&x, 1); }
    else if (t == "int16") { const std::int16_t x = std::int16_t(v); put(&x, 2); }
    else if (t == "uint16") { const std::uint16_t x = std::uint16_t(v); put(&x, 2); }
    else if (t == "int32") { const std::int32_t x = std::int32_t(v); put(&x, 4); }
    else if (t == "uint32") { const std::uint32_t x = std::uint32_t(std::int64_t(v)); put(&x, 4); }
    else if (t == "float32") { const float x = float(v); put(&x, 4); }
    else if (t == "float64") { put(&v, 8); }
    else throw std::runtime_error("bad type " + type);
    const bool hostLE = [] { const std::uint16_t one = 1; unsigned char c; std::memcpy(&c, &one, 1); return c == 1; }();
    if ((enc_ == Enc::LE) != hostLE)
      std::reverse(b, b + n);
    body_.append(reinterpret_cast<const char*>(b), n);
    return *this;
  }
  PlyBuilder& Raw(const std::string& bytes)
  {
    body_ += bytes;
    return *this;
  }
  PlyBuilder& EndRecord()
  {
    if (enc_ == Enc::Ascii)
    {
      body_ += nl_;
      atLineStart_ = true;
    }
    return *this;
  }
  std::string Bytes() const { return header_ + "end_header" + nl_ + body_; }
  std::string HeaderOnly() const { return header_; }

  static std::string Canon(const std::string& t)
  {
    if (t == "char" || t == "int8") return "int8";
    if (t == "uchar" || t == "uint8") return "uint8";
    if (t == "short" || t == "int16") return "int16";
    if (t == "ushort" || t == "uint16") return "uint16";
    if (t == "int" || t == "int32") return "int32";
    if (t == "uint" || t == "uint32") return "uint32";
    if (t == "float" || t == "float32") return "float32";
    if (t == "double" || t == "float64") return "float64";
    return t;
  }

private:
  Enc enc_;
  std::string nl_;
  std::string header_;
  std::string body_;
  bool atLineStart_ = true;
};

inline std::string DataDir()
{
#ifdef SIPMSS_SHARED_DATA_DIR
  return SIPMSS_SHARED_DATA_DIR;
#else
  return "../shared/data";
#endif
}

} // namespace sipmss::io::test
