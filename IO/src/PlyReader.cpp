// Streaming PLY reader: ASCII, binary little- and big-endian; any scalar types; unknown elements
// skipped; polygons triangulated as fans. See MeshIO.h for the contract.
#include "MeshIODetail.h"

#include <algorithm>
#include <initializer_list>

#if defined(__SSE2__)
#include <emmintrin.h>
#endif

namespace sipmss::io::detail
{
namespace
{

constexpr std::uint64_t kMaxHeaderBytes = 1u << 20;

enum class PT : std::uint8_t
{
  I8,
  U8,
  I16,
  U16,
  I32,
  U32,
  F32,
  F64
};

constexpr std::size_t TypeSize(PT t)
{
  constexpr std::size_t s[] = { 1, 1, 2, 2, 4, 4, 4, 8 };
  return s[int(t)];
}
constexpr bool IsInteger(PT t) { return t <= PT::U32; }

// The range of an integer type, and its PLY name (for errors).
struct IntRange
{
  std::int64_t lo, hi;
  const char* name;
};
constexpr IntRange kIntRanges[] = { { -128, 127, "char" }, { 0, 255, "uchar" },
  { -32768, 32767, "short" }, { 0, 65535, "ushort" }, { -2147483648LL, 2147483647LL, "int" },
  { 0, 4294967295LL, "uint" } };
inline const IntRange& RangeOf(PT t) { return kIntRanges[int(t) <= int(PT::U32) ? int(t) : 0]; }

bool ParseTypeName(std::string_view s, PT& t)
{
  static const struct
  {
    const char* name;
    PT type;
  } kNames[] = { { "char", PT::I8 }, { "int8", PT::I8 }, { "uchar", PT::U8 }, { "uint8", PT::U8 },
    { "short", PT::I16 }, { "int16", PT::I16 }, { "ushort", PT::U16 }, { "uint16", PT::U16 },
    { "int", PT::I32 }, { "int32", PT::I32 }, { "uint", PT::U32 }, { "uint32", PT::U32 },
    { "float", PT::F32 }, { "float32", PT::F32 }, { "double", PT::F64 }, { "float64", PT::F64 } };
  for (const auto& n : kNames)
    if (s == n.name)
    {
      t = n.type;
      return true;
    }
  return false;
}

struct Prop
{
  std::string name;
  bool list = false;
  PT type = PT::F32;     // the value type (the item type for lists)
  PT countType = PT::U8; // lists only
};

struct Elem
{
  std::string name;
  std::uint64_t count = 0;
  std::uint64_t line = 0; // header line declaring it
  std::vector<Prop> props;
  bool HasLists() const
  {
    for (const Prop& p : props)
      if (p.list)
        return true;
    return false;
  }
  std::size_t FixedSize() const // binary record size when there are no lists
  {
    std::size_t s = 0;
    for (const Prop& p : props)
      s += p.list ? 0 : TypeSize(p.type);
    return s;
  }
  std::size_t MinBinarySize() const
  {
    std::size_t s = 0;
    for (const Prop& p : props)
      s += TypeSize(p.list ? p.countType : p.type);
    return s;
  }
};

// Where a vertex property goes.
enum : std::uint8_t
{
  kArrXyz,
  kArrNormals,
  kArrTex,
  kArrScalars,
  kArrRgba,
  kArrNone
};

struct Target
{
  std::uint8_t arr = kArrNone;
  std::uint32_t comp = 0;
};

struct Header
{
  Format format = Format::Unknown;
  std::vector<Elem> elems;
  int vertexElem = -1;
  int faceElem = -1;
  int faceList = -1;           // index of vertex_indices in the face element
  std::vector<std::string> faceScalars; // the face element's numeric properties but the list
  std::vector<Target> targets; // per vertex property
  VertexLayout layout;
  std::uint64_t bodyOffset = 0;
};

std::vector<std::string_view> SplitWords(std::string_view s)
{
  std::vector<std::string_view> out;
  std::size_t i = 0;
  while (i < s.size())
  {
    while (i < s.size() && Input::IsSpace(s[i]))
      ++i;
    std::size_t j = i;
    while (j < s.size() && !Input::IsSpace(s[j]))
      ++j;
    if (j > i)
      out.push_back(s.substr(i, j - i));
    i = j;
  }
  return out;
}

std::string Printable(std::string_view s)
{
  std::string out(s.substr(0, 60));
  for (char& c : out)
    if (static_cast<unsigned char>(c) < 0x20 || static_cast<unsigned char>(c) >= 0x7f)
      c = '?';
  return out;
}

void ParseHeader(Input& in, Header& h)
{
  in.text = true;
  in.context = "header";
  std::uint64_t lineNo = in.line;
  auto fail = [&](const std::string& what) { Fail(in.Path(), "header", what, "line", lineNo); };

  std::string_view ln;
  if (!in.ReadLine(ln) || ln != "ply")
    fail("does not start with a 'ply' line");
  for (;;)
  {
    lineNo = in.line;
    if (in.Offset() > kMaxHeaderBytes)
      fail("is longer than 1 MiB (missing end_header?)");
    if (!in.ReadLine(ln))
      fail("has no end_header line");
    const std::vector<std::string_view> w = SplitWords(ln);
    if (w.empty())
      continue;
    const std::string_view kw = w[0];
    if (kw == "comment" || kw == "obj_info")
      continue;
    if (kw == "format")
    {
      if (h.format != Format::Unknown)
        fail("has a second format line");
      if (w.size() != 3)
        fail("has a bad format line '" + Printable(ln) + "'");
      if (w[1] == "ascii")
        h.format = Format::PlyAscii;
      else if (w[1] == "binary_little_endian")
        h.format = Format::PlyBinaryLE;
      else if (w[1] == "binary_big_endian")
        h.format = Format::PlyBinaryBE;
      else
        fail("has a bad format line '" + Printable(ln) + "' (unknown encoding)");
      if (w[2] != "1.0" && w[2] != "1")
        fail("has a bad format line '" + Printable(ln) + "' (unsupported version)");
      continue;
    }
    if (kw == "element")
    {
      if (h.format == Format::Unknown)
        fail("has an element before the format line");
      if (w.size() != 3)
        fail("has a bad element line '" + Printable(ln) + "'");
      Elem el;
      el.name = std::string(w[1]);
      el.line = lineNo;
      const std::string_view c = w[2];
      const std::string elName = "element '" + Printable(el.name) + "'";
      if (!c.empty() && c[0] == '-')
        Fail(in.Path(), el.name, "has a negative count " + Printable(c), "line", lineNo);
      std::int64_t v = 0;
      const char* q = nullptr;
      bool digits = !c.empty();
      for (char ch : c)
        digits = digits && unsigned(ch - '0') <= 9;
      if (!digits)
        fail(elName + " has a bad count '" + Printable(c) + "'");
      if (!ParseInt64(c.data(), c.data() + c.size(), q, v))
        Fail(in.Path(), el.name, "count " + Printable(c) + " overflows the size arithmetic", "line", lineNo);
      el.count = std::uint64_t(v);
      for (const Elem& o : h.elems)
        if (o.name == el.name)
          fail("has a second " + elName);
      if (el.name == "vertex")
        h.vertexElem = int(h.elems.size());
      else if (el.name == "face")
        h.faceElem = int(h.elems.size());
      h.elems.push_back(std::move(el));
      continue;
    }
    if (kw == "property")
    {
      if (h.elems.empty())
        fail("has a property before any element");
      Elem& el = h.elems.back();
      Prop pr;
      if (w.size() >= 2 && w[1] == "list")
      {
        if (w.size() != 5)
          fail("has a bad list property line '" + Printable(ln) + "'");
        if (!ParseTypeName(w[2], pr.countType))
          fail("has an unknown type name '" + Printable(w[2]) + "'");
        if (!ParseTypeName(w[3], pr.type))
          fail("has an unknown type name '" + Printable(w[3]) + "'");
        if (!IsInteger(pr.countType))
          fail("has a list with a non-integer count type '" + Printable(w[2]) + "'");
        pr.list = true;
        pr.name = std::string(w[4]);
      }
      else
      {
        if (w.size() != 3)
          fail("has a bad property line '" + Printable(ln) + "'");
        if (!ParseTypeName(w[1], pr.type))
          fail("has an unknown type name '" + Printable(w[1]) + "'");
        pr.name = std::string(w[2]);
      }
      for (const Prop& o : el.props)
        if (o.name == pr.name)
          fail("has a second property '" + Printable(pr.name) + "' in element '" +
            Printable(el.name) + "'");
      el.props.push_back(std::move(pr));
      continue;
    }
    if (kw == "end_header")
      break;
    fail("has an unknown keyword '" + Printable(kw) + "'");
  }
  h.bodyOffset = in.Offset();
  if (h.format == Format::Unknown)
    fail("has no format line");
  if (h.vertexElem < 0)
    fail("has no vertex element");

  // Vertex properties -> layout.
  const Elem& ve = h.elems[std::size_t(h.vertexElem)];
  if (ve.count > kMaxVertices)
    Fail(in.Path(), "vertex", "count " + std::to_string(ve.count) +
        " is too many vertices for 32-bit indices", "line", ve.line);
  h.targets.assign(ve.props.size(), Target{});
  auto find = [&](std::initializer_list<const char*> names) -> int {
    for (const char* n : names)
      for (std::size_t i = 0; i < ve.props.size(); ++i)
        if (!ve.props[i].list && ve.props[i].name == n && h.targets[i].arr == kArrNone)
          return int(i);
    return -1;
  };
  auto assign = [&](int i, std::uint8_t arr, std::uint32_t comp) {
    h.targets[std::size_t(i)].arr = arr;
    h.targets[std::size_t(i)].comp = comp;
  };
  const char* xyzNames[] = { "x", "y", "z" };
  for (std::uint32_t k = 0; k < 3; ++k)
  {
    const int i = find({ xyzNames[k] });
    if (i < 0)
      Fail(in.Path(), "vertex", std::string("has no scalar property '") + xyzNames[k] + "'", "line", ve.line);
    assign(i, kArrXyz, k);
  }
  {
    const int nx = find({ "nx" }), ny = find({ "ny" }), nz = find({ "nz" });
    if (nx >= 0 && ny >= 0 && nz >= 0)
    {
      assign(nx, kArrNormals, 0);
      assign(ny, kArrNormals, 1);
      assign(nz, kArrNormals, 2);
      h.layout.normals = true;
    }
  }
  {
    const int r = find({ "red", "diffuse_red" }), g = find({ "green", "diffuse_green" }),
              b = find({ "blue", "diffuse_blue" });
    if (r >= 0 && g >= 0 && b >= 0)
    {
      assign(r, kArrRgba, 0);
      assign(g, kArrRgba, 1);
      assign(b, kArrRgba, 2);
      const int a = find({ "alpha", "diffuse_alpha" });
      if (a >= 0)
        assign(a, kArrRgba, 3);
      h.layout.colors = true;
    }
  }
  {
    static const char* const kPairs[][2] = { { "u", "v" }, { "s", "t" }, { "texture_u", "texture_v" },
      { "texture_s", "texture_t" } };
    for (const auto& pair : kPairs)
    {
      const int u = find({ pair[0] }), v = find({ pair[1] });
      if (u >= 0 && v >= 0)
      {
        assign(u, kArrTex, 0);
        assign(v, kArrTex, 1);
        h.layout.texcoords = true;
        break;
      }
    }
  }
  for (std::size_t i = 0; i < ve.props.size(); ++i)
    if (!ve.props[i].list && h.targets[i].arr == kArrNone)
    {
      h.targets[i].arr = kArrScalars;
      h.targets[i].comp = std::uint32_t(h.layout.scalars.size());
      h.layout.scalars.push_back(ve.props[i].name);
    }

  if (h.faceElem >= 0)
  {
    const Elem& fe = h.elems[std::size_t(h.faceElem)];
    for (std::size_t i = 0; i < fe.props.size(); ++i)
      if (fe.props[i].list && (fe.props[i].name == "vertex_indices" || fe.props[i].name == "vertex_index"))
      {
        h.faceList = int(i);
        break;
      }
    if (h.faceList < 0)
      Fail(in.Path(), "face", "has no 'vertex_indices' list property", "line", fe.line);
    if (!IsInteger(fe.props[std::size_t(h.faceList)].type))
      Fail(in.Path(), "face", "has a non-integer vertex_indices type", "line", fe.line);
    for (const Prop& p : fe.props)
      if (!p.list)
        h.faceScalars.push_back(p.name);
  }
}

// Counts against the size arithmetic (always) and the input size (when known).
void CheckSizes(Input& in, const Header& h)
{
  const bool ascii = h.format == Format::PlyAscii;
  const Source& src = in.Src();
  std::uint64_t remaining = 0;
  if (src.sizeKnown)
    remaining = src.size > h.bodyOffset ? src.size - h.bodyOffset : 0;
  if (ascii)
    ++remaining; // the last record may lack its newline
  std::uint64_t at = h.bodyOffset;
  for (const Elem& el : h.elems)
  {
    const std::uint64_t minRecord = el.props.empty() ? 0 : ascii ? 2 : el.MinBinarySize();
    auto fail = [&](const std::string& what) {
      if (ascii)
        Fail(in.Path(), el.name, what, "line", el.line);
      Fail(in.Path(), el.name, what, "byte", at);
    };
    if (minRecord && el.count > std::numeric_limits<std::uint64_t>::max() / minRecord)
      fail("count " + std::to_string(el.count) + " overflows the size arithmetic");
    const std::uint64_t need = el.count * minRecord;
    if (src.sizeKnown && need > remaining)
      fail("count " + std::to_string(el.count) + " is larger than the file allows (needs at least " +
        std::to_string(need) + " bytes, " + std::to_string(ascii ? remaining - 1 : remaining) +
        " remain)");
    if (src.sizeKnown)
      remaining -= need;
    at += need;
    if (at < need)
      fail("count " + std::to_string(el.count) + " overflows the size arithmetic");
  }
}

// ---------------------------------------------------------------------------------------------
template <class T>
inline T Load(const char* p, bool swap)
{
  T v;
  std::memcpy(&v, p, sizeof(T));
  if constexpr (sizeof(T) == 1)
    return v;
  else
  {
    if (swap)
    {
      if constexpr (sizeof(T) == 2)
      {
        std::uint16_t u;
        std::memcpy(&u, &v, 2);
        u = __builtin_bswap16(u);
        std::memcpy(&v, &u, 2);
      }
      else if constexpr (sizeof(T) == 4)
      {
        std::uint32_t u;
        std::memcpy(&u, &v, 4);
        u = __builtin_bswap32(u);
        std::memcpy(&v, &u, 4);
      }
      else
      {
        std::uint64_t u;
        std::memcpy(&u, &v, 8);
        u = __builtin_bswap64(u);
        std::memcpy(&v, &u, 8);
      }
    }
    return v;
  }
}

inline std::int64_t LoadInt(const char* p, PT t, bool swap)
{
  switch (t)
  {
    case PT::I8: return Load<std::int8_t>(p, swap);
    case PT::U8: return Load<std::uint8_t>(p, swap);
    case PT::I16: return Load<std::int16_t>(p, swap);
    case PT::U16: return Load<std::uint16_t>(p, swap);
    case PT::I32: return Load<std::int32_t>(p, swap);
    case PT::U32: return Load<std::uint32_t>(p, swap);
    case PT::F32: return std::int64_t(Load<float>(p, swap)); // not reached: integers only
    case PT::F64: return std::int64_t(Load<double>(p, swap));
  }
  return 0;
}

inline double LoadReal(const char* p, PT t, bool swap)
{
  switch (t)
  {
    case PT::I8: return Load<std::int8_t>(p, swap);
    case PT::U8: return Load<std::uint8_t>(p, swap);
    case PT::I16: return Load<std::int16_t>(p, swap);
    case PT::U16: return Load<std::uint16_t>(p, swap);
    case PT::I32: return Load<std::int32_t>(p, swap);
    case PT::U32: return Load<std::uint32_t>(p, swap);
    case PT::F32: return Load<float>(p, swap);
    case PT::F64: return Load<double>(p, swap);
  }
  return 0;
}

inline std::uint8_t ToColor(double v, PT t)
{
  if (!IsInteger(t))
    v *= 255.0;
  if (!(v > 0)) // also NaN
    return 0;
  if (v >= 255)
    return 255;
  return static_cast<std::uint8_t>(IsInteger(t) ? v : v + 0.5);
}

struct VOp
{
  std::uint32_t off;
  PT type;
  std::uint8_t arr;
  std::uint32_t comp;
};

class PlyReader
{
public:
  PlyReader(Input& in, MeshSink& sink, const ReadOptions& options, Header& h)
    : in_(in)
    , sink_(sink)
    , opt_(options)
    , h_(h)
    , ascii_(h.format == Format::PlyAscii)
    , swap_((h.format == Format::PlyBinaryLE) != HostIsLittleEndian())
  {
  }

