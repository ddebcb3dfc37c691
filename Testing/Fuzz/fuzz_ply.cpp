// libFuzzer target: the PLY reader (all encodings, gzip) from memory.
#include "FuzzCommon.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size)
{
  using namespace sipmss::io;
  // PLY may store faces before vertices: only the header count bounds the indices.
  fuzz::Run(data, size, Format::PlyAscii, /*inOrder=*/false);
  return 0;
}
