// Algorithm I of SIPMSS (the decimation's private header: its state, its types and the map of
// its passes): a linear-time iterative full edge collapse with quadric error metrics,
// written against the DML so that it runs in core or out of core with identical results.
//
// Stages (paper section 4.1):
//   read      the source is streamed into DML blocks: positions as doubles relative to the first
//             vertex (exact for float input), triangles, packed point attributes. Blocks grow
//             with Resize when the source does not announce its counts (OBJ, STL, gzip), and
//             vertices and triangles may interleave (OBJ).
//   [weld]    optional (weldDistance >= 0): a spatial hash in the DML joins close vertices.
//   rings     one pass over the faces validates them, drops zero-area ones and counts degrees;
//             a prefix sum gives CSR offsets; a second pass fills the incident face lists.
//             Faces on one vertex set: copies of one orientation become one face; a double-
//             sided pair (opposite orientations) cancels where other faces already close its
//             edges (zero-volume pillows in scans) and keeps the face that matches its neighbour
//             where cancelling would open a hole (thin parts folded by clustering).
//   quadrics  area-weighted face plane quadrics (one per face, added to its corners in face
//             order), boundary constraint quadrics (plane through the edge perpendicular to its
//             face, weight boundaryWeight * |edge|^2), options.initialQuadric. Vertices on an edge
//             with > 2 faces, or where several boundary fans meet, are flagged kComplex: their
//             edges are counted before a collapse; a non-manifold edge collapses like any other
//             under the link condition (its common neighbours are exactly the vertices opposite
//             it, and no two of those faces become duplicates).
//   collapse  passes without a global priority queue. Each pass
//               1. keeps for every vertex its cheapest collapse (and the second cheapest edge):
//                  optimal placement from the summed quadric when well conditioned, else the
//                  best point of the segment, endpoints preferred on ties. Incremental and exact:
//                  only the survivors of the last pass and vertices whose best and second best
//                  both pointed at a collapsed pair evaluate their edges (each edge once);
//               2. orders the cheapest candidates (about twice the collapses the pass needs) by
//                  a counting sort on the cost's float bits: a cost quantile as threshold, linear
//                  time, deterministic;
//               3. collapses them in that order while the pass goal is not met, checking legality
//                  then (link condition, no tetrahedron collapse, no vanishing component, no
//                  normal flip or excessive turn, no zero-area face, boundary rules). The two
//                  endpoints of a collapse are busy for the rest of the pass (the survivor's ring
//                  list is stale until step 4); a candidate with a busy endpoint is skipped.
//                  Neighbours stay free: their rings are exact (faces are relabelled in place)
//                  and their candidates' costs unchanged, and legality is checked against the
//                  current positions, so collapses of one pass may share faces and a pass
//                  removes up to about a third of the triangles. Passes that cannot end on a
//                  level go group by group through fixed vertex chunks: a collapse whose
//                  endpoints and ring vertices all lie in one chunk touches only that chunk's
//                  data, so the chunks run at once (in core: on all cores); the others run one
//                  at a time after each round, in order;
//               4. compacts the live vertices and faces (in place, order kept), shrinks the
//                  blocks, rebuilds the rings and calls Reconfigure(): the run moves in core as
//                  the mesh shrinks.
//             A pass removes at most passFraction of the triangles (farPassFraction while the
//             mesh has more than farRatio times the level's) and never goes below the next
//             level's target, so levels and the final target are met exactly (or one below).
//             In core, the rings (validation, fill, duplicate search), the quadrics, the sweep,
//             the step's chunks and compaction (by vertex range or by array) run on all cores;
//             the output is the same for any thread count and storage mode.
//   write     the final level is streamed to the output sink.
// Every loop over many elements ticks the progress (abort within a few milliseconds). Each
// phase and each step of a pass announces its work (kWork: measured seconds per element) and an
// estimate of the rest of the run (the remaining passes simulated with the pass schedule): the
// progress is monotonic and about linear in time (Progress::BeginPhase).
//
// The state of a run is three structs, and every pass is a free function that takes the ones it
// uses: RunContext (the options, the progress, the statistics, the thread count), MeshState (the
// blocks in the DML, their counts and views, the input's description) and PassState (what a
// pass leaves for its steps: the cost histogram, the face split, the lazy sums, the threads'
// scratch). A phase reads and writes the blocks through the accessor (storage::View, and a
// template over the access kind with storage::WithAccess where a loop is hot) and runs on the
// workers storage::Workers gives it (in core on every thread, out of core on a helper with a
// forked DML, or on one); docs/architecture.md lists the few places that still depend on the
// mode (prefetch hints, the lazy quadric sums, the collapse rounds' schedule).
//
// Files: this header (the types, the state, the declarations of the passes), read and weld
// (Read.inl), rings and quadrics (Rings.inl), the candidate sweep (Sweep.inl), legality, the
// collapse and the step (Step.inl), compaction and output (Compact.inl), the schedule, the run
// (a pipeline of the passes) and the entry points (../Decimate.cpp).
// They are one translation unit: Decimate.cpp includes them after this header, so that all of
// Algorithm I stays internal (an anonymous namespace) and the compiler inlines and specializes
// across the passes as it did when they were one file (as separate translation units, 1.4% more
// instructions on dragon_vrip_res2 to 10K on one thread, callgrind).
#pragma once

#include "sipmss/algorithms/Attributes.h"
#include "sipmss/algorithms/Compare.h"
#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/Placement.h"
#include "sipmss/algorithms/Quadric.h"
#include "sipmss/algorithms/Vector.h"
#include "sipmss/storage/Access.h"
#include "sipmss/storage/Parallel.h"
#include "sipmss/storage/Prefault.h"
#include "sipmss/storage/Threads.h"

#include "../StoredMesh.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <ctime>
#include <limits>
#include <memory>
#include <atomic>
#include <condition_variable>
#include <exception>
#include <functional>
#include <initializer_list>
#include <mutex>
#include <string>
#include <system_error>
#include <thread>
#include <vector>
#if defined(__GLIBC__)
#include <malloc.h>
#endif

