// Streaming OBJ reader: `v x y z [w]` and `f` (i, i/t, i//n, i/t/n; negative = relative), in
// file order. Everything else (vn, vt, g, o, s, usemtl, ...) is ignored. Line continuations
// ('\' at the end of a line) are not supported.
#include "MeshIODetail.h"

namespace sipmss::io::detail
{

ReadStats ReadObj(Input& in, MeshSink& sink, const ReadOptions& options)
{
  in.text = true;
  in.context = "line";
  MeshHeader mh;
  mh.format = Format::Obj; // counts unknown until the end
  sink.Begin(mh);

  VertexBuffer vb;
  vb.Init(VertexLayout{}, options.chunkElements, 0);
  TriangleBuffer tb;
  tb.Init(options.chunkElements, 0);
  tb.dropDegenerate = options.dropDegenerateFaces;
  std::uint64_t polygons = 0;

  if (in.Ensure(3) && static_cast<unsigned char>(in.p[0]) == 0xEF &&
    static_cast<unsigned char>(in.p[1]) == 0xBB && static_cast<unsigned char>(in.p[2]) == 0xBF)
    in.p += 3; // UTF-8 byte order mark

  Fan fan;
  while (in.SkipSpace())
  {
    const char c0 = in.p[0];
    const char c1 = in.p + 1 < in.e ? in.p[1] : '\n';
    if (c0 == 'v' && (c1 == ' ' || c1 == '\t'))
    {
      in.context = "vertex";
      ++in.p;
      float v[3];
      for (int k = 0; k < 3; ++k)
      {
        if (!in.SkipBlanks())
          in.FailAtLine("has fewer than 3 coordinates");
        v[k] = in.ParseFloatToken<float>("a coordinate");
      }
      if (!AllFinite(v, 3))
        in.FailAtLine("has a non-finite coordinate (NaN or Inf)");
      const std::uint64_t nv = vb.first + vb.n;
      if (nv >= kMaxVertices)
        in.FailAtLine("count exceeds 32-bit indices");
      if (vb.Full())
        vb.Flush(sink, in);
      std::memcpy(vb.xyz.data() + 3 * vb.n, v, 12);
      ++vb.n;
      in.SkipLine(); // optional w, or the r g b of the vertex-color extension
      continue;
    }
    // A vertices-only pass skips faces, except those before any vertex: they can only be wrong,
    // and the error names them (instead of a caller's "no vertices").
    if (c0 == 'f' && (c1 == ' ' || c1 == '\t') &&
      (!options.verticesOnly || vb.first + vb.n == 0))
    {
      in.context = "face";
      ++in.p;
      const std::uint64_t nv = vb.first + vb.n;
      fan.Start();
      while (in.SkipBlanks())
      {
        std::int64_t v = 0;
        const char* q = in.p;
        bool ok = ParseInt64(in.p, in.e, q, v);
        if (ok && q < in.e && *q == '/')
          while (q < in.e && !Input::IsSpace(*q))
            ++q; // /t, //n, /t/n
        if (!ok || !in.AtDelimiter(q))
          in.FailAtLine("has a bad vertex reference '" + std::string(in.PeekToken().substr(0, 40)) + "'");
        std::int64_t idx = v > 0 ? v - 1 : std::int64_t(nv) + v;
        if (v == 0)
          in.FailAtLine("has vertex index 0 (OBJ indices start at 1)");
        if (idx < 0 || std::uint64_t(idx) >= nv)
          in.FailAtLine("references vertex " + std::to_string(v) + ", out of range (" +
            std::to_string(nv) + " vertices defined before it)");
        in.p = q;
        std::uint32_t a, b;
        if (fan.Add(std::uint32_t(idx), a, b))
        {
          if (tb.Full())
          {
            vb.Flush(sink, in); // the triangles' vertices go first
            tb.Flush(sink, in);
          }
          tb.Add(a, b, std::uint32_t(idx));
        }
      }
      if (fan.n < 3)
        ++tb.dropped;
      ++polygons;
      in.SkipLine();
      continue;
    }
    in.SkipLine(); // comments, vn, vt, groups, materials, ...
  }
  return Finish(in, sink, vb, tb, polygons);
}

} // namespace sipmss::io::detail
