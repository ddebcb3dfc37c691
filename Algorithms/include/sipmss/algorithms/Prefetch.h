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

// The queue's depth for a run with this memory budget (0: unbounded): 4 chunks, or 2 under a
// budget below 64 MiB, where the queue's buffers (about 0.2 MB a chunk, outside the DML) would
// be a visible share of the process (docs/architecture.md, "Memory outside the DML").
inline std::size_t PrefetchDepth(std::uint64_t memoryBudget)
{
  return memoryBudget == 0 || memoryBudget >= (std::uint64_t(64) << 20) ? 4 : 2;
}

} // namespace sipmss::algorithms
