// Entry points for tests and fuzzers: reading from memory, forcing a parser, small buffers, and
// the STL writer's in-memory limit. Not meant for application code (use MeshIO.h).
#pragma once

#include "sipmss/io/MeshIO.h"

#include <cstddef>
#include <string>

namespace sipmss::io
{

struct MemoryReadOptions
{
  // Parser to use regardless of what the content looks like: Unknown = detect by content;
  // PlyAscii/PlyBinaryLE/PlyBinaryBE = the PLY parser (the header decides the encoding);
  // StlAscii, StlBinary, Obj = that parser.
  Format force = Format::Unknown;
  // Size of the read buffer (0 = the default 1 MiB; at least 1 KiB). Small buffers exercise the
  // refill paths.
  std::size_t bufferBytes = 0;
  // Name used in error messages.
  std::string name = "<memory>";
};

// Reads a mesh held in memory (gzip-compressed or not, detected by magic).
ReadStats ReadMeshFromMemory(const void* data, std::size_t size, MeshSink& sink,
  const ReadOptions& options = {}, const MemoryReadOptions& memory = {});
Format DetectFormatFromMemory(const void* data, std::size_t size);

namespace detail
{
// Vertex positions the STL writer keeps in memory before spooling them to a temporary file next
// to the output (default 64 MiB). Returns the previous value. For tests.
std::size_t SetStlWriterMemoryLimit(std::size_t bytes);
} // namespace detail

} // namespace sipmss::io
