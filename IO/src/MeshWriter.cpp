// Streaming mesh writers: PLY (binary little-endian or ASCII), STL (binary or ASCII), OBJ.
// Buffered 1 MiB writes with write(2), gzip-compressed (zlib's deflate, level 6) when the path
// ends in .gz; every I/O failure throws MeshIOError(path: strerror).
#include "MeshIODetail.h"

#include <algorithm>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstring>

#include <fcntl.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <unistd.h>

#include <zlib.h>

namespace sipmss::io
{
namespace detail
{
namespace
{
std::atomic<std::size_t> gStlMemoryLimit{ std::size_t(64) << 20 };
} // namespace

std::size_t SetStlWriterMemoryLimit(std::size_t bytes)
{
  return gStlMemoryLimit.exchange(bytes);
}
} // namespace detail

namespace
{

using detail::HostIsLittleEndian;

[[noreturn]] void WriteFail(const std::string& path, const std::string& what)
{
  throw MeshIOError(path + ": " + what);
}

[[noreturn]] void ErrnoFail(const std::string& path, const char* what, int err)
{
  WriteFail(path, std::string(what) + ": " + std::strerror(err));
}

std::string LowerExtension(const std::string& path)
{
  const std::size_t slash = path.find_last_of('/');
  const std::size_t dot = path.find_last_of('.');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash))
    return {};
  std::string ext = path.substr(dot);
  for (char& c : ext)
    if (c >= 'A' && c <= 'Z')
      c = char(c - 'A' + 'a');
  return ext;
}

bool IsGzipPath(const std::string& path)
{
  return LowerExtension(path) == ".gz";
}

// The mesh format's extension: the last one, or the one before ".gz".
std::string MeshExtension(const std::string& path)
{
  return IsGzipPath(path) ? LowerExtension(path.substr(0, path.size() - 3)) : LowerExtension(path);
}

// Buffered output to a file descriptor, optionally through a gzip stream.
class FileOut
{
public:
  FileOut() = default;
  FileOut(const FileOut&) = delete;
  FileOut& operator=(const FileOut&) = delete;
  ~FileOut()
  {
    if (gzip_)
      deflateEnd(&z_);
    if (fd_ >= 0)
      ::close(fd_);
  }

  void Open(const std::string& path, bool gzip = false)
  {
    path_ = path;
    fd_ = ::open(path.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0666);
    if (fd_ < 0)
      ErrnoFail(path_, "cannot be opened for writing", errno);
    buf_.resize(detail::kDefaultBufferBytes);
    if (gzip)
    {
      z_ = z_stream{};
      // windowBits 15 + 16: a gzip header and trailer, as gzip(1) writes and the readers read
      if (deflateInit2(&z_, 6, Z_DEFLATED, 15 + 16, 8, Z_DEFAULT_STRATEGY) != Z_OK)
        WriteFail(path_, "cannot start gzip compression");
      gzip_ = true;
      zbuf_.resize(detail::kDefaultBufferBytes);
    }
  }
  void Adopt(int fd, const std::string& path)
  {
    path_ = path;
    fd_ = fd;
    buf_.resize(detail::kDefaultBufferBytes);
  }
  int Fd() const { return fd_; }

