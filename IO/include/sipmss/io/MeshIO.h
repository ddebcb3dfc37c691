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

// Thrown by a reader when the sink's AbortRequested() returned true ("FILE: ELEMENT read
// aborted, at ...").
class ReadAbortedError : public MeshIOError
{
public:
  using MeshIOError::MeshIOError;
};

// A sink may throw StopRead (or a type derived from it) to end a read early, e.g. once it has
// seen enough of the faces: it passes through the readers unchanged, and MeshInputFile still
// copies a FIFO's rest for the next reads before passing it on.
struct StopRead
{
  virtual ~StopRead() = default;
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
  // The face scalars the input has (PLY: numeric face properties other than vertex_indices; a
  // vtkPolyData: its one-component cell arrays), for ReadOptions::faceFlag.
  std::vector<std::string> faceScalars;
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
  // With ReadOptions::faceFlag naming one of MeshHeader::faceScalars: called right after each
  // Triangles() with one byte per triangle of that call, 1 where the face's value is not 0 (a
  // polygon's triangles all take its value).
  virtual void TriangleFlags(const std::uint8_t* flags, std::size_t count)
  {
    (void)flags;
    (void)count;
  }
  virtual void End(const ReadStats& stats) = 0;
  // Called between chunks and on every refill of the reader's input buffer (at least once per
  // MiB of input, whatever the content: a long line, skipped records, dropped faces), and every
  // 0.1 s while a FIFO has no data; returning true stops the read with ReadAbortedError.
  virtual bool AbortRequested() { return false; }
};

struct ReadOptions
{
  bool verticesOnly = false;   // stop after the vertices (e.g. a bounds pass)
  std::size_t chunkElements = 1 << 14;
  bool dropDegenerateFaces = true; // faces with repeated indices are dropped and counted
  // A face scalar (MeshHeader::faceScalars) to deliver as MeshSink::TriangleFlags; empty, or a
  // name the input does not have: none.
  std::string faceFlag;
};

// Behaviour details (see also MeshIOInternal.h for reading from memory):
// - Detection is by content: PLY magic; binary STL when 84 + 50 * n equals the file size with
//   n > 0 (a header starting with "solid" does not matter), ASCII STL when text starts with
//   "solid", OBJ when the first statement is an OBJ keyword. Non-text content named *.stl[.gz], or
//   of unknown size (gzip, a pipe) announcing n > 0 facets, is read as binary STL. A header count
//   of 0 alone is no evidence: 84 zero bytes or /dev/zero are "not a mesh file (... all zero)"
//   unless named *.stl (then an empty STL). An empty file, gzip inside gzip ("compressed twice")
//   and gzip from a pipe or device (only regular files are decompressed; MeshInputFile copies
//   them first) are errors saying so.
// - Binary STL: a facet count that disagrees with the data (more facets than the file holds, or
//   bytes after the announced facets) is an error at byte 80.
// - ASCII PLY: an integer outside its declared type's range (uchar 300, uchar -5, short 40000,
//   also list counts and indices) is an error naming the element, the property and the line.
// - Aborts: see MeshSink::AbortRequested; reads never block in open(2) (a FIFO without a writer)
//   and wait for a pipe's data in poll(2), so an abort is seen within 0.1 s.
// - PLY: vertex x y z required; nx ny nz -> normals, red green blue [alpha] (or diffuse_*) -> rgba
//   (float colours 0..1 are scaled), u v / s t / texture_u texture_v -> texcoords, every other
//   scalar -> layout.scalars (in file order); vertex list properties and unknown elements are
//   skipped. Faces: the `vertex_indices` or `vertex_index` list, fans for polygons.
// - droppedFaces counts faces with fewer than 3 vertices plus, with dropDegenerateFaces, every
//   fan triangle with a repeated index (so one polygon may count more than once).
// - STL: facet normals are not delivered (empty layout). OBJ: `v x y z [anything]`, `f` with
//   i, i/t, i//n, i/t/n and negative indices; everything else ignored; no '\' line continuations.
//   A verticesOnly pass skips faces, except those before the first vertex (an error there).
// - Begin() gets the announced counts only for uncompressed PLY; 0 otherwise (see MeshHeader).
Format DetectFormat(const std::string& path); // by content (and .gz transparently)
ReadStats ReadMesh(const std::string& path, MeshSink& sink, const ReadOptions& options = {});
// A mesh input read any number of times (a bounds pass, then the real read). A regular file is
// re-read from its path. Anything else (a FIFO, /dev/stdin, a character device) can be read only
// once: the first Read copies its bytes, as it reads them, to a temporary file in `tmpdir`
// (empty: $TMPDIR, else /tmp), reads on to the end of the input, and every later Read replays
// that copy. The copy is unlinked as soon as it is created, so it disappears with this object or
// the process, however it ends (error, Ctrl-C, kill -9). Content that is not a mesh (/dev/zero)
// fails at once, before anything is copied; gzip from a pipe is copied whole, then decompressed.
// Not thread-safe: one Read at a time.
class MeshInputFile
{
public:
  explicit MeshInputFile(std::string path, std::string tmpdir = {});
  ~MeshInputFile();
  MeshInputFile(const MeshInputFile&) = delete;
  MeshInputFile& operator=(const MeshInputFile&) = delete;
  ReadStats Read(MeshSink& sink, const ReadOptions& options = {});
  const std::string& Path() const { return path_; }
  bool Spooled() const { return spoolFd_ >= 0 && spoolComplete_; } // replaying a copy

private:
  std::string path_, tmpdir_;
  int spoolFd_ = -1;
  bool spoolComplete_ = false;
};