namespace sipmss::algorithms
{
namespace
{
using placement::PlaceLanes;
using placement::PlaceOut;
#ifdef SIPMSS_LANES
using placement::Lanes2;
#endif
using storage::Array;
using storage::BlockId;
using storage::DML;
using storage::RethrowFirst;
using storage::RunOnThreads;
using storage::View;
using storage::WithAccess;
using storage::Workers;


constexpr std::uint32_t kNone = 0xffffffffu;

// The attribute-aware paths (mesh.xSize > 0) are out of line and cold: a run without attributes
// keeps the hot loops' code as it was.
#if defined(__GNUC__)
#define SIPMSS_COLD __attribute__((noinline, cold))
#else
#define SIPMSS_COLD
#endif
constexpr int kCostBins = 1 << 15;
constexpr int kGroups = 4;
// Step 3 in chunks (StepChunks): by default at most kStepChunks chunks of at least
// kStepChunkMinSize vertices (measured on Dragon-size: 8192 defers 4x more collapses to the
// sequential part than 32768), for passes over at least two chunks; the last kStepTail faces of
// a pass's goal are collapsed one at a time.
constexpr std::uint64_t kStepChunks = 64;
constexpr std::uint64_t kStepChunkMinSize = 32768;
constexpr std::uint64_t kStepTail = 4096;
// A pass far from its level runs its cost groups in turn on each part of kStepPart vertices of
// a chunk (StepChunks). Lucy-size at 8 MB, the first pass's chunks: 88,000 page misses with
// parts of 4,096 vertices, 115,000 with 16,384, 153,000 with 65,536, 144,000 group by group.
constexpr std::uint64_t kStepPart = 4096;
// Out of core, StepChunks runs on two threads only when each half of the budget holds this
// many bytes of pages (a part's window over about eight arrays); with less, on one thread.
// Dragon-size at 1 MB: the forked step 0.74-0.76 s against 0.46-0.52 s on one thread; at
// 2 MB: 0.31-0.32 s against 0.39-0.43 s.
constexpr std::uint64_t kStepWindowBytes = 1 << 20;
// LegalFaces compares every vertex of one ring with every face of the other: above this product
// of the two rings' face counts (vertices of very high valence), Legal's sorted tables instead.
constexpr std::size_t kLegalFacesMax = 1024;
// A collapse whose two vertices have more faces than this in their rings (the lists built at
// the start of the pass) is not made: legality reads both rings, and a vertex of valence
// 200,000 (a fan) would cost that much on each of its neighbours' attempts. Its neighbours'
// collapses bring its valence down until it can collapse too. Scans have rings of 4 to 20.
constexpr std::uint32_t kMaxCollapseRing = 4096;
// The face split of the collapse rounds (FaceSplit) is used when at most 1 face in this many is
// on the wrong side of it.
constexpr std::uint64_t kSplitWrongShare = 256;
// BuildRings' passes 1 and 3 run on all cores from this many faces.
constexpr std::uint64_t kParallelRingsMin = 65536;
// Compact runs on several threads from this many vertices.
constexpr std::uint64_t kParallelCompactMin = 65536;

// Per-vertex state bits.
using State = std::uint16_t;
constexpr State kRemoved = 1;      // collapsed into another vertex during this pass
constexpr State kMarked = 2;       // touched by a collapse of this pass
constexpr State kBoundary = 4;     // has boundary edges
constexpr State kLocked = 8;       // never collapsed (reserved: nothing sets it at present)
constexpr State kFixed = 16;       // lockBoundary, locks, selections: never moves, never removed (may absorb)
constexpr State kNeedsLegal = 32;  // its cheapest collapse was illegal: evaluate with legality
constexpr State kSurvivor = 64;    // survived a collapse of the last pass: all its edges changed
constexpr State kRecompute = 128;  // its candidate is unknown: evaluate its edges
constexpr State kCollapsed = 256;  // survived a collapse of this pass
constexpr State kComplex = 512;    // on an edge with > 2 faces, or where several fans meet
constexpr State kPromote = 1024;   // its best partner collapsed: its second best became the best
constexpr State kDeferred = 2048;  // step 3: its collapse leaves its chunk, it runs after the round
constexpr State kMerged = 4096;    // survived a collapse of some pass (the final fit may move it)
static_assert((kRemoved | kMarked | kBoundary | kLocked | kFixed | kNeedsLegal | kSurvivor |
                kRecompute | kCollapsed | kComplex | kPromote | kDeferred | kMerged) ==
    kRemoved + kMarked + kBoundary + kLocked + kFixed + kNeedsLegal + kSurvivor + kRecompute +
      kCollapsed + kComplex + kPromote + kDeferred + kMerged,
  "one bit per state");
// An endpoint of a collapse of this pass: its ring in the CSR is stale until Compact.
constexpr State kBusy = kRemoved | kCollapsed;
// Vertices evaluated by the sweep (kNeedsLegal ones take the heavy path instead).
inline bool Active(State s)
{
  return (s & (kSurvivor | kRecompute)) != 0 && (s & (kNeedsLegal | kLocked)) == 0;
}

// The corner after and before corner c of a triangle: (c + 1) % 3 and (c + 2) % 3.
constexpr int kNextCorner[3] = { 1, 2, 0 };
constexpr int kPrevCorner[3] = { 2, 0, 1 };

struct Tri
{
  std::uint32_t v[3];
};
inline bool Alive(const Tri& t)
{
  return t.v[0] != kNone;
}
inline bool Has(const Tri& t, std::uint32_t x)
{
  return t.v[0] == x || t.v[1] == x || t.v[2] == x;
}
constexpr Tri kDeadTri = { { kNone, kNone, kNone } };
// The corner of t that is x (which appears once in a live face); no branches: which corner it is
// is random, and a mispredicted branch here cost 6% of a run.
inline int CornerOf(const Tri& t, std::uint32_t x)
{
  return int(t.v[1] == x) + 2 * int(t.v[2] == x);
}

// Symmetric 4x4 quadric, upper triangle row by row:
// a00 a01 a02 b0 | a11 a12 b1 | a22 b2 | c  ->  E(p) = p^T A p + 2 b.p + c
inline void AddPlane(Quadric& Q, const Vec3& n, double d, double w)
{
  AddTo(Q, PlaneQuadric(n.x, n.y, n.z, d, w));
}
inline double Eval(const Quadric& Q, const Vec3& p)
{
  return QuadricValue(Q.q, p.x, p.y, p.z);
}
inline double Trace(const Quadric& Q)
{
  return QuadricTrace(Q.q);
}

// The ranking key of a collapse whose summed quadric (with the attribute error, if any) has the
// value `cost` at its placement and geometric trace `trace`. Without attributes: the cost, an
// area-weighted sum (Garland-Heckbert; it keeps triangles even, which measured best for the
// geometry). With attributes: the cost per unit of trace, the error measure of the bound and of
// RunStats::achievedError, a mean squared distance plus the area-weighted attribute error, as
// meshoptimizer ranks its collapses, so that equal weights balance geometry and attributes as
// there. Ranked by the sum, a large region's collapse costs its area times more: the run spent
// its triangles on even interiors instead of the attribute borders (docs/benchmarks.md, the
// twenty-third session: color RMS at colors:1 on Dragon-size 0.0789 -> 0.0731).
inline double RankKey(std::size_t xSize, double cost, double trace)
{
  return xSize && trace > 0 ? cost / trace : cost;
}
// The error of a collapse (per unit of its trace, RunStats::achievedError squared) from its key.
inline double KeyError(std::size_t xSize, double key, double trace)
{
  return xSize ? key : key / trace;
}

// One pass's candidate of a vertex: collapse it with `partner` to p; t = position of p along the
// edge (0: this vertex, 1: partner) for the point data. cost: the ranking key (RankKey).
//
// cost2/partner2: the cheapest of the other edges (the second best), so that a vertex whose best
// partner collapsed can take it without evaluating all its edges again; cost2 is NaN when not
// known exactly. t < 0: the placement of the best edge is still to be computed (a promotion).
// Single precision (32 bytes, two to a cache line): the array is the largest per-vertex one
// after the quadrics and every pass reads and writes it at random. Costs are rounded to float
// before any comparison (Apply), so the order of offers still cannot change the outcome; p
// carries the float precision of the output's coordinates.
struct Cand
{
  float cost;
  float p[3];
  std::uint32_t partner;
  float t;
  float cost2;
  std::uint32_t partner2;
};
static_assert(sizeof(Cand) == 32, "Cand layout");
inline bool Before(double a, std::uint32_t pa, double b, std::uint32_t pb)
{
  return a < b || (a == b && pa < pb); // false when b is NaN (unknown)
}

struct Placement
{
  double cost;
  Vec3 p;
  double t;
};

// Edges of the candidate sweep waiting for their placement, as lanes: the summed quadric and
// both endpoints' positions, and where the result goes.
struct EdgeBatch
{
  static constexpr int kLanes = 2;
  int n = 0;
  alignas(32) double q[10][kLanes];
  alignas(32) double pu[3][kLanes];
  alignas(32) double pv[3][kLanes];
  double trace[kLanes]; // the summed quadric's (geometric) trace
  std::uint32_t u[kLanes], v[kLanes];
  bool offerV[kLanes];
};

// The views of one DML over the mesh's blocks: the mesh's own, or those of a worker's DML
// (an out-of-core helper thread's).
struct Views
{
  View<Vec3> P;
  View<Quadric> Q;
  View<std::uint8_t> A;
  View<double> X; // the attribute quadrics' extension (MeshState::extra), when attributes
  View<State> S;
  View<Tri> F;
  View<std::uint32_t> RO, RF;
  View<Cand> C;
  View<std::uint32_t> O;
};

// The sum of vertices u's and v's attribute extensions (n doubles each, MeshState::extra) into
// `sum`: read in place in core, through the buffers a and b out of core.
inline void SumExtension(const View<double>& X, std::size_t n, std::uint64_t u, std::uint64_t v,
  std::vector<double>& sum, std::vector<double>& a, std::vector<double>& b)
{
  sum.resize(n);
  const double* x = X.Run(u * n, n, a);
  const double* y = X.Run(v * n, n, b);
  for (std::size_t i = 0; i < n; ++i)
  {
    sum[i] = x[i] + y[i];
  }
}

// Fetches the cache lines of element *p (storage::PrefetchElement: a quadric spans two lines, a
// position or a face straddles two at some indices).
template <class T>
SIPMSS_ALWAYS_INLINE void Prefetch(const T* p)
{
  storage::PrefetchElement(p);
}

// The same for element i of an array that a dead face's corner (kNone) may index: the address
// is computed as an integer (no pointer past the array) and never dereferenced; a prefetch does
// not fault. Cheaper than testing which faces are dead (random, a mispredicted branch).
template <class T>
SIPMSS_ALWAYS_INLINE void PrefetchAt(const T* base, std::uint32_t i)
{
  Prefetch(reinterpret_cast<const T*>(
    reinterpret_cast<std::uintptr_t>(base) + std::uintptr_t(i) * sizeof(T)));
}

template <class T>
void FillBlock(DML& dml, const Array<T>& a, const T& value)
{
  dml.Fill(a.Id(), &value);
}

// A vertex's ring loaded into memory (bounded by its valence, not by the input).
struct RingFace
{
  std::uint32_t id;
  Tri t;
  int corner;          // index of the ring's vertex in t
  std::uint32_t nb[2]; // nbs index of t.v[(corner + 1) % 3] and of t.v[(corner + 2) % 3]
};
struct Nb
{
  std::uint32_t v;
  std::uint32_t count;  // faces of the ring containing the edge
  std::uint32_t opp[2]; // the third vertices of the first two of them
  Vec3 p;               // position of v (when loaded with positions)
};
struct Ring
{
  std::uint32_t x = kNone;
  Vec3 px{ 0, 0, 0 };
  std::vector<std::uint32_t> ids;
  std::vector<RingFace> faces;
  std::vector<Nb> nbs; // sorted by v
  std::vector<std::uint64_t> keys;

