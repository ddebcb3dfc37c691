#include "sipmss/algorithms/FilePiece.h"

#include "sipmss/io/MeshPiece.h"
#include "sipmss/storage/Access.h"

#include <algorithm>
#include <exception>
#include <limits>
#include <stdexcept>

namespace sipmss::algorithms
{
namespace
{
using storage::Array;
using storage::View;

struct Tri
{
  std::uint32_t v[3];
};

constexpr std::size_t kChunk = std::size_t(1) << 16;
} // namespace

struct FilePiece::Impl
{
  io::SplitLayout layout;
  std::string whyNot;
  std::string name; // in errors: the file and the rank
  bool split = false;
  std::uint64_t first = 0, count = 0; // the piece's faces of the file
  std::uint64_t bytes = 0;
  storage::DML dml;
  Array<Tri> faces;             // binary PLY: the piece's triangles, in the piece's numbers
  Array<std::uint32_t> vertices; // binary PLY: the file's numbers of the piece's vertices, ascending
  std::uint64_t vertexCount = 0;

  // Binary PLY: the piece's faces, and its vertices as the sorted set of the file's vertex
  // numbers they use; the faces renumbered into it. The numbers go through a dense map over the
  // range [lo, hi] the faces use (a file in scanner order: about the piece's share of the
  // vertices; a shuffled one: all of them), in this DML like the rest.
  void ReadPly(const storage::Profile& profile, Progress& progress)
  {
    storage::Profile p = profile;
    p.structures.push_back({ "file piece: faces", sizeof(Tri), std::max<std::uint64_t>(count, 1), 0.0 });
    p.structures.push_back(
      { "file piece: vertex numbers", 8, std::max<std::uint64_t>(3 * count, 1), 0.0 });
    this->dml.Config(p);
    this->faces = Array<Tri>(this->dml, std::max<std::uint64_t>(this->count, 1));
    std::uint32_t lo = std::numeric_limits<std::uint32_t>::max(), hi = 0;
    std::uint64_t at = 0;
    io::ReadPlyFaceIndices(
      this->layout, this->first, this->count,
      [&](const std::uint32_t* idx, std::size_t n) {
        this->faces.Write(at, n, reinterpret_cast<const Tri*>(idx));
        for (std::size_t k = 0; k < 3 * n; ++k)
        {
          lo = std::min(lo, idx[k]);
          hi = std::max(hi, idx[k]);
        }
        at += n;
      },
      this->bytes, [&progress] { return progress.Aborted(); }, kChunk);
    if (this->count == 0)
    {
      this->vertices = Array<std::uint32_t>(this->dml, 1);
      return;
    }
    // The map: 0 for a number no face uses, else its number in the piece plus one.
    Array<std::uint32_t> mapArray(this->dml, std::uint64_t(hi - lo) + 1);
    const std::uint32_t zero = 0;
    this->dml.Fill(mapArray.Id(), &zero);
    View<std::uint32_t> map(this->dml, mapArray);
    View<Tri> F(this->dml, this->faces);
    for (std::uint64_t f = 0; f < this->count; ++f)
    {
      if ((f & 0xffff) == 0 && progress.Aborted())
      {
        throw AbortedError();
      }
      const Tri t = F.Get(f);
      for (std::uint32_t v : t.v)
      {
        map.Set(v - lo, 1);
      }
    }
    const std::uint64_t range = std::uint64_t(hi - lo) + 1;
    for (std::uint64_t i = 0; i < range; ++i)
    {
      this->vertexCount += map.Get(i) != 0;
    }
    this->vertices = Array<std::uint32_t>(this->dml, this->vertexCount);
    map.Refresh();
    F.Refresh();
    View<std::uint32_t> V(this->dml, this->vertices);
    std::uint32_t next = 0;
    for (std::uint64_t i = 0; i < range; ++i)
    {
      if (map.Get(i))
      {
        V.Set(next, std::uint32_t(lo + i));
        map.Set(i, ++next);
      }
    }
    for (std::uint64_t f = 0; f < this->count; ++f)
    {
      Tri t = F.Get(f);
      for (std::uint32_t& v : t.v)
      {
        v = map.Get(v - lo) - 1;
      }
      F.Set(f, t);
    }
    mapArray.Close();
    this->dml.Reconfigure();
  }

