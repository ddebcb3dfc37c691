// One file read in pieces by byte ranges (MeshPiece.h). A piece is read by the format's own
// reader: its bytes come from a Source that puts a small header of its own before the file's
// records (pread at their offsets), so every check and every layout rule of a whole read holds.
#include "MeshIODetail.h"

#include <cerrno>
#include <fcntl.h>
#include <sys/stat.h>
#include <unistd.h>

#include <algorithm>
#include <cstring>
#include <vector>

namespace sipmss::io
{
namespace
{
using detail::Fail;

// A read-only descriptor of the file, closed with it.
class File
{
public:
  explicit File(const std::string& path)
    : path_(path)
    , fd_(::open(path.c_str(), O_RDONLY | O_CLOEXEC))
  {
    if (this->fd_ < 0)
      Fail(path, "file", std::string("cannot be opened: ") + std::strerror(errno), "byte", 0);
  }
  ~File() { ::close(this->fd_); }
  File(const File&) = delete;
  File& operator=(const File&) = delete;

  // n bytes at `at`, all of them (a shorter file is an error: it changed since the probe).
  void ReadAt(char* dst, std::size_t n, std::uint64_t at, std::uint64_t& bytes) const
  {
    std::size_t done = 0;
    while (done < n)
    {
      const ssize_t r = ::pread(this->fd_, dst + done, n - done, off_t(at + done));
      if (r < 0 && errno == EINTR)
        continue;
      if (r < 0)
        Fail(this->path_, "file", std::string("cannot be read: ") + std::strerror(errno), "byte",
          at + done);
      if (r == 0)
        Fail(this->path_, "file", "is shorter than its header says (did it change while read?)",
          "byte", at + done);
      done += std::size_t(r);
    }
    bytes += n;
  }

private:
  std::string path_;
  int fd_;
};

std::uint64_t LoadUnsigned(const unsigned char* p, std::uint32_t size, bool bigEndian)
{
  std::uint64_t v = 0;
  for (std::uint32_t k = 0; k < size; ++k)
    v |= std::uint64_t(p[bigEndian ? size - 1 - k : k]) << (8 * k);
  return v;
}

std::int64_t LoadIndex(const unsigned char* p, std::uint32_t size, bool isSigned, bool bigEndian)
{
  const std::uint64_t u = LoadUnsigned(p, size, bigEndian);
  if (isSigned && size < 8 && (u >> (8 * size - 1)) & 1)
    return std::int64_t(u) - (std::int64_t(1) << (8 * size));
  return std::int64_t(u);
}

// Bytes made by `fill` (a piece's own header, then the file's records or generated ones) as a
// Source of known size for the readers.
class GeneratedSource final : public detail::Source
{
public:
  // fill(buffer): appends the next bytes (at least one while any remain).
  GeneratedSource(std::uint64_t total, std::function<void(std::vector<char>&)> fill)
    : fill_(std::move(fill))
  {
    sizeKnown = true;
    size = total;
  }
  long long Read(char* dst, std::size_t n) override
  {
    if (this->at_ == this->buffer_.size())
    {
      this->buffer_.clear();
      this->at_ = 0;
      if (this->delivered_ < size)
        this->fill_(this->buffer_);
    }
    n = std::min(n, this->buffer_.size() - this->at_);
    std::memcpy(dst, this->buffer_.data() + this->at_, n);
    this->at_ += n;
    this->delivered_ += n;
    return static_cast<long long>(n);
  }
  std::string ErrorText() const override { return "read failed"; }

private:
  std::function<void(std::vector<char>&)> fill_;
  std::vector<char> buffer_;
  std::size_t at_ = 0;
  std::uint64_t delivered_ = 0;
};

constexpr std::size_t kRecordsPerFill = 8192;

} // namespace

SplitLayout ProbeSplit(const std::string& path)
{
  SplitLayout s;
  s.path = path;
  struct stat st;
  if (::stat(path.c_str(), &st) != 0)
    Fail(path, "file", std::string("cannot be opened: ") + std::strerror(errno), "byte", 0);
  if (!S_ISREG(st.st_mode))
  {
    s.whyNot = "it is not a regular file";
    return s;
  }
  s.fileBytes = std::uint64_t(st.st_size);
  if (detail::OpenFileSource(path)->compressed)
  {
    s.whyNot = "it is gzip-compressed";
    return s;
  }
  const Format f = DetectFormat(path);
  if (f == Format::PlyAscii || f == Format::PlyBinaryLE || f == Format::PlyBinaryBE)
  {
    detail::Input ply(detail::OpenFileSource(path), path);
    detail::DescribePlySplit(ply, s);
    return s;
  }
  s.format = f;
  if (f != Format::StlBinary)
  {
    s.whyNot = f == Format::Obj ? "it is OBJ (lines of varying length)"
      : f == Format::StlAscii   ? "it is ASCII STL (lines of varying length)"
                                : "its format cannot be read in pieces";
    return s;
  }
  if (s.fileBytes < 84 || (s.fileBytes - 84) % 50 != 0)
  {
    s.whyNot = "its size is not that of whole 50-byte facets";
    return s;
  }
  s.faceCount = (s.fileBytes - 84) / 50;
  if (s.faceCount == 0)
    s.whyNot = "it has no facets";
  return s;
}

std::pair<std::uint64_t, std::uint64_t> PieceFaces(const SplitLayout& layout, int piece, int pieces)
{
  const auto at = [&](int k) {
    // (128-bit: faceCount * k may overflow 64 bits for absurd counts)
    return std::uint64_t((unsigned __int128)layout.faceCount * unsigned(k) / unsigned(pieces));
  };
  return { at(piece), at(piece + 1) - at(piece) };
}

void ReadPlyFaceIndices(const SplitLayout& s, std::uint64_t first, std::uint64_t count,
  const std::function<void(const std::uint32_t*, std::size_t)>& onFaces, std::uint64_t& bytes,
  const std::function<bool()>& aborted, std::size_t chunkFaces)
{
  File file(s.path);
  chunkFaces = std::max<std::size_t>(chunkFaces, 1);
  std::vector<char> records(std::min<std::uint64_t>(count, chunkFaces) * s.faceStride);
  std::vector<std::uint32_t> indices(3 * std::min<std::uint64_t>(count, chunkFaces));
  for (std::uint64_t done = 0; done < count;)
  {
    if (aborted && aborted())
      throw ReadAbortedError(s.path + ": face read aborted, at face " + std::to_string(first + done));
    const std::size_t n = std::size_t(std::min<std::uint64_t>(count - done, chunkFaces));
    const std::uint64_t base = s.faceOffset + (first + done) * s.faceStride;
    file.ReadAt(records.data(), n * s.faceStride, base, bytes);
    for (std::size_t j = 0; j < n; ++j)
    {
      const auto* rec = reinterpret_cast<const unsigned char*>(records.data() + j * s.faceStride);
      const std::uint64_t face = first + done + j;
      const std::uint64_t c = LoadUnsigned(rec + s.countOffset, s.countSize, s.bigEndian);
      if (c != 3)
        throw NotSplittableError(s.path + ": face #" + std::to_string(face) + " has " +
          std::to_string(c) + " vertices: the file cannot be read in pieces");
      for (int k = 0; k < 3; ++k)
      {
        const std::int64_t v = LoadIndex(rec + s.countOffset + s.countSize + k * s.indexSize,
          s.indexSize, s.indexSigned, s.bigEndian);
        if (v < 0 || std::uint64_t(v) >= s.vertexCount)
          Fail(s.path, "face",
            "#" + std::to_string(face) +
              (v < 0 ? " has a negative vertex index " + std::to_string(v)
                     : " has vertex index " + std::to_string(v) + " out of range (" +
                    std::to_string(s.vertexCount) + " vertices)"),
            "byte", base + j * s.faceStride + s.countOffset + s.countSize + k * s.indexSize);
        indices[3 * j + std::size_t(k)] = std::uint32_t(v);
      }
    }
    onFaces(indices.data(), n);
    done += n;
  }
}

ReadStats ReadPlyPiece(const SplitLayout& s, std::uint64_t vertexCount,
  const IndexSource& nextVertices, std::uint64_t faceCount, const IndexSource& nextFaces,
  MeshSink& sink, const ReadOptions& options, std::uint64_t& bytes, const std::string& name)
{
  File file(s.path);
  const std::string header = std::string("ply\nformat ") +
    (s.bigEndian ? "binary_big_endian" : "binary_little_endian") + " 1.0\nelement vertex " +
    std::to_string(vertexCount) + "\n" + s.vertexProperties + "element face " +
    std::to_string(faceCount) + "\nproperty list uchar uint vertex_indices\nend_header\n";
  constexpr std::size_t kFaceRecord = 13;
  const std::uint64_t total =
    header.size() + vertexCount * s.vertexStride + faceCount * kFaceRecord;
  std::uint64_t verticesLeft = vertexCount, facesLeft = faceCount;
  bool headerDone = false;
  std::vector<std::uint32_t> ids(kRecordsPerFill * 3);
  auto fill = [&](std::vector<char>& out) {
    if (!headerDone)
    {
      out.assign(header.begin(), header.end());
      headerDone = true;
      return;
    }
    if (verticesLeft)
    {
      const std::size_t n =
        nextVertices(ids.data(), std::size_t(std::min<std::uint64_t>(verticesLeft, kRecordsPerFill)));
      if (n == 0)
        throw std::logic_error("ReadPlyPiece: fewer vertices than announced");
      out.resize(n * s.vertexStride);
      // Consecutive records in one read.
      for (std::size_t j = 0; j < n;)
      {
        std::size_t k = j + 1;
        while (k < n && ids[k] == ids[k - 1] + 1)
          ++k;
        file.ReadAt(out.data() + j * s.vertexStride, (k - j) * s.vertexStride,
          s.vertexOffset + std::uint64_t(ids[j]) * s.vertexStride, bytes);
        j = k;
      }
      verticesLeft -= n;
      return;
    }
    const std::size_t n =
      nextFaces(ids.data(), std::size_t(std::min<std::uint64_t>(facesLeft, kRecordsPerFill)));
    if (n == 0)
      throw std::logic_error("ReadPlyPiece: fewer faces than announced");
    out.resize(n * kFaceRecord);
    for (std::size_t j = 0; j < n; ++j)
    {
      unsigned char* rec = reinterpret_cast<unsigned char*>(out.data()) + j * kFaceRecord;
      rec[0] = 3;
      for (int k = 0; k < 3; ++k)
        for (int b = 0; b < 4; ++b)
          rec[1 + 4 * k + (s.bigEndian ? 3 - b : b)] =
            static_cast<unsigned char>(ids[3 * j + std::size_t(k)] >> (8 * b));
    }
    facesLeft -= n;
  };
  detail::Input in(std::make_unique<GeneratedSource>(total, fill), name);
  in.Src().abortSink = &sink;
  return detail::ReadPly(in, sink, options);
}

ReadStats ReadStlPiece(const SplitLayout& s, std::uint64_t first, std::uint64_t count,
  MeshSink& sink, const ReadOptions& options, std::uint64_t& bytes, const std::string& name)
{
  File file(s.path);
  std::uint64_t left = count;
  bool headerDone = false;
  auto fill = [&](std::vector<char>& out) {
    if (!headerDone)
    {
      out.assign(84, 0);
      for (int b = 0; b < 4; ++b)
        out[std::size_t(80 + b)] = char((count >> (8 * b)) & 0xff);
      headerDone = true;
      return;
    }
    const std::size_t n = std::size_t(std::min<std::uint64_t>(left, kRecordsPerFill));
    out.resize(50 * n);
    file.ReadAt(out.data(), out.size(), 84 + 50 * (first + count - left), bytes);
    left -= n;
  };
  detail::Input in(std::make_unique<GeneratedSource>(84 + 50 * count, fill), name);
  in.Src().abortSink = &sink;
  return detail::ReadStlBinary(in, sink, options);
}

} // namespace sipmss::io
