// Streaming STL readers (binary and ASCII). Every facet delivers 3 fresh vertices and the
// triangle (3i, 3i+1, 3i+2); facet normals are not delivered (the layout is empty).
#include "MeshIODetail.h"

#include <algorithm>

namespace sipmss::io::detail
{
namespace
{

bool KeywordIs(std::string_view tok, std::string_view kw)
{
  if (tok.size() != kw.size())
    return false;
  for (std::size_t i = 0; i < tok.size(); ++i)
  {
    char c = tok[i];
    if (c >= 'A' && c <= 'Z')
      c = char(c - 'A' + 'a');
    if (c != kw[i])
      return false;
  }
  return true;
}

std::string Printable(std::string_view s)
{
  std::string out(s.substr(0, 40));
  for (char& c : out)
    if (static_cast<unsigned char>(c) < 0x20 || static_cast<unsigned char>(c) >= 0x7f)
      c = '?';
  return out;
}

} // namespace

ReadStats ReadStlBinary(Input& in, MeshSink& sink, const ReadOptions& options)
{
  in.text = false;
  in.context = "header";
  if (!in.Ensure(84))
    in.FailAtByte("is truncated: a binary STL starts with an 84-byte header", in.Offset(in.e));
  const auto* b = reinterpret_cast<const unsigned char*>(in.p) + 80;
  const std::uint64_t n = std::uint64_t(b[0]) | std::uint64_t(b[1]) << 8 |
    std::uint64_t(b[2]) << 16 | std::uint64_t(b[3]) << 24;
  in.p += 84;
  in.context = "facet";
  if (3 * n > kMaxVertices)
    in.FailAtByte("count " + std::to_string(n) + " is too many vertices for 32-bit indices", 80);
  const Source& src = in.Src();
  if (src.sizeKnown && 50 * n > src.size - std::min<std::uint64_t>(src.size, 84))
    in.FailAtByte("count " + std::to_string(n) + " is larger than the file allows (needs " +
        std::to_string(84 + 50 * n) + " bytes, the file has " + std::to_string(src.size) + ")",
      80);
  // A count smaller than the data would silently lose the facets after it.
  if (src.sizeKnown && 84 + 50 * n < src.size)
  {
    const std::uint64_t extra = src.size - 84 - 50 * n;
    in.FailAtByte("count " + std::to_string(n) + " is smaller than the file: " +
        std::to_string(extra) + " bytes follow the " + std::to_string(n) + " facets it announces" +
        (extra % 50 == 0 ? " (the file holds " + std::to_string((src.size - 84) / 50) + " facets)"
                         : std::string(" (not a whole number of 50-byte facets)")),
      80);
  }

  MeshHeader mh;
  mh.format = Format::StlBinary; // counts: 0 = unknown (see MeshHeader)
  sink.Begin(mh);

  const std::size_t fc = ClampChunk(std::max<std::size_t>(1, options.chunkElements / 3), 48, n);
  VertexBuffer vb;
  vb.Init(VertexLayout{}, 3 * fc, 0);
  TriangleBuffer tb;
  tb.Init(fc, 0);
  const bool swap = !HostIsLittleEndian();

  std::uint64_t remaining = n;
  while (remaining)
  {
    if (vb.capacity - vb.n < 3 || tb.Full())
    {
      vb.Flush(sink, in);
      tb.Flush(sink, in);
    }
    in.Need(50);
    const std::size_t m = std::size_t(std::min<std::uint64_t>(
      { in.Avail() / 50, remaining, std::uint64_t((vb.capacity - vb.n) / 3), std::uint64_t(tb.capacity - tb.n) }));
    const char* s = in.p;
    float* xyz = vb.xyz.data() + 3 * vb.n;
    for (std::size_t j = 0; j < m; ++j)
      std::memcpy(xyz + 9 * j, s + 50 * j + 12, 36);
    if (swap)
      for (std::size_t k = 0; k < 9 * m; ++k)
      {
        std::uint32_t u;
        std::memcpy(&u, xyz + k, 4);
        u = __builtin_bswap32(u);
        std::memcpy(xyz + k, &u, 4);
      }
    if (!AllFinite(xyz, 9 * m))
      for (std::size_t j = 0; j < m; ++j)
        if (!AllFinite(xyz + 9 * j, 9))
          in.FailAtByte("#" + std::to_string(n - remaining + j) +
              " has a non-finite coordinate (NaN or Inf)",
            in.Offset(s + 50 * j));
    if (!options.verticesOnly)
    {
      std::uint32_t base = std::uint32_t(vb.first + vb.n);
      for (std::size_t j = 0; j < m; ++j, base += 3)
        tb.Add(base, base + 1, base + 2);
    }
    vb.n += 3 * m;
    in.p += 50 * m;
    remaining -= m;
  }
  // Size unknown up front (gzip, a pipe): data after the announced facets is the same mismatch.
  if (!src.sizeKnown && in.Ensure(1))
    in.FailAtByte("count " + std::to_string(n) + " is smaller than the data: more bytes follow the " +
        std::to_string(n) + " facets it announces",
      80);
  return Finish(in, sink, vb, tb, options.verticesOnly ? 0 : n);
}

ReadStats ReadStlAscii(Input& in, MeshSink& sink, const ReadOptions& options)
{
  in.text = true;
  in.context = "solid";
  MeshHeader mh;
  mh.format = Format::StlAscii;

  if (!in.SkipSpace())
    in.FailAtLine("is empty: an ASCII STL starts with 'solid'");
  if (in.Avail() >= 3 && static_cast<unsigned char>(in.p[0]) == 0xEF &&
    static_cast<unsigned char>(in.p[1]) == 0xBB && static_cast<unsigned char>(in.p[2]) == 0xBF)
  {
    in.p += 3;
    in.SkipSpace();
  }
  if (!KeywordIs(in.PeekToken(), "solid"))
    in.FailAtLine("does not start with 'solid'");
  in.SkipLine(); // the solid's name
  sink.Begin(mh);

  VertexBuffer vb;
  vb.Init(VertexLayout{}, options.chunkElements, 0);
  TriangleBuffer tb;
  tb.Init(options.chunkElements, 0);
  tb.dropDegenerate = false; // fresh vertices: never repeated
  std::uint64_t polygons = 0;

  auto expect = [&](const char* kw) {
    if (!in.SkipSpace())
      in.FailAtLine(std::string("is truncated (expected '") + kw + "')");
    if (!KeywordIs(in.PeekToken(), kw))
      in.FailAtLine(std::string("has '") + Printable(in.PeekToken()) + "' where '" + kw + "' belongs");
    in.p += in.PeekToken().size();
  };
  auto commit = [&](const float* v) -> std::uint32_t {
    if (vb.first + vb.n >= kMaxVertices)
      in.FailAtLine("has too many vertices for 32-bit indices");
    if (vb.Full())
      vb.Flush(sink, in);
    std::memcpy(vb.xyz.data() + 3 * vb.n, v, 12);
    return std::uint32_t(vb.first + vb.n++);
  };
  auto addTri = [&](std::uint32_t a, std::uint32_t b, std::uint32_t c) {
    if (options.verticesOnly)
      return;
    if (tb.Full())
    {
      vb.Flush(sink, in);
      tb.Flush(sink, in);
    }
    tb.Add(a, b, c);
  };

  for (;;)
  {
    in.context = "solid";
    if (!in.SkipSpace())
      break; // end of input between facets (a missing endsolid is tolerated)
    const std::string_view tok = in.PeekToken();
    if (KeywordIs(tok, "endsolid") || KeywordIs(tok, "solid"))
    {
      in.SkipLine();
      continue;
    }
    if (!KeywordIs(tok, "facet"))
      in.FailAtLine("has an unexpected keyword '" + Printable(tok) + "'");
    in.context = "facet";
    in.SkipLine(); // "normal nx ny nz": facet normals are recomputed by whoever needs them
    expect("outer");
    expect("loop");
    float pending[9];
    std::uint64_t nv = 0;
    std::uint32_t first = 0, prev = 0;
    for (;;)
    {
      if (!in.SkipSpace())
        in.FailAtLine("is truncated (expected 'vertex' or 'endloop')");
      const std::string_view t = in.PeekToken();
      if (KeywordIs(t, "endloop"))
      {
        in.p += t.size();
        break;
      }
      if (!KeywordIs(t, "vertex"))
        in.FailAtLine("has '" + Printable(t) + "' where 'vertex' or 'endloop' belongs");
      in.p += t.size();
      float v[3];
      for (int k = 0; k < 3; ++k)
      {
        if (!in.SkipBlanks())
          in.FailAtLine("has a vertex with fewer than 3 coordinates");
        v[k] = in.ParseFloatToken<float>("a vertex coordinate");
      }
      if (!AllFinite(v, 3))
        in.FailAtLine("has a non-finite coordinate (NaN or Inf)");
      in.EndOfRecord("has a vertex with more than 3 coordinates");
      if (nv < 3)
      {
        std::memcpy(pending + 3 * nv, v, 12);
        if (nv == 2)
        {
          first = commit(pending);
          const std::uint32_t b = commit(pending + 3);
          prev = commit(pending + 6);
          addTri(first, b, prev);
        }
      }
      else
      {
        const std::uint32_t c = commit(v);
        addTri(first, prev, c);
        prev = c;
      }
      ++nv;
    }
    expect("endfacet");
    if (nv < 3)
      ++tb.dropped; // its vertices were never delivered
    ++polygons;
  }
  return Finish(in, sink, vb, tb, options.verticesOnly ? 0 : polygons);
}

} // namespace sipmss::io::detail