  io::ReadStats Replay(io::MeshSink& sink, const io::ReadOptions& options)
  {
    if (this->layout.format == io::Format::StlBinary)
    {
      return io::ReadStlPiece(this->layout, this->first, this->count, sink, options, this->bytes,
        this->name);
    }
    std::uint64_t nextVertex = 0, nextFace = 0;
    const auto vertexNumbers = [this, &nextVertex](std::uint32_t* out, std::size_t n) {
      n = std::size_t(std::min<std::uint64_t>(n, this->vertexCount - nextVertex));
      this->vertices.Read(nextVertex, n, out);
      nextVertex += n;
      return n;
    };
    const auto triangles = [this, &nextFace](std::uint32_t* out, std::size_t n) {
      n = std::size_t(std::min<std::uint64_t>(n, this->count - nextFace));
      this->faces.Read(nextFace, n, reinterpret_cast<Tri*>(out));
      nextFace += n;
      return n;
    };
    return io::ReadPlyPiece(this->layout, this->vertexCount, vertexNumbers, this->count, triangles,
      sink, options, this->bytes, this->name);
  }
};

storage::Profile ReservePieceBudget(SimplifyRequest& request)
{
  storage::Profile profile = MakeProfile(request);
  if (profile.memoryBudget)
  {
    profile.memoryBudget = std::max<std::uint64_t>(profile.memoryBudget / 8, 64u << 10);
    request.reservedMemoryBytes = profile.memoryBudget;
  }
  return profile;
}

FilePiece::FilePiece(
  const std::string& path, Communicator& comm, const storage::Profile& profile, Progress& progress)
  : impl_(std::make_unique<Impl>())
{
  Impl& I = *this->impl_;
  const int rank = comm.Rank(), size = comm.Size();
  I.name = path + " (rank " + std::to_string(rank) + "'s piece)";
  std::exception_ptr failure;
  bool notTriangles = false, probed = false;
  try
  {
    I.layout = io::ProbeSplit(path);
    probed = true;
    I.whyNot = I.layout.whyNot;
    if (I.whyNot.empty())
    {
      const auto range = io::PieceFaces(I.layout, rank, size);
      I.first = range.first;
      I.count = range.second;
      if (I.layout.format != io::Format::StlBinary)
      {
        I.ReadPly(profile, progress);
      }
    }
  }
  catch (const io::NotSplittableError& e)
  {
    notTriangles = true;
    I.whyNot = e.what();
  }
  catch (...)
  {
    failure = std::current_exception();
  }
  // Every rank learns whether any found the file unsplittable, and whether any failed (and
  // which). A face that is not a triangle wins over failures: the ranks after it read their
  // records at the wrong places, and whatever they found there means nothing. (The rank whose
  // faces hold the file's first such face reads up to it at the right places, so it is found.)
  // A rank other than 0 that cannot even open the file (not on a file system every rank
  // shares) leaves it to rank 0, as for a file that cannot be split.
  std::uint64_t flags[4] = { failure ? 1u : 0u, notTriangles || !I.whyNot.empty() ? 1u : 0u,
    rank != 0 && !probed ? 1u : 0u, rank == 0 && !probed ? 1u : 0u };
  double failing = failure ? double(rank) : -1.0;
  comm.AllReduceSum(flags, 4);
  comm.AllReduceMax(&failing, 1);
  const bool leaveToRankZero = flags[1] || (flags[2] && !flags[3]);
  if (failure && !leaveToRankZero)
  {
    std::rethrow_exception(failure);
  }
  if (flags[0] && !leaveToRankZero)
  {
    throw std::runtime_error(path + ": rank " + std::to_string(int(failing)) +
      " could not read its piece of the file (its error is in its own output)");
  }
  I.split = !leaveToRankZero;
  if (!I.split)
  {
    if (I.whyNot.empty())
    {
      I.whyNot = flags[1] ? "another rank found a face that is not a triangle"
                          : "not every rank can open it (is it on a file system they share?)";
    }
    I.faces.Close();
    I.vertices.Close();
  }
}

FilePiece::~FilePiece() = default;

bool FilePiece::Split() const
{
  return this->impl_->split;
}

const std::string& FilePiece::WhyNot() const
{
  return this->impl_->whyNot;
}

MeshSource FilePiece::Source()
{
  Impl* I = this->impl_.get();
  return [I](io::MeshSink& sink, const io::ReadOptions& options) { return I->Replay(sink, options); };
}

std::uint64_t FilePiece::BytesRead() const
{
  return this->impl_->bytes;
}

std::uint64_t FilePiece::FileBytes() const
{
  return this->impl_->layout.fileBytes;
}

std::uint64_t FilePiece::Faces() const
{
  return this->impl_->count;
}

} // namespace sipmss::algorithms