// cheap: header only (PLY), else a scan. Uncompressed PLY: the header's counts (checked against
// the file size; faceCount = faces as announced, not triangles). Binary STL whose size matches:
// from its header. gzip PLY, ASCII STL, OBJ (and mismatched binary STL): a full validating read
// that counts (vertexCount = vertices delivered, faceCount = faces/polygons in the file).
MeshHeader ReadHeader(const std::string& path);

// The named properties alone, from the header (a PLY's, also gzip-compressed; never a scan):
// layout.scalars (the vertex properties a run can name as point arrays) and faceScalars (its
// face properties); the counts are 0. STL and OBJ name none (their layout comes from the body).
// It reads the start of `path`: a pipe loses those bytes (vtkSIPMSSDecimate calls it only for a
// regular file).
// Throws MeshIOError(path: reason) when the file cannot be opened or its header is malformed.
MeshHeader ReadProperties(const std::string& path);

// ---------------------------------------------------------------------------------------------
// Streaming writer. Counts are declared first; vertices then triangles are streamed.
// PLY needs every vertex before the first triangle; STL and OBJ accept triangles as soon as the
// vertices they reference were written. STL keeps vertex positions in memory up to 64 MiB, beyond
// that in a temporary file next to the output (unlinked as soon as it is created). Any count that
// differs from Begin's, an index out of range or an I/O failure throws MeshIOError(path: reason).
class MeshWriter
{
public:
  // format chosen from the extension (.ply binary LE unless ascii=true, .stl binary, .obj), each
  // optionally followed by .gz (then the file is gzip-compressed)
  static std::unique_ptr<MeshWriter> Create(const std::string& path, bool ascii = false);
  // Throws MeshIOError when Create would refuse path's extension; the message names shownAs
  // (default: path). Touches no file.
  static void CheckExtension(const std::string& path, const std::string& shownAs = {});
  virtual ~MeshWriter() = default;
  virtual void Begin(std::uint64_t vertexCount, std::uint64_t triangleCount,
    const VertexLayout& layout) = 0;
  virtual void Vertices(const VertexChunk& chunk) = 0;
  virtual void Triangles(const std::uint32_t* indices, std::size_t count) = 0;
  // With ReadOptions::faceFlag naming one of MeshHeader::faceScalars: called right after each
  // Triangles() with one byte per triangle of that call, 1 where the face's value is not 0 (a
  // polygon's triangles all take its value).
  virtual void TriangleFlags(const std::uint8_t* flags, std::size_t count)
  {
    (void)flags;
    (void)count;
  }
  virtual void End() = 0; // flushes and closes; throws MeshIOError on any I/O failure
};

} // namespace sipmss::io