  ReadStats Run()
  {
    CheckSizes(in_, h_);
    in_.text = ascii_;
    const Elem& ve = h_.elems[std::size_t(h_.vertexElem)];
    vertexCount_ = ve.count;
    MeshHeader mh;
    mh.format = h_.format;
    mh.layout = h_.layout;
    if (!in_.Src().compressed)
    {
      mh.vertexCount = ve.count;
      mh.faceCount = h_.faceElem >= 0 ? h_.elems[std::size_t(h_.faceElem)].count : 0;
    }
    mh.faceScalars = h_.faceScalars;
    vb_.Init(h_.layout, opt_.chunkElements, ve.count);
    const bool wantFaces = h_.faceElem >= 0 && !opt_.verticesOnly;
    tb_.dropDegenerate = opt_.dropDegenerateFaces;
    if (wantFaces && !opt_.faceFlag.empty())
    {
      const Elem& fe = h_.elems[std::size_t(h_.faceElem)];
      for (std::size_t i = 0; i < fe.props.size(); ++i)
        if (!fe.props[i].list && fe.props[i].name == opt_.faceFlag)
          flagProp_ = int(i);
      tb_.withFlags = flagProp_ >= 0;
    }
    if (wantFaces)
      tb_.Init(opt_.chunkElements, h_.elems[std::size_t(h_.faceElem)].count);
    sink_.Begin(mh);

    for (std::size_t i = 0; i < h_.elems.size(); ++i)
    {
      const Elem& el = h_.elems[i];
      in_.context = el.name;
      if (int(i) == h_.vertexElem)
      {
        if (ascii_)
          AsciiVertices(el);
        else
          BinaryVertices(el);
        vb_.Flush(sink_, in_);
        if (opt_.verticesOnly)
          break;
      }
      else if (int(i) == h_.faceElem && wantFaces)
      {
        if (ascii_)
          AsciiFaces(el);
        else
          BinaryFaces(el);
        tb_.Flush(sink_, in_);
      }
      else if (ascii_)
        AsciiSkip(el);
      else
        BinarySkip(el);
    }
    return Finish(in_, sink_, vb_, tb_, polygons_);
  }

private:
  // --- vertices -------------------------------------------------------------------------------
  void BuildOps(const Elem& el, std::vector<VOp>& ops) const
  {
    std::uint32_t off = 0;
    for (std::size_t i = 0; i < el.props.size(); ++i)
    {
      const Prop& p = el.props[i];
      if (!p.list)
        ops.push_back(VOp{ off, p.type, h_.targets[i].arr, h_.targets[i].comp });
      else
        ops.push_back(VOp{ off, p.type, kArrNone, 0 });
      off += p.list ? 0 : std::uint32_t(TypeSize(p.type));
    }
  }

