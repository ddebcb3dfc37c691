// Shared code of the mesh reader fuzzers: a sink that checks the reader's contract, and a driver
// that reads the input from memory (no temporary files) with small buffers and chunks.
#pragma once

#include "sipmss/io/MeshIO.h"
#include "sipmss/io/MeshIOInternal.h"

#include <cstddef>
#include <cstdint>
#include <cstring>

namespace sipmss::io::fuzz
{

#define SIPMSS_FUZZ_CHECK(cond)                                                                    \
  do                                                                                               \
  {                                                                                                \
    if (!(cond))                                                                                   \
      __builtin_trap();                                                                            \
  } while (0)

// Checks the chunk protocol and every index, and hashes what it gets (every byte is touched, so
// the sanitizers see any read past a chunk).
class CheckingSink final : public MeshSink
{
public:
  MeshHeader header;
  bool begun = false, ended = false;
  std::uint64_t vertices = 0, triangles = 0;
  std::uint64_t maxIndexPlusOne = 0;
  std::uint64_t vertexHash = 1469598103934665603ull;
  bool inOrder = true; // triangles may only reference vertices delivered before (STL, OBJ)

  void Begin(const MeshHeader& h) override
  {
    SIPMSS_FUZZ_CHECK(!begun);
    begun = true;
    header = h;
  }
  void Vertices(const VertexChunk& c) override
  {
    SIPMSS_FUZZ_CHECK(begun && !ended);
    SIPMSS_FUZZ_CHECK(c.count > 0 && c.first == vertices && c.xyz);
    SIPMSS_FUZZ_CHECK((c.normals != nullptr) == header.layout.normals);
    SIPMSS_FUZZ_CHECK((c.rgba != nullptr) == header.layout.colors);
    SIPMSS_FUZZ_CHECK((c.texcoords != nullptr) == header.layout.texcoords);
    SIPMSS_FUZZ_CHECK((c.scalars != nullptr) == !header.layout.scalars.empty());
    for (std::size_t i = 0; i < 3 * c.count; ++i)
    {
      std::uint32_t b;
      std::memcpy(&b, c.xyz + i, 4);
      SIPMSS_FUZZ_CHECK((b & 0x7f800000u) != 0x7f800000u); // finite
      vertexHash = (vertexHash ^ b) * 1099511628211ull;
    }
    volatile float sink = 0;
    if (c.normals)
      for (std::size_t i = 0; i < 3 * c.count; ++i)
        sink = sink + c.normals[i];
    if (c.texcoords)
      for (std::size_t i = 0; i < 2 * c.count; ++i)
        sink = sink + c.texcoords[i];
    if (c.scalars)
      for (std::size_t i = 0; i < header.layout.scalars.size() * c.count; ++i)
        sink = sink + c.scalars[i];
    if (c.rgba)
      for (std::size_t i = 0; i < 4 * c.count; ++i)
        sink = sink + c.rgba[i];
    vertices += c.count;
  }
  void Triangles(const std::uint32_t* idx, std::size_t n) override
  {
    SIPMSS_FUZZ_CHECK(begun && !ended && n > 0 && idx);
    for (std::size_t i = 0; i < 3 * n; ++i)
    {
      if (header.vertexCount)
        SIPMSS_FUZZ_CHECK(idx[i] < header.vertexCount);
      if (inOrder)
        SIPMSS_FUZZ_CHECK(idx[i] < vertices);
      if (idx[i] + std::uint64_t(1) > maxIndexPlusOne)
        maxIndexPlusOne = idx[i] + std::uint64_t(1);
    }
    triangles += n;
  }
  void End(const ReadStats& s) override
  {
    SIPMSS_FUZZ_CHECK(begun && !ended);
    ended = true;
    SIPMSS_FUZZ_CHECK(s.vertices == vertices);
    SIPMSS_FUZZ_CHECK(s.triangles == triangles);
    SIPMSS_FUZZ_CHECK(maxIndexPlusOne <= vertices);
    if (header.vertexCount)
      SIPMSS_FUZZ_CHECK(s.vertices == header.vertexCount);
  }
};

// Reads data with the parser `force` (Unknown = detect). A successful full read implies a
// successful vertices-only read with bit-identical vertices.
inline void Run(const std::uint8_t* data, std::size_t size, Format force, bool inOrder)
{
  MemoryReadOptions mo;
  mo.force = force;
  mo.bufferBytes = 1024; // small: the refill paths matter most
  mo.name = "fuzz";
  ReadOptions o;
  o.chunkElements = 1 + (size % 7);
  CheckingSink full;
  full.inOrder = inOrder;
  bool ok = true;
  try
  {
    ReadMeshFromMemory(data, size, full, o, mo);
    SIPMSS_FUZZ_CHECK(full.ended);
  }
  catch (const MeshIOError&)
  {
    ok = false;
  }
  CheckingSink vo;
  vo.inOrder = inOrder;
  o.verticesOnly = true;
  try
  {
    ReadMeshFromMemory(data, size, vo, o, mo);
    SIPMSS_FUZZ_CHECK(vo.ended && vo.triangles == 0);
    if (ok)
    {
      SIPMSS_FUZZ_CHECK(vo.vertices == full.vertices);
      SIPMSS_FUZZ_CHECK(vo.vertexHash == full.vertexHash);
    }
  }
  catch (const MeshIOError&)
  {
    SIPMSS_FUZZ_CHECK(!ok);
  }
}

} // namespace sipmss::io::fuzz