  // Room for n (<= 64 KiB) bytes at the returned pointer; Commit(k) after writing k <= n.
  char* Reserve(std::size_t n)
  {
    if (buf_.size() - len_ < n)
      Flush();
    return buf_.data() + len_;
  }
  void Commit(std::size_t n) { len_ += n; }
  void Put(const void* d, std::size_t n)
  {
    if (buf_.size() - len_ < n)
    {
      Flush();
      if (n >= buf_.size())
      {
        WriteAll(static_cast<const char*>(d), n);
        return;
      }
    }
    std::memcpy(buf_.data() + len_, d, n);
    len_ += n;
  }
  void Put(std::string_view s) { Put(s.data(), s.size()); }
  void Flush()
  {
    WriteAll(buf_.data(), len_);
    len_ = 0;
  }
  void Close()
  {
    Flush();
    if (gzip_)
    {
      Deflate(nullptr, 0, Z_FINISH);
      deflateEnd(&z_);
      gzip_ = false;
    }
    const int fd = fd_;
    fd_ = -1;
    if (fd >= 0 && ::close(fd) != 0)
      ErrnoFail(path_, "write failed", errno);
  }

private:
  void WriteAll(const char* d, std::size_t n)
  {
    if (fd_ < 0 && n)
      WriteFail(path_, "write after close");
    if (gzip_)
    {
      if (n)
        Deflate(d, n, Z_NO_FLUSH);
      return;
    }
    WriteRaw(d, n);
  }
  // Compresses n bytes (flush = Z_FINISH: and ends the stream) and writes what deflate produced.
  void Deflate(const char* d, std::size_t n, int flush)
  {
    while (true)
    {
      const uInt in = uInt(std::min<std::size_t>(n, std::size_t(1) << 30));
      z_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(d));
      z_.avail_in = in;
      do
      {
        z_.next_out = reinterpret_cast<Bytef*>(zbuf_.data());
        z_.avail_out = uInt(zbuf_.size());
        const int rc = deflate(&z_, n > in ? Z_NO_FLUSH : flush);
        if (rc == Z_STREAM_ERROR)
          WriteFail(path_, "gzip compression failed");
        WriteRaw(zbuf_.data(), zbuf_.size() - z_.avail_out);
      } while (z_.avail_out == 0);
      d += in;
      n -= in;
      if (n == 0)
        return;
    }
  }
  void WriteRaw(const char* d, std::size_t n)
  {
    while (n)
    {
      const ssize_t r = ::write(fd_, d, std::min<std::size_t>(n, std::size_t(1) << 30));
      if (r < 0)
      {
        if (errno == EINTR)
          continue;
        ErrnoFail(path_, "write failed", errno);
      }
      if (r == 0)
        ErrnoFail(path_, "write failed", EIO);
      d += r;
      n -= std::size_t(r);
    }
  }

  std::string path_;
  int fd_ = -1;
  std::vector<char> buf_;
  std::size_t len_ = 0;
  bool gzip_ = false;
  z_stream z_{};
  std::vector<char> zbuf_;
};

inline void StoreLE32(char* p, const void* v)
{
  std::uint32_t u;
  std::memcpy(&u, v, 4);
  if (!HostIsLittleEndian())
    u = __builtin_bswap32(u);
  std::memcpy(p, &u, 4);
}

inline char* PutFloat(char* p, float f)
{
  return std::to_chars(p, p + 32, f).ptr;
}
inline char* PutUInt(char* p, std::uint64_t v)
{
  return std::to_chars(p, p + 24, v).ptr;
}

class WriterBase : public MeshWriter
{
public:
  explicit WriterBase(const std::string& path)
    : path_(path)
  {
    out_.Open(path, IsGzipPath(path));
  }

  void Begin(std::uint64_t vertexCount, std::uint64_t triangleCount, const VertexLayout& layout) override
  {
    if (begun_)
      WriteFail(path_, "Begin called twice");
    if (vertexCount > detail::kMaxVertices)
      WriteFail(path_, "vertex count " + std::to_string(vertexCount) + " exceeds 32-bit indices");
    begun_ = true;
    nv_ = vertexCount;
    nt_ = triangleCount;
    layout_ = layout;
    DoBegin();
  }

  void Vertices(const VertexChunk& c) override
  {
    if (!begun_ || ended_)
      WriteFail(path_, "Vertices called outside Begin/End");
    if (c.count == 0)
      return;
    if (c.first != wv_)
      WriteFail(path_, "vertex chunk starts at " + std::to_string(c.first) + ", expected " +
          std::to_string(wv_));
    if (c.count > nv_ - wv_)
      WriteFail(path_, "more vertices than the " + std::to_string(nv_) + " declared in Begin");
    if (!c.xyz || (layout_.normals && !c.normals) || (layout_.colors && !c.rgba) ||
      (layout_.texcoords && !c.texcoords) || (!layout_.scalars.empty() && !c.scalars))
      WriteFail(path_, "vertex chunk lacks an attribute array the layout declares");
    DoVertices(c);
    wv_ += c.count;
  }