  void SetupArrays()
  {
    arr_[kArrXyz] = vb_.xyz.data();
    stride_[kArrXyz] = 3;
    arr_[kArrNormals] = vb_.normals.data();
    stride_[kArrNormals] = 3;
    arr_[kArrTex] = vb_.texcoords.data();
    stride_[kArrTex] = 2;
    arr_[kArrScalars] = vb_.scalars.data();
    stride_[kArrScalars] = vb_.nscalars;
  }

  void Store(std::size_t v, std::uint8_t arr, std::uint32_t comp, PT type, double val)
  {
    if (arr < kArrRgba)
      arr_[arr][v * stride_[arr] + comp] = static_cast<float>(val);
    else if (arr == kArrRgba)
      vb_.rgba[4 * v + comp] = ToColor(val, type);
  }

  [[noreturn]] void NonFinite(std::uint64_t vertex, std::uint64_t at)
  {
    const std::string what = "#" + std::to_string(vertex) + " has a non-finite coordinate (NaN or Inf)";
    if (ascii_)
      Fail(in_.Path(), "vertex", what, "line", at);
    Fail(in_.Path(), "vertex", what, "byte", at);
  }

  void BinaryVertices(const Elem& el)
  {
    SetupArrays();
    std::vector<VOp> ops;
    BuildOps(el, ops);
    const bool fixed = !el.HasLists();
    const std::size_t R = el.FixedSize();
    const bool xyzFast = fixed && !swap_ && el.props.size() >= 3 && ops[0].arr == kArrXyz &&
      ops[0].comp == 0 && ops[0].type == PT::F32 && ops[1].arr == kArrXyz && ops[1].comp == 1 &&
      ops[1].type == PT::F32 && ops[2].arr == kArrXyz && ops[2].comp == 2 && ops[2].type == PT::F32;
    std::vector<VOp> rest;
    for (std::size_t i = xyzFast ? 3 : 0; i < ops.size(); ++i)
      if (ops[i].arr != kArrNone)
        rest.push_back(ops[i]);

    std::uint64_t remaining = el.count;
    while (remaining)
    {
      if (vb_.Full())
        vb_.Flush(sink_, in_);
      if (fixed && R > 0 && R <= in_.Capacity() / 2)
      {
        in_.Need(R);
        const std::size_t n = std::size_t(std::min<std::uint64_t>(
          { in_.Avail() / R, remaining, std::uint64_t(vb_.capacity - vb_.n) }));
        const char* src = in_.p;
        const std::size_t v0 = vb_.n;
        float* xyz = vb_.xyz.data() + 3 * v0;
        if (xyzFast && R == 12)
          std::memcpy(xyz, src, 12 * n);
        else
          for (std::size_t j = 0; j < n; ++j)
          {
            const char* rec = src + j * R;
            if (xyzFast)
              std::memcpy(xyz + 3 * j, rec, 12);
            for (const VOp& op : rest)
              Store(v0 + j, op.arr, op.comp, op.type, LoadReal(rec + op.off, op.type, swap_));
          }
        if (!AllFinite(xyz, 3 * n))
          for (std::size_t j = 0; j < n; ++j)
            if (!AllFinite(xyz + 3 * j, 3))
              NonFinite(vb_.first + v0 + j, in_.Offset(src + j * R));
        in_.p += n * R;
        vb_.n += n;
        remaining -= n;
      }
      else
      {
        const std::uint64_t at = in_.Offset();
        const std::size_t v = vb_.n;
        for (std::size_t i = 0; i < el.props.size(); ++i)
        {
          const Prop& p = el.props[i];
          if (p.list)
            SkipBinaryList(p);
          else
          {
            const std::size_t sz = TypeSize(p.type);
            in_.Need(sz);
            Store(v, ops[i].arr, ops[i].comp, p.type, LoadReal(in_.p, p.type, swap_));
            in_.p += sz;
          }
        }
        if (!AllFinite(vb_.xyz.data() + 3 * v, 3))
          NonFinite(vb_.first + v, at);
        ++vb_.n;
        --remaining;
      }
    }
  }