  const Nb* Find(std::uint32_t v) const
  {
    auto it = std::lower_bound(
      this->nbs.begin(), this->nbs.end(), v, [](const Nb& n, std::uint32_t x) { return n.v < x; });
    return (it != this->nbs.end() && it->v == v) ? &*it : nullptr;
  }
  // Is there a face (x, a, b) in the ring?
  bool HasFace(std::uint32_t a, std::uint32_t b) const
  {
    const Nb* n = this->Find(a);
    if (!n)
    {
      return false;
    }
    if (n->count <= 2)
    {
      return n->opp[0] == b || (n->count == 2 && n->opp[1] == b);
    }
    return this->HasFaceWith(a, b);
  }
  // The same from the faces alone (no neighbour table).
  bool HasFaceWith(std::uint32_t a, std::uint32_t b) const
  {
    for (const RingFace& f : this->faces)
    {
      if (Has(f.t, a) && Has(f.t, b))
      {
        return true;
      }
    }
    return false;
  }
  // The corner positions of face `slot`, in the face's order.
  void Corners(std::size_t slot, Vec3 out[3]) const
  {
    const RingFace& f = this->faces[slot];
    out[f.corner] = this->px;
    out[(f.corner + 1) % 3] = this->nbs[f.nb[0]].p;
    out[(f.corner + 2) % 3] = this->nbs[f.nb[1]].p;
  }
};

template <class K>
void SmallSort(K* a, std::size_t n)
{
  if (n > 24)
  {
    std::sort(a, a + n);
    return;
  }
  for (std::size_t i = 1; i < n; ++i)
  {
    K k = a[i];
    std::size_t j = i;
    while (j > 0 && k < a[j - 1])
    {
      a[j] = a[j - 1];
      --j;
    }
    a[j] = k;
  }
}

struct EdgeCand
{
  double cost;
  std::uint32_t v;
  std::uint32_t nbIndex;
  Placement pl;
};

// An offer to a vertex of another thread's range, applied after a barrier.
struct Deferred
{
  std::uint32_t x, partner;
  bool fromPartner;
  Placement pl;
};

// One thread's scratch for the candidate sweep (and the main thread's for the collapses).
// Scratch vectors keep their capacity from one vertex to the next, except after a ring of a
// vertex of very high valence: then they are released, so that its memory is not held on.
template <typename T>
void ReleaseIfLarge(std::vector<T>& v)
{
  if (v.capacity() > 65536)
  {
    std::vector<T>().swap(v);
  }
}

// Where a vertex's neighbours occur in its ring's next and prev corner lists (the vertex after
// and before it in each face), answered in log n. The linear scans that small rings use are
// quadratic for a vertex of high valence (a fan of 200,000 faces); the answers are the same.
class LinkTally
{
public:
  // Rings with more entries than this use the tally.
  static constexpr std::size_t kMinEntries = 32;

