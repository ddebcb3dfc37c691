#include "sipmss/algorithms/FilePiece.h"

#include "Distributed.h"
#include "StoredMesh.h"
#include "sipmss/io/MeshPiece.h"
#include "sipmss/storage/Access.h"

#include <algorithm>
#include <cstring>
#include <exception>
#include <limits>
#include <optional>
#include <stdexcept>

namespace sipmss::algorithms
{
namespace
{
using storage::Array;
using storage::View;
using detail::Rounds;

struct Tri
{
  std::uint32_t v[3];
};

constexpr std::size_t kChunk = std::size_t(1) << 16;

// The scatter's records, rank 0 to each rank (its own piece included): a header, vertex chunks,
// triangle chunks, the end.
enum Record : std::uint8_t
{
  kHeader = 'H',
  kVertices = 'V',
  kTriangles = 'T',
  kEnd = 'E'
};

// Rank 0's side of the scatter of a file that cannot be read by byte ranges: the file read
// whole, once, into a mesh in a DML of its own; then, rank after rank, the faces of its share
// and the vertices they use (a dense map over the range of numbers they use, as a piece read by
// byte ranges has), renumbered in the file's order.
class ScatterSender
{
public:
  ScatterSender(const storage::Profile& profile, int ranks)
    : profile_(profile)
    , ranks_(ranks)
  {
  }

  void Read(const std::string& path, Progress& progress)
  {
    this->mesh_.SetProgress(&progress);
    this->mesh_.OnHeader([this](std::uint64_t v, std::uint64_t f) {
      // (the counts of a PLY header; 0 for OBJ, STL and gzip, whose blocks grow as they come)
      storage::Profile p = this->profile_;
      p.structures.push_back({ "file scatter: points", 12, std::max<std::uint64_t>(v, 1), 0.0 });
      p.structures.push_back({ "file scatter: triangles", 12, std::max<std::uint64_t>(f, 1), 0.0 });
      p.structures.push_back({ "file scatter: vertex map", 4, std::max<std::uint64_t>(v, 1), 0.0 });
      this->dml_.Config(p);
    });
    this->read_ = FileSource(path)(this->mesh_, io::ReadOptions{});
    const std::uint64_t V = this->mesh_.VertexCount();
    this->map_ = Array<std::uint32_t>(this->dml_, std::max<std::uint64_t>(V, 1));
    const std::uint32_t zero = 0;
    this->dml_.Fill(this->map_.Id(), &zero);
  }

  const io::ReadStats& ReadStats() const { return this->read_; }

