// Prefetched(): the same calls in the same order, reader errors rethrown, consumer errors stop
// the reader.
#include "sipmss/algorithms/Prefetch.h"

#include <gtest/gtest.h>

#include <atomic>

using namespace sipmss;
using namespace sipmss::algorithms;

namespace
{
// A source of `chunks` vertex chunks and triangle chunks; throws at chunk `failAt` if >= 0.
MeshSource Counting(int chunks, int failAt, std::atomic<int>* produced)
{
  return [=](io::MeshSink& sink, const io::ReadOptions&) {
    io::MeshHeader h;
    h.vertexCount = std::uint64_t(chunks) * 3;
    h.layout.scalars = { "s" };
    sink.Begin(h);
    io::ReadStats st;
    for (int i = 0; i < chunks; ++i)
    {
      if (i == failAt)
      {
        throw io::MeshIOError("reader failed at chunk " + std::to_string(i));
      }
      if (sink.AbortRequested())
      {
        throw io::MeshIOError("aborted");
      }
      float xyz[9] = { float(i), 0, 0, 0, float(i), 0, 0, 0, float(i) };
      float s[3] = { float(i), float(i) + 0.5f, float(i) + 0.25f };
      io::VertexChunk c;
      c.first = std::uint64_t(i) * 3;
      c.count = 3;
      c.xyz = xyz;
      c.scalars = s;
      sink.Vertices(c);
      std::uint32_t t[3] = { std::uint32_t(3 * i), std::uint32_t(3 * i + 1), std::uint32_t(3 * i + 2) };
      sink.Triangles(t, 1);
      const std::uint8_t flag = std::uint8_t(i % 3 == 0);
      sink.TriangleFlags(&flag, 1);
      ++*produced;
    }
    st.vertices = h.vertexCount;
    st.triangles = std::uint64_t(chunks);
    sink.End(st);
    return st;
  };
}

struct Log final : io::MeshSink
{
  std::vector<float> xyz, s;
  std::vector<std::uint32_t> t;
  int begins = 0, ends = 0;
  int throwAfter = -1;
  void Begin(const io::MeshHeader&) override { ++this->begins; }
  void Vertices(const io::VertexChunk& c) override
  {
    if (this->throwAfter >= 0 && int(this->xyz.size() / 9) == this->throwAfter)
    {
      throw std::runtime_error("sink failed");
    }
    this->xyz.insert(this->xyz.end(), c.xyz, c.xyz + 3 * c.count);
    this->s.insert(this->s.end(), c.scalars, c.scalars + c.count);
  }
  void Triangles(const std::uint32_t* i, std::size_t n) override { this->t.insert(this->t.end(), i, i + 3 * n); }
  void TriangleFlags(const std::uint8_t* f, std::size_t n) override
  {
    EXPECT_EQ(this->flags.size() + n, this->t.size() / 3); // (right after their triangles)
    this->flags.insert(this->flags.end(), f, f + n);
  }
  std::vector<std::uint8_t> flags;
  void End(const io::ReadStats&) override { ++this->ends; }
};
} // namespace

TEST(Prefetch, SameCallsInOrder)
{
  std::atomic<int> produced{ 0 };
  Log direct, prefetched;
  Counting(500, -1, &produced)(direct, {});
  const io::ReadStats st = Prefetched(Counting(500, -1, &produced), 3)(prefetched, {});
  EXPECT_EQ(st.triangles, 500u);
  EXPECT_EQ(direct.xyz, prefetched.xyz);
  EXPECT_EQ(direct.s, prefetched.s);
  EXPECT_EQ(direct.t, prefetched.t);
  EXPECT_EQ(direct.flags, prefetched.flags);
  EXPECT_EQ(prefetched.flags.size(), 500u);
  EXPECT_EQ(prefetched.begins, 1);
  EXPECT_EQ(prefetched.ends, 1);
}

TEST(Prefetch, ReaderErrorIsRethrown)
{
  std::atomic<int> produced{ 0 };
  Log sink;
  try
  {
    Prefetched(Counting(100, 40, &produced))(sink, {});
    FAIL() << "no exception";
  }
  catch (const io::MeshIOError& e)
  {
    EXPECT_NE(std::string(e.what()).find("chunk 40"), std::string::npos);
  }
}

TEST(Prefetch, SinkErrorStopsTheReader)
{
  std::atomic<int> produced{ 0 };
  Log sink;
  sink.throwAfter = 5;
  EXPECT_THROW(Prefetched(Counting(100000, -1, &produced), 2)(sink, {}), std::runtime_error);
  EXPECT_LT(produced.load(), 100000); // stopped early, and joined (no crash at exit)
}