  void Build(const std::uint32_t* next, const std::uint32_t* prev, std::size_t n)
  {
    Fill(this->next_, next, n);
    Fill(this->prev_, prev, n);
  }
  // How many entries of next (inNext) or prev are a.
  std::size_t Count(bool inNext, std::uint32_t a) const
  {
    const std::vector<std::uint64_t>& keys = inNext ? this->next_ : this->prev_;
    const std::uint64_t lo = std::uint64_t(a) << 32;
    return std::size_t(std::upper_bound(keys.begin(), keys.end(), lo | 0xffffffffu) -
      std::lower_bound(keys.begin(), keys.end(), lo));
  }
  // Whether entry i of next (inNext) or prev is the first occurrence of its value a there.
  bool First(bool inNext, std::uint32_t a, std::size_t i) const
  {
    const std::vector<std::uint64_t>& keys = inNext ? this->next_ : this->prev_;
    const std::uint64_t lo = std::uint64_t(a) << 32;
    const auto it = std::lower_bound(keys.begin(), keys.end(), lo);
    return it != keys.end() && (*it >> 32) == a && (*it & 0xffffffffu) == i;
  }
  void Release()
  {
    ReleaseIfLarge(this->next_);
    ReleaseIfLarge(this->prev_);
  }

private:
  static void Fill(std::vector<std::uint64_t>& keys, const std::uint32_t* a, std::size_t n)
  {
    keys.resize(n);
    for (std::size_t i = 0; i < n; ++i)
    {
      keys[i] = (std::uint64_t(a[i]) << 32) | i; // (value, index): ascending indices per value
    }
    std::sort(keys.begin(), keys.end());
  }

