#include "sipmss/algorithms/Common.h"

namespace sipmss::algorithms
{

MeshSource FileSource(const std::string& path)
{
  return [path](io::MeshSink& sink, const io::ReadOptions& options) {
    return io::ReadMesh(path, sink, options);
  };
}

} // namespace sipmss::algorithms