  // Appends the next records to send[r] until about `limit` bytes are pending in all; false
  // once every rank's piece has gone.
  bool Fill(std::vector<std::vector<std::uint8_t>>& send, std::size_t limit)
  {
    const io::VertexLayout& L = this->mesh_.PointLayout();
    // (a record at most half the round's bytes, whatever the point data)
    const std::size_t stride = this->mesh_.Stride();
    const std::size_t window =
      std::clamp<std::size_t>(limit / (2 * (12 + 4 * stride)), 1, kWindow);
    std::size_t pending = 0;
    for (const auto& b : send)
    {
      pending += b.size();
    }
    while (this->rank_ < this->ranks_ && pending < limit)
    {
      std::vector<std::uint8_t>& out = send[std::size_t(this->rank_)];
      const std::size_t before = out.size();
      if (this->phase_ == Phase::Start)
      {
        this->Start();
        Rounds::Put(out, std::uint8_t(kHeader));
        Rounds::Put(out, this->pieceVertices_);
        Rounds::Put(out, this->count_);
        // (the file's repairs are reported once, with rank 0's piece)
        Rounds::Put(out, this->rank_ == 0 ? this->read_.droppedFaces : std::uint64_t(0));
        Rounds::Put(out, std::uint8_t(this->mesh_.Format()));
        Rounds::Put(out, std::uint8_t(L.normals));
        Rounds::Put(out, std::uint8_t(L.colors));
        Rounds::Put(out, std::uint8_t(L.texcoords));
        Rounds::Put(out, std::uint64_t(L.scalars.size()));
        for (const std::string& n : L.scalars)
        {
          Rounds::Put(out, std::uint64_t(n.size()));
          out.insert(out.end(), n.begin(), n.end());
        }
        this->phase_ = Phase::Vertices;
        this->at_ = this->lo_;
      }
      else if (this->phase_ == Phase::Vertices)
      {
        if (this->pieceVertices_ == 0 || this->at_ > this->hi_)
        {
          this->phase_ = Phase::Triangles;
          this->at_ = 0;
          continue;
        }
        const std::size_t n = std::size_t(std::min<std::uint64_t>(window, this->hi_ + 1 - this->at_));
        this->mesh_.ReadVertices(this->at_, n, this->xyz_, this->words_);
        View<std::uint32_t> map(this->dml_, this->map_);
        std::size_t picked = 0;
        for (std::size_t i = 0; i < n; ++i)
        {
          if (map.Get(this->at_ + i))
          {
            // (pointers, not elements: without point data words_ is empty and stride 0)
            std::copy_n(this->xyz_.data() + 3 * i, 3, this->xyz_.data() + 3 * picked);
            std::copy_n(this->words_.data() + stride * i, stride, this->words_.data() + stride * picked);
            ++picked;
          }
        }
        this->at_ += n;
        if (picked)
        {
          Rounds::Put(out, std::uint8_t(kVertices));
          Rounds::Put(out, std::uint64_t(picked));
          const auto* x = reinterpret_cast<const std::uint8_t*>(this->xyz_.data());
          out.insert(out.end(), x, x + 12 * picked);
          const auto* w = reinterpret_cast<const std::uint8_t*>(this->words_.data());
          out.insert(out.end(), w, w + 4 * stride * picked);
        }
      }
      else
      {
        if (this->at_ == this->count_)
        {
          Rounds::Put(out, std::uint8_t(kEnd));
          this->Clear();
          this->phase_ = Phase::Start;
          ++this->rank_;
          pending += out.size() - before;
          continue;
        }
        const std::size_t n = std::size_t(std::min<std::uint64_t>(window, this->count_ - this->at_));
        this->tris_.resize(3 * n);
        this->mesh_.ReadTriangles(this->first_ + this->at_, n, this->tris_.data());
        View<std::uint32_t> map(this->dml_, this->map_);
        for (std::uint32_t& v : this->tris_)
        {
          v = map.Get(v) - 1;
        }
        this->at_ += n;
        Rounds::Put(out, std::uint8_t(kTriangles));
        Rounds::Put(out, std::uint64_t(n));
        const auto* t = reinterpret_cast<const std::uint8_t*>(this->tris_.data());
        out.insert(out.end(), t, t + 12 * n);
      }
      pending += out.size() - before;
    }
    return this->rank_ < this->ranks_;
  }

private:
  static constexpr std::size_t kWindow = std::size_t(1) << 14; // vertices or faces a record
  enum class Phase
  {
    Start,
    Vertices,
    Triangles
  };
  // Rank rank_'s faces: marks the vertices they use in the map, then numbers them in the
  // file's order (the map holds the piece's number plus one).
  void Start()
  {
    const std::uint64_t F = this->mesh_.TriangleCount();
    this->first_ = F * std::uint64_t(this->rank_) / std::uint64_t(this->ranks_);
    this->count_ = F * std::uint64_t(this->rank_ + 1) / std::uint64_t(this->ranks_) - this->first_;
    this->lo_ = std::numeric_limits<std::uint64_t>::max();
    this->hi_ = 0;
    this->pieceVertices_ = 0;
    View<std::uint32_t> map(this->dml_, this->map_);
    for (std::uint64_t f = 0; f < this->count_; f += kWindow)
    {
      const std::size_t n = std::size_t(std::min<std::uint64_t>(kWindow, this->count_ - f));
      this->tris_.resize(3 * n);
      this->mesh_.ReadTriangles(this->first_ + f, n, this->tris_.data());
      for (std::uint32_t v : this->tris_)
      {
        map.Set(v, 1);
        this->lo_ = std::min<std::uint64_t>(this->lo_, v);
        this->hi_ = std::max<std::uint64_t>(this->hi_, v);
      }
    }
    if (this->count_ == 0)
    {
      return;
    }
    std::uint32_t next = 0;
    for (std::uint64_t i = this->lo_; i <= this->hi_; ++i)
    {
      if (map.Get(i))
      {
        map.Set(i, ++next);
      }
    }
    this->pieceVertices_ = next;
  }