  void Triangles(const std::uint32_t* idx, std::size_t n) override
  {
    if (!begun_ || ended_)
      WriteFail(path_, "Triangles called outside Begin/End");
    if (n == 0)
      return;
    if (n > nt_ - wt_)
      WriteFail(path_, "more triangles than the " + std::to_string(nt_) + " declared in Begin");
    const std::uint64_t limit = TriangleIndexLimit();
    for (std::size_t i = 0; i < 3 * n; ++i)
      if (idx[i] >= limit)
        WriteFail(path_, "triangle " + std::to_string(wt_ + i / 3) + " references vertex " +
            std::to_string(idx[i]) + (limit < nv_ ? ", not written yet" : ", out of range") + " (" +
            std::to_string(limit) + " vertices)");
    DoTriangles(idx, n);
    wt_ += n;
  }

  void End() override
  {
    if (!begun_ || ended_)
      WriteFail(path_, "End called without Begin or twice");
    if (wv_ != nv_)
      WriteFail(path_, "wrote " + std::to_string(wv_) + " vertices, but Begin declared " + std::to_string(nv_));
    if (wt_ != nt_)
      WriteFail(path_, "wrote " + std::to_string(wt_) + " triangles, but Begin declared " + std::to_string(nt_));
    ended_ = true;
    DoEnd();
    out_.Close();
  }

protected:
  virtual void DoBegin() = 0;
  virtual void DoVertices(const VertexChunk& c) = 0;
  virtual void DoTriangles(const std::uint32_t* idx, std::size_t n) = 0;
  virtual void DoEnd() {}
  // Indices must be below this (PLY: all vertices first; OBJ/STL: those written so far).
  virtual std::uint64_t TriangleIndexLimit() const { return wv_; }

  std::string path_;
  FileOut out_;
  bool begun_ = false, ended_ = false;
  std::uint64_t nv_ = 0, nt_ = 0, wv_ = 0, wt_ = 0;
  VertexLayout layout_;
};

// ---------------------------------------------------------------------------------------------
class PlyWriter final : public WriterBase
{
public:
  PlyWriter(const std::string& path, bool ascii)
    : WriterBase(path)
    , ascii_(ascii)
  {
  }

private:
  void DoBegin() override
  {
    std::string h = "ply\nformat ";
    h += ascii_ ? "ascii 1.0\n" : "binary_little_endian 1.0\n";
    h += "comment written by SIPMSS\n";
    h += "element vertex " + std::to_string(nv_) + "\n";
    h += "property float x\nproperty float y\nproperty float z\n";
    if (layout_.normals)
      h += "property float nx\nproperty float ny\nproperty float nz\n";
    if (layout_.colors)
      h += "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n";
    if (layout_.texcoords)
      h += "property float u\nproperty float v\n";
    std::vector<std::string> names = { "x", "y", "z" };
    if (layout_.normals)
      names.insert(names.end(), { "nx", "ny", "nz" });
    if (layout_.colors)
      names.insert(names.end(), { "red", "green", "blue", "alpha" });
    if (layout_.texcoords)
      names.insert(names.end(), { "u", "v" });
    for (const std::string& s : layout_.scalars)
    {
      if (s.empty() || s.find_first_of(" \t\r\n") != std::string::npos ||
        std::find(names.begin(), names.end(), s) != names.end())
        WriteFail(path_, "scalar name '" + s + "' cannot be a PLY property name (empty, blanks or a duplicate)");
      names.push_back(s);
      h += "property float " + s + "\n";
    }
    h += "element face " + std::to_string(nt_) + "\n";
    h += "property list uchar int vertex_indices\nend_header\n";
    out_.Put(h);
    record_ = 12 + (layout_.normals ? 12 : 0) + (layout_.colors ? 4 : 0) + (layout_.texcoords ? 8 : 0) +
      4 * layout_.scalars.size();
  }