  std::vector<std::uint64_t> next_, prev_;
};

// A cache line of its own for each thread's scratch (and each chunk's counters): the threads
// write them all the time, and two of them sharing a line cost up to 30% of a run, depending
// on where the heap happened to put them.
constexpr std::size_t kCacheLine = 64;
struct alignas(kCacheLine) Scratch
{
  Ring ru, rv;
  LinkTally tally; // Evaluate's, for rings of more than LinkTally::kMinEntries
  std::vector<EdgeCand> edges;
  std::vector<std::uint32_t> ids, next = std::vector<std::uint32_t>(64),
                                  prev = std::vector<std::uint32_t>(64);
  std::vector<std::uint8_t> abuf, abuf2; // point data of a collapse
  std::vector<double> xbuf, xbuf2, xbuf3; // attribute quadrics' extensions of an edge
  std::uint32_t lo = 0, hi = kNone;        // the vertices whose candidates this thread writes
  std::vector<std::vector<Deferred>> out; // offers to the other threads' vertices, by thread
  EdgeBatch batch;                        // the sweep's edges waiting for their placement
  Views* w = nullptr; // the views this thread uses; nullptr: the mesh's
  double achievedErr2 = 0; // the largest error of this thread's collapses (Compact gathers it)
  // This pass's step-1 counts (RunStats::passes; Pass gathers and resets them); promoted: the
  // placements of promoted second bests among `placed` (made once: a sweep run again after its
  // threads gave way finds them done).
  std::uint64_t active = 0, placed = 0, promoted = 0;
};

// A worker's views for the scratch it uses, for the scope of its range.
struct ScratchViews
{
  Scratch& s;
  ScratchViews(Scratch& scratch, Views& views)
    : s(scratch)
  {
    scratch.w = &views;
  }
  ~ScratchViews() { this->s.w = nullptr; }
  ScratchViews(const ScratchViews&) = delete;
  ScratchViews& operator=(const ScratchViews&) = delete;
};

// A reusable barrier for a fixed number of threads (C++17 has none).
class Barrier
{
public:
  explicit Barrier(int n)
    : n_(n)
  {
  }
  void Wait()
  {
    std::unique_lock<std::mutex> lock(this->m_);
    const std::uint64_t gen = this->gen_;
    if (++this->count_ == this->n_)
    {
      this->count_ = 0;
      ++this->gen_;
      this->cv_.notify_all();
      return;
    }
    this->cv_.wait(lock, [&] { return gen != this->gen_; });
  }
  // Wait(), and returns `flag` as the last participant to arrive saw it: the same value for
  // all of them (a flag read after the barrier may already be set by a participant that went
  // on, e.g. an abort in the next round: the others would then leave while it waits alone).
  bool WaitAndAgree(const std::atomic<bool>& flag)
  {
    std::unique_lock<std::mutex> lock(this->m_);
    const std::uint64_t gen = this->gen_;
    if (++this->count_ == this->n_)
    {
      this->count_ = 0;
      this->agreed_ = flag.load();
      ++this->gen_;
      this->cv_.notify_all();
      return this->agreed_;
    }
    this->cv_.wait(lock, [&] { return gen != this->gen_; });
    return this->agreed_; // (the next generation needs this participant: not overwritten yet)
  }
  // One participant leaves for good (a thread that could not be started).
  void Drop()
  {
    std::unique_lock<std::mutex> lock(this->m_);
    if (--this->n_ > 0 && this->count_ == this->n_)
    {
      this->count_ = 0;
      ++this->gen_;
      this->cv_.notify_all();
    }
  }

private:
  std::mutex m_;
  std::condition_variable cv_;
  int n_;
  int count_ = 0;
  std::uint64_t gen_ = 0;
  bool agreed_ = false;
};

// The final fit's sample: an input vertex's position (about the origin) and the vertex of the
// current mesh that stands for it (kNone: none, its faces are gone).
struct FitSample
{
  float p[3];
  std::uint32_t owner;
};

// The state of a run, in three parts that the passes take explicitly.

// What the run is asked and where it reports; fixed for the run.
struct RunContext
{
  RunContext(const DecimateOptions& options, Progress& progress_, RunStats& stats_)
    : opt(options)
    , progress(progress_)
    , stats(stats_)
    , cosThreshold(options.minNormalCosine)
    , threads(std::min(storage::ResolveThreads(options.threads), 16))
  {
  }
  const DecimateOptions& opt;
  Progress& progress;
  RunStats& stats;
  double cosThreshold;
  int threads;
  bool emitsLevels = false; // onLevel given: each level is emitted during the passes
  // Triangles added to the target for the fixed vertices (opt.trianglesPerFixedVertex).
  std::uint64_t extraTarget = 0;
  // The error bound as a quadric cost per unit of trace (a squared distance; set once the input
  // is read: SetErrorBound), and the largest such cost of the collapses made (Compact).
  double maxErr2 = std::numeric_limits<double>::infinity();
  double diagonal = 0;
  double achievedErr2 = 0;
  // Element i of n of the current phase: the progress every 1024 elements (and an abort check).
  void Tick(std::uint64_t i, std::uint64_t n)
  {
    if ((i & 1023) == 0)
    {
      this->progress.Tick(n ? double(i) / double(n) : 0.0);
    }
  }
};

// The mesh the passes transform: its blocks in the DML, their counts, the input's description.
struct MeshState
{
  explicit MeshState(const DecimateOptions& options)
    : ownDml(options.dml ? nullptr : new DML())
    , dml(options.dml ? *options.dml : *ownDml)
  {
    if (options.origin)
    {
      this->origin = { (*options.origin)[0], (*options.origin)[1], (*options.origin)[2] };
      this->haveOrigin = true;
      // (the bounds start empty: the origin need not be a vertex)
      constexpr double inf = std::numeric_limits<double>::infinity();
      this->lo = { inf, inf, inf };
      this->hi = { -inf, -inf, -inf };
    }
  }
  // The DML: the caller's (options.dml) or our own; declared before every block so that the
  // blocks close first.
  std::unique_ptr<DML> ownDml;
  DML& dml;

  // Input description.
  io::VertexLayout layout;
  std::size_t nFloats = 0; // normals, texcoords, scalars as floats
  std::size_t recSize = 0; // bytes of one vertex's attribute record
  // The float index in the attribute record of the lock and selection scalars (-1: none).
  int lockFloat = -1, selectFloat = -1;
  // Attribute-aware error (DecimateOptions::attributes): the record's channels in the error, and
  // per vertex xSize doubles in `extra` (Attributes.h: alpha, Qa, B and e per channel); the
  // quadrics stay geometric. xSize 0: none.
  std::vector<AttributeChannel> channels;
  std::size_t xSize = 0;
  // A selection by a face scalar (faceSelect): outside[v] != 0 when v is a corner of a face
  // outside the selection (set as the faces are read; such a vertex is fixed). lastTris: the
  // corners of the reader's last Triangles() call, which its TriangleFlags() follows.
  bool faceSelect = false;
  Array<std::uint8_t> outside;
  std::vector<std::uint32_t> lastTris;
  std::uint64_t trianglesRead = 0, trianglesFlagged = 0; // (every triangle must get its flag)
  std::uint64_t announcedV = 0, announcedF = 0;
  bool begun = false;
  Vec3 origin{ 0, 0, 0 };
  bool haveOrigin = false;
  Vec3 lo{ 0, 0, 0 }, hi{ 0, 0, 0 }; // the input's bounds (about origin; once haveOrigin)
  std::uint64_t vCap = 0, fCap = 0;
  std::uint64_t readerDropped = 0, dropped = 0;