  void Clear()
  {
    if (this->pieceVertices_ == 0)
    {
      return;
    }
    View<std::uint32_t> map(this->dml_, this->map_);
    for (std::uint64_t i = this->lo_; i <= this->hi_; ++i)
    {
      map.Set(i, 0);
    }
  }

  storage::Profile profile_;
  int ranks_;
  storage::DML dml_;
  detail::StoredMesh mesh_{ dml_ };
  io::ReadStats read_;
  Array<std::uint32_t> map_;
  int rank_ = 0;
  Phase phase_ = Phase::Start;
  std::uint64_t first_ = 0, count_ = 0, lo_ = 0, hi_ = 0, at_ = 0, pieceVertices_ = 0;
  std::vector<float> xyz_;
  std::vector<std::uint32_t> words_, tris_;
};
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
  // A file that cannot be read by byte ranges: rank 0 reads it and sends every rank its piece,
  // kept here (the faces [F r / N, F (r + 1) / N) and the vertices they use).
  bool scattered = false;
  std::unique_ptr<detail::StoredMesh> stored;
  std::uint64_t storedVertices = 0, dropped = 0;
  bool ended = false;
  CommunicationStats traffic;

  void Scatter(const std::string& path, Communicator& comm, const storage::Profile& profile,
    Progress& progress)
  {
    this->scattered = true;
    Rounds rounds(comm, detail::RoundBytes(profile), this->traffic);
    std::optional<ScatterSender> sender;
    bool more = false;
    if (comm.Rank() == 0)
    {
      rounds.Local([&] {
        sender.emplace(profile, comm.Size());
        sender->Read(path, progress);
        this->bytes += sender->ReadStats().bytes;
        more = true;
      });
    }
    bool read = false; // (past the first agreement: rank 0 has read the file)
    try
    {
      while (rounds.Continue(more) && (read = true))
      {
        rounds.Local([&] {
          if (progress.Aborted())
          {
            throw AbortedError();
          }
          if (sender)
          {
            more = sender->Fill(rounds.send, rounds.Limit());
          }
        });
        more = more && !rounds.Failed();
        rounds.Exchange();
        rounds.Local([&] { this->Take(rounds.received[0], profile); });
      }
    }
    catch (const std::exception&)
    {
      if (rounds.Failed())
      {
        throw; // (this rank's own error)
      }
      throw std::runtime_error(path +
        (read ? ": rank 0 could not send the ranks their pieces, or a rank could not keep its "
                "piece (its error is in its own output)"
              : ": rank 0 could not read the file (its error is in its own output)"));
    }
    if (!this->ended)
    {
      throw std::runtime_error(this->name + ": rank 0's messages ended before the piece did");
    }
    this->dml.Reconfigure();
  }