  void DoVertices(const VertexChunk& c) override
  {
    const std::size_t ns = layout_.scalars.size();
    if (!ascii_)
    {
      if (record_ == 12 && HostIsLittleEndian())
      {
        out_.Put(c.xyz, 12 * c.count);
        return;
      }
      for (std::size_t i = 0; i < c.count; ++i)
      {
        if (record_ > (std::size_t(1) << 16))
        {
          // very many scalars: property by property
          char tmp[4];
          for (int k = 0; k < 3; ++k)
            StoreLE32(tmp, c.xyz + 3 * i + k), out_.Put(tmp, 4);
          if (layout_.normals)
            for (int k = 0; k < 3; ++k)
              StoreLE32(tmp, c.normals + 3 * i + k), out_.Put(tmp, 4);
          if (layout_.colors)
            out_.Put(c.rgba + 4 * i, 4);
          if (layout_.texcoords)
            for (int k = 0; k < 2; ++k)
              StoreLE32(tmp, c.texcoords + 2 * i + k), out_.Put(tmp, 4);
          for (std::size_t k = 0; k < ns; ++k)
            StoreLE32(tmp, c.scalars + ns * i + k), out_.Put(tmp, 4);
          continue;
        }
        char* p = out_.Reserve(record_);
        char* q = p;
        for (int k = 0; k < 3; ++k, q += 4)
          StoreLE32(q, c.xyz + 3 * i + k);
        if (layout_.normals)
          for (int k = 0; k < 3; ++k, q += 4)
            StoreLE32(q, c.normals + 3 * i + k);
        if (layout_.colors)
        {
          std::memcpy(q, c.rgba + 4 * i, 4);
          q += 4;
        }
        if (layout_.texcoords)
          for (int k = 0; k < 2; ++k, q += 4)
            StoreLE32(q, c.texcoords + 2 * i + k);
        for (std::size_t k = 0; k < ns; ++k, q += 4)
          StoreLE32(q, c.scalars + ns * i + k);
        out_.Commit(record_);
      }
      return;
    }
    for (std::size_t i = 0; i < c.count; ++i)
    {
      char* p = out_.Reserve(200);
      char* q = p;
      for (int k = 0; k < 3; ++k)
      {
        if (k)
          *q++ = ' ';
        q = PutFloat(q, c.xyz[3 * i + k]);
      }
      if (layout_.normals)
        for (int k = 0; k < 3; ++k)
          *q++ = ' ', q = PutFloat(q, c.normals[3 * i + k]);
      if (layout_.colors)
        for (int k = 0; k < 4; ++k)
          *q++ = ' ', q = PutUInt(q, c.rgba[4 * i + k]);
      if (layout_.texcoords)
        for (int k = 0; k < 2; ++k)
          *q++ = ' ', q = PutFloat(q, c.texcoords[2 * i + k]);
      out_.Commit(std::size_t(q - p));
      for (std::size_t k = 0; k < ns; ++k)
      {
        char* r = out_.Reserve(40);
        char* s = r;
        *s++ = ' ';
        s = PutFloat(s, c.scalars[ns * i + k]);
        out_.Commit(std::size_t(s - r));
      }
      out_.Put("\n", 1);
    }
  }

  std::uint64_t TriangleIndexLimit() const override
  {
    if (wv_ != nv_)
      WriteFail(path_, "triangles before all vertices (a PLY file stores the vertices first)");
    return nv_;
  }

  void DoTriangles(const std::uint32_t* idx, std::size_t n) override
  {
    for (std::size_t t = 0; t < n; ++t)
    {
      const std::uint32_t* v = idx + 3 * t;
      if (!ascii_)
      {
        char* p = out_.Reserve(13);
        p[0] = 3;
        StoreLE32(p + 1, v);
        StoreLE32(p + 5, v + 1);
        StoreLE32(p + 9, v + 2);
        out_.Commit(13);
      }
      else
      {
        char* p = out_.Reserve(48);
        char* q = p;
        *q++ = '3';
        for (int k = 0; k < 3; ++k)
          *q++ = ' ', q = PutUInt(q, v[k]);
        *q++ = '\n';
        out_.Commit(std::size_t(q - p));
      }
    }
  }

