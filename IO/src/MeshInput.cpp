// Input plumbing for the mesh readers: byte sources (read(2), gzread, memory, inflate from
// memory), the bounded input window, format detection, ReadMesh/ReadHeader/DetectFormat.
#include "MeshIODetail.h"

#include <zlib.h>

#include <algorithm>
#include <cerrno>
#include <climits>
#include <cstring>

#include <cstdlib>

#include <fcntl.h>
#include <poll.h>
#include <sys/stat.h>
#include <unistd.h>

namespace sipmss::io
{

const char* ToString(Format f)
{
  switch (f)
  {
    case Format::PlyAscii: return "PLY (ASCII)";
    case Format::PlyBinaryLE: return "PLY (binary little-endian)";
    case Format::PlyBinaryBE: return "PLY (binary big-endian)";
    case Format::StlAscii: return "STL (ASCII)";
    case Format::StlBinary: return "STL (binary)";
    case Format::Obj: return "OBJ";
    case Format::Unknown: break;
  }
  return "unknown";
}

namespace detail
{

void Fail(const std::string& path, std::string_view element, const std::string& what,
  const char* unit, std::uint64_t where)
{
  std::string m;
  m.reserve(path.size() + element.size() + what.size() + 32);
  m += path;
  m += ": ";
  m += element;
  m += ' ';
  m += what;
  m += ", at ";
  m += unit;
  m += ' ';
  m += std::to_string(where);
  throw MeshIOError(m);
}

namespace
{

// ---------------------------------------------------------------------------------------------
class FdSource final : public Source
{
public:
  explicit FdSource(int fd)
    : fd_(fd)
  {
  }
  ~FdSource() override { ::close(fd_); }
  long long Read(char* dst, std::size_t n) override
  {
    for (;;)
    {
      if (!regular)
      {
        // A FIFO, a terminal, a device: wait for data in poll(2), 0.1 s at a time, so an abort
        // is seen even when nothing comes (a writer that never writes, or never opens).
        pollfd pfd{ fd_, POLLIN, 0 };
        const int pr = ::poll(&pfd, 1, 100);
        if (pr < 0 && errno != EINTR)
        {
          err_ = errno;
          return -1;
        }
        if (pr <= 0)
        {
          if (AbortRequested())
            return kReadAborted;
          continue;
        }
      }
      const ssize_t r = ::read(fd_, dst, std::min<std::size_t>(n, std::size_t(1) << 30));
      if (r >= 0)
        return r;
      if (errno == EINTR)
        continue;
      if (errno == EAGAIN || errno == EWOULDBLOCK)
        continue; // non-blocking descriptor with nothing to read yet: poll again
      err_ = errno;
      return -1;
    }
  }
  std::string ErrorText() const override { return std::string("read failed: ") + std::strerror(err_); }

private:
  int fd_;
  int err_ = 0;
};

class GzFileSource final : public Source
{
public:
  explicit GzFileSource(gzFile gz)
    : gz_(gz)
  {
    compressed = true;
  }
  ~GzFileSource() override { gzclose(gz_); }
  long long Read(char* dst, std::size_t n) override
  {
    const int r = gzread(gz_, dst, unsigned(std::min<std::size_t>(n, std::size_t(1) << 30)));
    if (r < 0)
      return -1;
    if (r == 0)
    {
      // gzread reports a truncated stream ("unexpected end of file") as 0 bytes plus an error.
      int errnum = Z_OK;
      gzerror(gz_, &errnum);
      if (errnum != Z_OK)
        return -1;
    }
    return r;
  }
  std::string ErrorText() const override
  {
    int errnum = Z_OK;
    const char* msg = gzerror(gz_, &errnum);
    if (errnum == Z_ERRNO)
      return std::string("read failed: ") + std::strerror(errno);
    std::string m = msg ? msg : "unknown error";
    if (m.rfind("<fd:", 0) == 0 && m.find(": ") != std::string::npos)
      m = m.substr(m.find(": ") + 2); // gzdopen names the stream "<fd:N>"
    return "gzip data is corrupt (zlib: " + m + ")";
  }

private:
  gzFile gz_;
};

class MemorySource final : public Source
{
public:
  MemorySource(const char* data, std::size_t n)
    : data_(data)
    , left_(n)
  {
    sizeKnown = true;
    size = n;
  }
  long long Read(char* dst, std::size_t n) override
  {
    n = std::min(n, left_);
    if (n)
      std::memcpy(dst, data_, n);
    data_ += n;
    left_ -= n;
    return static_cast<long long>(n);
  }
  std::string ErrorText() const override { return "read failed"; }

private:
  const char* data_;
  std::size_t left_;
};

// gzip members in memory, inflated with zlib (the memory twin of gzread, for tests and fuzzers).
class MemoryGzSource final : public Source
{
public:
  MemoryGzSource(const char* data, std::size_t n)
  {
    compressed = true;
    std::memset(&z_, 0, sizeof z_);
    z_.next_in = reinterpret_cast<Bytef*>(const_cast<char*>(data));
    z_.avail_in = static_cast<uInt>(std::min<std::size_t>(n, UINT_MAX));
    if (inflateInit2(&z_, 15 + 16) != Z_OK)
      error_ = "inflateInit2 failed";
    else
      init_ = true;
  }
  ~MemoryGzSource() override
  {
    if (init_)
      inflateEnd(&z_);
  }
  long long Read(char* dst, std::size_t n) override
  {
    if (!error_.empty())
      return -1;
    if (done_)
      return 0;
    z_.next_out = reinterpret_cast<Bytef*>(dst);
    z_.avail_out = static_cast<uInt>(std::min<std::size_t>(n, std::size_t(1) << 30));
    const uInt before = z_.avail_out;
    while (z_.avail_out == before)
    {
      const int r = inflate(&z_, Z_NO_FLUSH);
      if (r == Z_STREAM_END)
      {
        // Another member follows? (like gzread, anything else after a member is ignored)
        if (z_.avail_in >= 2 && z_.next_in[0] == 0x1f && z_.next_in[1] == 0x8b)
        {
          inflateReset(&z_);
          continue;
        }
        done_ = true;
        break;
      }
      if (r == Z_OK)
        continue;
      if (r == Z_BUF_ERROR && z_.avail_in == 0)
        error_ = "unexpected end of file";
      else
        error_ = z_.msg ? z_.msg : "error " + std::to_string(r);
      if (z_.avail_out != before)
        break; // deliver what came; the error is reported on the next call
      return -1;
    }
    return static_cast<long long>(before - z_.avail_out);
  }
  std::string ErrorText() const override { return "gzip data is corrupt (zlib: " + error_ + ")"; }

private:
  z_stream z_;
  bool init_ = false;
  bool done_ = false;
  std::string error_;
};

[[noreturn]] void FailOpen(const std::string& path, const std::string& what)
{
  Fail(path, "file", what, "byte", 0);
}

std::string SpoolFailure(const std::string& dir, int err)
{
  return "cannot be copied (a pipe or device can be read only once) to a temporary file in " +
    dir + ": " + std::strerror(err);
}

// Reads a non-regular input and appends every byte it delivers to the spool file; a failed
// write (a full disk) is an error naming the input and the directory.
class TeeSource final : public Source
{
public:
  TeeSource(std::unique_ptr<Source> inner, int spool, std::string dir, std::string path)
    : inner_(std::move(inner))
    , spool_(spool)
    , dir_(std::move(dir))
    , path_(std::move(path))
  {
    regular = false;
  }
  long long Read(char* dst, std::size_t n) override
  {
    inner_->abortSink = abortSink;
    const long long r = inner_->Read(dst, n);
    for (long long done = 0; r > 0 && done < r;)
    {
      const ssize_t w = ::write(spool_, dst + done, std::size_t(r - done));
      if (w < 0 && errno == EINTR)
        continue;
      if (w <= 0)
        FailOpen(path_, SpoolFailure(dir_, w < 0 ? errno : EIO));
      done += w;
    }
    return r;
  }
  std::string ErrorText() const override { return inner_->ErrorText(); }

private:
  std::unique_ptr<Source> inner_;
  int spool_;
  std::string dir_, path_;
};

} // namespace

std::unique_ptr<Source> OpenFileSource(const std::string& path, const std::string& shownAs)
{
  const std::string& name = shownAs.empty() ? path : shownAs;
  // O_NONBLOCK: opening a FIFO for reading would otherwise block until a writer opens it, deaf
  // to Ctrl-C; reads of non-regular files wait in poll(2) instead (FdSource).
  int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC | O_NONBLOCK);
  if (fd < 0)
    FailOpen(name, std::string("cannot be opened: ") + std::strerror(errno));
  struct stat st;
  if (::fstat(fd, &st) != 0)
  {
    const int err = errno;
    ::close(fd);
    FailOpen(name, std::string("cannot be inspected: ") + std::strerror(err));
  }
  if (S_ISDIR(st.st_mode))
  {
    ::close(fd);
    FailOpen(name, "is a directory");
  }
  unsigned char magic[2] = { 0, 0 };
  const bool regular = S_ISREG(st.st_mode);
  if (regular)
  {
    const int flags = ::fcntl(fd, F_GETFL);
    if (flags >= 0)
      ::fcntl(fd, F_SETFL, flags & ~O_NONBLOCK);
  }
  if (regular && st.st_size >= 2 && ::pread(fd, magic, 2, 0) == 2 && magic[0] == 0x1f &&
    magic[1] == 0x8b)
  {
    gzFile gz = gzdopen(fd, "rb");
    if (!gz)
    {
      ::close(fd);
      FailOpen(name, "cannot be opened as gzip");
    }
    gzbuffer(gz, 256u << 10);
    return std::make_unique<GzFileSource>(gz);
  }
#ifdef POSIX_FADV_SEQUENTIAL
  if (regular)
    ::posix_fadvise(fd, 0, 0, POSIX_FADV_SEQUENTIAL);
#endif
  auto src = std::make_unique<FdSource>(fd);
  src->sizeKnown = regular;
  src->size = regular ? std::uint64_t(st.st_size) : 0;
  src->regular = regular;
  return src;
}

std::unique_ptr<Source> OpenMemorySource(const void* data, std::size_t size)
{
  const auto* c = static_cast<const unsigned char*>(data);
  if (size >= 2 && c[0] == 0x1f && c[1] == 0x8b)
    return std::make_unique<MemoryGzSource>(static_cast<const char*>(data), size);
  return std::make_unique<MemorySource>(static_cast<const char*>(data), size);
}

// ---------------------------------------------------------------------------------------------
Input::Input(std::unique_ptr<Source> source, std::string path, std::size_t bufferBytes)
  : source_(std::move(source))
  , path_(std::move(path))
{
  if (bufferBytes == 0)
  {
    bufferBytes = kDefaultBufferBytes;
    // Small uncompressed inputs (memory, small files) get a buffer twice their size: the same
    // detection window (half the buffer) as the default, without allocating a MiB.
    if (source_->sizeKnown && !source_->compressed && source_->size < kDefaultBufferBytes / 2)
      bufferBytes = std::size_t(2 * source_->size + 2);
  }
  capacity_ = std::max(bufferBytes, kMinBufferBytes);
  buffer_.reset(new char[capacity_]);
  p = e = buffer_.get();
}

bool Input::Refill()
{
  char* b = buffer_.get();
  const std::size_t keep = Avail();
  if (p != b)
  {
    if (keep)
      std::memmove(b, p, keep);
    base_ += std::uint64_t(p - b);
    p = b;
    e = b + keep;
  }
  if (eof)
    return false;
  const std::size_t space = capacity_ - keep;
  if (space == 0)
    return false;
  // The abort poll of every loop that consumes input, however long a line, a run of skipped
  // records or of dropped faces is: once per buffer refill (1 MiB), not per byte.
  if (source_->AbortRequested())
    Aborted(*this);
  const long long r = source_->Read(b + keep, space);
  if (r == kReadAborted)
    Aborted(*this);
  if (r < 0)
    Fail(path_, context, source_->ErrorText(), "byte", Offset(e));
  if (r == 0)
  {
    eof = true;
    return false;
  }
  e += r;
  return true;
}

bool Input::EnsureSlow(std::size_t n)
{
  while (Avail() < n)
    if (!Refill())
      return Avail() >= n;
  return true;
}

void Input::SkipBytes(std::uint64_t n)
{
  while (n)
  {
    if (p == e && !Refill())
      FailAtByte("truncated (unexpected end of data)");
    const std::size_t k = std::size_t(std::min<std::uint64_t>(n, Avail()));
    p += k;
    n -= k;
  }
}

void Input::SkipLine()
{
  for (;;)
  {
    const void* q = p < e ? std::memchr(p, '\n', Avail()) : nullptr;
    if (q)
    {
      p = static_cast<const char*>(q) + 1;
      ++line;
      return;
    }
    p = e;
    if (!Refill())
      return;
  }
}

void Input::EndOfRecord(const char* what)
{
  if (SkipBlanks())
    FailAtLine(what);
  if (p < e) // '\n'
  {
    ++p;
    ++line;
  }
}

void Input::BadNumber(const char* what) const
{
  std::string tok(PeekToken().substr(0, 40));
  if (tok.empty())
    tok = p < e ? std::string(1, *p) : std::string("end of data");
  for (char& c : tok)
    if (static_cast<unsigned char>(c) < 0x20 || static_cast<unsigned char>(c) >= 0x7f)
      c = '?';
  FailAtLine("has a bad number '" + tok + "' for " + what);
}

bool Input::ReadLine(std::string_view& out)
{
  for (;;)
  {
    const void* q = p < e ? std::memchr(p, '\n', Avail()) : nullptr;
    const char* end = nullptr;
    if (q)
      end = static_cast<const char*>(q);
    else if (eof)
    {
      if (p == e)
        return false;
      end = e;
    }
    if (end)
    {
      const char* s = p;
      const char* t = end;
      if (t > s && t[-1] == '\r')
        --t;
      out = std::string_view(s, std::size_t(t - s));
      p = end < e ? end + 1 : end;
      if (q)
        ++line;
      return true;
    }
    if (Avail() == Capacity())
      FailAtLine("has a line longer than " + std::to_string(Capacity()) + " bytes");
    Refill();
  }
}

// ---------------------------------------------------------------------------------------------
std::size_t ClampChunk(std::size_t chunkElements, std::size_t bytesPerElement, std::uint64_t expected)
{
  std::size_t c = std::max<std::size_t>(1, chunkElements);
  c = std::min(c, std::max<std::size_t>(1, kMaxChunkBytes / std::max<std::size_t>(1, bytesPerElement)));
  if (expected > 0 && expected < c)
    c = std::size_t(expected);
  return c;
}

void VertexBuffer::Init(const VertexLayout& layout, std::size_t chunkElements, std::uint64_t expected)
{
  hasNormals = layout.normals;
  hasColors = layout.colors;
  hasTexcoords = layout.texcoords;
  nscalars = layout.scalars.size();
  const std::size_t bytes = 12 + (hasNormals ? 12 : 0) + (hasColors ? 4 : 0) +
    (hasTexcoords ? 8 : 0) + 4 * nscalars;
  capacity = ClampChunk(chunkElements, bytes, expected);
  xyz.assign(3 * capacity, 0.f);
  if (hasNormals)
    normals.assign(3 * capacity, 0.f);
  if (hasColors)
    rgba.assign(4 * capacity, 255);
  if (hasTexcoords)
    texcoords.assign(2 * capacity, 0.f);
  if (nscalars)
    scalars.assign(nscalars * capacity, 0.f);
  n = 0;
  first = 0;
}

void Aborted(const Input& in)
{
  std::string m = in.Path() + ": " + std::string(in.context) + " read aborted, at " +
    (in.text ? "line " + std::to_string(in.line) : "byte " + std::to_string(in.Offset()));
  throw ReadAbortedError(m);
}

void VertexBuffer::Flush(MeshSink& sink, const Input& in)
{
  if (n == 0)
    return;
  if (sink.AbortRequested())
    Aborted(in);
  VertexChunk c;
  c.first = first;
  c.count = n;
  c.xyz = xyz.data();
  c.normals = hasNormals ? normals.data() : nullptr;
  c.rgba = hasColors ? rgba.data() : nullptr;
  c.texcoords = hasTexcoords ? texcoords.data() : nullptr;
  c.scalars = nscalars ? scalars.data() : nullptr;
  sink.Vertices(c);
  first += n;
  n = 0;
}

void TriangleBuffer::Init(std::size_t chunkElements, std::uint64_t expected)
{
  capacity = ClampChunk(chunkElements, 12, expected);
  idx.assign(3 * capacity + 4, 0); // + spare slots for 16-byte stores
  if (withFlags)
    flags.assign(capacity, 0);
  n = 0;
}

void TriangleBuffer::Flush(MeshSink& sink, const Input& in)
{
  if (n == 0)
    return;
  if (sink.AbortRequested())
    Aborted(in);
  sink.Triangles(idx.data(), n);
  if (withFlags)
    sink.TriangleFlags(flags.data(), n);
  n = 0;
}

void TriangleBuffer::Reserve(MeshSink& sink, const Input& in, std::uint64_t more)
{
  if (!withFlags || n + more <= capacity)
    return;
  Flush(sink, in);
  if (more > capacity)
  {
    if (more > (std::uint64_t(1) << 26))
      throw MeshIOError(in.Path() + ": face: a polygon of " + std::to_string(more + 2) +
        " vertices is too large to carry a face selection (at most 2^26)");
    capacity = std::size_t(more);
    idx.resize(3 * capacity + 4, 0);
    flags.resize(capacity, 0);
  }
}

// ---------------------------------------------------------------------------------------------
namespace
{

enum class Family
{
  Unknown,
  Ply,
  StlAscii,
  StlBinary,
  Obj
};

bool IsTextByte(unsigned char c)
{
  return c >= 0x20 ? c != 0x7f : (c == '\n' || c == '\r' || c == '\t' || c == '\f' || c == '\v');
}

bool LooksLikeText(const char* s, std::size_t n)
{
  for (std::size_t i = 0; i < n; ++i)
    if (!IsTextByte(static_cast<unsigned char>(s[i])))
      return false;
  return true;
}

bool EqualsNoCase(std::string_view a, std::string_view b)
{
  if (a.size() != b.size())
    return false;
  for (std::size_t i = 0; i < a.size(); ++i)
  {
    char x = a[i], y = b[i];
    if (x >= 'A' && x <= 'Z')
      x = char(x - 'A' + 'a');
    if (y >= 'A' && y <= 'Z')
      y = char(y - 'A' + 'a');
    if (x != y)
      return false;
  }
  return true;
}

bool EndsWithNoCase(std::string_view s, std::string_view suffix)
{
  return s.size() >= suffix.size() && EqualsNoCase(s.substr(s.size() - suffix.size()), suffix);
}

bool IsObjKeyword(std::string_view k)
{
  static const char* const kWords[] = { "v", "vt", "vn", "vp", "f", "fo", "l", "p", "o", "g", "s",
    "usemtl", "mtllib", "cstype", "deg", "bmat", "step", "curv", "curv2", "surf", "parm", "trim",
    "hole", "scrv", "sp", "end", "con", "mg", "bevel", "c_interp", "d_interp", "lod", "shadow_obj",
    "trace_obj", "ctech", "stech", "maplib", "usemap" };
  for (const char* w : kWords)
    if (k == w)
      return true;
  return false;
}

// PLY magic: "ply" alone on the first line.
bool IsPlyMagic(std::string_view w)
{
  return w.size() >= 4 && w.substr(0, 3) == "ply" && (w[3] == '\n' || (w[3] == '\r'));
}

bool IsGzipMagic(std::string_view w)
{
  return w.size() >= 2 && static_cast<unsigned char>(w[0]) == 0x1f &&
    static_cast<unsigned char>(w[1]) == 0x8b;
}

bool NamedStl(const Input& in)
{
  return EndsWithNoCase(in.Path(), ".stl") || EndsWithNoCase(in.Path(), ".stl.gz");
}

Family DetectFamily(Input& in)
{
  const std::size_t want = std::min<std::size_t>(in.Capacity() / 2, 64u << 10);
  in.Ensure(want);
  std::string_view w(in.p, in.Avail());
  const Source& src = in.Src();
  if (w.empty() || IsGzipMagic(w))
    return Family::Unknown; // empty, or gzip that was not decompressed: FailUnknown says which
  if (IsPlyMagic(w))
    return Family::Ply;

  // The 80-byte header + facet count of a binary STL. A count of 0 is not evidence of an STL
  // (84 zero bytes, /dev/zero): only a name ending in .stl makes such a file an empty STL.
  std::uint64_t stlCount = 0;
  if (w.size() >= 84 && in.Offset() == 0)
  {
    const auto* b = reinterpret_cast<const unsigned char*>(w.data()) + 80;
    stlCount = std::uint64_t(b[0]) | std::uint64_t(b[1]) << 8 | std::uint64_t(b[2]) << 16 |
      std::uint64_t(b[3]) << 24;
    if (src.sizeKnown && 84 + 50 * stlCount == src.size && (stlCount > 0 || NamedStl(in)))
      return Family::StlBinary;
  }
  const bool text = LooksLikeText(w.data(), std::min<std::size_t>(w.size(), 4096));

  // "solid" first (after blanks): ASCII STL when the content is text, else a binary STL whose
  // 80-byte header happens to start with "solid".
  std::size_t i = 0;
  if (w.size() >= 3 && static_cast<unsigned char>(w[0]) == 0xEF &&
    static_cast<unsigned char>(w[1]) == 0xBB && static_cast<unsigned char>(w[2]) == 0xBF)
    i = 3; // UTF-8 byte order mark
  while (i < w.size() && Input::IsSpace(w[i]))
    ++i;
  if (w.size() - i >= 5 && EqualsNoCase(w.substr(i, 5), "solid") &&
    (w.size() - i == 5 || Input::IsSpace(w[i + 5])))
    return text ? Family::StlAscii : Family::StlBinary;

  if (text && !w.empty())
  {
    // OBJ: the first statement (after blank and comment lines) is an OBJ keyword.
    std::size_t pos = 0;
    while (pos < w.size())
    {
      std::size_t eol = w.find('\n', pos);
      if (eol == std::string_view::npos)
        eol = w.size();
      std::string_view ln = w.substr(pos, eol - pos);
      std::size_t s = 0;
      if (pos == 0 && ln.size() >= 3 && static_cast<unsigned char>(ln[0]) == 0xEF)
        s = 3;
      while (s < ln.size() && Input::IsSpace(ln[s]))
        ++s;
      if (s < ln.size() && ln[s] != '#')
      {
        std::size_t t = s;
        while (t < ln.size() && !Input::IsSpace(ln[t]))
          ++t;
        return IsObjKeyword(ln.substr(s, t - s)) ? Family::Obj : Family::Unknown;
      }
      if (eol == w.size() && !in.eof)
        break; // only comments so far, and more follows: call it OBJ
      pos = eol + 1;
    }
    return Family::Obj; // blank/comments only: an empty OBJ
  }
  // Binary content that is not PLY: a binary STL if the name says so, or if its size cannot be
  // checked (gzip, a pipe) and it announces facets; a wrong size is then reported by the STL
  // reader.
  if (!text && !w.empty() && ((!src.sizeKnown && stlCount > 0) || NamedStl(in)))
    return Family::StlBinary;
  return Family::Unknown;
}

[[noreturn]] void FailUnknown(Input& in)
{
  std::string_view w(in.p, in.Avail());
  const Source& src = in.Src();
  if (w.empty() && in.Offset() == 0)
    Fail(in.Path(), "file",
      std::string("is empty (0 bytes") + (src.compressed ? " after decompression" : "") +
        "; unknown format: expected PLY, STL or OBJ)",
      "byte", 0);
  if (IsGzipMagic(w) && src.compressed)
    Fail(in.Path(), "file",
      "is gzip inside gzip (compressed twice): decompress it once (gunzip) and read the result",
      "byte", 0);
  if (IsGzipMagic(w))
    Fail(in.Path(), "file",
      "is gzip-compressed data from a pipe or device (only regular files are decompressed): "
      "decompress it first, e.g. zcat FILE.gz | sipmss ... /dev/stdin",
      "byte", 0);
  w = w.substr(0, 4096);
  std::size_t zeros = 0;
  while (zeros < w.size() && w[zeros] == '\0')
    ++zeros;
  if (zeros > 0 && zeros == w.size())
    Fail(in.Path(), "file",
      "is not a mesh file (unknown format: its first " + std::to_string(zeros) +
        " bytes are all zero; expected PLY, STL or OBJ)",
      "byte", 0);
  Fail(in.Path(), "file", "is not a mesh file (unknown format: expected PLY, STL or OBJ)", "byte", 0);
}

Format PlyFormatFromWindow(std::string_view w)
{
  std::size_t pos = 0;
  while (pos < w.size())
  {
    std::size_t eol = w.find('\n', pos);
    if (eol == std::string_view::npos)
      eol = w.size();
    std::string_view ln = w.substr(pos, eol - pos);
    while (!ln.empty() && Input::IsSpace(ln.back()))
      ln.remove_suffix(1);
    if (ln.substr(0, 7) == "format ")
    {
      std::string_view f = ln.substr(7);
      while (!f.empty() && f.front() == ' ')
        f.remove_prefix(1);
      if (f.substr(0, 6) == "ascii ")
        return Format::PlyAscii;
      if (f.substr(0, 21) == "binary_little_endian ")
        return Format::PlyBinaryLE;
      if (f.substr(0, 18) == "binary_big_endian ")
        return Format::PlyBinaryBE;
      return Format::Unknown;
    }
    if (ln == "end_header")
      break;
    pos = eol + 1;
  }
  return Format::Unknown;
}

Format FormatOf(Family f, Input& in)
{
  switch (f)
  {
    case Family::Ply: return PlyFormatFromWindow(std::string_view(in.p, in.Avail()));
    case Family::StlAscii: return Format::StlAscii;
    case Family::StlBinary: return Format::StlBinary;
    case Family::Obj: return Format::Obj;
    case Family::Unknown: break;
  }
  return Format::Unknown;
}

Family FamilyOf(Format f)
{
  switch (f)
  {
    case Format::PlyAscii:
    case Format::PlyBinaryLE:
    case Format::PlyBinaryBE: return Family::Ply;
    case Format::StlAscii: return Family::StlAscii;
    case Format::StlBinary: return Family::StlBinary;
    case Format::Obj: return Family::Obj;
    case Format::Unknown: break;
  }
  return Family::Unknown;
}

ReadStats ReadFromInput(Input& in, MeshSink& sink, const ReadOptions& options, Format force)
{
  in.Src().abortSink = &sink;
  Family fam = force == Format::Unknown ? DetectFamily(in) : FamilyOf(force);
  switch (fam)
  {
    case Family::Ply: return ReadPly(in, sink, options);
    case Family::StlAscii: return ReadStlAscii(in, sink, options);
    case Family::StlBinary: return ReadStlBinary(in, sink, options);
    case Family::Obj: return ReadObj(in, sink, options);
    case Family::Unknown: break;
  }
  FailUnknown(in);
}

// Counts what a full read delivers (ReadHeader's scan for formats without a header).
class ScanSink final : public MeshSink
{
public:
  MeshHeader header;
  ReadStats stats;
  void Begin(const MeshHeader& h) override { header = h; }
  void Vertices(const VertexChunk&) override {}
  void Triangles(const std::uint32_t*, std::size_t) override {}
  void End(const ReadStats& s) override { stats = s; }
};

MeshHeader ScanHeader(Input& in, Format force)
{
  ScanSink sink;
  ReadFromInput(in, sink, ReadOptions{}, force);
  MeshHeader h = sink.header;
  h.vertexCount = sink.stats.vertices;
  h.faceCount = sink.stats.polygons;
  return h;
}

} // namespace
} // namespace detail