  // A message of the scatter: records from rank 0.
  void Take(const std::vector<std::uint8_t>& message, const storage::Profile& profile)
  {
    const std::uint8_t* p = message.data();
    const std::uint8_t* const end = p + message.size();
    const auto need = [&](std::uint64_t n) {
      if (std::uint64_t(end - p) < n)
      {
        throw std::runtime_error(this->name + ": a malformed message from rank 0");
      }
    };
    std::vector<float> xyz;
    std::vector<std::uint32_t> words;
    detail::PointDataBuffers buffers;
    while (p < end)
    {
      const auto kind = Rounds::Take<std::uint8_t>(p);
      if (kind == kHeader && !this->stored)
      {
        need(3 * 8 + 4 + 8);
        io::MeshHeader h;
        h.vertexCount = Rounds::Take<std::uint64_t>(p);
        h.faceCount = Rounds::Take<std::uint64_t>(p);
        this->dropped = Rounds::Take<std::uint64_t>(p);
        h.format = io::Format(Rounds::Take<std::uint8_t>(p));
        h.layout.normals = Rounds::Take<std::uint8_t>(p) != 0;
        h.layout.colors = Rounds::Take<std::uint8_t>(p) != 0;
        h.layout.texcoords = Rounds::Take<std::uint8_t>(p) != 0;
        const auto k = Rounds::Take<std::uint64_t>(p);
        for (std::uint64_t i = 0; i < k; ++i)
        {
          need(8);
          const auto len = Rounds::Take<std::uint64_t>(p);
          need(len);
          h.layout.scalars.emplace_back(reinterpret_cast<const char*>(p), std::size_t(len));
          p += len;
        }
        this->count = h.faceCount;
        this->vertexCount = h.vertexCount;
        storage::Profile pp = profile;
        const std::uint64_t V = std::max<std::uint64_t>(h.vertexCount, 1);
        pp.structures.push_back({ "file piece: points", 12, V, 0.0 });
        if (const std::size_t stride = detail::PointDataWords(h.layout))
        {
          pp.structures.push_back({ "file piece: point data", 4 * stride, V, 0.0 });
        }
        pp.structures.push_back(
          { "file piece: triangles", 12, std::max<std::uint64_t>(h.faceCount, 1), 0.0 });
        this->dml.Config(pp);
        this->stored = std::make_unique<detail::StoredMesh>(this->dml);
        this->stored->Begin(h);
      }
      else if (kind == kVertices && this->stored && !this->ended)
      {
        need(8);
        const auto n = Rounds::Take<std::uint64_t>(p);
        const std::size_t stride = this->stored->Stride();
        need(n * (12 + 4 * stride));
        if (this->storedVertices + n > this->vertexCount)
        {
          throw std::runtime_error(this->name + ": more vertices from rank 0 than announced");
        }
        xyz.resize(3 * n);
        std::memcpy(xyz.data(), p, 12 * n);
        p += 12 * n;
        io::VertexChunk c;
        c.first = this->storedVertices;
        c.count = std::size_t(n);
        c.xyz = xyz.data();
        if (stride)
        {
          words.resize(stride * n);
          std::memcpy(words.data(), p, 4 * stride * n);
          p += 4 * stride * n;
          buffers.Unpack(words.data(), c.count, this->stored->PointLayout(), stride, c);
        }
        this->stored->Vertices(c);
        this->storedVertices += n;
      }
      else if (kind == kTriangles && this->stored && !this->ended)
      {
        need(8);
        const auto n = Rounds::Take<std::uint64_t>(p);
        need(12 * n);
        words.resize(3 * n);
        std::memcpy(words.data(), p, 12 * n);
        p += 12 * n;
        for (std::uint32_t v : words)
        {
          if (v >= this->storedVertices)
          {
            throw std::runtime_error(this->name + ": a triangle from rank 0 before its vertices");
          }
        }
        this->stored->Triangles(words.data(), std::size_t(n));
      }
      else if (kind == kEnd && this->stored && !this->ended)
      {
        if (this->storedVertices != this->vertexCount ||
          this->stored->TriangleCount() != this->count)
        {
          throw std::runtime_error(this->name + ": rank 0 sent a piece of other sizes than announced");
        }
        io::ReadStats st;
        st.vertices = this->vertexCount;
        st.triangles = st.polygons = this->count;
        st.droppedFaces = this->dropped;
        this->stored->End(st);
        this->ended = true;
      }
      else
      {
        throw std::runtime_error(this->name + ": a malformed message from rank 0");
      }
    }
  }

  // Binary PLY: the piece's faces, and its vertices as the sorted set of the file's vertex
  // numbers they use; the faces renumbered into it. The numbers go through a dense map over the
  // range [lo, hi] the faces use (a file in scanner order: about the piece's share of the
  // vertices; a shuffled one: all of them), in this DML like the rest.
  void ReadPly(const storage::Profile& profile, Progress& progress)
  {
    storage::Profile p = profile;
    p.structures.push_back({ "file piece: faces", sizeof(Tri), std::max<std::uint64_t>(count, 1), 0.0 });
    // (the map and the vertex list, 4 bytes a number each: declared as 8 bytes a corner, the
    // size of both when every corner has a number of its own; a map over a shuffled file's whole
    // range of numbers may take more, and the DML then spills it)
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
    if (this->scattered)
    {
      return this->stored->Replay(sink, options);
    }
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
    I.Scatter(path, comm, profile, progress);
  }
}

FilePiece::~FilePiece() = default;

bool FilePiece::Split() const
{
  return this->impl_->split;
}

bool FilePiece::Scattered() const
{
  return this->impl_->scattered;
}

const CommunicationStats& FilePiece::Traffic() const
{
  return this->impl_->traffic;
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