  void AsciiVertices(const Elem& el)
  {
    SetupArrays();
    std::vector<VOp> ops;
    BuildOps(el, ops);
    std::uint64_t remaining = el.count;
    while (remaining)
    {
      if (vb_.Full())
        vb_.Flush(sink_, in_);
      if (!in_.SkipSpace())
        in_.FailAtLine("truncated: " + std::to_string(remaining) + " of " +
          std::to_string(el.count) + " records missing");
      const std::size_t v = vb_.n;
      for (std::size_t i = 0; i < el.props.size(); ++i)
      {
        const Prop& p = el.props[i];
        if (!in_.SkipBlanks())
          TooFew(p);
        if (p.list)
        {
          SkipAsciiList(p);
          continue;
        }
        Store(v, ops[i].arr, ops[i].comp, p.type, AsciiScalar(el, p));
      }
      if (!AllFinite(vb_.xyz.data() + 3 * v, 3))
        NonFinite(vb_.first + v, in_.line);
      in_.EndOfRecord();
      ++vb_.n;
      --remaining;
    }
  }

  // The next token as property p's value (an integer checked against p's type's range).
  double AsciiScalar(const Elem& el, const Prop& p)
  {
    if (p.type == PT::F32)
      return in_.ParseFloatToken<float>(p.name.c_str());
    if (p.type == PT::F64)
      return in_.ParseFloatToken<double>(p.name.c_str());
    const std::int64_t iv = in_.ParseIntToken(p.name.c_str());
    const IntRange& r = RangeOf(p.type);
    if (iv < r.lo || iv > r.hi)
      OutOfRange(el, p, iv, r);
    return double(iv);
  }

