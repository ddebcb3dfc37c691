// Writes the fuzzers' seed corpus: small valid meshes in every encoding (and gzip), made with the
// project's writers plus hand-written variants the writers never produce.
//   sipmss_fuzz_seeds <dir>   -> <dir>/ply, <dir>/stl, <dir>/obj
#include "sipmss/io/MeshIO.h"

#include <zlib.h>

#include <cstdio>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

namespace
{
namespace fs = std::filesystem;
using namespace sipmss::io;

void Write(const fs::path& p, const std::string& bytes)
{
  std::ofstream(p, std::ios::binary).write(bytes.data(), std::streamsize(bytes.size()));
}

std::string Read(const fs::path& p)
{
  std::ifstream f(p, std::ios::binary);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

void WriteGz(const fs::path& p, const std::string& bytes)
{
  gzFile gz = gzopen(p.string().c_str(), "wb9");
  gzwrite(gz, bytes.data(), unsigned(bytes.size()));
  gzclose(gz);
}

void Mesh(const fs::path& p, bool ascii, bool attributes)
{
  VertexLayout l;
  if (attributes)
  {
    l.normals = l.colors = l.texcoords = true;
    l.scalars = { "quality" };
  }
  const float xyz[15] = { 0, 0, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 0.5f, 0.5f, 1 };
  const float n[15] = { 0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 0, 1, 0, 1, 0 };
  const std::uint8_t rgba[20] = { 255, 0, 0, 255, 0, 255, 0, 255, 0, 0, 255, 255, 9, 9, 9, 9, 1, 2, 3, 4 };
  const float uv[10] = { 0, 0, 1, 0, 1, 1, 0, 1, 0.5f, 0.5f };
  const float q[5] = { 1, 2, 3, 4, 5 };
  const std::uint32_t tris[12] = { 0, 1, 4, 1, 2, 4, 2, 3, 4, 3, 0, 4 };
  auto w = MeshWriter::Create(p.string(), ascii);
  w->Begin(5, 4, l);
  VertexChunk c;
  c.count = 5;
  c.xyz = xyz;
  if (attributes)
  {
    c.normals = n;
    c.rgba = rgba;
    c.texcoords = uv;
    c.scalars = q;
  }
  w->Vertices(c);
  w->Triangles(tris, 4);
  w->End();
}

} // namespace

int main(int argc, char** argv)
{
  if (argc != 2)
  {
    std::fprintf(stderr, "usage: %s <seed-dir>\n", argv[0]);
    return 2;
  }
  const fs::path root = argv[1];
  for (const char* d : { "ply", "stl", "obj" })
    fs::create_directories(root / d);

  // Writers' output.
  Mesh(root / "ply" / "bin.ply", false, false);
  Mesh(root / "ply" / "bin_attr.ply", false, true);
  Mesh(root / "ply" / "ascii.ply", true, false);
  Mesh(root / "ply" / "ascii_attr.ply", true, true);
  Mesh(root / "stl" / "bin.stl", false, false);
  Mesh(root / "stl" / "ascii.stl", true, false);
  Mesh(root / "obj" / "w.obj", false, false);

  // Hand-written PLY: big-endian, odd types, unknown elements with lists, polygons, CRLF.
  {
    std::string h = "ply\r\nformat binary_big_endian 1.0\r\ncomment c\r\nobj_info o\r\n"
                    "element extra 1\r\nproperty list uchar short l\r\n"
                    "element vertex 4\r\nproperty double x\r\nproperty float y\r\nproperty short z\r\n"
                    "property uchar red\r\nproperty uchar green\r\nproperty uchar blue\r\nproperty list char int junk\r\n"
                    "element face 2\r\nproperty uint flags\r\nproperty list ushort uint vertex_indices\r\n"
                    "end_header\r\n";
    std::string b = h;
    auto be = [&b](const void* v, int n) {
      for (int i = n - 1; i >= 0; --i)
        b += static_cast<const char*>(v)[i];
    };
    const std::uint8_t two = 2;
    const std::int16_t s7 = 7;
    b += char(two);
    be(&s7, 2);
    be(&s7, 2);
    for (int i = 0; i < 4; ++i)
    {
      const double x = i;
      const float y = 0.5f * float(i);
      const std::int16_t z = std::int16_t(-i);
      be(&x, 8);
      be(&y, 4);
      be(&z, 2);
      b += char(10 * i);
      b += char(20);
      b += char(30);
      b += char(1);
      const std::int32_t j = i;
      be(&j, 4);
    }
    const std::uint32_t flags = 5;
    const std::uint16_t three = 3, four = 4;
    const std::uint32_t f0[3] = { 0, 1, 2 }, f1[4] = { 0, 1, 2, 3 };
    be(&flags, 4);
    be(&three, 2);
    for (std::uint32_t v : f0)
      be(&v, 4);
    be(&flags, 4);
    be(&four, 2);
    for (std::uint32_t v : f1)
      be(&v, 4);
    Write(root / "ply" / "be_types.ply", b);
    WriteGz(root / "ply" / "be_types.ply.gz", b);
  }
  Write(root / "ply" / "ascii_poly.ply",
    "ply\nformat ascii 1.0\nelement vertex 5\nproperty float x\nproperty float y\nproperty float z\n"
    "property float nx\nproperty float ny\nproperty float nz\nproperty float s\nproperty float t\n"
    "element face 3\nproperty list int int vertex_index\nproperty list uchar float uv\n"
    "element edge 1\nproperty int a\nproperty int b\nend_header\n"
    "0 0 0 0 0 1 0 0\n1 0 0 0 0 1 1 0\n1 1 0 0 0 1 1 1\n0 1 0 0 0 1 0 1\n0.5 0.5 1e-3 0 0 1 .5 +.5\n"
    "4 0 1 2 3 0\n5 0 1 2 3 4 2 0.5 0.5\n2 0 1 0\n0 1\n");
  WriteGz(root / "ply" / "ascii_poly.ply.gz", Read(root / "ply" / "ascii_poly.ply"));
  WriteGz(root / "ply" / "bin_attr.ply.gz", Read(root / "ply" / "bin_attr.ply"));

  // STL: binary whose header starts with "solid", ASCII CRLF with a polygon facet, gzip.
  {
    std::string s = Read(root / "stl" / "bin.stl");
    std::memcpy(&s[0], "solid fake", 10);
    Write(root / "stl" / "bin_solid.stl", s);
    WriteGz(root / "stl" / "bin.stl.gz", s);
    Write(root / "stl" / "ascii_crlf.stl",
      "solid t\r\n facet normal 0 0 1\r\n  outer loop\r\n   vertex 0 0 0\r\n   vertex 1 0 0\r\n"
      "   vertex 1 1 0\r\n   vertex 0 1 0\r\n  endloop\r\n endfacet\r\nendsolid t\r\nsolid u\r\nendsolid\r\n");
    WriteGz(root / "stl" / "ascii.stl.gz", Read(root / "stl" / "ascii.stl"));
  }

  // OBJ: every face form, relative indices, comments, ignored statements.
  Write(root / "obj" / "forms.obj",
    "# comment\nmtllib m.mtl\no obj\nv 0 0 0\nv 1 0 0\nv 1 1 0 1\nvt 0 0\nvn 0 0 1\nf 1 2 3\n"
    "v 0 1 0 1 0 0\ng g\ns 1\nusemtl m\nf 1/1 3/1 4/1\nf 1//1 2//1 3//1\nf -4/1/1 -3/1/1 -2/1/1 -1/1/1\n"
    "l 1 2\nf 1 2\n");
  Write(root / "obj" / "crlf.obj", "v 0 0 0\r\nv 1 0 0\r\nv 0 1 0\r\nf 1 2 3\r\n");
  WriteGz(root / "obj" / "forms.obj.gz", Read(root / "obj" / "forms.obj"));
  std::printf("seeds written to %s\n", root.string().c_str());
  return 0;
}