// ---------------------------------------------------------------------------------------------
Format DetectFormat(const std::string& path)
{
  detail::Input in(detail::OpenFileSource(path), path);
  return detail::FormatOf(detail::DetectFamily(in), in);
}

Format DetectFormatFromMemory(const void* data, std::size_t size)
{
  try
  {
    detail::Input in(detail::OpenMemorySource(data, size), "<memory>");
    return detail::FormatOf(detail::DetectFamily(in), in);
  }
  catch (const MeshIOError&)
  {
    return Format::Unknown; // e.g. corrupt gzip
  }
}

ReadStats ReadMesh(const std::string& path, MeshSink& sink, const ReadOptions& options)
{
  detail::Input in(detail::OpenFileSource(path), path);
  return detail::ReadFromInput(in, sink, options, Format::Unknown);
}

ReadStats ReadMeshFromMemory(const void* data, std::size_t size, MeshSink& sink,
  const ReadOptions& options, const MemoryReadOptions& memory)
{
  detail::Input in(detail::OpenMemorySource(data, size), memory.name, memory.bufferBytes);
  return detail::ReadFromInput(in, sink, options, memory.force);
}

MeshHeader ReadHeader(const std::string& path)
{
  using namespace detail;
  Input in(OpenFileSource(path), path);
  const Family fam = DetectFamily(in);
  switch (fam)
  {
    case Family::Ply:
      if (!in.Src().compressed)
        return ReadPlyHeader(in); // announced counts, checked against the file size
      return ScanHeader(in, Format::PlyAscii); // gzip: counts cannot be checked up front
    case Family::StlBinary:
      if (in.Src().sizeKnown && in.Avail() >= 84)
      {
        const auto* b = reinterpret_cast<const unsigned char*>(in.p) + 80;
        const std::uint64_t n = std::uint64_t(b[0]) | std::uint64_t(b[1]) << 8 |
          std::uint64_t(b[2]) << 16 | std::uint64_t(b[3]) << 24;
        if (84 + 50 * n == in.Src().size)
        {
          MeshHeader h;
          h.format = Format::StlBinary;
          h.vertexCount = 3 * n;
          h.faceCount = n;
          return h;
        }
      }
      return ScanHeader(in, Format::StlBinary);
    case Family::StlAscii: return ScanHeader(in, Format::StlAscii);
    case Family::Obj: return ScanHeader(in, Format::Obj);
    case Family::Unknown: break;
  }
  FailUnknown(in);
}