  [[noreturn]] __attribute__((noinline, cold)) void OutOfRange(
    const Elem& el, const Prop& p, std::int64_t v, const IntRange& r)
  {
    Fail(in_.Path(), el.name,
      "property '" + Printable(p.name) + "' has value " + std::to_string(v) +
        ", out of range for " + r.name + " (" + std::to_string(r.lo) + " to " +
        std::to_string(r.hi) + ")",
      "line", in_.line);
  }

  [[noreturn]] void TooFew(const Prop& p)
  {
    in_.FailAtLine("record has too few values (missing '" + Printable(p.name) + "')");
  }

  void SkipBinaryList(const Prop& p)
  {
    const std::size_t cs = TypeSize(p.countType);
    in_.Need(cs);
    const std::int64_t cnt = LoadInt(in_.p, p.countType, swap_);
    if (cnt < 0)
      in_.FailAtByte("list '" + Printable(p.name) + "' has a negative count " + std::to_string(cnt));
    in_.p += cs;
    in_.SkipBytes(std::uint64_t(cnt) * TypeSize(p.type));
  }

  void SkipAsciiList(const Prop& p)
  {
    const std::int64_t cnt = in_.ParseIntToken(p.name.c_str());
    if (cnt < 0)
      in_.FailAtLine("list '" + Printable(p.name) + "' has a negative count " + std::to_string(cnt));
    for (std::int64_t k = 0; k < cnt; ++k)
    {
      if (!in_.SkipBlanks())
        TooFew(p);
      in_.SkipToken();
    }
  }

