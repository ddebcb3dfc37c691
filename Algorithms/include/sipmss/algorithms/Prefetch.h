// Reads a MeshSource on a second thread while the caller's thread consumes the chunks.
#pragma once

#include "sipmss/algorithms/Common.h"

namespace sipmss::algorithms
{

// Wraps `source` so that its reader (parsing, decompression) runs on its own thread and hands
// copies of its chunks through a bounded queue (`depth` chunks, a few MB at most) to the sink on
// the calling thread. The sink sees exactly the same calls in the same order, so results do not
// depend on it. Errors of the reader are rethrown on the calling thread; when the sink throws
// (e.g. an abort), the reader is stopped and joined before the exception propagates.
MeshSource Prefetched(MeshSource source, std::size_t depth = 4);

} // namespace sipmss::algorithms
