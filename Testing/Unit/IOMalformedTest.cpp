// A generated corpus of malformed files: each must fail with a MeshIOError naming the file, the
// element and the byte or line, plus the expected reason. No crash, no huge allocation (run this
// binary under -fsanitize=address,undefined by hand to check).
#include "IOTestUtil.h"

#include <cmath>
#include <limits>

namespace sipmss::io::test
{
namespace
{

struct BadCase
{
  std::string name;  // file name (extension matters for some)
  std::string bytes; // content
  bool gzip = false; // write gzip-compressed
  std::vector<std::string> expect; // substrings of the message
  const char* unit = "byte";       // "byte" or "line"
};

std::ostream& operator<<(std::ostream& os, const BadCase& c)
{
  return os << c.name;
}

PlyBuilder Xyz(Enc enc, std::uint64_t nv, const std::string& extraHeader = "")
{
  PlyBuilder b(enc);
  b.H("element vertex " + std::to_string(nv)).H("property float x").H("property float y").H("property float z");
  if (!extraHeader.empty())
    b.H(extraHeader);
  return b;
}

std::string Gzip(const std::string& bytes)
{
  TempDir dir;
  WriteGzip(dir.File("x.gz"), bytes);
  return ReadFileBytes(dir.File("x.gz"));
}

std::string StlBinaryBytes(std::uint32_t declared, std::uint32_t actual, float value = 1.f)
{
  std::string s = "binary stl";
  s.resize(80, '\0');
  s.append(reinterpret_cast<const char*>(&declared), 4);
  for (std::uint32_t t = 0; t < actual; ++t)
  {
    float f[12] = { 0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0 };
    if (t == actual - 1)
      f[7] = value;
    s.append(reinterpret_cast<const char*>(f), 48);
    s.append("\0\0", 2);
  }
  return s;
}

std::vector<BadCase> Corpus()
{
  std::vector<BadCase> c;
  auto add = [&](std::string name, std::string bytes, std::vector<std::string> expect, const char* unit,
               bool gz = false) {
    BadCase b;
    b.name = std::move(name);
    b.bytes = std::move(bytes);
    b.expect = std::move(expect);
    b.unit = unit;
    b.gzip = gz;
    c.push_back(std::move(b));
  };
  const float nan = std::numeric_limits<float>::quiet_NaN();
  const float inf = std::numeric_limits<float>::infinity();

  // --- not a mesh ------------------------------------------------------------------------------
  add("not_a_mesh.txt", "hello world\nthis is text\n", { "file", "unknown format" }, "byte");
  add("empty.ply", "", { "file", "unknown format" }, "byte");
  {
    std::string junk;
    for (int i = 0; i < 300; ++i)
      junk += char((i * 7919) % 251);
    add("random.bin", junk, { "file", "unknown format" }, "byte");
  }

  // --- PLY header ------------------------------------------------------------------------------
  add("no_end_header.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\n",
    { "header", "no end_header", "at line 5" }, "line");
  add("bad_format.ply", "ply\nformat foo 1.0\nend_header\n", { "header", "bad format line", "at line 2" }, "line");
  add("bad_format_version.ply", "ply\nformat ascii 2.0\nend_header\n", { "header", "unsupported version" }, "line");
  add("bad_format_fields.ply", "ply\nformat ascii\nend_header\n", { "header", "bad format line" }, "line");
  add("no_format.ply", "ply\ncomment x\nend_header\n", { "header", "no format line" }, "line");
  add("unknown_type.ply", Xyz(Enc::Ascii, 1, "property flt w").Bytes() + "1 2 3 4\n",
    { "header", "unknown type name 'flt'", "at line 7" }, "line");
  add("unknown_list_type.ply",
    Xyz(Enc::Ascii, 0, "element face 0\nproperty list uchar integer vertex_indices").Bytes(),
    { "header", "unknown type name 'integer'" }, "line");
  add("float_list_count.ply", Xyz(Enc::Ascii, 0, "element face 0\nproperty list float int vertex_indices").Bytes(),
    { "header", "non-integer count type" }, "line");
  add("property_before_element.ply", "ply\nformat ascii 1.0\nproperty float x\nend_header\n",
    { "header", "property before any element", "at line 3" }, "line");
  add("element_before_format.ply", "ply\nelement vertex 0\nformat ascii 1.0\nend_header\n",
    { "header", "element before the format line" }, "line");
  add("unknown_keyword.ply", "ply\nformat ascii 1.0\nelemnt vertex 1\nend_header\n",
    { "header", "unknown keyword 'elemnt'" }, "line");
  add("missing_z.ply", "ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nend_header\n1 2\n",
    { "vertex", "no scalar property 'z'", "at line 3" }, "line");
  add("list_x.ply",
    "ply\nformat ascii 1.0\nelement vertex 1\nproperty list uchar float x\nproperty float y\nproperty float "
    "z\nend_header\n1 1 2 3\n",
    { "vertex", "no scalar property 'x'" }, "line");
  add("no_vertex_element.ply", "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n",
    { "header", "no vertex element" }, "line");
  add("face_without_indices.ply", Xyz(Enc::Ascii, 0, "element face 0\nproperty int flags").Bytes(),
    { "face", "vertex_indices" }, "line");
  add("face_float_indices.ply", Xyz(Enc::Ascii, 0, "element face 0\nproperty list uchar float vertex_indices").Bytes(),
    { "face", "non-integer vertex_indices" }, "line");
  add("duplicate_element.ply", Xyz(Enc::Ascii, 0, "element vertex 0").Bytes(), { "header", "second element 'vertex'" }, "line");
  add("duplicate_property.ply", Xyz(Enc::Ascii, 0, "property float x").Bytes(), { "header", "second property 'x'" }, "line");
  {
    std::string h = "ply\nformat ascii 1.0\n";
    while (h.size() < (1u << 20) + 100)
      h += "comment padding padding padding padding\n";
    add("header_too_long.ply", h + "end_header\n", { "header", "longer than 1 MiB" }, "line");
  }

  // --- counts ------------------------------------------------------------------------------------
  add("negative_count.ply", "ply\nformat ascii 1.0\nelement vertex -5\nproperty float x\nend_header\n",
    { "vertex", "negative count -5", "at line 3" }, "line");
  add("bad_count.ply", "ply\nformat ascii 1.0\nelement vertex abc\nend_header\n", { "header", "bad count 'abc'" }, "line");
  add("count_overflows_64_bits.ply",
    "ply\nformat ascii 1.0\nelement vertex 99999999999999999999999\nproperty float x\nend_header\n",
    { "vertex", "overflows" }, "line");
  add("too_many_vertices.ply", Xyz(Enc::LE, 4294967296ull).Bytes(), { "vertex", "too many vertices", "at line 3" }, "line");
  add("binary_count_larger_than_file.ply", Xyz(Enc::LE, 1000000).V("float", 1).V("float", 2).V("float", 3).Bytes(),
    { "vertex", "larger than the file", "needs at least 12000000 bytes" }, "byte");
  add("ascii_count_larger_than_file.ply", Xyz(Enc::Ascii, 1000).V("float", 1).V("float", 2).V("float", 3).EndRecord().Bytes(),
    { "vertex", "larger than the file", "at line 3" }, "line");
  add("face_count_larger_than_file.ply",
    Xyz(Enc::LE, 1, "element face 100000\nproperty list uchar int vertex_indices").V("float", 1).V("float", 2).V("float", 3).Bytes(),
    { "face", "larger than the file" }, "byte");
  {
    const std::string h = "element junk 4611686018427387904\nproperty double a\nproperty double b";
    add("size_overflow.ply", Xyz(Enc::LE, 1, h).V("float", 1).V("float", 2).V("float", 3).Bytes(),
      { "junk", "overflows the size arithmetic" }, "byte");
    add("size_overflow.ply.gz", Xyz(Enc::LE, 1, h).V("float", 1).V("float", 2).V("float", 3).Bytes(),
      { "junk", "overflows the size arithmetic" }, "byte", true);
    add("size_overflow_sum.ply.gz",
      Xyz(Enc::LE, 1, "element a 1152921504606846976\nproperty double a\nelement b 1152921504606846976\nproperty double b")
        .Bytes(),
      { "overflows the size arithmetic" }, "byte", true);
  }
  add("list_count_larger_than_file.ply",
    Xyz(Enc::LE, 3, "element face 1\nproperty list uint int vertex_indices")
      .V("float", 1).V("float", 2).V("float", 3).V("float", 1).V("float", 2).V("float", 3).V("float", 1).V("float", 2).V("float", 3)
      .V("uint", 1000000000).V("int", 0).V("int", 1).V("int", 2)
      .Bytes(),
    { "face #0", "has 1000000000 vertices, more than the file holds" }, "byte");
  add("negative_face_count.ply",
    Xyz(Enc::LE, 3, "element face 1\nproperty list char int vertex_indices")
      .V("float", 1).V("float", 2).V("float", 3).V("float", 1).V("float", 2).V("float", 3).V("float", 1).V("float", 2).V("float", 3)
      .V("char", -1).Raw(std::string(12, '\0'))
      .Bytes(),
    { "face", "negative vertex count -1" }, "byte");
  add("negative_vertex_list_count.ply",
    Xyz(Enc::BE, 1, "property list short int extra").V("float", 1).V("float", 2).V("float", 3).V("short", -2).Bytes(),
    { "vertex", "negative count -2" }, "byte");
  add("negative_ascii_face_count.ply",
    Xyz(Enc::Ascii, 3, "element face 1\nproperty list int int vertex_indices").Raw("0 0 0\n0 0 0\n0 0 0\n-3 0 1 2\n").Bytes(),
    { "face", "negative vertex count -3", "at line 13" }, "line");

  // --- indices -----------------------------------------------------------------------------------
  const std::string faceHeader = "element face 2\nproperty list uchar int vertex_indices";
  add("negative_index_ascii.ply", Xyz(Enc::Ascii, 3, faceHeader).Raw("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 -1 2\n").Bytes(),
    { "face #1", "negative vertex index -1", "at line 14" }, "line");
  {
    PlyBuilder b = Xyz(Enc::LE, 3, faceHeader);
    for (int i = 0; i < 9; ++i)
      b.V("float", i);
    b.V("uchar", 3).V("int", 0).V("int", 1).V("int", 2).V("uchar", 3).V("int", 0).V("int", -1).V("int", 2);
    add("negative_index_binary.ply", b.Bytes(), { "face #1", "negative vertex index -1" }, "byte");
  }
  add("index_out_of_range_ascii.ply", Xyz(Enc::Ascii, 3, faceHeader).Raw("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n3 0 1 7\n").Bytes(),
    { "face #1", "vertex index 7 out of range (3 vertices)", "at line 14" }, "line");
  for (Enc enc : { Enc::LE, Enc::BE })
    for (const char* it : { "int", "ushort", "uint" })
    {
      PlyBuilder b = Xyz(enc, 3, std::string("element face 2\nproperty list uchar ") + it + " vertex_indices");
      for (int i = 0; i < 9; ++i)
        b.V("float", i);
      b.V("uchar", 3).V(it, 0).V(it, 1).V(it, 2).V("uchar", 4).V(it, 0).V(it, 1).V(it, 2).V(it, 3);
      add(std::string("index_out_of_range_") + (enc == Enc::LE ? "le_" : "be_") + it + ".ply", b.Bytes(),
        { "face #1", "vertex index 3 out of range (3 vertices)" }, "byte");
    }

  // --- truncation ----------------------------------------------------------------------------------
  {
    PlyBuilder b = Xyz(Enc::LE, 3, "property list uchar int extra");
    b.V("float", 1).V("float", 2).V("float", 3).V("uchar", 0);
    b.V("float", 1).V("float", 2).V("float", 3).V("uchar", 0);
    b.V("float", 1).V("float", 2).V("float", 3).V("uchar", 5).V("int", 1);
    add("truncated_binary_vertices.ply", b.Bytes(), { "vertex", "truncated" }, "byte");
  }
  {
    PlyBuilder b = Xyz(Enc::LE, 3, faceHeader);
    for (int i = 0; i < 9; ++i)
      b.V("float", i);
    b.V("uchar", 3).V("int", 0).V("int", 1).V("int", 2).V("uchar", 3).V("int", 0);
    add("truncated_binary_faces.ply.gz", b.Bytes(), { "face", "truncated" }, "byte", true);
    add("truncated_binary_faces.ply", b.Bytes(), { "face #1", "more than the file holds" }, "byte");
  }
  add("truncated_ascii.ply", Xyz(Enc::Ascii, 3).Raw("1.000000 2.000000 3.000000\n").Bytes(),
    { "vertex", "truncated", "2 of 3 records missing" }, "line");
  add("truncated_ascii_faces.ply.gz", Xyz(Enc::Ascii, 3, faceHeader).Raw("0 0 0\n1 0 0\n0 1 0\n3 0 1 2\n").Bytes(),
    { "face", "truncated" }, "line", true);
  add("too_few_values_ascii.ply", Xyz(Enc::Ascii, 1).Raw("1 2\n").Bytes(), { "vertex", "too few values", "'z'", "at line 8" }, "line");
  add("too_few_indices_ascii.ply", Xyz(Enc::Ascii, 3, faceHeader).Raw("0 0 0\n1 0 0\n0 1 0\n3 0 1\n3 0 1 2\n").Bytes(),
    { "face", "too few values" }, "line");
  add("extra_values_ascii.ply", Xyz(Enc::Ascii, 1).Raw("1 2 3 4\n").Bytes(), { "vertex", "extra values", "at line 8" }, "line");

  // --- numbers -----------------------------------------------------------------------------------
  add("nan_ascii.ply", Xyz(Enc::Ascii, 2).Raw("0 0 0\nnan 0 0\n").Bytes(), { "vertex #1", "non-finite", "at line 9" }, "line");
  add("inf_ascii.ply", Xyz(Enc::Ascii, 1).Raw("0 inf 0\n").Bytes(), { "vertex #0", "non-finite" }, "line");
  add("overflow_ascii.ply", Xyz(Enc::Ascii, 1).Raw("0 1e39 0\n").Bytes(), { "vertex #0", "non-finite" }, "line");
  add("inf_binary.ply", Xyz(Enc::LE, 2).V("float", 0).V("float", 0).V("float", 0).V("float", 0).V("float", inf).V("float", 0).Bytes(),
    { "vertex #1", "non-finite", "at byte " + std::to_string(Xyz(Enc::LE, 2).Bytes().size() + 12) }, "byte");
  {
    PlyBuilder b(Enc::BE);
    b.H("element vertex 1").H("property double x").H("property double y").H("property double z").H("property list uchar int l");
    b.V("double", 0).V("double", double(nan)).V("double", 0).V("uchar", 0);
    add("nan_binary_be_double.ply", b.Bytes(), { "vertex #0", "non-finite" }, "byte");
  }
  add("bad_number_ascii.ply", Xyz(Enc::Ascii, 1).Raw("1.2.3 0 0\n").Bytes(), { "vertex", "bad number '1.2.3'", "at line 8" }, "line");
  add("bad_number_word.ply", Xyz(Enc::Ascii, 1).Raw("0 zero 0\n").Bytes(), { "vertex", "bad number 'zero'" }, "line");
  add("bad_number_face.ply", Xyz(Enc::Ascii, 3, faceHeader).Raw("0 0 0\n1 0 0\n0 1 0\n3 0 1 x\n3 0 1 2\n").Bytes(),
    { "face", "bad number 'x'", "at line 13" }, "line");
  add("bad_number_int_property.ply", Xyz(Enc::Ascii, 1, "property uchar red").Raw("0 0 0 12.5\n").Bytes(),
    { "vertex", "bad number '12.5'" }, "line");
  add("bad_number_count.ply", Xyz(Enc::Ascii, 3, faceHeader).Raw("0 0 0\n1 0 0\n0 1 0\nthree 0 1 2\n").Bytes(),
    { "face", "bad number 'three'" }, "line");
  add("huge_number_token.ply", Xyz(Enc::Ascii, 1).Raw("0 " + std::string(5000, '1') + " 0\n").Bytes(),
    { "vertex", "bad number" }, "line");

  // --- gzip ----------------------------------------------------------------------------------------
  {
    std::string body;
    PlyBuilder b = Xyz(Enc::Ascii, 2000);
    for (int i = 0; i < 2000; ++i)
      b.V("float", i * 0.123).V("float", i).V("float", -i).EndRecord();
    const std::string gz = Gzip(b.Bytes());
    add("truncated.ply.gz", gz.substr(0, gz.size() / 2), { "zlib", "unexpected end of file" }, "byte");
    std::string crc = gz;
    crc[crc.size() - 6] = char(crc[crc.size() - 6] ^ 0x55);
    add("bad_crc.ply.gz", crc, { "zlib", "incorrect data check" }, "byte");
    std::string garbage = gz.substr(0, 10) + std::string(500, '\xff');
    add("garbage.ply.gz", garbage, { "gzip data is corrupt (zlib: " }, "byte");
  }

  // --- STL -----------------------------------------------------------------------------------------
  add("stl_count_larger_than_file.stl", StlBinaryBytes(10, 2), { "facet", "count 10 is larger than the file", "at byte 80" }, "byte");
  add("stl_too_many_vertices.stl", StlBinaryBytes(0x60000000u, 1), { "facet", "too many vertices", "at byte 80" }, "byte");
  add("stl_short_header.stl", std::string(40, '\0'), { "header", "truncated" }, "byte");
  add("stl_binary_nan.stl", StlBinaryBytes(3, 3, nan), { "facet #2", "non-finite", "at byte " + std::to_string(84 + 100) }, "byte");
  add("stl_binary_truncated.stl.gz", StlBinaryBytes(5, 3), { "facet", "truncated" }, "byte", true);
  {
    const std::string pre = "solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\n";
    add("stl_ascii_bad_keyword.stl", pre + "vertx 1 0 0\n", { "facet", "'vertx'", "at line 5" }, "line");
    add("stl_ascii_truncated.stl", pre + "vertex 1 0 0\n", { "facet", "truncated" }, "line");
    add("stl_ascii_bad_number.stl", pre + "vertex 1 0 o\n", { "facet", "bad number 'o'", "at line 5" }, "line");
    add("stl_ascii_nan.stl", pre + "vertex nan 0 0\n", { "facet", "non-finite" }, "line");
    add("stl_ascii_few_coordinates.stl", pre + "vertex 1 0\nvertex 0 1 0\n", { "facet", "fewer than 3 coordinates" }, "line");
    add("stl_ascii_extra_coordinate.stl", pre + "vertex 1 0 0 0\n", { "facet", "more than 3 coordinates" }, "line");
    add("stl_ascii_junk_between_facets.stl", "solid x\nendfacet\n", { "solid", "unexpected keyword 'endfacet'", "at line 2" }, "line");
    add("stl_ascii_missing_loop.stl", "solid x\nfacet normal 0 0 1\nvertex 0 0 0\n", { "facet", "'outer'" }, "line");
  }

  // --- OBJ -----------------------------------------------------------------------------------------
  add("obj_index_out_of_range.obj", "v 0 0 0\nf 1 2 3\n", { "face", "references vertex 2, out of range", "at line 2" }, "line");
  add("obj_forward_reference.obj", "v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n", { "face", "references vertex 3" }, "line");
  add("obj_index_zero.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 0 1 2\n", { "face", "index 0", "at line 4" }, "line");
  add("obj_relative_too_far.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf -1 -2 -4\n", { "face", "references vertex -4" }, "line");
  add("obj_bad_number.obj", "v 1 x 3\n", { "vertex", "bad number 'x'", "at line 1" }, "line");
  add("obj_nan.obj", "# c\nv nan 0 0\n", { "vertex", "non-finite", "at line 2" }, "line");
  add("obj_few_coordinates.obj", "v 1 2\n", { "vertex", "fewer than 3 coordinates" }, "line");
  add("obj_bad_face_token.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 a 2\n", { "face", "bad vertex reference 'a'" }, "line");
  add("obj_bad_face_suffix.obj", "v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2x 3\n", { "face", "bad vertex reference '2x'" }, "line");
  add("obj_huge_index.obj", "v 0 0 0\nf 1 99999999999999999999999 1\n", { "face", "bad vertex reference" }, "line");
  add("obj_gz_out_of_range.obj.gz", "v 0 0 0\r\nf 1 2 3\r\n", { "face", "out of range", "at line 2" }, "line", true);
  return c;
}

class IOMalformedCorpus : public ::testing::TestWithParam<BadCase>
{
};

TEST_P(IOMalformedCorpus, FailsWithPathElementAndPosition)
{
  const BadCase& bc = GetParam();
  TempDir dir;
  const std::string path = dir.File(bc.name);
  if (bc.gzip)
    WriteGzip(path, bc.bytes);
  else
    WriteFile(path, bc.bytes);
  const std::string err = ReadError(path);
  ASSERT_FALSE(err.empty()) << bc.name << " was read without an error";
  RecordProperty("error", err); // visible with --gtest_output=xml
  EXPECT_EQ(err.rfind(path + ": ", 0), 0u) << err;
  EXPECT_NE(err.find(std::string(", at ") + bc.unit + " "), std::string::npos) << err;
  for (const std::string& s : bc.expect)
    EXPECT_NE(err.find(s), std::string::npos) << "expected '" << s << "' in: " << err;
  // The same bytes from memory, with a tiny buffer: the same failure, no crash.
  CollectSink sink;
  MemoryReadOptions mo;
  mo.bufferBytes = 1024;
  mo.name = bc.name;
  const std::string bytes = bc.gzip ? ReadFileBytes(path) : bc.bytes;
  EXPECT_THROW(ReadMeshFromMemory(bytes.data(), bytes.size(), sink, ReadOptions{}, mo), MeshIOError);
  // ReadHeader fails too, or succeeds when the error is in the body of a PLY.
  try
  {
    ReadHeader(path);
  }
  catch (const MeshIOError&)
  {
  }
}

INSTANTIATE_TEST_SUITE_P(IO, IOMalformedCorpus, ::testing::ValuesIn(Corpus()),
  [](const ::testing::TestParamInfo<BadCase>& info) {
    std::string n = info.param.name;
    for (char& ch : n)
      if (!std::isalnum(static_cast<unsigned char>(ch)))
        ch = '_';
    return n;
  });

TEST(IOMalformed, MissingFile)
{
  const std::string err = ReadError("/nonexistent/dir/mesh.ply");
  EXPECT_NE(err.find("/nonexistent/dir/mesh.ply: file cannot be opened: No such file or directory"),
    std::string::npos)
    << err;
  EXPECT_THROW(ReadHeader("/nonexistent/x.ply"), MeshIOError);
  EXPECT_THROW(DetectFormat("/nonexistent/x.ply"), MeshIOError);
}

TEST(IOMalformed, DirectoryIsNotAMesh)
{
  TempDir dir;
  const std::string err = ReadError(dir.Path());
  EXPECT_NE(err.find("is a directory"), std::string::npos) << err;
}

// ---------------------------------------------------------------------------------------------
// Issue 20 items 9 and 10: degenerate and inconsistent inputs are named errors, not silently
// read as something else.
std::string ErrorOf(const std::string& path, const ReadOptions& options = {})
{
  const std::string e = ReadError(path, options);
  EXPECT_FALSE(e.empty()) << path << ": read without an error";
  EXPECT_EQ(e.rfind(path + ": ", 0), 0u) << e;
  return e;
}

TEST(IOMalformed, ZeroBytesAreNotAnEmptyStl)
{
  TempDir dir;
  // 84 zero bytes were "an empty binary STL" (header count 0 = 84 + 50 * 0 bytes) whatever the
  // name; /dev/zero, of unknown size, too.
  WriteFile(dir.File("zeros.ply"), std::string(84, '\0'));
  WriteFile(dir.File("zeros4k.obj"), std::string(5000, '\0'));
  for (const std::string& path : { dir.File("zeros.ply"), dir.File("zeros4k.obj"), std::string("/dev/zero") })
  {
    const std::string e = ErrorOf(path);
    EXPECT_NE(e.find("file is not a mesh file (unknown format: its first"), std::string::npos) << e;
    EXPECT_NE(e.find("bytes are all zero"), std::string::npos) << e;
    EXPECT_EQ(DetectFormat(path), Format::Unknown) << path;
  }
  // An empty file says so.
  WriteFile(dir.File("empty.obj"), "");
  EXPECT_NE(ErrorOf(dir.File("empty.obj")).find("file is empty (0 bytes"), std::string::npos);
  // A zero-facet binary STL stays readable when its name says STL.
  WriteFile(dir.File("none.stl"), std::string(84, '\0'));
  CollectSink s = ReadAll(dir.File("none.stl"));
  EXPECT_EQ(s.header.format, Format::StlBinary);
  EXPECT_TRUE(s.ended);
}

TEST(IOMalformed, GzipInsideGzip)
{
  TempDir dir;
  // A binary STL gzipped twice: the inner gzip header was read as an STL with a huge count.
  const std::string once = Gzip(StlBinaryBytes(3, 3));
  for (const char* name : { "twice.stl.gz", "twice.ply.gz", "twice.bin" })
  {
    WriteGzip(dir.File(name), once);
    const std::string e = ErrorOf(dir.File(name));
    EXPECT_NE(e.find("file is gzip inside gzip (compressed twice)"), std::string::npos) << e;
    EXPECT_EQ(DetectFormat(dir.File(name)), Format::Unknown) << name;
  }
}

TEST(IOMalformed, BinaryStlCountSmallerThanItsFacets)
{
  TempDir dir;
  // 3 facets, the header says 2: the third was dropped without a word.
  WriteFile(dir.File("short.stl"), StlBinaryBytes(2, 3));
  std::string e = ErrorOf(dir.File("short.stl"));
  EXPECT_NE(e.find("facet count 2 is smaller than the file: 50 bytes follow the 2 facets it "
                   "announces (the file holds 3 facets), at byte 80"),
    std::string::npos)
    << e;
  // Not a whole facet of extra bytes.
  WriteFile(dir.File("tail.stl"), StlBinaryBytes(3, 3) + "junk");
  e = ErrorOf(dir.File("tail.stl"));
  EXPECT_NE(e.find("count 3 is smaller than the file: 4 bytes follow"), std::string::npos) << e;
  // Through gzip (size unknown up front) the same mismatch is found at the end of the facets.
  WriteGzip(dir.File("short.stl.gz"), StlBinaryBytes(2, 3));
  e = ErrorOf(dir.File("short.stl.gz"));
  EXPECT_NE(e.find("facet count 2 is smaller than the data: more bytes follow the 2 facets"),
    std::string::npos)
    << e;
  // Exact counts still read.
  WriteGzip(dir.File("ok.stl.gz"), StlBinaryBytes(3, 3));
  EXPECT_EQ(ReadAll(dir.File("ok.stl.gz")).tris.size(), 9u);
}

TEST(IOMalformed, AsciiPlyIntegersOutOfTheirTypesRange)
{
  TempDir dir;
  const std::string head = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                           "property float y\nproperty float z\nproperty uchar red\n"
                           "property uchar green\nproperty uchar blue\nproperty short s\n"
                           "element face 1\nproperty list uchar int vertex_indices\nend_header\n";
  const struct
  {
    std::string body, expect;
  } cases[] = {
    { "0 0 0 300 0 0 1\n1 0 0 0 0 0 1\n0 1 0 0 0 0 1\n3 0 1 2\n",
      "vertex property 'red' has value 300, out of range for uchar (0 to 255), at line 14" },
    { "0 0 0 0 0 0 1\n1 0 0 0 -5 0 1\n0 1 0 0 0 0 1\n3 0 1 2\n",
      "vertex property 'green' has value -5, out of range for uchar (0 to 255), at line 15" },
    { "0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n0 1 0 0 0 0 40000\n3 0 1 2\n",
      "vertex property 's' has value 40000, out of range for short (-32768 to 32767), at line 16" },
    { "0 0 0 0 0 0 1\n1 0 0 0 0 0 1\n0 1 0 0 0 0 1\n256 0 1 2\n",
      "face property 'vertex_indices' has value 256, out of range for uchar (0 to 255), at line 17" },
  };
  int k = 0;
  for (const auto& c : cases)
  {
    const std::string path = dir.File("range" + std::to_string(k++) + ".ply");
    WriteFile(path, head + c.body);
    const std::string e = ErrorOf(path);
    EXPECT_NE(e.find(path + ": " + c.expect), std::string::npos) << e;
  }
  // The limits themselves are fine.
  WriteFile(dir.File("limits.ply"),
    head + "0 0 0 255 0 0 -32768\n1 0 0 0 255 0 32767\n0 1 0 0 0 255 0\n3 0 1 2\n");
  const CollectSink s = ReadAll(dir.File("limits.ply"));
  ASSERT_EQ(s.rgba.size(), 12u);
  EXPECT_EQ(int(s.rgba[0]), 255);
  EXPECT_EQ(int(s.rgba[5]), 255);
}

TEST(IOMalformed, ObjFacesBeforeAnyVertexInAVerticesOnlyPass)
{
  // A bounds pass (verticesOnly) used to skip such faces and report "no vertices": the reader's
  // own message names the line.
  TempDir dir;
  WriteFile(dir.File("fb.obj"), "# x\nf 1 2 3\nv 0 0 0\nv 1 0 0\nv 0 1 0\n");
  ReadOptions o;
  o.verticesOnly = true;
  const std::string e = ErrorOf(dir.File("fb.obj"), o);
  EXPECT_NE(e.find("face references vertex 1, out of range (0 vertices defined before it), at line 2"),
    std::string::npos)
    << e;
}

} // namespace
} // namespace sipmss::io::test