  // The current mesh.
  std::uint64_t nv = 0, nf = 0, liveFaces = 0;
  Array<Vec3> pos;
  Array<Quadric> quad;
  Array<std::uint8_t> attr; // nv * recSize bytes
  Array<double> extra;       // nv * xSize doubles
  Array<State> state;
  Array<Tri> faces;
  Array<std::uint32_t> ringOff;  // nv + 1
  Array<std::uint32_t> ringFace; // ringOff[nv]
  Array<Cand> cand;
  Array<std::uint32_t> order; // the pass's candidates in processing order (<= nv of them)
  Array<std::uint32_t> remap; // compaction: old vertex -> new

  // The final fit (Fit.inl): a sample of the input's vertices, each with the vertex of the
  // current mesh that stands for it (Compact follows the collapses), and the fitted positions
  // of the current mesh (valid until the next Compact, which closes them).
  Array<FitSample> samples;
  std::uint64_t nSamples = 0;
  Array<Vec3> fitted;
  bool fittedValid = false;

  // The views of the blocks through the DML (BindViews after anything that opens, resizes or
  // reconfigures), and those of a worker (through its DML, within its write ranges).
  Views views;
  void BindViews();
  void BindViews(Views& w, DML& on) const;
  void BindViews(Views& w, const Workers& workers, int t) const;
  // The views a thread uses: its scratch's, else the mesh's own.
  Views& W(const Scratch& s) { return s.w ? *s.w : this->views; }

