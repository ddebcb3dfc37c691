// libFuzzer target: the OBJ reader, plus detection and the auto-detected reader, from memory.
#include "FuzzCommon.h"

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size)
{
  using namespace sipmss::io;
  fuzz::Run(data, size, Format::Obj, true);
  const Format f = DetectFormatFromMemory(data, size);
  const bool ply = f == Format::PlyAscii || f == Format::PlyBinaryLE || f == Format::PlyBinaryBE;
  fuzz::Run(data, size, Format::Unknown, !ply);
  return 0;
}