  bool ascii_;
  std::size_t record_ = 12;
};

// ---------------------------------------------------------------------------------------------
class StlWriter final : public WriterBase
{
public:
  StlWriter(const std::string& path, bool ascii)
    : WriterBase(path)
    , ascii_(ascii)
  {
  }
  ~StlWriter() override { CloseSpool(); }

private:
  void DoBegin() override
  {
    if (!ascii_)
    {
      if (nt_ > 0xFFFFFFFFull)
        WriteFail(path_, "binary STL holds at most 4294967295 triangles, not " + std::to_string(nt_));
      char h[84];
      std::memset(h, ' ', 80);
      const char title[] = "binary STL written by SIPMSS";
      std::memcpy(h, title, sizeof title - 1);
      const std::uint32_t n = std::uint32_t(nt_);
      StoreLE32(h + 80, &n);
      out_.Put(h, 84);
    }
    else
      out_.Put("solid sipmss\n");
    if (nv_ * 12 <= detail::gStlMemoryLimit.load())
      positions_.reserve(std::size_t(3 * nv_));
    else
      OpenSpool();
  }

  void OpenSpool()
  {
    std::string tmpl = path_ + ".spool-XXXXXX";
    std::vector<char> name(tmpl.begin(), tmpl.end());
    name.push_back('\0');
    const int fd = ::mkstemp(name.data());
    if (fd < 0)
      ErrnoFail(path_, "cannot create the vertex spool file next to it", errno);
    // Unlinked at once: the spool lives only as long as the descriptor, whatever happens.
    ::unlink(name.data());
    spool_.Adopt(fd, path_ + " (vertex spool)");
    spooling_ = true;
  }

  void CloseSpool()
  {
    if (map_)
      ::munmap(map_, mapBytes_);
    map_ = nullptr;
  }

  void DoVertices(const VertexChunk& c) override
  {
    if (!spooling_)
      positions_.insert(positions_.end(), c.xyz, c.xyz + 3 * c.count);
    else
      spool_.Put(c.xyz, 12 * c.count);
  }

  void Position(std::uint32_t i, float* v)
  {
    if (!spooling_)
    {
      std::memcpy(v, positions_.data() + 3 * std::size_t(i), 12);
      return;
    }
    if (map_)
    {
      std::memcpy(v, static_cast<const char*>(map_) + 12 * std::size_t(i), 12);
      return;
    }
    const off_t at = off_t(12) * off_t(i);
    std::size_t got = 0;
    while (got < 12)
    {
      const ssize_t r = ::pread(spool_.Fd(), reinterpret_cast<char*>(v) + got, 12 - got, at + off_t(got));
      if (r < 0 && errno == EINTR)
        continue;
      if (r <= 0)
        ErrnoFail(path_, "reading the vertex spool failed", r < 0 ? errno : EIO);
      got += std::size_t(r);
    }
  }

  void PrepareSpool()
  {
    if (!spooling_ || map_)
      return;
    spool_.Flush();
    if (wv_ == nv_ && nv_ > 0)
    {
      mapBytes_ = std::size_t(12 * nv_);
      void* m = ::mmap(nullptr, mapBytes_, PROT_READ, MAP_SHARED, spool_.Fd(), 0);
      if (m != MAP_FAILED)
        map_ = m; // else pread per vertex
    }
  }

