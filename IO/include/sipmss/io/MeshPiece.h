// One file read in pieces by byte ranges, for ranks that share the work of one file: piece k of
// n reads its share of the faces (or STL facets) and only the vertex records those faces use,
// never the whole file. Possible for uncompressed binary PLY whose records have fixed sizes (all
// faces triangles) and for binary STL; anything else is read whole by one reader
// (SplitLayout::whyNot says why). The vertex bookkeeping of a PLY piece (which records its faces
// use, their numbers in the piece) is the caller's: algorithms::FilePiece keeps it in the DML.
#pragma once

#include "sipmss/io/MeshIO.h"

#include <cstdint>
#include <functional>
#include <string>
#include <utility>

namespace sipmss::io
{

// A file whose faces turn out not to be all triangles while a piece reads them (its sizes added
// up as if they were): the file cannot be read in pieces after all.
class NotSplittableError : public MeshIOError
{
public:
  using MeshIOError::MeshIOError;
};

// What ProbeSplit found.
struct SplitLayout
{
  std::string path;
  Format format = Format::Unknown;
  std::string whyNot;        // empty: the file can be read in pieces
  std::uint64_t fileBytes = 0;
  std::uint64_t vertexCount = 0; // binary PLY (binary STL: 0, vertices come with the facets)
  std::uint64_t faceCount = 0;   // PLY faces or STL facets
  // Binary PLY: where the records are (fixed sizes, checked against the file's size).
  std::uint64_t vertexOffset = 0, vertexStride = 0;
  std::uint64_t faceOffset = 0, faceStride = 0;
  std::uint32_t countOffset = 0, countSize = 0, indexSize = 0; // in a face record
  bool indexSigned = false;
  bool bigEndian = false;
  std::string vertexProperties; // the vertex element's property lines (for a piece's header)
};

// Reads the file's header (and size) only. A header the readers refuse is the same error here.
SplitLayout ProbeSplit(const std::string& path);

// The faces (STL facets) that piece k of n reads: [first, first + count), consecutive runs of
// about faceCount / n.
std::pair<std::uint64_t, std::uint64_t> PieceFaces(const SplitLayout& layout, int piece, int pieces);

// Binary PLY: the faces [first, first + count) as indices into the whole file's vertices, 3 a
// face, in chunks of at most `chunkFaces`. An index out of range is a MeshIOError naming the
// file, the face and its byte; a face that is not a triangle a NotSplittableError. Adds the
// bytes read to `bytes`; stops with ReadAbortedError when `aborted` returns true (asked once per
// chunk).
void ReadPlyFaceIndices(const SplitLayout& layout, std::uint64_t first, std::uint64_t count,
  const std::function<void(const std::uint32_t* indices, std::size_t faces)>& onFaces,
  std::uint64_t& bytes, const std::function<bool()>& aborted = nullptr,
  std::size_t chunkFaces = std::size_t(1) << 16);

// Binary PLY: a piece as a mesh of its own, read by the PLY reader (its checks, its layout and
// point data): `vertexCount` vertex records of the file, named by `nextVertices` in ascending
// order (fill up to n indices of the file, return how many), then `faceCount` triangles from
// `nextFaces` (fill up to n triangles, 3n indices into the piece's vertices). `name` names the
// piece in errors. Adds the bytes read from the file to `bytes`.
using IndexSource = std::function<std::size_t(std::uint32_t* out, std::size_t n)>;
ReadStats ReadPlyPiece(const SplitLayout& layout, std::uint64_t vertexCount,
  const IndexSource& nextVertices, std::uint64_t faceCount, const IndexSource& nextFaces,
  MeshSink& sink, const ReadOptions& options, std::uint64_t& bytes, const std::string& name);

// Binary STL: the facets [first, first + count) as an STL of their own (read by the STL reader).
ReadStats ReadStlPiece(const SplitLayout& layout, std::uint64_t first, std::uint64_t count,
  MeshSink& sink, const ReadOptions& options, std::uint64_t& bytes, const std::string& name);

} // namespace sipmss::io
