// Internal plumbing shared by the mesh readers and writers: buffered input over a file, a gzip
// stream or memory; error formatting; ASCII tokenizing and number parsing; chunk buffers.
// Not installed, not part of the API.
#pragma once

#include <algorithm>

#include "sipmss/io/MeshIO.h"
#include "sipmss/io/MeshIOInternal.h"
#include "sipmss/io/MeshPiece.h"

#include <charconv>
#include <cstdint>
#include <cstring>
#include <limits>
#include <memory>
#include <string>
#include <string_view>
#include <system_error>
#include <vector>

namespace sipmss::io::detail
{

constexpr std::size_t kDefaultBufferBytes = std::size_t(1) << 20; // one read(2)/gzread per MiB
constexpr std::size_t kMinBufferBytes = 1024;
constexpr std::size_t kMaxToken = 256;           // longest ASCII number token accepted
constexpr std::size_t kMaxChunkBytes = 16u << 20; // cap on one chunk buffer, whatever the layout
constexpr std::uint64_t kMaxVertices = 0xFFFFFFFFull; // indices are uint32

[[noreturn]] void Fail(const std::string& path, std::string_view element, const std::string& what,
  const char* unit, std::uint64_t where);

inline bool HostIsLittleEndian()
{
#if defined(__BYTE_ORDER__) && defined(__ORDER_LITTLE_ENDIAN__)
  return __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__;
#else
  const std::uint16_t one = 1;
  unsigned char c;
  std::memcpy(&c, &one, 1);
  return c == 1;
#endif
}

// ---------------------------------------------------------------------------------------------
// Byte sources. Read returns the number of bytes read, 0 at the end, -1 on error (ErrorText()),
// kReadAborted when abortSink asked to stop while the source was waiting for data (a FIFO).
constexpr long long kReadAborted = -2;
class Source
{
public:
  virtual ~Source() = default;
  virtual long long Read(char* dst, std::size_t n) = 0;
  virtual std::string ErrorText() const = 0;
  bool sizeKnown = false;   // true for uncompressed files and memory: size is the input size
  std::uint64_t size = 0;
  bool compressed = false;
  bool regular = true;      // false for FIFOs, character devices, sockets (no size, one pass)
  // Asked for an abort on every refill of the input window (once per buffer, not per byte) and
  // while a non-regular source waits for data. Null: never aborted.
  MeshSink* abortSink = nullptr;
  bool AbortRequested() const { return abortSink && abortSink->AbortRequested(); }
};

// gzip by magic (regular files), else read(2). Never blocks in open(2) (a FIFO without a writer
// is opened non-blocking); a non-regular file's reads wait in poll(2), asking abortSink every
// 0.1 s. `name` (default: path) names the input in errors.
std::unique_ptr<Source> OpenFileSource(const std::string& path, const std::string& name = {});
std::unique_ptr<Source> OpenMemorySource(const void* data, std::size_t size); // gzip by magic

// Parses an integer in [s, e): optional sign, decimal digits. Sets q past it. False on no digits
// or overflow of int64.
inline bool ParseInt64(const char* s, const char* e, const char*& q, std::int64_t& out)
{
  bool neg = false;
  if (s < e && (*s == '-' || *s == '+'))
  {
    neg = *s == '-';
    ++s;
  }
  // Up to 18 digits cannot overflow: no checks in the common case.
  const char* t = s;
  std::uint64_t v = 0;
#if defined(__BYTE_ORDER__) && __BYTE_ORDER__ == __ORDER_LITTLE_ENDIAN__
  if (e - s >= 8)
  {
    // SWAR: the leading digits of the next 8 bytes at once (first character = lowest byte).
    std::uint64_t c;
    std::memcpy(&c, s, 8);
    const std::uint64_t d = c ^ 0x3030303030303030ull; // digits -> 0..9, others -> >= 10
    const std::uint64_t nondigit = ((d + 0x7676767676767676ull) | d) & 0x8080808080808080ull;
    const int n = nondigit ? __builtin_ctzll(nondigit) >> 3 : 8;
    if (n > 0)
    {
      std::uint64_t x = n == 8 ? d : d << (8 * (8 - n)); // leading zero digits
      x = (x * 10) + (x >> 8);
      x = (((x & 0x000000FF000000FFull) * 0x000F424000000064ull) +
            (((x >> 16) & 0x000000FF000000FFull) * 0x0000271000000001ull)) >> 32;
      v = x;
      t = s + n;
    }
    else
      return false;
  }
#endif
  const char* lim = e - s > 18 ? s + 18 : e;
  while (t < lim && unsigned(*t - '0') <= 9)
  {
    v = v * 10 + unsigned(*t - '0');
    ++t;
  }
  if (t == s)
    return false;
  for (; t < e && unsigned(*t - '0') <= 9; ++t)
  {
    const unsigned d = unsigned(*t - '0');
    if (v > (std::numeric_limits<std::uint64_t>::max() - d) / 10)
      return false;
    v = v * 10 + d;
  }
  if (neg)
  {
    if (v > std::uint64_t(std::numeric_limits<std::int64_t>::max()) + 1)
      return false;
    out = v == std::uint64_t(std::numeric_limits<std::int64_t>::max()) + 1
      ? std::numeric_limits<std::int64_t>::min()
      : -std::int64_t(v);
  }
  else
  {
    if (v > std::uint64_t(std::numeric_limits<std::int64_t>::max()))
      return false;
    out = std::int64_t(v);
  }
  q = t;
  return true;
}

// Parses a float/double in [s, e) with from_chars (plus a leading '+'); values out of the type's
// range are parsed as double and converted (so 1e-50 gives 0 and 1e39 gives inf for float).
template <class T>
inline bool ParseReal(const char* s, const char* e, const char*& q, T& out)
{
  if (s < e && *s == '+')
  {
    ++s;
    if (s < e && (*s == '-' || *s == '+'))
      return false;
  }
  auto r = std::from_chars(s, e, out, std::chars_format::general);
  if (r.ec == std::errc::result_out_of_range)
  {
    if constexpr (std::is_same_v<T, float>)
    {
      double d = 0;
      auto r2 = std::from_chars(s, e, d, std::chars_format::general);
      if (r2.ec != std::errc())
        return false;
      out = static_cast<float>(d);
      q = r2.ptr;
      return true;
    }
    return false;
  }
  if (r.ec != std::errc())
    return false;
  q = r.ptr;
  return true;
}

// ---------------------------------------------------------------------------------------------
// A bounded window over a Source. [p, e) is the unread part of the buffer.
class Input
{
public:
  Input(std::unique_ptr<Source> source, std::string path, std::size_t bufferBytes = 0);
  Input(const Input&) = delete;
  Input& operator=(const Input&) = delete;