  void DoTriangles(const std::uint32_t* idx, std::size_t n) override
  {
    PrepareSpool();
    for (std::size_t t = 0; t < n; ++t)
    {
      float v[9];
      for (int k = 0; k < 3; ++k)
        Position(idx[3 * t + k], v + 3 * k);
      const float ux = v[3] - v[0], uy = v[4] - v[1], uz = v[5] - v[2];
      const float wx = v[6] - v[0], wy = v[7] - v[1], wz = v[8] - v[2];
      float nrm[3] = { uy * wz - uz * wy, uz * wx - ux * wz, ux * wy - uy * wx };
      const float len = std::sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2]);
      if (len > 0 && std::isfinite(len))
        for (float& x : nrm)
          x /= len;
      else
        nrm[0] = nrm[1] = nrm[2] = 0;
      if (!ascii_)
      {
        char* p = out_.Reserve(50);
        for (int k = 0; k < 3; ++k)
          StoreLE32(p + 4 * k, nrm + k);
        for (int k = 0; k < 9; ++k)
          StoreLE32(p + 12 + 4 * k, v + k);
        p[48] = p[49] = 0;
        out_.Commit(50);
      }
      else
      {
        char* p = out_.Reserve(512);
        char* q = p;
        auto put = [&q](const char* s) {
          const std::size_t l = std::strlen(s);
          std::memcpy(q, s, l);
          q += l;
        };
        put("facet normal ");
        for (int k = 0; k < 3; ++k)
          q = PutFloat(q, nrm[k]), *q++ = k < 2 ? ' ' : '\n';
        put("  outer loop\n");
        for (int c = 0; c < 3; ++c)
        {
          put("    vertex ");
          for (int k = 0; k < 3; ++k)
            q = PutFloat(q, v[3 * c + k]), *q++ = k < 2 ? ' ' : '\n';
        }
        put("  endloop\nendfacet\n");
        out_.Commit(std::size_t(q - p));
      }
    }
  }

  void DoEnd() override
  {
    if (ascii_)
      out_.Put("endsolid sipmss\n");
    CloseSpool();
    if (spooling_)
    {
      spool_.Close(); // the file was unlinked at creation
      spooling_ = false;
    }
    std::vector<float>().swap(positions_);
  }

  bool ascii_;
  std::vector<float> positions_;
  bool spooling_ = false;
  FileOut spool_;
  void* map_ = nullptr;
  std::size_t mapBytes_ = 0;
};

// ---------------------------------------------------------------------------------------------
class ObjWriter final : public WriterBase
{
public:
  explicit ObjWriter(const std::string& path)
    : WriterBase(path)
  {
  }

private:
  void DoBegin() override
  {
    out_.Put("# written by SIPMSS: " + std::to_string(nv_) + " vertices, " + std::to_string(nt_) +
      " triangles\n");
  }
  void DoVertices(const VertexChunk& c) override
  {
    for (std::size_t i = 0; i < c.count; ++i)
    {
      char* p = out_.Reserve(120);
      char* q = p;
      *q++ = 'v';
      for (int k = 0; k < 3; ++k)
        *q++ = ' ', q = PutFloat(q, c.xyz[3 * i + k]);
      *q++ = '\n';
      out_.Commit(std::size_t(q - p));
    }
  }
  void DoTriangles(const std::uint32_t* idx, std::size_t n) override
  {
    for (std::size_t t = 0; t < n; ++t)
    {
      char* p = out_.Reserve(80);
      char* q = p;
      *q++ = 'f';
      for (int k = 0; k < 3; ++k)
        *q++ = ' ', q = PutUInt(q, std::uint64_t(idx[3 * t + k]) + 1);
      *q++ = '\n';
      out_.Commit(std::size_t(q - p));
    }
  }
};


} // namespace

void MeshWriter::CheckExtension(const std::string& path, const std::string& shownAs)
{
  const std::string ext = MeshExtension(path);
  if (ext != ".ply" && ext != ".stl" && ext != ".obj")
    throw MeshIOError((shownAs.empty() ? path : shownAs) +
      (ext.empty() ? ": no mesh file extension" : ": unknown mesh file extension '" + ext + "'") +
      " (expected .ply, .stl or .obj, each optionally followed by .gz)");
}

std::unique_ptr<MeshWriter> MeshWriter::Create(const std::string& path, bool ascii)
{
  CheckExtension(path);
  const std::string ext = MeshExtension(path);
  if (ext == ".ply")
    return std::make_unique<PlyWriter>(path, ascii);
  if (ext == ".stl")
    return std::make_unique<StlWriter>(path, ascii);
  return std::make_unique<ObjWriter>(path);
}

} // namespace sipmss::io