  // Buffers of the read and the output.
  std::vector<Vec3> vbuf;
  std::vector<std::uint8_t> abuf;
  std::vector<Tri> tbuf;
  // In core with more than one thread, the read's blocks are made present on another core
  // while the reader fills them (storage/Prefault.h; BeginInput starts it, the read stops it
  // before a block grows and at its end). The last member: it stops before the blocks go.
  storage::Prefaulter prefault;
};

// The state of the passes: what one pass leaves for its steps (and the next pass reuses).
struct PassState
{
  // Out of core, a collapse leaves the survivor's quadric alone and Compact adds the partner's
  // (nothing reads a survivor's quadric before: it is busy for the rest of the pass), so the
  // collapse step, which sweeps the vertices once per cost group, does not page the largest
  // array in and out each time. The same sums either way.
  bool lazySums = false;
  // The middle chunk boundary of a pass's collapse rounds (StepChunks) also splits the faces
  // (FaceSplit): a chunk below splitMid collapses only faces below splitFace, one above only
  // faces at or above it; other collapses are deferred. Out of core, the two halves of the
  // chunks then write disjoint ranges of every block, and run on two threads (DML::Fork). The
  // split is used when the faces follow the vertices (scanner order: few faces on the wrong
  // side), in every mode and for any thread count, so the result does not depend on them.
  std::uint64_t splitMid = 0, splitFace = 0;
  bool splitOn = false;
  std::uint64_t stepTotal = 1; // the candidates the pass takes (the step's progress unit)
  // Out of core, whether the helper thread pays in the phases every pass runs (Parallel.h).
  storage::ForkRecord sweepFork, stepFork, compactFork;
  // Scratch bounded by valences and chunk sizes: [0] is the main thread's, one per sweep thread.
  std::vector<Scratch> scratch = std::vector<Scratch>(1);
  std::vector<std::uint32_t> partStart; // first vertex of each sweep thread's range
  std::vector<std::uint32_t> hist = std::vector<std::uint32_t>(kCostBins, 0);
  std::vector<std::uint64_t> starts;
};

// No candidate (yet): no partner, infinite costs.
const Cand kNoCandidate = { std::numeric_limits<float>::infinity(), { 0, 0, 0 }, kNone, 0.0f,
  std::numeric_limits<float>::infinity(), kNone };

// Progress weights: seconds per element of each phase, measured in core on one thread on a
// 2M-triangle scan (docs/architecture.md, "Progress and abort"). Only their ratios matter.
namespace kWork
{
constexpr double kRead = 4.0e-8;     // per input vertex + face
constexpr double kWeld = 1.0e-7;     // per vertex + face
constexpr double kRings = 1.1e-7;    // per face
constexpr double kQuadrics = 2.4e-7; // per face
constexpr double kPrune = 1.0e-7;    // per vertex + face (pruneSize > 0)
constexpr double kSweep = 3.0e-7;    // per vertex of the pass
constexpr double kOrder = 2.5e-8;    // per vertex of the pass (histogram and order)
constexpr double kStep = 2.5e-7;     // per candidate the pass takes
constexpr double kCompact = 3.5e-8;  // per face + vertex of the pass
constexpr double kWrite = 5.0e-8;    // per output vertex + face
}

// The sink that streams the source into the DML.
class Loader final : public io::MeshSink
{
public:
  Loader(RunContext& ctx, MeshState& mesh)
    : ctx_(ctx)
    , mesh_(mesh)
  {
  }
  void Begin(const io::MeshHeader& header) override;
  void Vertices(const io::VertexChunk& chunk) override;
  void Triangles(const std::uint32_t* indices, std::size_t count) override;
  void TriangleFlags(const std::uint8_t* flags, std::size_t count) override;
  void End(const io::ReadStats& stats) override;
  bool AbortRequested() override
  {
    try
    {
      this->Tick();
    }
    catch (const AbortedError&)
    {
      return true;
    }
    return false;
  }
  bool Aborted() const { return this->aborted_; }
  void Tick();
  // Measures the layout of the first faces; an incoherent one throws detail::ReorderNeeded.
  void MeasureLayout(std::uint64_t vertices)
  {
    this->measure_ = true;
    this->meter_.Start(vertices);
  }
  const detail::LayoutMeter& Layout() const { return this->meter_; }

private:
  void Measured()
  {
    this->measure_ = false;
    if (this->meter_.FarFraction() > detail::kIncoherentFarFraction)
    {
      throw detail::ReorderNeeded{};
    }
  }
  RunContext& ctx_;
  MeshState& mesh_;
  bool aborted_ = false;
  bool measure_ = false;
  detail::LayoutMeter meter_;
};

// A collapse candidate's fate in step 3.
enum class Try
{
  Skip,
  Done,
  Illegal,
  Defer
};
struct alignas(kCacheLine) StepRun
{
  std::uint64_t removed = 0, done = 0, illegal = 0;
};

// The passes, as free functions over the state they use (in the order of the files).
// ---------------------------------------------------------------------------------------------
// The loader measures the input's layout: a run on a DML of its own, layout Automatic.
inline bool MeasuresLayout(const RunContext& ctx)
{
  return !ctx.opt.dml && ctx.opt.layout == LayoutPolicy::Automatic;
}
// How far the read is (announced counts).
inline double ReadFraction(const MeshState& mesh)
{
  double total = double(mesh.announcedV + mesh.announcedF);
  return total > 0 ? double(mesh.nv + mesh.nf) / total : 0.5;
}
// The length of x's face list (its live faces and those that died in this pass).
inline std::uint32_t RingLength(const Views& w, std::uint32_t x)
{
  return w.RO.Get(x + 1) - w.RO.Get(x);
}
// Out of core, for prefetch hints: vertex x's range of ring entries [first, second) when both
// its offsets are on pages at hand (Peek; a hint never reads a page), else an empty one.
template <class ROA>
SIPMSS_ALWAYS_INLINE std::pair<std::uint32_t, std::uint32_t> RingAtHand(
  const ROA& RO, std::uint32_t x)
{
  const std::uint32_t* b = RO.Peek(x);
  const std::uint32_t* e = RO.Peek(std::uint64_t(x) + 1);
  return b && e ? std::make_pair(*b, *e) : std::make_pair(0u, 0u);
}
// Out of core: the faces of vertex x, those whose ids are on pages at hand.
template <class ROA, class RFA, class FA>
SIPMSS_ALWAYS_INLINE void PrefetchRingFaces(
  const ROA& RO, const RFA& RF, const FA& F, std::uint32_t x)
{
  for (auto [k, end] = RingAtHand(RO, x); k < end; ++k)
  {
    if (const std::uint32_t* id = RF.Peek(k))
    {
      F.Prefetch(*id);
    }
  }
}
// The faces of an active vertex kAhead ahead in the sweep: in core from the blocks' memory, out
// of core from the pages at hand (a template over the access kind, see WithAccess). Always
// inlined: GCC takes a function whose only effect is a prefetch for one without effects, and
// drops the calls.
template <class SA, class ROA, class RFA, class FA>
SIPMSS_ALWAYS_INLINE void PrefetchSweep(
  const SA& S, const ROA& RO, const RFA& RF, const FA& F, std::uint64_t u, std::uint64_t end)
{
  if constexpr (SA::kInCore)
  {
    constexpr std::uint64_t kAhead = 8;
    const State* Sp = S.Data();
    const std::uint32_t* ROp = RO.Data();
    const std::uint32_t* RFp = RF.Data();
    const Tri* Fp = F.Data();
    if (u + kAhead < end && Active(Sp[u + kAhead]))
    {
      for (std::uint32_t k = ROp[u + kAhead], e = ROp[u + kAhead + 1]; k < e; ++k)
      {
        Prefetch(Fp + RFp[k]);
      }
    }
    // (The neighbours' records are fetched by Evaluate once it has the ring: fetching them
    // here too, for every corner of the ring's faces, cost more than it saved.)
  }
  else
  {
    // Out of core the same, from the pages at hand (Peek: no read for a hint).
    constexpr std::uint64_t kAhead = 8;
    if (u + kAhead < end)
    {
      const State* s = S.Peek(u + kAhead);
      if (s && Active(*s))
      {
        PrefetchRingFaces(RO, RF, F, std::uint32_t(u + kAhead));
      }
    }
  }
}
// Step 3's vertex chunks: options.stepChunkSize, else at most kStepChunks chunks of at least
// kStepChunkMinSize vertices.
inline std::uint64_t StepChunkSize(const RunContext& ctx, std::uint64_t nv)
{
  return ctx.opt.stepChunkSize ? ctx.opt.stepChunkSize
                               : std::max(kStepChunkMinSize, (nv + kStepChunks - 1) / kStepChunks);
}
// Vertices per face of the mesh now (or as announced).
inline double VerticesPerFace(const MeshState& mesh)
{
  const double v = double(mesh.nv ? mesh.nv : mesh.announcedV);
  const double f = double(mesh.liveFaces ? mesh.liveFaces : (mesh.nf ? mesh.nf : mesh.announcedF));
  return f > 0 ? v / f : 0.5;
}

// read and weld (Read.inl)
void BeginInput(RunContext& ctx, MeshState& mesh, const io::MeshHeader& header);
void EnsureVertexCapacity(MeshState& mesh, std::uint64_t n);
void EnsureFaceCapacity(MeshState& mesh, std::uint64_t n);
void AddVertices(MeshState& mesh, const io::VertexChunk& c);
void AddTriangles(MeshState& mesh, const std::uint32_t* idx, std::size_t count);
void Read(RunContext& ctx, MeshState& mesh, const MeshSource& input);
void Weld(RunContext& ctx, MeshState& mesh);

// rings and quadrics (Rings.inl)
void CountDegrees(RunContext& ctx, MeshState& mesh, std::uint64_t nf, std::uint64_t parallelMin,
  std::uint64_t tickBase, std::uint64_t tickTotal, const Array<std::uint32_t>* spare = nullptr);
void FillRings(RunContext& ctx, MeshState& mesh, std::uint64_t nf, std::uint64_t tickBase,
  std::uint64_t tickTotal);
void BuildRings(RunContext& ctx, MeshState& mesh);
bool FixedByArrays(const MeshState& mesh, const View<std::uint8_t>& A, std::uint32_t u);
void BuildQuadrics(RunContext& ctx, MeshState& mesh);
// decimate/Prune.inl
void Prune(RunContext& ctx, MeshState& mesh);

// step 1 of a pass, the candidate sweep (Sweep.inl)
double EdgeQuadric(const MeshState& mesh, const Views& w, std::uint32_t u, std::uint32_t v,
  Quadric& Q, Scratch& s);
void AddEdgeAttributeError(const MeshState& mesh, const Views& w, std::uint32_t u, std::uint32_t v,
  Quadric& Q, Scratch& s);
void Apply(Views& w, std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner);
Placement Place(const Quadric& Q, const Vec3& pu, const Vec3& pv, State su, State sv);
void Offer(MeshState& mesh, PassState& pass, std::uint32_t x, std::uint32_t partner,
  const Placement& pl, bool fromPartner, Scratch& s);
void Sweep(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t nv);
void Evaluate(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint32_t u, Scratch& s);
void EvaluateEdge(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint32_t u, State su,
  const Quadric& Qu, const Vec3& pu, std::uint32_t v, const std::uint32_t* next,
  const std::uint32_t* prev, std::size_t n, const LinkTally* tally, Scratch& s);
void FlushEdges(RunContext& ctx, MeshState& mesh, PassState& pass, Scratch& s);
void OfferEdge(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint32_t u, std::uint32_t v,
  const Placement& pl, double trace, bool offerV, Scratch& s);
void EvaluateFull(RunContext& ctx, MeshState& mesh, std::uint32_t u, State su, Scratch& s);

// legality, the collapse and step 3 of a pass (Step.inl)
void LoadFaces(Views& w, std::uint32_t x, Ring& r);
void LoadRing(Views& w, std::uint32_t x, Ring& r, bool positions);
void BuildNeighbours(Views& w, Ring& r, bool positions);
bool FaceOk(const RunContext& ctx, const Ring& r, std::size_t slot, const Vec3& p);
bool FaceOk(const RunContext& ctx, Vec3 c[3], int corner, const Vec3& p);
bool Legal(RunContext& ctx, MeshState& mesh, std::uint32_t u, const Nb& nb, const Vec3& p,
  Scratch& s, bool rvLoaded = false);
bool LegalFaces(RunContext& ctx, MeshState& mesh, std::uint32_t u, std::uint32_t v, std::uint32_t m,
  const std::uint32_t opp[2], const Vec3& p, Scratch& s);
void InterpolateAttributes(MeshState& mesh, std::uint32_t u, std::uint32_t v, double t, Scratch& s);
void SumExtensions(MeshState& mesh, PassState& pass, std::uint32_t u, std::uint32_t v, Scratch& s);
void OptimalAttributes(MeshState& mesh, std::uint32_t u, Scratch& s);
std::uint64_t Collapse(
  MeshState& mesh, PassState& pass, std::uint32_t u, const Cand& c, Scratch& s);
Try TryCollapse(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint32_t u, Scratch& s,
  std::uint32_t lo, std::uint32_t hi, std::uint64_t& removed);
std::uint64_t Step(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t first,
  std::uint64_t last, std::uint32_t lo, std::uint32_t hi, std::uint64_t budget, Scratch& s,
  StepRun& run, std::int64_t tickAt = -1, std::uint64_t tickScale = 1);
void FaceSplit(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t nv);
void StepChunks(RunContext& ctx, MeshState& mesh, PassState& pass,
  const std::vector<std::uint64_t>& groups, std::uint64_t nv, std::uint64_t goal, StepRun& total);
bool Pass(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t goal, bool exact,
  bool far, double workAfter);

// compaction and output (Compact.inl)
void Compact(RunContext& ctx, MeshState& mesh, PassState& pass);
void Emit(RunContext& ctx, MeshState& mesh, io::MeshSink& sink);

// the final fit (Fit.inl)
void SampleInput(RunContext& ctx, MeshState& mesh, const std::vector<std::uint64_t>& levels);
void TrackSamples(MeshState& mesh, const View<std::uint32_t>& R);
void ExportSamples(RunContext& ctx, MeshState& mesh);
void Fit(RunContext& ctx, MeshState& mesh);

// the pass schedule and the run (../Decimate.cpp)
std::vector<std::uint64_t> Levels(const RunContext& ctx, std::uint64_t F0);
bool FarFromLevel(const RunContext& ctx, std::uint64_t T, std::uint64_t level);
std::uint64_t PassGoal(const RunContext& ctx, std::uint64_t T, std::uint64_t level);
double PassesWork(const RunContext& ctx, const MeshState& mesh, std::uint64_t T, std::size_t level,
  const std::vector<std::uint64_t>& levels);
double RestWork(
  const RunContext& ctx, const MeshState& mesh, int stage, std::uint64_t V, std::uint64_t F);
void Run(RunContext& ctx, MeshState& mesh, PassState& pass, const MeshSource& input,
  io::MeshSink& output,
  const std::function<void(int, const std::function<void(io::MeshSink&)>&)>& onLevel);

// Work after the read: weld, rings, quadrics, the passes and the write, for V and F.
inline double WorkAfterRead(
  const RunContext& ctx, const MeshState& mesh, std::uint64_t V, std::uint64_t F)
{
  return RestWork(ctx, mesh, 0, V, F);
}
// The estimated work of a run on V vertices and F faces (EstimateDecimateWork).
inline double Plan(const RunContext& ctx, MeshState& mesh, std::uint64_t V, std::uint64_t F)
{
  mesh.announcedV = V;
  mesh.announcedF = F;
  return kWork::kRead * double(V + F) + WorkAfterRead(ctx, mesh, V, F);
}

} // namespace
} // namespace sipmss::algorithms