  const std::string& Path() const { return path_; }
  Source& Src() { return *source_; }
  std::size_t Capacity() const { return capacity_; }

  const char* p = nullptr;
  const char* e = nullptr;
  bool eof = false;                 // the source is exhausted (what is buffered is all there is)
  std::uint64_t line = 1;           // for text formats: the line p is on
  bool text = false;                // errors name lines (true) or byte offsets (false)
  std::string_view context = "input"; // element named in errors

  std::uint64_t Offset(const char* at) const { return base_ + std::uint64_t(at - buffer_.get()); }
  std::uint64_t Offset() const { return Offset(p); }
  std::size_t Avail() const { return std::size_t(e - p); }

  // Reads more input after e (moving [p, e) to the front first). False when nothing more came.
  bool Refill();
  // At least n (<= Capacity()/2) bytes buffered; false when the input ends first.
  bool Ensure(std::size_t n) { return Avail() >= n || EnsureSlow(n); }

  [[noreturn]] void FailAtByte(const std::string& what) const { FailAtByte(what, Offset()); }
  [[noreturn]] void FailAtByte(const std::string& what, std::uint64_t at) const
  {
    Fail(path_, context, what, "byte", at);
  }
  [[noreturn]] void FailAtLine(const std::string& what) const { Fail(path_, context, what, "line", line); }
  [[noreturn]] void FailHere(const std::string& what) const
  {
    if (text)
      FailAtLine(what);
    FailAtByte(what);
  }

  // Binary helpers -----------------------------------------------------------------------------
  // Ensures n bytes or fails with "truncated".
  void Need(std::size_t n)
  {
    if (Avail() < n && !EnsureSlow(n))
      FailAtByte("truncated (unexpected end of data)");
  }
  void SkipBytes(std::uint64_t n);