MeshHeader ReadProperties(const std::string& path)
{
  using namespace detail;
  Input in(OpenFileSource(path), path);
  const Family fam = DetectFamily(in);
  if (fam == Family::Unknown)
  {
    FailUnknown(in);
  }
  MeshHeader h;
  if (fam == Family::Ply)
  {
    const MeshHeader full = ReadPlyHeader(in, false);
    h.format = full.format;
    h.layout.scalars = full.layout.scalars;
    h.faceScalars = full.faceScalars;
  }
  else
  {
    h.format = FormatOf(fam, in);
  }
  return h;
}

// ---------------------------------------------------------------------------------------------
MeshInputFile::MeshInputFile(std::string path, std::string tmpdir)
  : path_(std::move(path))
  , tmpdir_(std::move(tmpdir))
{
}

MeshInputFile::~MeshInputFile()
{
  if (spoolFd_ >= 0)
    ::close(spoolFd_);
}

ReadStats MeshInputFile::Read(MeshSink& sink, const ReadOptions& options)
{
  using namespace detail;
  if (spoolComplete_)
  {
    // /proc/self/fd/N opens the unlinked copy afresh: its own offset (and gzip works on it).
    Input in(OpenFileSource("/proc/self/fd/" + std::to_string(spoolFd_), path_), path_);
    return ReadFromInput(in, sink, options, Format::Unknown);
  }
  if (spoolFd_ != -1)
    Fail(path_, "file",
      "cannot be read again: a pipe or device can be read only once, and its first read failed",
      "byte", 0);
  std::unique_ptr<Source> src = OpenFileSource(path_);
  if (src->regular)
  {
    Input in(std::move(src), path_);
    return ReadFromInput(in, sink, options, Format::Unknown);
  }

  std::string dir = tmpdir_;
  if (dir.empty())
  {
    const char* t = std::getenv("TMPDIR");
    dir = t && *t ? t : "/tmp";
  }
  std::string name = dir + "/.sipmss-input-XXXXXX";
  const int fd = ::mkstemp(name.data());
  if (fd < 0)
    Fail(path_, "file", SpoolFailure(dir, errno), "byte", 0);
  ::unlink(name.c_str()); // nothing is left behind, whatever happens next
  ::fcntl(fd, F_SETFD, FD_CLOEXEC);
  spoolFd_ = fd;
  try
  {
    Input in(std::make_unique<TeeSource>(std::move(src), fd, dir, path_), path_);
    in.Src().abortSink = &sink;
    // gzip is decompressed from the copy: copy it all first.
    const bool gzip = in.Ensure(2) && static_cast<unsigned char>(in.p[0]) == 0x1f &&
      static_cast<unsigned char>(in.p[1]) == 0x8b;
    ReadStats st;
    // The rest of the input (after a vertices-only pass or a sink's StopRead), for the next reads.
    auto drain = [&] {
      in.context = "file";
      do
        in.p = in.e;
      while (in.Refill());
      spoolComplete_ = true;
    };
    try
    {
      if (!gzip)
        st = ReadFromInput(in, sink, options, Format::Unknown);
    }
    catch (const StopRead&)
    {
      drain();
      throw;
    }
    drain();
    if (gzip)
      return Read(sink, options);
    return st;
  }
  catch (...)
  {
    if (!spoolComplete_)
    {
      ::close(spoolFd_);
      spoolFd_ = -2; // the input is consumed: a later Read says so
    }
    throw;
  }
}

} // namespace sipmss::io
