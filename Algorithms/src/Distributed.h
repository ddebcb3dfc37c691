// What the distributed runs share (cluster/Distributed.inl, decimate/Distributed.inl): the
// exchanges in bounded rounds with their failure protocol, the agreement on the pieces' point
// data, and the owner hash. Internal to the algorithm cores.
#pragma once

#include "sipmss/algorithms/Common.h"
#include "sipmss/algorithms/Communicator.h"
#include "sipmss/storage/Hash.h"

#include <algorithm>
#include <chrono>
#include <cstdint>
#include <cstring>
#include <exception>
#include <stdexcept>
#include <string>
#include <vector>

namespace sipmss::algorithms::detail
{
using storage::Mix; // (sipmss/storage/Hash.h: hash slots and owner ranks)

// The exchanges of a distributed run, counted and timed.
class Rounds
{
public:
  Rounds(Communicator& comm, std::size_t limit, CommunicationStats& stats)
    : comm_(comm)
    , limit_(limit)
    , stats_(stats)
    , send(std::size_t(comm.Size()))
    , received(std::size_t(comm.Size()))
  {
    stats.rank = comm.Rank();
    stats.ranks = comm.Size();
  }
  std::size_t Limit() const { return this->limit_; }
  int Owner(std::uint64_t key) const { return int(Mix(key) % std::uint64_t(this->comm_.Size())); }
  // Sends `send`, fills `received`, clears `send`.
  void Exchange()
  {
    const auto start = std::chrono::steady_clock::now();
    this->comm_.Exchange(this->send, this->received);
    this->Account(start);
    ++this->stats_.rounds;
    for (int r = 0; r < this->comm_.Size(); ++r)
    {
      if (r != this->comm_.Rank())
      {
        this->stats_.bytesSent += this->send[r].size();
        this->stats_.bytesReceived += this->received[r].size();
      }
      this->send[r].clear();
    }
  }
  std::size_t Pending() const
  {
    std::size_t n = 0;
    for (const auto& b : this->send)
    {
      n += b.size();
    }
    return n;
  }
  // Runs a rank's local work. A failure (an abort, a full disk, bad input, a malformed message)
  // is kept: the rank sends nothing more and goes on taking part in the collectives until the
  // next Continue or Agree, where every rank learns of it and throws.
  template <class F>
  void Local(F&& f)
  {
    if (this->failure_)
    {
      return;
    }
    try
    {
      f();
    }
    catch (...)
    {
      this->failure_ = std::current_exception();
      for (auto& b : this->send)
      {
        b.clear();
      }
    }
  }
  bool Failed() const { return this->failure_ != nullptr; }
  // Whether any rank has more to send; throws on every rank if one failed.
  bool Continue(bool more)
  {
    std::uint64_t v[2] = { more && !this->failure_ ? 1u : 0u, this->failure_ ? 1u : 0u };
    const auto start = std::chrono::steady_clock::now();
    this->comm_.AllReduceSum(v, 2);
    this->Account(start);
    if (v[1])
    {
      if (this->failure_)
      {
        std::rethrow_exception(this->failure_);
      }
      throw std::runtime_error("another rank failed (see its error)");
    }
    return v[0] != 0;
  }
  void Agree() { this->Continue(false); }
  void Max(double* v, std::size_t n)
  {
    const auto start = std::chrono::steady_clock::now();
    this->comm_.AllReduceMax(v, n);
    this->Account(start);
  }
  void Sum(std::uint64_t* v, std::size_t n)
  {
    const auto start = std::chrono::steady_clock::now();
    this->comm_.AllReduceSum(v, n);
    this->Account(start);
  }
  void Min(double* v, std::size_t n)
  {
    const auto start = std::chrono::steady_clock::now();
    this->comm_.AllReduceMin(v, n);
    this->Account(start);
  }
  template <class T>
  static void Put(std::vector<std::uint8_t>& b, const T& v)
  {
    const std::size_t at = b.size();
    b.resize(at + sizeof(T));
    std::memcpy(b.data() + at, &v, sizeof(T));
  }
  template <class T>
  static T Take(const std::uint8_t*& p)
  {
    T v;
    std::memcpy(&v, p, sizeof(T));
    p += sizeof(T);
    return v;
  }

private:
  void Account(std::chrono::steady_clock::time_point start)
  {
    this->stats_.seconds +=
      std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  }
  Communicator& comm_;
  std::size_t limit_;
  CommunicationStats& stats_;
  std::exception_ptr failure_;

public:
  std::vector<std::vector<std::uint8_t>> send, received;
};

// Forwards a read to `inner`, recording the header's layout and giving `inner` another one when
// `layout` is set (a rank whose piece is empty takes the layout the others agreed on).
class LayoutSink final : public io::MeshSink
{
public:
  LayoutSink(io::MeshSink& inner, const io::VertexLayout* layout)
    : inner_(inner)
    , layout_(layout)
  {
  }
  const io::VertexLayout& Seen() const { return this->seen_; }
  void Begin(const io::MeshHeader& h) override
  {
    this->seen_ = h.layout;
    io::MeshHeader g = h;
    if (this->layout_)
    {
      g.layout = *this->layout_;
    }
    this->inner_.Begin(g);
  }
  void Vertices(const io::VertexChunk& c) override { this->inner_.Vertices(c); }
  void Triangles(const std::uint32_t* i, std::size_t n) override { this->inner_.Triangles(i, n); }
  void TriangleFlags(const std::uint8_t* f, std::size_t n) override
  {
    this->inner_.TriangleFlags(f, n);
  }
  void End(const io::ReadStats& s) override { this->inner_.End(s); }
  bool AbortRequested() override { return this->inner_.AbortRequested(); }

private:
  io::MeshSink& inner_;
  const io::VertexLayout* layout_;
  io::VertexLayout seen_;
};

inline std::string Describe(const io::VertexLayout& l)
{
  std::string s;
  auto add = [&s](const std::string& name) { s += (s.empty() ? "" : ", ") + name; };
  if (l.normals)
  {
    add("normals");
  }
  if (l.colors)
  {
    add("colours");
  }
  if (l.texcoords)
  {
    add("texture coordinates");
  }
  for (const auto& n : l.scalars)
  {
    add(n);
  }
  return s.empty() ? "no point data" : s;
}

// The point data every rank's piece carries: the first non-empty piece's. A non-empty piece with
// other point data is an error (the same words on every rank); an empty piece takes it.
// The attribute list goes with it: a rank turns the names of its arrays into the core's keywords
// (the filters' CoreAttributeNames), which an empty piece cannot.
inline io::VertexLayout AgreeOnLayout(const io::VertexLayout& mine, std::uint64_t vertices,
  std::string& attributes, Rounds& rounds)
{
  std::vector<std::uint8_t> me;
  Rounds::Put(me, std::uint64_t(attributes.size()));
  me.insert(me.end(), attributes.begin(), attributes.end());
  Rounds::Put(me, vertices);
  Rounds::Put(me, std::uint8_t(mine.normals));
  Rounds::Put(me, std::uint8_t(mine.colors));
  Rounds::Put(me, std::uint8_t(mine.texcoords));
  Rounds::Put(me, std::uint64_t(mine.scalars.size()));
  for (const auto& n : mine.scalars)
  {
    Rounds::Put(me, std::uint64_t(n.size()));
    me.insert(me.end(), n.begin(), n.end());
  }
  for (auto& b : rounds.send)
  {
    b = me;
  }
  rounds.Exchange();
  int chosen = -1;
  io::VertexLayout agreed;
  std::string agreedAttributes;
  for (std::size_t r = 0; r < rounds.received.size(); ++r)
  {
    const std::uint8_t* p = rounds.received[r].data();
    const std::uint64_t alen = Rounds::Take<std::uint64_t>(p);
    const std::string a(reinterpret_cast<const char*>(p), alen);
    p += alen;
    const std::uint64_t n = Rounds::Take<std::uint64_t>(p);
    io::VertexLayout l;
    l.normals = Rounds::Take<std::uint8_t>(p) != 0;
    l.colors = Rounds::Take<std::uint8_t>(p) != 0;
    l.texcoords = Rounds::Take<std::uint8_t>(p) != 0;
    const std::uint64_t k = Rounds::Take<std::uint64_t>(p);
    for (std::uint64_t i = 0; i < k; ++i)
    {
      const std::uint64_t len = Rounds::Take<std::uint64_t>(p);
      l.scalars.emplace_back(reinterpret_cast<const char*>(p), len);
      p += len;
    }
    if (!n)
    {
      continue;
    }
    if (chosen < 0)
    {
      chosen = int(r);
      agreed = l;
      agreedAttributes = a;
    }
    else if (l.normals != agreed.normals || l.colors != agreed.colors ||
      l.texcoords != agreed.texcoords || l.scalars != agreed.scalars)
    {
      throw std::runtime_error("the pieces carry different point data: rank " +
        std::to_string(chosen) + "'s has " + Describe(agreed) + ", rank " + std::to_string(r) +
        "'s has " + Describe(l));
    }
    else if (a != agreedAttributes)
    {
      throw std::runtime_error("the ranks name different attributes: rank " +
        std::to_string(chosen) + " \"" + agreedAttributes + "\", rank " + std::to_string(r) +
        " \"" + a + "\"");
    }
  }
  if (chosen >= 0)
  {
    attributes = agreedAttributes;
    return agreed;
  }
  return mine;
}

// The exchanges' round size: a sixteenth of the budget, from 256 KiB to 16 MiB.
inline std::size_t RoundBytes(const storage::Profile& profile)
{
  const std::uint64_t budget = profile.memoryBudget;
  constexpr std::uint64_t lo = 256 << 10, hi = 16 << 20;
  return std::size_t(budget ? std::clamp<std::uint64_t>(budget / 16, lo, hi) : hi);
}
} // namespace sipmss::algorithms::detail