  // --- faces ----------------------------------------------------------------------------------
  void CheckIndex(std::int64_t idx, std::uint64_t at)
  {
    if (idx >= 0 && std::uint64_t(idx) < vertexCount_)
      return;
    BadIndex(idx, at);
  }

  [[noreturn]] __attribute__((noinline, cold)) void BadIndex(std::int64_t idx, std::uint64_t at)
  {
    const std::string what = "#" + std::to_string(polygons_) +
      (idx < 0 ? " has a negative vertex index " + std::to_string(idx)
               : " has vertex index " + std::to_string(idx) + " out of range (" +
            std::to_string(vertexCount_) + " vertices)");
    if (ascii_)
      Fail(in_.Path(), "face", what, "line", at);
    Fail(in_.Path(), "face", what, "byte", at);
  }

  void AddFanIndex(Fan& fan, std::uint32_t idx)
  {
    std::uint32_t a, b;
    if (fan.Add(idx, a, b))
    {
      if (tb_.Full())
        tb_.Flush(sink_, in_);
      tb_.Add(a, b, idx);
    }
  }

  void EndFace(const Fan& fan)
  {
    if (fan.n < 3)
      ++tb_.dropped;
    ++polygons_;
  }

  // (not inlined: the rare path of BinaryFaces, whose fast loop it would otherwise crowd)
  __attribute__((noinline)) void BinaryFace(const Elem& el)
  {
    Fan fan;
    bool flag = false;
    std::size_t start = tb_.n;
    for (std::size_t i = 0; i < el.props.size(); ++i)
    {
      const Prop& p = el.props[i];
      if (int(i) == flagProp_)
      {
        in_.Need(TypeSize(p.type));
        flag = LoadReal(in_.p, p.type, swap_) != 0.0;
        in_.p += TypeSize(p.type);
        continue;
      }
      if (int(i) != h_.faceList)
      {
        if (p.list)
          SkipBinaryList(p);
        else
          in_.SkipBytes(TypeSize(p.type));
        continue;
      }
      const std::size_t cs = TypeSize(p.countType), is = TypeSize(p.type);
      in_.Need(cs);
      const std::int64_t cnt = LoadInt(in_.p, p.countType, swap_);
      if (cnt < 0)
        in_.FailAtByte("#" + std::to_string(polygons_) + " has a negative vertex count " +
          std::to_string(cnt));
      const Source& src = in_.Src();
      if (src.sizeKnown && std::uint64_t(cnt) * is > src.size - std::min(src.size, in_.Offset() + cs))
        in_.FailAtByte("#" + std::to_string(polygons_) + " has " + std::to_string(cnt) +
          " vertices, more than the file holds");
      in_.p += cs;
      tb_.Reserve(sink_, in_, cnt > 2 ? std::uint64_t(cnt - 2) : 0);
      start = tb_.n;
      fan.Start();
      for (std::int64_t k = 0; k < cnt; ++k)
      {
        in_.Need(is);
        const std::int64_t idx = LoadInt(in_.p, p.type, swap_);
        CheckIndex(idx, in_.Offset());
        in_.p += is;
        AddFanIndex(fan, std::uint32_t(idx));
      }
      EndFace(fan);
    }
    if (tb_.withFlags)
      tb_.SetFlags(start, flag);
  }

