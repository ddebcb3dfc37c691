// Streaming, VTK-free mesh readers and writers (PLY, STL, OBJ; gzip input).
//
// Readers never hold the whole file: they parse into a bounded buffer and hand vertices and
// triangles to a MeshSink in chunks. Every count read from a header is checked against the
// file size before it sizes anything. Errors throw MeshIOError naming the file, the element
// and the byte or line offset.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <stdexcept>
#include <string>
#include <vector>

namespace sipmss::io
{

enum class Format : std::uint8_t
{
  Unknown,
  PlyAscii,
  PlyBinaryLE,
  PlyBinaryBE,
  StlAscii,
  StlBinary,
  Obj
};
const char* ToString(Format f);

class MeshIOError : public std::runtime_error
{
public:
  explicit MeshIOError(const std::string& message)
    : std::runtime_error(message)
  {
  }
};

// Which per-vertex attributes a file carries (as delivered to the sink).
struct VertexLayout
{
  bool normals = false;              // nx ny nz
  bool colors = false;               // red green blue [alpha] as uint8 RGBA
  bool texcoords = false;            // u v (s t, texture_u texture_v)
  std::vector<std::string> scalars;  // every other numeric vertex property, as float
};

struct MeshHeader
{
  Format format = Format::Unknown;
  // Counts announced by the file (PLY header). For STL/OBJ/gzip input they are 0 = unknown
  // until the end of the stream; the sink is told the final counts in End().
  std::uint64_t vertexCount = 0;
  std::uint64_t faceCount = 0;
  VertexLayout layout;
};

// One chunk of consecutive vertices [first, first + count).
struct VertexChunk
{
  std::uint64_t first = 0;
  std::size_t count = 0;
  const float* xyz = nullptr;       // 3 * count
  const float* normals = nullptr;   // 3 * count or null
  const std::uint8_t* rgba = nullptr; // 4 * count or null
  const float* texcoords = nullptr; // 2 * count or null
  const float* scalars = nullptr;   // layout.scalars.size() * count (interleaved per vertex) or null
};

struct ReadStats
{
  std::uint64_t vertices = 0;
  std::uint64_t triangles = 0;        // after triangulating polygons as fans
  std::uint64_t polygons = 0;         // faces as they appear in the file
  std::uint64_t droppedFaces = 0;     // faces with < 3 vertices or repeated indices (repair)
  std::uint64_t bytes = 0;            // bytes of (uncompressed) input consumed
};

class MeshSink
{
public:
  virtual ~MeshSink() = default;
  virtual void Begin(const MeshHeader& header) = 0;
  virtual void Vertices(const VertexChunk& chunk) = 0;
  // count triangles, 3 * count vertex indices (each < the final vertex count; checked by the
  // reader when the vertex count is known first, as for PLY, else at End()).
  virtual void Triangles(const std::uint32_t* indices, std::size_t count) = 0;
  virtual void End(const ReadStats& stats) = 0;
  // Called between chunks; returning true stops the read with MeshIOError("aborted").
  virtual bool AbortRequested() { return false; }
};

struct ReadOptions
{
  bool verticesOnly = false;   // stop after the vertices (e.g. a bounds pass)
  std::size_t chunkElements = 1 << 14;
  bool dropDegenerateFaces = true; // faces with repeated indices are dropped and counted
};

Format DetectFormat(const std::string& path); // by content (and .gz transparently)
ReadStats ReadMesh(const std::string& path, MeshSink& sink, const ReadOptions& options = {});
MeshHeader ReadHeader(const std::string& path); // cheap: header only (PLY), else a scan

// ---------------------------------------------------------------------------------------------
// Streaming writer. Counts are declared first; vertices then triangles are streamed.
class MeshWriter
{
public:
  // format chosen from the extension (.ply binary LE unless ascii=true, .stl binary, .obj)
  static std::unique_ptr<MeshWriter> Create(const std::string& path, bool ascii = false);
  virtual ~MeshWriter() = default;
  virtual void Begin(std::uint64_t vertexCount, std::uint64_t triangleCount,
    const VertexLayout& layout) = 0;
  virtual void Vertices(const VertexChunk& chunk) = 0;
  virtual void Triangles(const std::uint32_t* indices, std::size_t count) = 0;
  virtual void End() = 0; // flushes and closes; throws MeshIOError on any I/O failure
};

} // namespace sipmss::io
