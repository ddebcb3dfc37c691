// libFuzzer target: both STL readers on every input, plus detection, from memory.
#include "FuzzCommon.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size)
{
  using namespace sipmss::io;
  fuzz::Run(data, size, Format::StlAscii, true);
  fuzz::Run(data, size, Format::StlBinary, true);
  (void)DetectFormatFromMemory(data, size);
  return 0;
}