  void BinaryFaces(const Elem& el)
  {
    const Prop& lp = el.props[std::size_t(h_.faceList)];
    const bool fast = el.props.size() == 1 && !swap_ && TypeSize(lp.countType) == 1 &&
      (lp.type == PT::U32 || (lp.type == PT::I32 && vertexCount_ <= 0x80000000ull));
    const std::uint32_t vc = std::uint32_t(vertexCount_); // <= kMaxVertices
    std::uint64_t remaining = el.count;
    while (remaining)
    {
      if (fast)
      {
        if (tb_.Full())
          tb_.Flush(sink_, in_);
        std::size_t n = std::size_t(std::min<std::uint64_t>(
          { in_.Avail() / 13, remaining, std::uint64_t(tb_.capacity - tb_.n) }));
        const char* q = in_.p;
        std::uint32_t* out = tb_.idx.data() + 3 * tb_.n;
        std::uint32_t bad = 0, deg = 0;
        std::size_t j = 0;
#if defined(__SSE2__)
        // One 16-byte load and store per face (the 4th lane is the next record's count byte and
        // first index bytes: overwritten by the next store; TriangleBuffer keeps 4 spare slots).
        {
          const std::size_t n16 = in_.Avail() >= 17 ? std::min<std::size_t>(n, (in_.Avail() - 4) / 13) : 0;
          const __m128i sign = _mm_set1_epi32(int(0x80000000u));
          const __m128i vcs = _mm_xor_si128(_mm_set1_epi32(int(vc)), sign);
          const __m128i lane3 = _mm_set_epi32(-1, 0, 0, 0);
          __m128i lt = _mm_set1_epi32(-1);
          __m128i eq = _mm_setzero_si128();
          for (; j < n16; ++j)
          {
            const char* r = q + 13 * j;
            if (r[0] != 3)
              break;
            const __m128i v = _mm_loadu_si128(reinterpret_cast<const __m128i*>(r + 1));
            _mm_storeu_si128(reinterpret_cast<__m128i*>(out + 3 * j), v);
            lt = _mm_and_si128(lt, _mm_cmpgt_epi32(vcs, _mm_xor_si128(v, sign)));
            eq = _mm_or_si128(eq, _mm_cmpeq_epi32(v, _mm_shuffle_epi32(v, _MM_SHUFFLE(3, 0, 2, 1))));
          }
          bad = _mm_movemask_epi8(_mm_or_si128(lt, lane3)) != 0xFFFF;
          deg = _mm_movemask_epi8(_mm_andnot_si128(lane3, eq)) != 0;
          if (j < n16)
            n = j; // a face that is not a triangle: the generic path takes it
        }
#endif
        // Plain triangles, branch-free; degenerate ones are squeezed out afterwards (rare).
        for (; j < n; ++j)
        {
          const char* r = q + 13 * j;
          if (r[0] != 3)
            break;
          std::uint32_t a, b, c;
          std::memcpy(&a, r + 1, 4);
          std::memcpy(&b, r + 5, 4);
          std::memcpy(&c, r + 9, 4);
          bad |= std::uint32_t(a >= vc) | std::uint32_t(b >= vc) | std::uint32_t(c >= vc);
          deg |= std::uint32_t(a == b) | std::uint32_t(b == c) | std::uint32_t(a == c);
          out[3 * j] = a;
          out[3 * j + 1] = b;
          out[3 * j + 2] = c;
        }
        std::size_t w = j;
        if (deg && tb_.dropDegenerate)
        {
          w = 0;
          for (std::size_t k = 0; k < j; ++k)
          {
            const std::uint32_t a = out[3 * k], b = out[3 * k + 1], c = out[3 * k + 2];
            if (a == b || b == c || a == c)
              continue;
            out[3 * w] = a;
            out[3 * w + 1] = b;
            out[3 * w + 2] = c;
            ++w;
          }
        }
        if (bad)
          for (std::size_t k = 0; k < j; ++k)
          {
            const char* r = q + 13 * k;
            for (int m = 0; m < 3; ++m)
            {
              std::uint32_t t;
              std::memcpy(&t, r + 1 + 4 * m, 4);
              if (t >= vc)
              {
                polygons_ += k;
                CheckIndex(lp.type == PT::I32 ? std::int64_t(std::int32_t(t)) : std::int64_t(t),
                  in_.Offset(r + 1 + 4 * m));
              }
            }
          }
        tb_.n += w;
        tb_.triangles += w;
        tb_.dropped += j - w;
        polygons_ += j;
        in_.p = q + 13 * j;
        remaining -= j;
        if (j == n && n != 0)
          continue; // the whole block was plain triangles: take the next one
        if (!remaining)
          break;
        if (tb_.Full())
          tb_.Flush(sink_, in_);
      }
      BinaryFace(el);
      --remaining;
    }
  }

  void AsciiFaces(const Elem& el)
  {
    std::uint64_t remaining = el.count;
    Fan fan;
    while (remaining)
    {
      if (!in_.SkipSpace())
        in_.FailAtLine("truncated: " + std::to_string(remaining) + " of " +
          std::to_string(el.count) + " records missing");
      bool flag = false;
      std::size_t start = tb_.n;
      for (std::size_t i = 0; i < el.props.size(); ++i)
      {
        const Prop& p = el.props[i];
        if (!in_.SkipBlanks())
          TooFew(p);
        if (int(i) == flagProp_)
        {
          flag = AsciiScalar(el, p) != 0.0;
          continue;
        }
        if (int(i) != h_.faceList)
        {
          if (p.list)
            SkipAsciiList(p);
          else
            in_.SkipToken();
          continue;
        }
        const std::int64_t cnt = in_.ParseIntToken("the vertex count");
        if (cnt < 0)
          in_.FailAtLine("#" + std::to_string(polygons_) + " has a negative vertex count " +
            std::to_string(cnt));
        if (cnt > RangeOf(p.countType).hi)
          OutOfRange(el, p, cnt, RangeOf(p.countType));
        const std::int64_t idxMax = RangeOf(p.type).hi;
        tb_.Reserve(sink_, in_, cnt > 2 ? std::uint64_t(cnt - 2) : 0);
        start = tb_.n;
        fan.Start();
        for (std::int64_t k = 0; k < cnt; ++k)
        {
          if (!in_.SkipBlanks())
            TooFew(p);
          const std::int64_t idx = in_.ParseIntToken("a vertex index");
          if (idx > idxMax)
            OutOfRange(el, p, idx, RangeOf(p.type));
          CheckIndex(idx, in_.line);
          AddFanIndex(fan, std::uint32_t(idx));
        }
        EndFace(fan);
      }
      if (tb_.withFlags)
        tb_.SetFlags(start, flag);
      in_.EndOfRecord();
      --remaining;
    }
  }