  // Text helpers -------------------------------------------------------------------------------
  // Skips spaces, tabs and '\r' on the current line, keeping >= kMaxToken bytes of look-ahead (or
  // everything up to the end). True when a token starts at p (false at '\n' or end of input).
  bool SkipBlanks()
  {
    for (;;)
    {
      while (p < e && (*p == ' ' || *p == '\t' || *p == '\r' || *p == '\f' || *p == '\v'))
        ++p;
      if (Avail() < kMaxToken && !eof)
      {
        Refill();
        continue;
      }
      return p < e && *p != '\n';
    }
  }
  // Skips whitespace and newlines (counting lines). True when a token starts at p.
  bool SkipSpace()
  {
    for (;;)
    {
      if (!SkipBlanks())
      {
        if (p < e) // at '\n'
        {
          ++p;
          ++line;
          continue;
        }
        return false;
      }
      return true;
    }
  }
  // Consumes the rest of the current line including its '\n'.
  void SkipLine();
  // After the last value of a record: only blanks may remain on the line; consumes the '\n'.
  void EndOfRecord(const char* what = "has extra values on the line");
  // The token at p (SkipBlanks() returned true), up to the next whitespace.
  std::string_view PeekToken() const
  {
    const char* s = p;
    while (s < e && !IsSpace(*s))
      ++s;
    return std::string_view(p, std::size_t(s - p));
  }
  void SkipToken()
  {
    std::string_view t = PeekToken();
    if (t.size() >= kMaxToken && !eof)
      FailAtLine("has a value longer than " + std::to_string(kMaxToken) + " characters");
    p += t.size();
  }

  static bool IsSpace(char c)
  {
    return c == ' ' || c == '\n' || c == '\r' || c == '\t' || c == '\f' || c == '\v';
  }
  // A value token ends at whitespace or at the very end of the input.
  bool AtDelimiter(const char* q) const { return q < e ? IsSpace(*q) : eof; }

  // Number tokens at p (after SkipBlanks() returned true); fail with "bad number" otherwise.
  template <class T>
  T ParseFloatToken(const char* what);
  std::int64_t ParseIntToken(const char* what)
  {
    std::int64_t v = 0;
    const char* q = p;
    if (!ParseInt64(p, e, q, v) || !AtDelimiter(q) || std::size_t(q - p) > kMaxToken)
      BadNumber(what);
    p = q;
    return v;
  }

  // Reads one '\n'-terminated line (without "\r\n"); it must fit in the buffer. False at the end.
  bool ReadLine(std::string_view& out);

private:
  bool EnsureSlow(std::size_t n);
  [[noreturn]] void BadNumber(const char* what) const;

  std::unique_ptr<Source> source_;
  std::string path_;
  std::unique_ptr<char[]> buffer_; // not zero-filled
  std::size_t capacity_ = 0;
  std::uint64_t base_ = 0; // input offset of buffer_[0]
};

template <class T>
T Input::ParseFloatToken(const char* what)
{
  T v{};
  const char* q = p;
  if (!ParseReal<T>(p, e, q, v) || !AtDelimiter(q) || std::size_t(q - p) > kMaxToken)
    BadNumber(what);
  p = q;
  return v;
}

inline bool IsFiniteFloat(float f)
{
  std::uint32_t b;
  std::memcpy(&b, &f, 4);
  return (b & 0x7f800000u) != 0x7f800000u;
}

// True when all n floats are finite (vectorizable).
inline bool AllFinite(const float* v, std::size_t n)
{
  std::uint32_t bad = 0;
  for (std::size_t i = 0; i < n; ++i)
  {
    std::uint32_t b;
    std::memcpy(&b, v + i, 4);
    bad |= ((b & 0x7f800000u) == 0x7f800000u);
  }
  return bad == 0;
}

// ---------------------------------------------------------------------------------------------
// Chunk buffers handed to the sink.
class VertexBuffer
{
public:
  void Init(const VertexLayout& layout, std::size_t chunkElements, std::uint64_t expected);
  std::size_t capacity = 0;
  std::size_t n = 0;          // vertices buffered
  std::uint64_t first = 0;    // index of the first buffered vertex
  std::size_t nscalars = 0;
  std::vector<float> xyz, normals, texcoords, scalars;
  std::vector<std::uint8_t> rgba;
  bool hasNormals = false, hasColors = false, hasTexcoords = false;