  // --- other elements -------------------------------------------------------------------------
  void BinarySkip(const Elem& el)
  {
    if (el.props.empty())
      return;
    if (!el.HasLists())
    {
      in_.SkipBytes(el.count * el.FixedSize()); // no overflow: CheckSizes
      return;
    }
    for (std::uint64_t r = 0; r < el.count; ++r)
      for (const Prop& p : el.props)
      {
        if (p.list)
          SkipBinaryList(p);
        else
          in_.SkipBytes(TypeSize(p.type));
      }
  }

  void AsciiSkip(const Elem& el)
  {
    if (el.props.empty())
      return;
    for (std::uint64_t r = 0; r < el.count; ++r)
    {
      if (!in_.SkipSpace())
        in_.FailAtLine("truncated: " + std::to_string(el.count - r) + " of " +
          std::to_string(el.count) + " records missing");
      in_.SkipLine();
    }
  }

  Input& in_;
  MeshSink& sink_;
  const ReadOptions& opt_;
  Header& h_;
  const bool ascii_;
  const bool swap_;
  std::uint64_t vertexCount_ = 0;
  std::uint64_t polygons_ = 0;
  VertexBuffer vb_;
  TriangleBuffer tb_;
  float* arr_[4] = {};
  std::size_t stride_[4] = {};
  int flagProp_ = -1; // the face property of ReadOptions::faceFlag
};

} // namespace

ReadStats ReadPly(Input& in, MeshSink& sink, const ReadOptions& options)
{
  Header h;
  ParseHeader(in, h);
  PlyReader r(in, sink, options, h);
  return r.Run();
}

void DescribePlySplit(Input& in, SplitLayout& s)
{
  Header h;
  ParseHeader(in, h);
  CheckSizes(in, h); // (the same errors as a read of the whole file)
  s.format = h.format;
  const Elem& ve = h.elems[std::size_t(h.vertexElem)];
  s.vertexCount = ve.count;
  s.faceCount = h.faceElem >= 0 ? h.elems[std::size_t(h.faceElem)].count : 0;
  if (h.format == Format::PlyAscii)
  {
    s.whyNot = "it is ASCII PLY (lines of varying length)";
    return;
  }
  if (h.faceElem < 0 || s.faceCount == 0)
  {
    s.whyNot = "it has no faces";
    return;
  }
  s.bigEndian = h.format == Format::PlyBinaryBE;
  std::uint64_t at = h.bodyOffset;
  for (std::size_t i = 0; i < h.elems.size(); ++i)
  {
    const Elem& el = h.elems[i];
    if (int(i) == h.faceElem)
    {
      const Prop& list = el.props[std::size_t(h.faceList)];
      for (std::size_t k = 0; k < el.props.size(); ++k)
      {
        if (el.props[k].list && int(k) != h.faceList)
        {
          s.whyNot = "its faces have a list property besides " + list.name;
          return;
        }
        if (int(k) < h.faceList)
          s.countOffset += std::uint32_t(TypeSize(el.props[k].type));
      }
      s.countSize = std::uint32_t(TypeSize(list.countType));
      s.indexSize = std::uint32_t(TypeSize(list.type));
      s.indexSigned = list.type == PT::I8 || list.type == PT::I16 || list.type == PT::I32;
      s.faceOffset = at;
      s.faceStride = el.FixedSize() + s.countSize + 3 * s.indexSize;
      at += el.count * s.faceStride; // (CheckSizes bounds each count by the file's size)
      continue;
    }
    if (el.HasLists())
    {
      s.whyNot = "its element '" + el.name + "' has list properties";
      return;
    }
    if (int(i) == h.vertexElem)
    {
      s.vertexOffset = at;
      s.vertexStride = el.FixedSize();
    }
    at += el.count * el.FixedSize();
  }
  if (at != s.fileBytes)
  {
    s.whyNot = "its faces are not all triangles (the sizes do not add up to fixed records)";
    return;
  }
  static const char* const kTypeNames[] = { "char", "uchar", "short", "ushort", "int", "uint",
    "float", "double" };
  for (const Prop& p : ve.props)
    s.vertexProperties += std::string("property ") + kTypeNames[int(p.type)] + " " + p.name + "\n";
}

MeshHeader ReadPlyHeader(Input& in, bool checkSizes)
{
  Header h;
  ParseHeader(in, h);
  if (checkSizes)
  {
    CheckSizes(in, h);
  }
  MeshHeader mh;
  mh.format = h.format;
  mh.layout = h.layout;
  mh.vertexCount = h.elems[std::size_t(h.vertexElem)].count;
  mh.faceCount = h.faceElem >= 0 ? h.elems[std::size_t(h.faceElem)].count : 0;
  mh.faceScalars = h.faceScalars;
  return mh;
}

} // namespace sipmss::io::detail