  bool Full() const { return n == capacity; }
  // Delivers the buffered vertices (if any); checks AbortRequested first.
  void Flush(MeshSink& sink, const Input& in);
};

class TriangleBuffer
{
public:
  void Init(std::size_t chunkElements, std::uint64_t expected);
  std::vector<std::uint32_t> idx;
  std::size_t capacity = 0; // triangles
  std::size_t n = 0;
  std::uint64_t triangles = 0;
  std::uint64_t dropped = 0;
  bool dropDegenerate = true;
  // ReadOptions::faceFlag: one flag per triangle, set by SetFlags once its face is read.
  bool withFlags = false;
  std::vector<std::uint8_t> flags;

  // Adds a triangle; false when dropped as degenerate.
  void Add(std::uint32_t a, std::uint32_t b, std::uint32_t c)
  {
    if (dropDegenerate && (a == b || b == c || a == c))
    {
      ++dropped;
      return;
    }
    std::uint32_t* t = idx.data() + 3 * n;
    t[0] = a;
    t[1] = b;
    t[2] = c;
    ++triangles;
    ++n;
  }
  bool Full() const { return n == capacity; }
  void Flush(MeshSink& sink, const Input& in);
  // With flags: room for a face of `more` triangles without a flush inside it (flushed first,
  // or grown for a polygon larger than the buffer), so that its flag can be set after it.
  void Reserve(MeshSink& sink, const Input& in, std::uint64_t more);
  void SetFlags(std::size_t from, bool flag)
  {
    std::fill(flags.begin() + std::ptrdiff_t(from), flags.begin() + std::ptrdiff_t(n),
      std::uint8_t(flag ? 1 : 0));
  }
};

// Fan triangulation of one polygon, fed index by index.
struct Fan
{
  std::uint32_t first = 0, prev = 0;
  std::uint64_t n = 0;
  void Start() { n = 0; }
  // Returns true when a triangle (first, prev, idx) is due.
  bool Add(std::uint32_t idx, std::uint32_t& a, std::uint32_t& b)
  {
    bool tri = false;
    if (n == 0)
      first = idx;
    else if (n >= 2)
    {
      a = first;
      b = prev;
      tri = true;
    }
    prev = idx;
    ++n;
    return tri;
  }
};

[[noreturn]] void Aborted(const Input& in);

// Readers (one per format family). in is positioned at the start of the input.
ReadStats ReadPly(Input& in, MeshSink& sink, const ReadOptions& options);
ReadStats ReadStlAscii(Input& in, MeshSink& sink, const ReadOptions& options);
ReadStats ReadStlBinary(Input& in, MeshSink& sink, const ReadOptions& options);
ReadStats ReadObj(Input& in, MeshSink& sink, const ReadOptions& options);
// PLY header only (counts announced, layout); in is left after end_header. checkSizes: the
// counts are checked against the file's size (an uncompressed file's).
MeshHeader ReadPlyHeader(Input& in, bool checkSizes = true);
// The PLY header's part of ProbeSplit (MeshPiece.h): format, counts, the records' places and
// sizes, or why the file cannot be read in pieces; `layout.fileBytes` is set by the caller.
void DescribePlySplit(Input& in, SplitLayout& layout);

// Format detection from the buffered start of the input (fills the buffer).
Format DetectFromInput(Input& in);

std::size_t ClampChunk(std::size_t chunkElements, std::size_t bytesPerElement, std::uint64_t expected);

// The end of every reader: flush the buffers, tell the sink the final counts.
inline ReadStats Finish(
  Input& in, MeshSink& sink, VertexBuffer& vb, TriangleBuffer& tb, std::uint64_t polygons)
{
  vb.Flush(sink, in);
  tb.Flush(sink, in);
  ReadStats st;
  st.vertices = vb.first;
  st.triangles = tb.triangles;
  st.polygons = polygons;
  st.droppedFaces = tb.dropped;
  st.bytes = in.Offset();
  sink.End(st);
  return st;
}

} // namespace sipmss::io::detail
