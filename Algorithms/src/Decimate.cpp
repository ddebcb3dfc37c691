// Algorithm I of SIPMSS: a linear-time iterative full edge collapse with quadric error metrics,
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
#include "sipmss/algorithms/Decimate.h"
#include "sipmss/algorithms/Placement.h"
#include "sipmss/storage/Threads.h"

#include "StoredMesh.h"

#include <algorithm>
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

constexpr std::uint32_t kNone = 0xffffffffu;
constexpr int kCostBins = 1 << 15;
constexpr int kGroups = 4;
// Step 3 in chunks (StepChunks): by default at most kStepChunks chunks of at least
// kStepChunkMinSize vertices (measured on Dragon-size: 8192 defers 4x more collapses to the
// sequential part than 32768), for passes over at least two chunks; the last kStepTail faces of
// a pass's goal are collapsed one at a time.
constexpr std::uint64_t kStepChunks = 64;
constexpr std::uint64_t kStepChunkMinSize = 32768;
constexpr std::uint64_t kStepTail = 4096;
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
constexpr State kFixed = 16;       // lockBoundary: never moves, never removed (may absorb)
constexpr State kNeedsLegal = 32;  // its cheapest collapse was illegal: evaluate with legality
constexpr State kSurvivor = 64;    // survived a collapse of the last pass: all its edges changed
constexpr State kRecompute = 128;  // its candidate is unknown: evaluate its edges
constexpr State kCollapsed = 256;  // survived a collapse of this pass
constexpr State kComplex = 512;    // on an edge with > 2 faces, or where several fans meet
constexpr State kPromote = 1024;   // its best partner collapsed: its second best became the best
constexpr State kDeferred = 2048;  // step 3: its collapse leaves its chunk, it runs after the round
// An endpoint of a collapse of this pass: its ring in the CSR is stale until Compact.
constexpr State kBusy = kRemoved | kCollapsed;
// Vertices evaluated by the sweep (kNeedsLegal ones take the heavy path instead).
inline bool Active(State s)
{
  return (s & (kSurvivor | kRecompute)) != 0 && (s & (kNeedsLegal | kLocked)) == 0;
}

struct Vec3
{
  double x, y, z;
};
inline Vec3 operator-(const Vec3& a, const Vec3& b)
{
  return { a.x - b.x, a.y - b.y, a.z - b.z };
}
inline Vec3 operator+(const Vec3& a, const Vec3& b)
{
  return { a.x + b.x, a.y + b.y, a.z + b.z };
}
inline Vec3 operator*(double s, const Vec3& a)
{
  return { s * a.x, s * a.y, s * a.z };
}
inline double Dot(const Vec3& a, const Vec3& b)
{
  return a.x * b.x + a.y * b.y + a.z * b.z;
}
inline Vec3 Cross(const Vec3& a, const Vec3& b)
{
  return { a.y * b.z - a.z * b.y, a.z * b.x - a.x * b.z, a.x * b.y - a.y * b.x };
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
struct Quadric
{
  double q[10];
};
inline void AddTo(Quadric& dst, const Quadric& src)
{
  for (int i = 0; i < 10; ++i)
  {
    dst.q[i] += src.q[i];
  }
}
inline void AddPlane(Quadric& Q, const Vec3& n, double d, double w)
{
  double* q = Q.q;
  q[0] += w * n.x * n.x;
  q[1] += w * n.x * n.y;
  q[2] += w * n.x * n.z;
  q[3] += w * n.x * d;
  q[4] += w * n.y * n.y;
  q[5] += w * n.y * n.z;
  q[6] += w * n.y * d;
  q[7] += w * n.z * n.z;
  q[8] += w * n.z * d;
  q[9] += w * d * d;
}
inline double Eval(const Quadric& Q, const Vec3& p)
{
  const double* q = Q.q;
  return p.x * (q[0] * p.x + 2.0 * (q[1] * p.y + q[2] * p.z + q[3])) +
    p.y * (q[4] * p.y + 2.0 * (q[5] * p.z + q[6])) + p.z * (q[7] * p.z + 2.0 * q[8]) + q[9];
}
inline double Trace(const Quadric& Q)
{
  return Q.q[0] + Q.q[4] + Q.q[7];
}

// One pass's candidate of a vertex: collapse it with `partner` to p; t = position of p along the
// edge (0: this vertex, 1: partner) for the point data.
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
  std::uint32_t u[kLanes], v[kLanes];
  bool offerV[kLanes];
};

// Fast element access: the block's memory when in core, the DML's read/write otherwise.
// Refresh() after any OpenBlock/Resize/Reconfigure (they may change the mode).
template <class T>
class View
{
public:
  View() = default;
  View(DML& dml, const Array<T>& a)
    : dml_(&dml)
    , id_(a.Id())
  {
    this->Refresh();
  }
  void Refresh() { this->base_ = static_cast<T*>(this->dml_->BasePointer(this->id_)); }
  // Direct pointer to element i when in core, else nullptr.
  SIPMSS_ALWAYS_INLINE const T* Ptr(std::uint64_t i) const
  {
    return this->base_ ? this->base_ + i : nullptr;
  }
  SIPMSS_ALWAYS_INLINE T Get(std::uint64_t i) const
  {
    if (this->base_)
    {
      return this->base_[i];
    }
    T v;
    this->dml_->Read(this->id_, sizeof(T), i, &v);
    return v;
  }
  SIPMSS_ALWAYS_INLINE void Set(std::uint64_t i, const T& v)
  {
    if (this->base_)
    {
      this->base_[i] = v;
      return;
    }
    this->dml_->Write(this->id_, sizeof(T), i, &v);
  }
  void GetRange(std::uint64_t first, std::uint64_t n, T* dst) const
  {
    if (n == 0)
    {
      return;
    }
    if (this->base_)
    {
      std::memcpy(dst, this->base_ + first, n * sizeof(T));
      return;
    }
    this->dml_->ReadRange(this->id_, first, n, dst);
  }
  void SetRange(std::uint64_t first, std::uint64_t n, const T* src)
  {
    if (n == 0)
    {
      return;
    }
    if (this->base_)
    {
      std::memcpy(this->base_ + first, src, n * sizeof(T));
      return;
    }
    this->dml_->WriteRange(this->id_, first, n, src);
  }

private:
  DML* dml_ = nullptr;
  BlockId id_ = -1;
  T* base_ = nullptr;
};

// The views of one DML over the mesh's blocks: the Decimator's own, or those of a forked DML
// (an out-of-core helper thread's).
struct Views
{
  View<Vec3> P;
  View<Quadric> Q;
  View<std::uint8_t> A;
  View<State> S;
  View<Tri> F;
  View<std::uint32_t> RO, RF;
  View<Cand> C;
  View<std::uint32_t> O;
};

// Fetches the cache lines of element *p: its first and its last byte (a quadric spans two lines,
// a position or a face straddles two at some indices).
template <class T>
inline void Prefetch(const T* p)
{
#if defined(__GNUC__)
  __builtin_prefetch(static_cast<const void*>(p));
  if constexpr (sizeof(T) > 8)
  {
    __builtin_prefetch(reinterpret_cast<const char*>(p) + sizeof(T) - 1);
  }
#else
  (void)p;
#endif
}

// The same for element i of an array that a dead face's corner (kNone) may index: the address
// is computed as an integer (no pointer past the array) and never dereferenced; a prefetch does
// not fault. Cheaper than testing which faces are dead (random, a mispredicted branch).
template <class T>
inline void PrefetchAt(const T* base, std::uint32_t i)
{
  Prefetch(reinterpret_cast<const T*>(reinterpret_cast<std::uintptr_t>(base) + std::uintptr_t(i) * sizeof(T)));
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

struct Scratch
{
  Ring ru, rv;
  LinkTally tally; // Evaluate's, for rings of more than LinkTally::kMinEntries
  std::vector<EdgeCand> edges;
  std::vector<std::uint32_t> ids, next = std::vector<std::uint32_t>(64),
                                  prev = std::vector<std::uint32_t>(64);
  std::vector<std::uint8_t> abuf, abuf2; // point data of a collapse
  std::uint32_t lo = 0, hi = kNone;        // the vertices whose candidates this thread writes
  std::vector<std::vector<Deferred>> out; // offers to the other threads' vertices, by thread
  EdgeBatch batch;                        // the sweep's edges waiting for their placement
  Views* w = nullptr; // the views this thread uses; nullptr: the Decimator's
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

// Runs work(0) on the calling thread and work(1..T-1) on new ones, and joins them. A thread that
// cannot be started ends the list: onShort(started) runs before work(0), so that the caller can
// release those that did start. Returns how many ran. With whileWaiting (which must not throw),
// the calling thread runs it every 2 ms once work(0) is done and others are still running.
int RunOnThreads(int T, const std::function<void(int)>& work, const std::function<void(int)>& onShort,
  const std::function<void()>& whileWaiting = nullptr)
{
  std::vector<std::thread> workers;
  std::atomic<int> finished{ 0 };
  int started = 1;
  for (; started < T; ++started)
  {
    try
    {
      workers.emplace_back([&work, &finished](int t) {
        work(t);
        finished.fetch_add(1);
      }, started);
    }
    catch (const std::system_error&)
    {
      if (onShort)
      {
        onShort(started);
      }
      break;
    }
  }
  work(0);
  if (whileWaiting)
  {
    while (finished.load() < int(workers.size()))
    {
      std::this_thread::sleep_for(std::chrono::milliseconds(2));
      whileWaiting();
    }
  }
  for (std::thread& w : workers)
  {
    w.join();
  }
  return started;
}

void RethrowFirst(const std::vector<std::exception_ptr>& errors)
{
  for (const std::exception_ptr& e : errors)
  {
    if (e)
    {
      std::rethrow_exception(e);
    }
  }
}

// Runs body(t, begin, end, stop) on [0, n) cut into T ranges, range t on thread t (0: the
// calling one); the ranges of threads that could not be started run on the calling thread
// afterwards. The bodies must be independent of each other (each writes only its own range's
// records) and should return early once `stop` is set (another one threw, e.g. an abort). With
// poll (e.g. Progress::Poll), the calling thread polls while it waits for the others: a range
// with one costly element (a vertex of valence 2,000,000) is then still stopped by an abort, if
// the body also checks `stop` inside that element.
using RangeBody =
  std::function<void(int t, std::uint64_t begin, std::uint64_t end, const std::atomic<bool>& stop)>;
void ForRanges(int T, std::uint64_t n, const RangeBody& body,
  const std::function<void()>& beforeFallback = nullptr, const std::function<void()>& poll = nullptr)
{
  auto begin = [n, T](int t) { return n * std::uint64_t(t) / std::uint64_t(T); };
  std::vector<std::exception_ptr> errors(static_cast<std::size_t>(T));
  std::atomic<bool> stop{ false };
  const int started = RunOnThreads(
    T,
    [&](int t) {
      try
      {
        body(t, begin(t), begin(t + 1), stop);
      }
      catch (...)
      {
        errors[std::size_t(t)] = std::current_exception();
        stop = true;
      }
    },
    nullptr,
    poll ? std::function<void()>([&]() {
      if (stop.load())
      {
        return;
      }
      try
      {
        poll();
      }
      catch (...)
      {
        errors[0] = std::current_exception();
        stop = true;
      }
    })
         : std::function<void()>());
  RethrowFirst(errors);
  if (started < T)
  {
    if (beforeFallback)
    {
      beforeFallback();
    }
    body(0, begin(started), n, stop);
  }
}

class Decimator;

// Progress weights: seconds per element of each phase, measured in core on one thread on a
// 2M-triangle scan (docs/architecture.md, "Progress and abort"). Only their ratios matter.
namespace kWork
{
constexpr double kRead = 4.0e-8;     // per input vertex + face
constexpr double kWeld = 1.0e-7;     // per vertex + face
constexpr double kRings = 1.1e-7;    // per face
constexpr double kQuadrics = 2.4e-7; // per face
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
  Loader(Decimator& d, Progress& p)
    : d_(d)
    , progress_(p)
  {
  }
  void Begin(const io::MeshHeader& header) override;
  void Vertices(const io::VertexChunk& chunk) override;
  void Triangles(const std::uint32_t* indices, std::size_t count) override;
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
  Decimator& d_;
  Progress& progress_;
  bool aborted_ = false;
  bool measure_ = false;
  detail::LayoutMeter meter_;
};

class Decimator
{
public:
  // The loader measures the input's layout: a run on a DML of its own, layout Automatic.
  bool MeasuresLayout() const
  {
    return !this->opt_.dml && this->opt_.layout == LayoutPolicy::Automatic;
  }
  Decimator(const DecimateOptions& options, Progress& progress, RunStats& stats)
    : opt_(options)
    , progress_(progress)
    , stats_(stats)
    , ownDml_(options.dml ? nullptr : new DML())
    , dml_(options.dml ? *options.dml : *ownDml_)
    , hist_(kCostBins, 0)
  {
    this->cosThreshold_ = options.minNormalCosine;
    this->threads_ = storage::ResolveThreads(options.threads);
    this->threads_ = std::min(this->threads_, 16);
  }

  void Run(const MeshSource& input, io::MeshSink& output,
    const std::function<void(int, const std::function<void(io::MeshSink&)>&)>& onLevel);
  // The estimated work of a run on V vertices and F faces (EstimateDecimateWork).
  double Plan(std::uint64_t V, std::uint64_t F)
  {
    this->announcedV_ = V;
    this->announcedF_ = F;
    return kWork::kRead * double(V + F) + this->WorkAfterRead(V, F);
  }

  // Loader callbacks.
  void BeginInput(const io::MeshHeader& header);
  void AddVertices(const io::VertexChunk& chunk);
  void AddTriangles(const std::uint32_t* indices, std::size_t count);
  void EndInput(const io::ReadStats& stats) { this->readerDropped_ = stats.droppedFaces; }
  double ReadFraction() const
  {
    double total = double(this->announcedV_ + this->announcedF_);
    return total > 0 ? double(this->nv_ + this->nf_) / total : 0.5;
  }

private:
  void Read(const MeshSource& input);
  void Weld();
  void BuildRings();
  void FillRings(std::uint64_t nf, std::uint64_t tickBase, std::uint64_t tickTotal);
  void CountDegrees(std::uint64_t nf, int threads, std::uint64_t tickBase, std::uint64_t tickTotal,
    std::uint32_t* spare = nullptr);
  void BuildQuadrics();
  // One pass down to `goal` faces; workAfter: the estimated work of the rest of the run.
  bool Pass(std::uint64_t goal, bool exact, double workAfter);
  void Compact();
  void Emit(io::MeshSink& sink);

  void BindViews();
  void BindViews(Views& w, DML& dml) const;
  void LoadRing(Views& w, std::uint32_t x, Ring& r, bool positions);
  // The length of x's face list (its live faces and those that died in this pass).
  static std::uint32_t RingLength(const Views& w, std::uint32_t x)
  {
    return w.RO.Get(x + 1) - w.RO.Get(x);
  }
  void LoadFaces(Views& w, std::uint32_t x, Ring& r);
  void BuildNeighbours(Views& w, Ring& r, bool positions);
  // Out of core, a collapse leaves the survivor's quadric alone and Compact adds the partner's
  // (nothing reads a survivor's quadric before: it is busy for the rest of the pass), so the
  // collapse step, which sweeps the vertices once per cost group, does not page the largest
  // array in and out each time. The same sums either way.
  bool lazySums_ = false;
  // The middle chunk boundary of a pass's collapse rounds (StepChunks) also splits the faces
  // (FaceSplit): a chunk below splitMid_ collapses only faces below splitFace_, one above only
  // faces at or above it; other collapses are deferred. Out of core, the two halves of the
  // chunks then write disjoint ranges of every block, and run on two threads (DML::Fork). The
  // split is used when the faces follow the vertices (scanner order: few faces on the wrong
  // side), in every mode and for any thread count, so the result does not depend on them.
  std::uint64_t splitMid_ = 0, splitFace_ = 0;
  bool splitOn_ = false;
  void FaceSplit(std::uint64_t nv);
  bool AllInCore() const
  {
    return this->v_.S.Ptr(0) && this->v_.C.Ptr(0) && this->v_.Q.Ptr(0) && this->v_.P.Ptr(0) &&
      this->v_.F.Ptr(0) && this->v_.RO.Ptr(0) && this->v_.RF.Ptr(0);
  }
  void Sweep(std::uint64_t nv);
  // Out of core on two or more threads: a DML forked for a helper thread that writes only the
  // elements [mid, nv) of `blocks` (DML::Fork, half of the budget), with `w` bound to it;
  // nullptr in core, on one thread, for small meshes, or when the budget cannot be shared.
  std::unique_ptr<DML> ForkHelper(std::uint64_t nv, std::uint64_t mid,
    std::initializer_list<storage::BlockId> blocks, Views& w,
    const std::vector<DML::Range>& more = {});
  void JoinHelper(std::unique_ptr<DML>& fork); // (no-op for nullptr)
  // Joins a fork on every exit of a scope (there a failing Join is dropped: the scope is
  // already left by an exception); the normal path joins with JoinHelper and sees its errors.
  struct ForkGuard
  {
    Decimator& d;
    std::unique_ptr<DML>& fork;
    ForkGuard(const ForkGuard&) = delete;
    ForkGuard& operator=(const ForkGuard&) = delete;
    ~ForkGuard()
    {
      try
      {
        this->d.JoinHelper(this->fork);
      }
      catch (...)
      {
      }
    }
  };
  // In core: the faces of an active vertex kAhead ahead in the sweep.
  void PrefetchSweep(std::uint64_t u, std::uint64_t end) const
  {
    constexpr std::uint64_t kAhead = 8;
    const State* Sp = this->v_.S.Ptr(0);
    const std::uint32_t* ROp = this->v_.RO.Ptr(0);
    const std::uint32_t* RFp = this->v_.RF.Ptr(0);
    const Tri* Fp = this->v_.F.Ptr(0);
    if (!Sp || !ROp || !RFp || !Fp)
    {
      return;
    }
    if (u + kAhead < end && Active(Sp[u + kAhead]))
    {
      for (std::uint32_t k = ROp[u + kAhead], e = ROp[u + kAhead + 1]; k < e; ++k)
      {
        Prefetch(Fp + RFp[k]);
      }
    }
    // (The neighbours' records are fetched by Evaluate once it has the ring: fetching them here
    // too, for every corner of the ring's faces, cost more than it saved.)
  }
  void Evaluate(std::uint32_t u, Scratch& s);
  // (tally: next and prev's LinkTally for a large ring, else nullptr: they are scanned)
  void EvaluateEdge(std::uint32_t u, State su, const Quadric& Qu, const Vec3& pu,
    std::uint32_t v, const std::uint32_t* next, const std::uint32_t* prev, std::size_t n,
    const LinkTally* tally, Scratch& s);
  void FlushEdges(Scratch& s);
  void OfferEdge(std::uint32_t u, std::uint32_t v, const Placement& pl, double trace, bool offerV,
    Scratch& s);
  void EvaluateFull(std::uint32_t u, State su, Scratch& s);
  void Offer(std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner,
    Scratch& s);
  void Apply(Views& w, std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner);
  bool Legal(std::uint32_t u, const Nb& nb, const Vec3& p, Scratch& s, bool rvLoaded = false);
  bool FaceOk(const Ring& r, std::size_t slot, const Vec3& p) const;
  bool FaceOk(Vec3 c[3], int corner, const Vec3& p) const;
  bool LegalFaces(std::uint32_t u, std::uint32_t v, std::uint32_t m, const std::uint32_t opp[2],
    const Vec3& p, Scratch& s);
  Placement Place(const Quadric& Q, const Vec3& pu, const Vec3& pv, State su, State sv) const;
  std::uint64_t Collapse(std::uint32_t u, const Cand& c, Scratch& s);
  void InterpolateAttributes(std::uint32_t u, std::uint32_t v, double t, Scratch& s);
  enum class Try
  {
    Skip,
    Done,
    Illegal,
    Defer
  };
  Try TryCollapse(std::uint32_t u, Scratch& s, std::uint32_t lo, std::uint32_t hi,
    std::uint64_t& removed);
  struct StepRun
  {
    std::uint64_t removed = 0, done = 0, illegal = 0;
  };
  std::uint64_t StepChunkSize(std::uint64_t nv) const
  {
    return this->opt_.stepChunkSize ? this->opt_.stepChunkSize
                                    : std::max(kStepChunkMinSize, (nv + kStepChunks - 1) / kStepChunks);
  }
  // tickAt >= 0 (the calling thread only): ticks the step's progress at position tickAt +
  // tickScale * (i - first) of the pass's stepTotal_ candidates every 1024 candidates.
  std::uint64_t Step(std::uint64_t first, std::uint64_t last, std::uint32_t lo, std::uint32_t hi,
    std::uint64_t budget, Scratch& s, StepRun& run, std::int64_t tickAt = -1,
    std::uint64_t tickScale = 1);
  std::uint64_t stepTotal_ = 1; // the candidates the pass takes (the step's progress unit)
  void StepChunks(std::uint64_t groupBegin, std::uint64_t groupEnd, std::uint64_t nv,
    std::uint64_t goal, StepRun& total);
  void EnsureVertexCapacity(std::uint64_t n);
  void EnsureFaceCapacity(std::uint64_t n);
  // The levels' targets for F0 faces (the last one is the final target).
  std::vector<std::uint64_t> Levels(std::uint64_t F0) const;
  // Progress planning: estimated work of the passes from `faces` live faces at `level` (the
  // pass schedule of Run simulated, vertices per face as now), and of writing the result.
  // The face count a pass from T faces aims at, for the level's target (the pass schedule).
  std::uint64_t PassGoal(std::uint64_t T, std::uint64_t level) const;
  double PassesWork(std::uint64_t faces, std::size_t level, const std::vector<std::uint64_t>& levels) const;
  double VerticesPerFace() const
  {
    const double v = double(this->nv_ ? this->nv_ : this->announcedV_);
    const double f = double(this->liveFaces_ ? this->liveFaces_ : (this->nf_ ? this->nf_ : this->announcedF_));
    return f > 0 ? v / f : 0.5;
  }
  // Work after the read: weld, rings, quadrics, the passes and the write, for V and F.
  double WorkAfterRead(std::uint64_t V, std::uint64_t F) const { return this->RestWork(0, V, F); }
  // Work of the stages from `stage` on (0 weld, 1 rings, 2 quadrics, 3 passes and write).
  double RestWork(int stage, std::uint64_t V, std::uint64_t F) const;
  bool emitsLevels_ = false; // onLevel given: each level is emitted during the passes
  void Tick(std::uint64_t i, std::uint64_t n)
  {
    if ((i & 1023) == 0)
    {
      this->progress_.Tick(n ? double(i) / double(n) : 0.0);
    }
  }

  const DecimateOptions& opt_;
  Progress& progress_;
  RunStats& stats_;
  double cosThreshold_ = 0.2;
  int threads_ = 1;

  // The DML: the caller's (options.dml) or our own; declared before every block so that the
  // blocks close first.
  std::unique_ptr<DML> ownDml_;
  DML& dml_;

  // Input description.
  io::VertexLayout layout_;
  std::size_t nFloats_ = 0; // normals, texcoords, scalars as floats
  std::size_t recSize_ = 0; // bytes of one vertex's attribute record
  std::uint64_t announcedV_ = 0, announcedF_ = 0;
  bool begun_ = false;
  Vec3 origin_{ 0, 0, 0 };
  bool haveOrigin_ = false;
  std::uint64_t vCap_ = 0, fCap_ = 0;
  std::uint64_t readerDropped_ = 0, dropped_ = 0;

  // The current mesh.
  std::uint64_t nv_ = 0, nf_ = 0, liveFaces_ = 0;
  Array<Vec3> pos_;
  Array<Quadric> quad_;
  Array<std::uint8_t> attr_; // nv_ * recSize_ bytes
  Array<State> state_;
  Array<Tri> faces_;
  Array<std::uint32_t> ringOff_;  // nv_ + 1
  Array<std::uint32_t> ringFace_; // ringOff_[nv_]
  Array<Cand> cand_;
  Array<std::uint32_t> order_; // the pass's candidates in processing order (<= nv_ of them)
  Array<std::uint32_t> remap_; // compaction: old vertex -> new

  Views v_;
  Views& W(const Scratch& s) { return s.w ? *s.w : this->v_; }

  // Scratch bounded by valences and chunk sizes: [0] is the main thread's, one per sweep thread.
  std::vector<Scratch> scratch_ = std::vector<Scratch>(1);
  std::vector<std::uint32_t> partStart_; // first vertex of each sweep thread's range
  const Cand none_ = { std::numeric_limits<float>::infinity(), { 0, 0, 0 }, kNone, 0.0f,
    std::numeric_limits<float>::infinity(), kNone };
  std::vector<std::uint32_t> hist_;
  std::vector<std::uint64_t> starts_;
  std::vector<Vec3> vbuf_;
  std::vector<std::uint8_t> abuf_;
  std::vector<Tri> tbuf_;
};

void Loader::Tick()
{
  try
  {
    this->progress_.Tick(this->d_.ReadFraction());
  }
  catch (const AbortedError&)
  {
    this->aborted_ = true;
    throw;
  }
}
void Loader::Begin(const io::MeshHeader& header)
{
  this->d_.BeginInput(header);
  if (this->d_.MeasuresLayout())
  {
    this->MeasureLayout(header.vertexCount);
  }
}
void Loader::Vertices(const io::VertexChunk& chunk)
{
  this->Tick();
  this->d_.AddVertices(chunk);
}
void Loader::Triangles(const std::uint32_t* indices, std::size_t count)
{
  this->Tick();
  if (this->measure_)
  {
    if (this->meter_.Chunk(indices, count))
    {
      this->Measured();
    }
  }
  this->d_.AddTriangles(indices, count);
}
void Loader::End(const io::ReadStats& stats)
{
  if (this->measure_)
  {
    this->Measured();
  }
  this->d_.EndInput(stats);
}

// ---------------------------------------------------------------------------------------------
// read

void Decimator::BeginInput(const io::MeshHeader& header)
{
  if (this->begun_)
  {
    return;
  }
  this->begun_ = true;
  this->layout_ = header.layout;
  this->nFloats_ = (this->layout_.normals ? 3 : 0) + (this->layout_.texcoords ? 2 : 0) +
    this->layout_.scalars.size();
  this->recSize_ = this->nFloats_ * sizeof(float) + (this->layout_.colors ? 4 : 0);
  this->announcedV_ = header.vertexCount;
  this->announcedF_ = header.faceCount;
  if (header.vertexCount + header.faceCount > 0)
  {
    this->progress_.Sized(header.vertexCount, header.faceCount);
    this->progress_.BeginPhase("read", kWork::kRead * double(header.vertexCount + header.faceCount),
      this->WorkAfterRead(header.vertexCount, header.faceCount));
  }

  // The profile: the structures of the run, sized from the header (0 when unknown: the blocks
  // then grow with Resize and the DML re-evaluates the mode as they do).
  storage::Profile profile = this->opt_.storage;
  const std::uint64_t V = header.vertexCount, F = header.faceCount;
  auto add = [&profile](const char* name, std::size_t size, std::uint64_t count) {
    if (size == 0)
    {
      return;
    }
    storage::StructureSpec s;
    s.name = name;
    s.elementSize = size;
    s.maxCount = count;
    profile.structures.push_back(std::move(s));
  };
  add("decimate.positions", sizeof(Vec3), V);
  add("decimate.attributes", this->recSize_, V);
  add("decimate.quadrics", sizeof(Quadric), V);
  add("decimate.vertexState", sizeof(State), V);
  add("decimate.faces", sizeof(Tri), F);
  add("decimate.ringOffsets", sizeof(std::uint32_t), V + 1);
  add("decimate.ringFaces", sizeof(std::uint32_t), 3 * F);
  add("decimate.candidates", sizeof(Cand), V);
  add("decimate.order", sizeof(std::uint32_t), V);
  add("decimate.remap", sizeof(std::uint32_t), V);
  if (!this->opt_.dml)
  {
    this->dml_.Config(profile);
  }

  this->vCap_ = std::max<std::uint64_t>(V, 1);
  this->fCap_ = std::max<std::uint64_t>(F, 1);
  this->pos_ = Array<Vec3>(this->dml_, this->vCap_);
  if (this->recSize_)
  {
    this->attr_ = Array<std::uint8_t>(this->dml_, this->vCap_ * this->recSize_);
  }
  this->faces_ = Array<Tri>(this->dml_, this->fCap_);
}

void Decimator::EnsureVertexCapacity(std::uint64_t n)
{
  if (n <= this->vCap_)
  {
    return;
  }
  std::uint64_t cap = std::max<std::uint64_t>({ n, this->vCap_ * 2, 1024 });
  this->pos_.Resize(cap);
  if (this->recSize_)
  {
    this->attr_.Resize(cap * this->recSize_);
  }
  this->vCap_ = cap;
}

void Decimator::EnsureFaceCapacity(std::uint64_t n)
{
  if (n <= this->fCap_)
  {
    return;
  }
  std::uint64_t cap = std::max<std::uint64_t>({ n, this->fCap_ * 2, 1024 });
  this->faces_.Resize(cap);
  this->fCap_ = cap;
}

void Decimator::AddVertices(const io::VertexChunk& c)
{
  if (!this->begun_)
  {
    throw io::MeshIOError("decimate: the source sent vertices before Begin()");
  }
  if (c.count == 0)
  {
    return;
  }
  const std::uint64_t end = c.first + c.count;
  if (end >= kNone)
  {
    throw io::MeshIOError("decimate: more than 2^32 - 1 vertices");
  }
  this->EnsureVertexCapacity(end);
  if (!this->haveOrigin_)
  {
    this->origin_ = { double(c.xyz[0]), double(c.xyz[1]), double(c.xyz[2]) };
    this->haveOrigin_ = true;
  }
  this->vbuf_.resize(c.count);
  for (std::size_t i = 0; i < c.count; ++i)
  {
    this->vbuf_[i] = { double(c.xyz[3 * i]) - this->origin_.x,
      double(c.xyz[3 * i + 1]) - this->origin_.y, double(c.xyz[3 * i + 2]) - this->origin_.z };
  }
  View<Vec3>(this->dml_, this->pos_).SetRange(c.first, c.count, this->vbuf_.data());
  if (this->recSize_)
  {
    const std::size_t rec = this->recSize_;
    const std::size_t ns = this->layout_.scalars.size();
    this->abuf_.assign(c.count * rec, 0);
    for (std::size_t i = 0; i < c.count; ++i)
    {
      float* f = reinterpret_cast<float*>(this->abuf_.data() + i * rec);
      std::size_t k = 0;
      if (this->layout_.normals)
      {
        for (int j = 0; j < 3; ++j)
        {
          f[k++] = c.normals ? c.normals[3 * i + j] : 0.0f;
        }
      }
      if (this->layout_.texcoords)
      {
        for (int j = 0; j < 2; ++j)
        {
          f[k++] = c.texcoords ? c.texcoords[2 * i + j] : 0.0f;
        }
      }
      for (std::size_t j = 0; j < ns; ++j)
      {
        f[k++] = c.scalars ? c.scalars[ns * i + j] : 0.0f;
      }
      if (this->layout_.colors)
      {
        std::uint8_t* rgba = this->abuf_.data() + i * rec + this->nFloats_ * sizeof(float);
        for (int j = 0; j < 4; ++j)
        {
          rgba[j] = c.rgba ? c.rgba[4 * i + j] : std::uint8_t(255);
        }
      }
    }
    View<std::uint8_t>(this->dml_, this->attr_)
      .SetRange(c.first * rec, c.count * rec, this->abuf_.data());
  }
  this->nv_ = std::max(this->nv_, end);
}

void Decimator::AddTriangles(const std::uint32_t* idx, std::size_t count)
{
  if (!this->begun_)
  {
    throw io::MeshIOError("decimate: the source sent triangles before Begin()");
  }
  this->tbuf_.clear();
  for (std::size_t i = 0; i < count; ++i)
  {
    Tri t = { { idx[3 * i], idx[3 * i + 1], idx[3 * i + 2] } };
    if (t.v[0] == t.v[1] || t.v[1] == t.v[2] || t.v[0] == t.v[2])
    {
      ++this->dropped_;
      continue;
    }
    this->tbuf_.push_back(t);
  }
  if (this->tbuf_.empty())
  {
    return;
  }
  this->EnsureFaceCapacity(this->nf_ + this->tbuf_.size());
  View<Tri>(this->dml_, this->faces_).SetRange(this->nf_, this->tbuf_.size(), this->tbuf_.data());
  this->nf_ += this->tbuf_.size();
}

void Decimator::Read(const MeshSource& input)
{
  PhaseTimer timer(this->stats_, this->dml_, "read");
  this->progress_.BeginPhase("read", 0.0, 1.0); // (its share once the header gives the sizes)
  Loader loader(*this, this->progress_);
  io::ReadOptions ro;
  io::ReadStats rs;
  try
  {
    rs = input(loader, ro);
  }
  catch (const AbortedError&)
  {
    throw;
  }
  catch (...)
  {
    if (loader.Aborted())
    {
      throw AbortedError();
    }
    throw;
  }
  if (loader.Aborted())
  {
    throw AbortedError();
  }
  if (loader.Layout().Faces() > 0)
  {
    this->stats_.layoutFarFraction = loader.Layout().FarFraction();
  }
  this->progress_.Poll(); // (the exact sizes and the mode's re-evaluation follow: storage calls)
  if (!this->begun_)
  {
    io::MeshHeader h;
    this->BeginInput(h);
  }
  this->stats_.inputVertices = this->nv_;
  this->stats_.inputTriangles = this->nf_ + this->dropped_;
  this->readerDropped_ = std::max(this->readerDropped_, rs.droppedFaces);
  // Exact sizes, then let the DML re-evaluate the mode.
  this->vCap_ = std::max<std::uint64_t>(this->nv_, 1);
  this->fCap_ = std::max<std::uint64_t>(this->nf_, 1);
  this->pos_.Resize(this->vCap_);
  if (this->recSize_)
  {
    this->attr_.Resize(this->vCap_ * this->recSize_);
  }
  this->faces_.Resize(this->fCap_);
  this->progress_.Poll();
  this->dml_.Reconfigure();
}

// Greedy welding: each vertex joins the lowest-index representative within weldDistance (a
// spatial hash of cells of that size in the DML), else becomes a representative.
void Decimator::Weld()
{
  const double d = this->opt_.weldDistance;
  const std::uint64_t nv = this->nv_;
  if (nv == 0)
  {
    return;
  }
  std::uint64_t tableSize = 1024;
  while (tableSize < 2 * nv)
  {
    tableSize *= 2;
  }
  const std::uint64_t mask = tableSize - 1;
  Array<std::uint32_t> head(this->dml_, tableSize);
  Array<std::uint32_t> next(this->dml_, nv);
  Array<std::uint32_t> rep(this->dml_, nv);
  FillBlock(this->dml_, head, kNone);
  View<std::uint32_t> H(this->dml_, head), N(this->dml_, next), R(this->dml_, rep);
  View<Vec3> P(this->dml_, this->pos_);
  const double inv = d > 0 ? 1.0 / d : 0.0;
  const double d2 = d * d;
  // (clamped to +-2^62 before the conversion: a tiny distance makes the quotients huge, and
  // the neighbour cells c +- 1 must not overflow either)
  auto cellIndex = [](double q) {
    constexpr double kLimit = 4611686018427387904.0; // 2^62
    return q == q ? std::int64_t(std::clamp(std::floor(q), -kLimit, kLimit)) : 0; // (0 * inf)
  };
  auto cellOf = [&](const Vec3& p, std::int64_t c[3]) {
    if (d > 0)
    {
      c[0] = cellIndex(p.x * inv);
      c[1] = cellIndex(p.y * inv);
      c[2] = cellIndex(p.z * inv);
    }
    else
    {
      std::memcpy(&c[0], &p.x, 8);
      std::memcpy(&c[1], &p.y, 8);
      std::memcpy(&c[2], &p.z, 8);
    }
  };
  auto hash = [mask](std::int64_t x, std::int64_t y, std::int64_t z) {
    std::uint64_t h = std::uint64_t(x) * 0x9E3779B97F4A7C15ull;
    h ^= std::uint64_t(y) * 0xC2B2AE3D27D4EB4Full + (h << 6) + (h >> 2);
    h ^= std::uint64_t(z) * 0x165667B19E3779F9ull + (h << 6) + (h >> 2);
    h ^= h >> 29;
    return h & mask;
  };
  const int reach = d > 0 ? 1 : 0;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    this->Tick(v, nv);
    Vec3 p = P.Get(v);
    std::int64_t c[3];
    cellOf(p, c);
    std::uint32_t best = kNone;
    for (int dx = -reach; dx <= reach; ++dx)
    {
      for (int dy = -reach; dy <= reach; ++dy)
      {
        for (int dz = -reach; dz <= reach; ++dz)
        {
          for (std::uint32_t w = H.Get(hash(c[0] + dx, c[1] + dy, c[2] + dz)); w != kNone;
               w = N.Get(w))
          {
            if (w >= best)
            {
              continue;
            }
            Vec3 q = P.Get(w);
            Vec3 e = q - p;
            bool match = d > 0 ? Dot(e, e) <= d2 : (q.x == p.x && q.y == p.y && q.z == p.z);
            if (match)
            {
              best = w;
            }
          }
        }
      }
    }
    if (best == kNone)
    {
      std::uint64_t h = hash(c[0], c[1], c[2]);
      N.Set(v, H.Get(h));
      H.Set(h, std::uint32_t(v));
      R.Set(v, std::uint32_t(v));
    }
    else
    {
      R.Set(v, best);
    }
  }
  View<Tri> F(this->dml_, this->faces_);
  for (std::uint64_t f = 0; f < this->nf_; ++f)
  {
    this->Tick(f, this->nf_);
    Tri t = F.Get(f);
    if (!Alive(t))
    {
      continue;
    }
    Tri w = t;
    for (int k = 0; k < 3; ++k)
    {
      if (t.v[k] >= nv)
      {
        throw io::MeshIOError("decimate: triangle " + std::to_string(f) + " has vertex index " +
          std::to_string(t.v[k]) + " >= vertex count " + std::to_string(nv));
      }
      w.v[k] = R.Get(t.v[k]);
    }
    if (w.v[0] == w.v[1] || w.v[1] == w.v[2] || w.v[0] == w.v[2])
    {
      F.Set(f, kDeadTri);
      ++this->dropped_;
    }
    else if (w.v[0] != t.v[0] || w.v[1] != t.v[1] || w.v[2] != t.v[2])
    {
      F.Set(f, w);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// rings

// Adds the live faces [0, nf) to the degrees in the ring offsets (zero before). In core on two or
// more threads with a `spare` array of nv counters: two threads count half of the faces each,
// the second into `spare`, which is then added. Else by vertex range on `threads` threads in core
// (each thread scans every face and counts only its own vertices, no atomics; a thread never
// writes another's counter, not even adding zero), on two threads out of core (the upper half
// through a forked DML).
void Decimator::CountDegrees(std::uint64_t nf, int threads, std::uint64_t tickBase,
  std::uint64_t tickTotal, std::uint32_t* spare)
{
  this->BindViews();
  const std::uint64_t nv = this->nv_;
  const Tri* Fp = this->v_.F.Ptr(0);
  std::uint32_t* ROp = const_cast<std::uint32_t*>(this->v_.RO.Ptr(0));
  auto tick = [&](int t, std::uint64_t f, const std::atomic<bool>& stop) {
    if ((f & 4095) != 0)
    {
      return true;
    }
    if (stop.load(std::memory_order_relaxed))
    {
      return false;
    }
    if (t == 0 && tickTotal)
    {
      // (strided: Tick's own 1-in-1024 filter would miss; abort is checked here too)
      this->progress_.Tick(double(tickBase + f) / double(tickTotal));
    }
    return true;
  };
  if (threads > 1 && Fp && ROp && spare)
  {
    ForRanges(2, nf, [&](int t, std::uint64_t fb, std::uint64_t fe, const std::atomic<bool>& stop) {
      std::uint32_t* count = t == 0 ? ROp : spare;
      if (t == 1)
      {
        std::fill(spare, spare + nv, 0u);
      }
      for (std::uint64_t f = fb; f < fe && tick(t, f, stop); ++f)
      {
        const Tri t3 = Fp[f];
        if (Alive(t3))
        {
          ++count[t3.v[0]];
          ++count[t3.v[1]];
          ++count[t3.v[2]];
        }
      }
    });
    ForRanges(2, nv, [&](int, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>&) {
      for (std::uint64_t v = lo; v < hi; ++v)
      {
        ROp[v] += spare[v];
      }
    });
    return;
  }
  Views forkViews;
  std::unique_ptr<DML> fork;
  ForkGuard joinOnExit{ *this, fork };
  int T = (Fp && ROp) ? threads : 1;
  if (T == 1)
  {
    fork = this->ForkHelper(nv, nv / 2, { this->ringOff_.Id() }, forkViews);
    T = fork ? 2 : 1;
  }
  auto count = [&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
    Views& w = (fork && t == 1) ? forkViews : this->v_;
    for (std::uint64_t f = 0; f < nf && tick(t, f, stop); ++f)
    {
      const Tri t3 = Fp ? Fp[f] : w.F.Get(f);
      if (Alive(t3))
      {
        for (int c = 0; c < 3; ++c)
        {
          const std::uint32_t x = t3.v[c];
          if (x >= lo && x < hi)
          {
            if (ROp)
            {
              ++ROp[x];
            }
            else
            {
              w.RO.Set(x, w.RO.Get(x) + 1);
            }
          }
        }
      }
    }
  };
  ForRanges(T, nv, count, [&]() { this->JoinHelper(fork); });
  this->JoinHelper(fork);
}

// Fills the incident face lists of faces [0, nf) (dead ones skipped) from the ring offsets, which
// hold the end of each list: faces in reverse, so each list ends up in increasing face order and
// RO[v] at its start. In core on all cores, each thread owns a range of vertices and scans every
// face (the reads are sequential, the writes it splits are not): the same lists.
void Decimator::FillRings(std::uint64_t nf, std::uint64_t tickBase, std::uint64_t tickTotal)
{
  const Tri* F = this->v_.F.Ptr(0);
  std::uint32_t* RO = const_cast<std::uint32_t*>(this->v_.RO.Ptr(0));
  std::uint32_t* RF = const_cast<std::uint32_t*>(this->v_.RF.Ptr(0));
  const bool inCore = F && RO && RF;
  const std::uint64_t nv = this->nv_;
  int T = (nf >= kParallelRingsMin && inCore) ? this->threads_ : 1;
  // Out of core: the upper half of the vertices (their offsets and lists) on a helper thread
  // through a forked DML.
  Views forkViews;
  const std::uint64_t mid = nv / 2;
  std::unique_ptr<DML> fork;
  ForkGuard joinOnExit{ *this, fork };
  if (T == 1 && mid > 0)
  {
    const std::uint64_t rfBegin = this->v_.RO.Get(mid - 1), rfEnd = this->v_.RO.Get(nv);
    if (rfBegin < rfEnd)
    {
      fork = this->ForkHelper(nv, mid, { this->ringOff_.Id() }, forkViews,
        { { this->ringFace_.Id(), rfBegin, rfEnd - rfBegin } });
      T = fork ? 2 : 1;
    }
  }
  auto fill = [&](int th, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
    Views& w = (fork && th == 1) ? forkViews : this->v_;
    for (std::uint64_t i = nf; i-- > 0;)
    {
      if ((i & 4095) == 0)
      {
        if (stop.load(std::memory_order_relaxed))
        {
          return;
        }
        if (th == 0 && tickTotal)
        {
          // (strided: Tick's own 1-in-1024 filter would miss; abort is checked here too)
          this->progress_.Tick(double(tickBase + (nf - i)) / double(tickTotal));
        }
      }
      const Tri t = inCore ? F[i] : w.F.Get(i);
      if (!Alive(t))
      {
        continue;
      }
      for (int k = 0; k < 3; ++k)
      {
        const std::uint32_t x = t.v[k];
        if (x >= lo && x < hi)
        {
          if (inCore)
          {
            RF[--RO[x]] = std::uint32_t(i);
          }
          else
          {
            const std::uint32_t e = w.RO.Get(x) - 1;
            w.RO.Set(x, e);
            w.RF.Set(e, std::uint32_t(i));
          }
        }
      }
    }
  };
  ForRanges(T, nv, fill, [&]() { this->JoinHelper(fork); });
  this->JoinHelper(fork);
}

void Decimator::BuildRings()
{
  PhaseTimer timer(this->stats_, this->dml_, "rings");
  this->progress_.BeginPhase(
    "rings", kWork::kRings * double(this->nf_), this->RestWork(2, this->nv_, this->nf_));
  const std::uint64_t nv = this->nv_, nf = this->nf_;
  if (3 * nf >= kNone)
  {
    throw std::runtime_error("decimate: more than 1.4 billion triangles");
  }
  this->ringOff_ = Array<std::uint32_t>(this->dml_, nv + 1);
  FillBlock(this->dml_, this->ringOff_, std::uint32_t(0));
  View<Tri> F(this->dml_, this->faces_);
  View<Vec3> P(this->dml_, this->pos_);
  View<std::uint32_t> RO(this->dml_, this->ringOff_);
  // In core, passes 1 and 3 run on all cores (each thread on its own faces), the degrees and
  // pass 2 by vertex range (CountDegrees, FillRings); same result.
  const int T = (nf >= kParallelRingsMin && F.Ptr(0) && P.Ptr(0) && RO.Ptr(0)) ? this->threads_ : 1;
  // Pass 1 over the faces: validate, drop zero-area faces, count the degrees. The first bad
  // face is reported, whatever the threads. Out of core on two threads: the upper half of the
  // faces through a forked DML, then the degrees (CountDegrees).
  std::uint64_t live = 0;
  {
    Views forkViews;
    std::unique_ptr<DML> fork =
      T == 1 ? this->ForkHelper(nf, nf / 2, { this->faces_.Id() }, forkViews) : nullptr;
    ForkGuard joinOnExit{ *this, fork };
    const int T1 = fork ? 2 : T;
    std::vector<std::uint64_t> lives(std::size_t(T1), 0), drops(std::size_t(T1), 0);
    std::vector<std::uint64_t> bad(std::size_t(T1), ~std::uint64_t(0));
    auto pass1 = [&](int th, std::uint64_t fb, std::uint64_t fe, const std::atomic<bool>& stop) {
      View<Tri>& Fv = (fork && th == 1) ? forkViews.F : F;
      const View<Vec3>& Pv = (fork && th == 1) ? forkViews.P : P;
      for (std::uint64_t f = fb; f < fe && !stop.load(std::memory_order_relaxed); ++f)
      {
        if (th == 0 && ((f - fb) & 1023) == 0)
        {
          this->progress_.Tick(double((f - fb) * T1) / double(4 * nf));
        }
        Tri t = Fv.Get(f);
        if (!Alive(t))
        {
          continue;
        }
        if (t.v[0] >= nv || t.v[1] >= nv || t.v[2] >= nv)
        {
          bad[std::size_t(th)] = std::min(bad[std::size_t(th)], f);
          break;
        }
        Vec3 a = Pv.Get(t.v[0]), b = Pv.Get(t.v[1]), c = Pv.Get(t.v[2]);
        Vec3 n = Cross(b - a, c - a);
        if (Dot(n, n) == 0.0)
        {
          Fv.Set(f, kDeadTri);
          ++drops[std::size_t(th)];
          continue;
        }
        if (T1 <= 1)
        {
          for (int k = 0; k < 3; ++k)
          {
            RO.Set(t.v[k], RO.Get(t.v[k]) + 1);
          }
        }
        ++lives[std::size_t(th)];
      }
    };
    ForRanges(T1, nf, pass1, [&]() { this->JoinHelper(fork); });
    this->JoinHelper(fork);
    const std::uint64_t first = *std::min_element(bad.begin(), bad.end());
    if (first != ~std::uint64_t(0))
    {
      const Tri t = F.Get(first);
      const std::uint32_t v = t.v[0] >= nv ? t.v[0] : (t.v[1] >= nv ? t.v[1] : t.v[2]);
      throw io::MeshIOError("decimate: triangle " + std::to_string(first) + " has vertex index " +
        std::to_string(v) + " >= vertex count " + std::to_string(nv));
    }
    for (int th = 0; th < T1; ++th)
    {
      live += lives[std::size_t(th)];
      this->dropped_ += drops[std::size_t(th)];
    }
    if (T1 > 1)
    {
      this->CountDegrees(nf, T, nf, 4 * nf);
      F.Refresh();
      P.Refresh();
      RO.Refresh();
    }
  }
  // Inclusive prefix sums: RO[v] = end of v's list.
  std::uint32_t sum = 0;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    sum += RO.Get(v);
    RO.Set(v, sum);
  }
  RO.Set(nv, sum);
  this->ringFace_ = Array<std::uint32_t>(this->dml_, std::max<std::uint32_t>(sum, 1));
  F.Refresh();
  P.Refresh();
  RO.Refresh();
  View<std::uint32_t> RF(this->dml_, this->ringFace_);
  // Pass 2: the incident face lists.
  this->BindViews();
  this->FillRings(nf, 2 * nf, 4 * nf);
  // Faces on the same vertex set: copies of one orientation are one face, and two faces of
  // opposite orientations cancel (a zero-volume double-sided pair: keeping one of them would
  // leave three faces on each of its edges). A group is settled by its first live member; the
  // net orientation decides what survives: nothing, or its first member of that orientation.
  std::vector<std::uint32_t> ring;
  auto sameSet = [](const Tri& a, const std::uint32_t s[3]) {
    std::uint32_t r[3] = { a.v[0], a.v[1], a.v[2] };
    SmallSort(r, 3);
    return r[0] == s[0] && r[1] == s[1] && r[2] == s[2];
  };
  auto orientation = [](const Tri& a, const Tri& ref) {
    // +1: a is a rotation of ref, -1: of its reverse
    for (int k = 0; k < 3; ++k)
    {
      if (a.v[0] == ref.v[k])
      {
        return a.v[1] == ref.v[(k + 1) % 3] ? 1 : -1;
      }
    }
    return 1;
  };
  // The groups of live faces on one vertex set (rare), found per vertex: a face belongs to its
  // lowest vertex x, and x's faces are sorted by their other two vertices, so each face is read
  // once and a ring of any size costs n log n (a fan of 200,000 faces around one vertex too).
  // On all cores in core; on two out of core, the upper half of the vertices through a forked
  // DML that writes nothing. The mode is taken again here, not from T: opening the ring face
  // list above may have moved every block out of core, and out of core a DML serves one thread
  // only (a second one goes through a fork). A group is stored as its size, then its members in
  // increasing order.
  const int Tin = (nf >= kParallelRingsMin && F.Ptr(0) && RO.Ptr(0) && RF.Ptr(0))
    ? this->threads_
    : 1;
  Views forkViews;
  std::unique_ptr<DML> fork =
    Tin == 1 ? this->ForkHelper(nv, nv / 2, {}, forkViews) : nullptr;
  ForkGuard joinOnExit{ *this, fork };
  const int T3 = fork ? 2 : Tin;
  std::vector<std::vector<std::uint64_t>> found(static_cast<std::size_t>(T3));
  auto pass3 = [&](int th, std::uint64_t vb, std::uint64_t ve, const std::atomic<bool>& stop) {
    const bool helper = fork && th == 1;
    const View<Tri>& Fv = helper ? forkViews.F : F;
    const View<std::uint32_t>& ROv = helper ? forkViews.RO : RO;
    const View<std::uint32_t>& RFv = helper ? forkViews.RF : RF;
    std::vector<std::uint32_t> list;
    std::vector<std::pair<std::uint64_t, std::uint32_t>> keyed; // (other two vertices, face)
    std::uint64_t work = 0; // ring entries since the last poll
    for (std::uint64_t x = vb; x < ve && !stop.load(std::memory_order_relaxed); ++x)
    {
      if (th == 0 && work >= 4096)
      {
        work = 0;
        this->progress_.Tick(double(3 * nf) / double(4 * nf) +
          double((x - vb) * std::uint64_t(T3)) / double(4 * std::max<std::uint64_t>(nv, 1)));
      }
      const std::uint32_t b = ROv.Get(x), e = ROv.Get(x + 1);
      work += 1 + (e - b);
      if (e - b < 2)
      {
        continue;
      }
      const std::uint32_t* faceIds = RFv.Ptr(b); // in core: the list itself
      if (!faceIds)
      {
        list.resize(e - b);
        RFv.GetRange(b, e - b, list.data());
        faceIds = list.data();
      }
      keyed.clear();
      for (std::uint32_t k = 0; k < e - b; ++k)
      {
        if ((k & 4095) == 4095)
        {
          if (th == 0)
          {
            this->progress_.Poll(); // (a vertex of very high valence)
          }
          else if (stop.load(std::memory_order_relaxed))
          {
            return;
          }
        }
        const Tri t = Fv.Get(faceIds[k]);
        if (!Alive(t) || std::min(t.v[0], std::min(t.v[1], t.v[2])) != x)
        {
          continue;
        }
        std::uint32_t a = t.v[0] == x ? t.v[1] : t.v[0];
        std::uint32_t c = t.v[2] == x ? t.v[1] : t.v[2];
        if (c < a)
        {
          std::swap(a, c);
        }
        keyed.push_back({ (std::uint64_t(a) << 32) | c, faceIds[k] });
      }
      if (keyed.size() < 2)
      {
        continue;
      }
      SmallSort(keyed.data(), keyed.size());
      for (std::size_t i = 0; i < keyed.size();)
      {
        std::size_t j = i + 1;
        while (j < keyed.size() && keyed[j].first == keyed[i].first)
        {
          ++j;
        }
        if (j - i > 1)
        {
          std::vector<std::uint64_t>& out = found[std::size_t(th)];
          out.push_back(j - i);
          for (std::size_t k = i; k < j; ++k)
          {
            out.push_back(keyed[k].second);
          }
        }
        i = j;
      }
      ReleaseIfLarge(keyed);
      ReleaseIfLarge(list);
    }
  };
  ForRanges(T3, nv, pass3, [&]() { this->JoinHelper(fork); }, [this]() { this->progress_.Poll(); });
  this->JoinHelper(fork);
  // The groups in the order of their first members (face order, as a sweep over the faces
  // would settle them).
  std::vector<std::uint64_t> members; // the threads' lists, one after the other
  std::vector<std::pair<std::uint64_t, std::size_t>> groups; // (first member, where)
  for (const std::vector<std::uint64_t>& list : found)
  {
    const std::size_t base = members.size();
    members.insert(members.end(), list.begin(), list.end());
    for (std::size_t i = 0; i < list.size(); i += 1 + list[i])
    {
      groups.push_back({ list[i + 1], base + i });
    }
  }
  found.clear();
  std::sort(groups.begin(), groups.end());
  std::uint64_t work = 0; // faces read since the last poll
  for (const auto& group : groups)
  {
    if (work >= 4096)
    {
      work = 0;
      this->progress_.Tick(1.0);
    }
    const std::uint64_t* ids = members.data() + group.second + 1;
    const std::uint64_t count = ids[-1];
    const std::uint64_t f = ids[0];
    work += count;
    const Tri t = F.Get(f);
    std::uint32_t s[3] = { t.v[0], t.v[1], t.v[2] };
    SmallSort(s, 3);
    int net = 1;
    for (std::uint64_t k = 1; k < count; ++k)
    {
      net += orientation(F.Get(ids[k]), t);
    }
    // Keep at most one face: the first member whose orientation has the sign of net.
    // Net zero (a double-sided pair): cancelling it suits edges that other faces already make
    // manifold (two more faces each: fins, scans); on edges with one other face it would open a
    // hole (clustered meshes, where a thin part folds onto itself), and one face of the pair,
    // oriented like that neighbour, closes them. The edges decide by majority.
    if (net == 0)
    {
      int single = 0, pairs = 0, agree = 0;
      for (int k = 0; k < 3; ++k)
      {
        const std::uint32_t a = t.v[k], c = t.v[(k + 1) % 3];
        // The edge's faces are in both rings: the shorter one is read.
        const std::uint32_t ab = RO.Get(a), ae = RO.Get(a + 1);
        const std::uint32_t cb = RO.Get(c), ce = RO.Get(c + 1);
        const std::uint32_t rb = ae - ab <= ce - cb ? ab : cb;
        const std::uint32_t re = ae - ab <= ce - cb ? ae : ce;
        work += re - rb;
        ring.resize(re - rb);
        RF.GetRange(rb, re - rb, ring.data());
        int others = 0, dir = 0;
        for (std::uint32_t g : ring)
        {
          const Tri u = F.Get(g);
          if (!Alive(u) || !Has(u, a) || !Has(u, c) || sameSet(u, s))
          {
            continue;
          }
          ++others;
          dir = u.v[kNextCorner[CornerOf(u, a)]] == c ? 1 : -1; // +1: it runs a -> c like t
        }
        if (others == 1)
        {
          ++single;
          agree += -dir; // a consistent neighbour runs c -> a: t's orientation is right
        }
        else if (others == 2)
        {
          ++pairs;
        }
      }
      if (single > pairs)
      {
        net = agree >= 0 ? 1 : -1;
      }
    }
    bool kept = net > 0; // f itself has orientation +1
    if (!kept)
    {
      F.Set(f, kDeadTri);
      ++this->dropped_;
      --live;
    }
    for (std::uint64_t k = 1; k < count; ++k)
    {
      const std::uint64_t g = ids[k];
      const Tri u = F.Get(g);
      if (!kept && net < 0 && orientation(u, t) < 0)
      {
        kept = true;
        continue;
      }
      F.Set(g, kDeadTri);
      ++this->dropped_;
      --live;
    }
  }
  this->liveFaces_ = live;
}

// ---------------------------------------------------------------------------------------------
// rings of single vertices

void Decimator::BindViews()
{
  this->BindViews(this->v_, this->dml_);
}

void Decimator::BindViews(Views& w, DML& dml) const
{
  w.P = View<Vec3>(dml, this->pos_);
  w.Q = this->quad_.IsOpen() ? View<Quadric>(dml, this->quad_) : View<Quadric>();
  w.A = this->recSize_ ? View<std::uint8_t>(dml, this->attr_) : View<std::uint8_t>();
  w.S = this->state_.IsOpen() ? View<State>(dml, this->state_) : View<State>();
  w.F = View<Tri>(dml, this->faces_);
  w.RO = View<std::uint32_t>(dml, this->ringOff_);
  w.RF = View<std::uint32_t>(dml, this->ringFace_);
  w.C = this->cand_.IsOpen() ? View<Cand>(dml, this->cand_) : View<Cand>();
  w.O = this->order_.IsOpen() ? View<std::uint32_t>(dml, this->order_) : View<std::uint32_t>();
}

// x's live faces only (r.faces; no neighbour table, no positions).
void Decimator::LoadFaces(Views& w, std::uint32_t x, Ring& r)
{
  r.x = x;
  r.faces.clear();
  r.nbs.clear();
  r.keys.clear();
  const std::uint32_t b = w.RO.Get(x), e = w.RO.Get(x + 1);
  const std::uint32_t* ids = w.RF.Ptr(b); // in core: the list itself
  if (!ids)
  {
    r.ids.resize(e - b);
    w.RF.GetRange(b, e - b, r.ids.data());
    ids = r.ids.data();
  }
  if (const Tri* fp = w.F.Ptr(0))
  {
    for (std::uint32_t k = 0; k < e - b; ++k)
    {
      Prefetch(fp + ids[k]);
    }
  }
  for (std::uint32_t k = 0; k < e - b; ++k)
  {
    const std::uint32_t id = ids[k];
    const Tri t = w.F.Get(id);
    if (!Alive(t))
    {
      continue;
    }
    const int corner = CornerOf(t, x);
    r.faces.push_back({ id, t, corner, { 0, 0 } });
  }
}

void Decimator::LoadRing(Views& w, std::uint32_t x, Ring& r, bool positions)
{
  this->LoadFaces(w, x, r);
  this->BuildNeighbours(w, r, positions);
}

// The sorted neighbour table of a ring whose faces are loaded (and their positions).
void Decimator::BuildNeighbours(Views& w, Ring& r, bool positions)
{
  r.nbs.clear();
  r.keys.clear();
  for (std::size_t slot = 0; slot < r.faces.size(); ++slot)
  {
    // key: neighbour | slot | which (0: next corner, 1: previous corner)
    const RingFace& f = r.faces[slot];
    r.keys.push_back((std::uint64_t(f.t.v[kNextCorner[f.corner]]) << 32) | (slot << 1));
    r.keys.push_back((std::uint64_t(f.t.v[kPrevCorner[f.corner]]) << 32) | (slot << 1) | 1);
  }
  SmallSort(r.keys.data(), r.keys.size());
  for (std::uint64_t key : r.keys)
  {
    const std::uint32_t v = std::uint32_t(key >> 32);
    const std::uint32_t slot = std::uint32_t(key & 0xffffffffu) >> 1;
    const int which = int(key & 1);
    RingFace& rf = r.faces[slot];
    const std::uint32_t opp = rf.t.v[which == 0 ? kPrevCorner[rf.corner] : kNextCorner[rf.corner]];
    if (r.nbs.empty() || r.nbs.back().v != v)
    {
      r.nbs.push_back({ v, 1, { opp, kNone }, { 0, 0, 0 } });
    }
    else
    {
      Nb& n = r.nbs.back();
      if (n.count < 2)
      {
        n.opp[1] = opp;
      }
      ++n.count;
    }
    rf.nb[which] = std::uint32_t(r.nbs.size() - 1);
  }
  if (positions)
  {
    if (const Vec3* pp = w.P.Ptr(0))
    {
      for (const Nb& n : r.nbs)
      {
        Prefetch(pp + n.v);
      }
    }
    r.px = w.P.Get(r.x);
    for (Nb& n : r.nbs)
    {
      n.p = w.P.Get(n.v);
    }
  }
}

// ---------------------------------------------------------------------------------------------
// quadrics

void Decimator::BuildQuadrics()
{
  PhaseTimer timer(this->stats_, this->dml_, "quadrics");
  this->progress_.BeginPhase("quadrics", kWork::kQuadrics * double(this->liveFaces_),
    this->RestWork(3, this->nv_, this->liveFaces_));
  const std::uint64_t nv = this->nv_;
  this->quad_ = Array<Quadric>(this->dml_, std::max<std::uint64_t>(nv, 1));
  this->state_ = Array<State>(this->dml_, std::max<std::uint64_t>(nv, 1));
  this->cand_ = Array<Cand>(this->dml_, std::max<std::uint64_t>(nv, 1));
  this->order_ = Array<std::uint32_t>(this->dml_, std::max<std::uint64_t>(nv, 1));
  this->remap_ = Array<std::uint32_t>(this->dml_, std::max<std::uint64_t>(nv, 1));
  this->BindViews();
  // One gather per vertex over its ring (faces in increasing order, so the sums are those of a
  // scatter in face order, whatever the threads): the area-weighted face plane quadrics, the edge
  // multiplicities (topology flags, boundary constraint planes), the initial quadric, and the
  // empty candidate. Every vertex writes only its own records: in core the vertex range is split
  // among threads (not with initialQuadric, a caller's callback).
  const double bw = this->opt_.boundaryWeight;
  auto vertex = [this, bw](Views& w, std::uint32_t u, std::vector<Tri>& tris,
                  std::vector<std::uint32_t>& next, std::vector<std::uint32_t>& prev,
                  LinkTally& tally, const std::atomic<bool>& stop, bool caller) {
    // A vertex of very high valence takes long: the calling thread polls inside it (an abort
    // throws), another thread stops early when the run is being stopped.
    auto stopped = [this, &stop, caller](std::size_t i) {
      if ((i & 4095) != 4095)
      {
        return false;
      }
      if (caller)
      {
        this->progress_.Poll();
      }
      return stop.load(std::memory_order_relaxed);
    };
    State flags = kRecompute;
    const std::uint32_t b = w.RO.Get(u), e = w.RO.Get(u + 1);
    tris.clear();
    next.clear();
    prev.clear();
    Quadric Q = { { 0, 0, 0, 0, 0, 0, 0, 0, 0, 0 } };
    for (std::uint32_t k = b; k < e; ++k)
    {
      if (stopped(k - b))
      {
        return;
      }
      const Tri t = w.F.Get(w.RF.Get(k));
      if (!Alive(t))
      {
        continue;
      }
      const int c = CornerOf(t, u);
      tris.push_back(t);
      next.push_back(t.v[kNextCorner[c]]);
      prev.push_back(t.v[kPrevCorner[c]]);
      const Vec3 a = w.P.Get(t.v[0]);
      Vec3 nn = Cross(w.P.Get(t.v[1]) - a, w.P.Get(t.v[2]) - a);
      const double len = std::sqrt(Dot(nn, nn));
      if (len > 0)
      {
        nn = (1.0 / len) * nn;
        AddPlane(Q, nn, -Dot(nn, a), 0.5 * len);
      }
    }
    const std::size_t n = tris.size();
    const bool useTally = n > LinkTally::kMinEntries;
    if (useTally)
    {
      tally.Build(next.data(), prev.data(), n);
    }
    auto countIn = [&](bool inNext, std::uint32_t x) {
      if (useTally)
      {
        return tally.Count(inNext, x);
      }
      std::size_t m = 0;
      for (std::uint32_t y : inNext ? next : prev)
      {
        m += y == x;
      }
      return m;
    };
    // Whether entry i of next (inNext) or prev is the first x there.
    auto first = [&](bool inNext, std::uint32_t x, std::size_t i) {
      if (useTally)
      {
        return tally.First(inNext, x, i);
      }
      const std::vector<std::uint32_t>& list = inNext ? next : prev;
      return std::find(list.begin(), list.begin() + std::ptrdiff_t(i), x) ==
        list.begin() + std::ptrdiff_t(i);
    };
    int boundaryEdges = 0;
    auto boundaryPlane = [&](std::uint32_t a, std::size_t face) {
      ++boundaryEdges;
      if (!(bw > 0))
      {
        return;
      }
      const Tri& t = tris[face];
      const Vec3 p0 = w.P.Get(t.v[0]);
      Vec3 fn = Cross(w.P.Get(t.v[1]) - p0, w.P.Get(t.v[2]) - p0);
      const Vec3 pu = w.P.Get(u);
      const Vec3 ev = w.P.Get(a) - pu;
      Vec3 m = Cross(ev, fn);
      const double len = std::sqrt(Dot(m, m));
      if (len > 0)
      {
        m = (1.0 / len) * m;
        AddPlane(Q, m, -Dot(m, pu), bw * Dot(ev, ev));
      }
    };
    for (std::size_t i = 0; i < n; ++i)
    {
      if (stopped(i))
      {
        return;
      }
      const std::uint32_t a = next[i];
      if (!first(true, a, i))
      {
        continue;
      }
      const std::size_t m = countIn(true, a) + countIn(false, a);
      if (m > 2)
      {
        flags |= kComplex; // a non-manifold edge: its face count is checked before collapses
      }
      else if (m == 1)
      {
        boundaryPlane(a, i);
      }
    }
    for (std::size_t i = 0; i < n; ++i)
    {
      if (stopped(i))
      {
        return;
      }
      const std::uint32_t a = prev[i];
      if (countIn(true, a) > 0 || !first(false, a, i))
      {
        continue;
      }
      const std::size_t m = countIn(false, a);
      if (m > 2)
      {
        flags |= kComplex;
      }
      else if (m == 1)
      {
        boundaryPlane(a, i);
      }
    }
    if (boundaryEdges > 0)
    {
      flags |= kBoundary;
      if (boundaryEdges != 2)
      {
        flags |= kComplex; // several fans meet here: the link condition keeps them apart
      }
      if (this->opt_.lockBoundary)
      {
        flags |= kFixed;
      }
    }
    if (this->opt_.initialQuadric)
    {
      double iq[10] = { 0 };
      if (this->opt_.initialQuadric(u, iq))
      {
        // World to local coordinates: x = y + o.
        const Vec3 o = this->origin_;
        const double ax = iq[0] * o.x + iq[1] * o.y + iq[2] * o.z;
        const double ay = iq[1] * o.x + iq[4] * o.y + iq[5] * o.z;
        const double az = iq[2] * o.x + iq[5] * o.y + iq[7] * o.z;
        Quadric T;
        std::copy(iq, iq + 10, T.q);
        T.q[3] = ax + iq[3];
        T.q[6] = ay + iq[6];
        T.q[8] = az + iq[8];
        T.q[9] = o.x * ax + o.y * ay + o.z * az + 2.0 * (iq[3] * o.x + iq[6] * o.y + iq[8] * o.z) +
          iq[9];
        AddTo(Q, T);
      }
    }
    w.Q.Set(u, Q);
    w.S.Set(u, flags);
    w.C.Set(u, this->none_);
    if (useTally)
    {
      tally.Release();
      ReleaseIfLarge(tris);
      ReleaseIfLarge(next);
      ReleaseIfLarge(prev);
    }
  };
  int T = (this->AllInCore() && !this->opt_.initialQuadric && nv >= 8192) ? this->threads_ : 1;
  // Out of core: the upper half of the vertices on a helper thread through a forked DML.
  Views forkViews;
  std::unique_ptr<DML> fork = (T == 1 && !this->opt_.initialQuadric)
    ? this->ForkHelper(nv, nv / 2, { this->quad_.Id(), this->state_.Id(), this->cand_.Id() },
        forkViews)
    : nullptr;
  ForkGuard joinOnExit{ *this, fork };
  if (fork)
  {
    T = 2; // ForRanges' halves: [0, nv / 2) and [nv / 2, nv)
  }
  ForRanges(
    T, nv,
    [&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
      Views& w = (fork && t == 1) ? forkViews : this->v_;
      std::vector<Tri> tris;
      std::vector<std::uint32_t> next, prev;
      LinkTally tally;
      // In core: the faces of the vertices 8 ahead, the corner positions of those 4 ahead.
      const std::uint32_t* ROp = w.RO.Ptr(0);
      const std::uint32_t* RFp = w.RF.Ptr(0);
      const Tri* Fp = w.F.Ptr(0);
      const Vec3* Pp = w.P.Ptr(0);
      const bool prefetch = ROp && RFp && Fp && Pp;
      for (std::uint64_t u = lo; u < hi && !stop.load(std::memory_order_relaxed); ++u)
      {
        if (t == 0)
        {
          this->Tick(u - lo, hi - lo); // progress and abort: the calling thread only
        }
        if (prefetch && u + 8 < hi)
        {
          for (std::uint32_t k = ROp[u + 8], e = ROp[u + 9]; k < e; ++k)
          {
            Prefetch(Fp + RFp[k]);
          }
          for (std::uint32_t k = ROp[u + 4], e = ROp[u + 5]; k < e; ++k)
          {
            for (const std::uint32_t y : Fp[RFp[k]].v)
            {
              PrefetchAt(Pp, y); // (the duplicate search may have killed the face)
            }
          }
        }
        vertex(w, std::uint32_t(u), tris, next, prev, tally, stop, t == 0);
      }
    },
    [&]() { this->JoinHelper(fork); }, [this]() { this->progress_.Poll(); });
  this->JoinHelper(fork);
}

// ---------------------------------------------------------------------------------------------
// collapse

// The placement of a collapse with summed quadric Q (PlaceLanes for one edge); a fixed endpoint
// stays where it is.
Placement Decimator::Place(const Quadric& Q, const Vec3& pu, const Vec3& pv, State su, State sv) const
{
  if (su & kFixed)
  {
    return { std::max(0.0, Eval(Q, pu)), pu, 0.0 };
  }
  if (sv & kFixed)
  {
    return { std::max(0.0, Eval(Q, pv)), pv, 1.0 };
  }
  const double u[3] = { pu.x, pu.y, pu.z }, v[3] = { pv.x, pv.y, pv.z };
  const PlaceOut<double> o = PlaceLanes<double>(Q.q, u, v);
  return { o.cost, { o.px, o.py, o.pz }, o.t };
}

bool Decimator::FaceOk(const Ring& r, std::size_t slot, const Vec3& p) const
{
  Vec3 c[3];
  r.Corners(slot, c);
  return this->FaceOk(c, r.faces[slot].corner, p);
}

// Face with corners c (overwritten) when corner `corner` moves to p.
bool Decimator::FaceOk(Vec3 c[3], int corner, const Vec3& p) const
{
  const Vec3 n0 = Cross(c[1] - c[0], c[2] - c[0]);
  c[corner] = p;
  const Vec3 e0 = c[1] - c[0], e1 = c[2] - c[0], e2 = c[2] - c[1];
  const Vec3 n1 = Cross(e0, e1);
  const double l1 = Dot(n1, n1);
  const double maxE = std::max({ Dot(e0, e0), Dot(e1, e1), Dot(e2, e2) });
  if (!(l1 > 1e-20 * maxE * maxE))
  {
    return false; // (nearly) zero area
  }
  const double l0 = Dot(n0, n0);
  if (!(l0 > 0))
  {
    return true;
  }
  // Flips or turns too much: n0.n1 < cos |n0| |n1|, compared squared (no square root).
  const double dot = Dot(n0, n1), k = this->cosThreshold_;
  const double bound2 = k * k * l0 * l1;
  return k >= 0 ? (dot >= 0 && dot * dot >= bound2) : (dot >= 0 || dot * dot <= bound2);
}

// Is collapsing u (ring in s.ru, with its neighbour table and positions) and nb.v to p legal?
// Loads s.rv the same way unless rvLoaded.
bool Decimator::Legal(std::uint32_t u, const Nb& nb, const Vec3& p, Scratch& s, bool rvLoaded)
{
  const std::uint32_t v = nb.v;
  const std::uint32_t m = nb.count;
  Ring& ru = s.ru;
  Ring& rv = s.rv;
  if (!rvLoaded)
  {
    this->LoadRing(this->W(s), v, rv, true);
  }
  // The collapse must leave faces (no vanishing component).
  if (ru.faces.size() + rv.faces.size() <= 2 * std::size_t(m))
  {
    return false;
  }
  // Link condition: the common neighbours are exactly the vertices opposite the edge.
  std::uint32_t common = 0;
  {
    std::size_t i = 0, j = 0;
    while (i < ru.nbs.size() && j < rv.nbs.size())
    {
      const std::uint32_t a = ru.nbs[i].v, b = rv.nbs[j].v;
      if (a < b)
      {
        ++i;
      }
      else if (b < a)
      {
        ++j;
      }
      else
      {
        if (a != u && a != v)
        {
          ++common;
        }
        ++i;
        ++j;
      }
    }
  }
  if (common != m)
  {
    return false;
  }
  // A face (u, o1, o2) and a face (v, o1, o2) would become duplicates (tetrahedron).
  if (m == 2 && ru.HasFace(nb.opp[0], nb.opp[1]) && rv.HasFace(nb.opp[0], nb.opp[1]))
  {
    return false;
  }
  if (m > 2)
  {
    // A non-manifold edge (m sheets meet on it): the same test for every face of u's ring whose
    // other two corners are both common neighbours.
    for (const RingFace& f : ru.faces)
    {
      if (Has(f.t, v))
      {
        continue;
      }
      const std::uint32_t a = f.t.v[(f.corner + 1) % 3], b = f.t.v[(f.corner + 2) % 3];
      if (rv.HasFace(a, b))
      {
        return false;
      }
    }
  }
  // Geometry of the faces that survive.
  for (std::size_t s = 0; s < ru.faces.size(); ++s)
  {
    if (!Has(ru.faces[s].t, v) && !this->FaceOk(ru, s, p))
    {
      return false;
    }
  }
  for (std::size_t s = 0; s < rv.faces.size(); ++s)
  {
    if (!Has(rv.faces[s].t, u) && !this->FaceOk(rv, s, p))
    {
      return false;
    }
  }
  return true;
}

// Legal for u and v with their faces loaded (s.ru, s.rv: LoadFaces), when the edge has m <= 2
// faces, whose third vertices are opp[0..m-1]: the same rules, without neighbour tables. The
// common neighbours are exactly the opposite vertices when those differ and no other vertex of
// v's faces without u is a corner of u's faces; positions are read per face.
bool Decimator::LegalFaces(std::uint32_t u, std::uint32_t v, std::uint32_t m,
  const std::uint32_t opp[2], const Vec3& p, Scratch& s)
{
  const Ring& ru = s.ru;
  const Ring& rv = s.rv;
  if (ru.faces.size() + rv.faces.size() <= 2 * std::size_t(m))
  {
    return false;
  }
  if (m == 2 && opp[0] == opp[1])
  {
    // Two faces (u, v, o) and (v, u, o): Legal counted o once and could let one more common
    // neighbour through; neither BuildRings (it settles such pairs) nor a legal collapse makes
    // them, and the stricter answer is the right one.
    return false;
  }
  const std::uint32_t o1 = m == 2 ? opp[1] : opp[0];
  bool clash = false; // (no early exits: fixed trip counts instead of mispredicted branches)
  for (const RingFace& f : rv.faces)
  {
    if (Has(f.t, u))
    {
      continue;
    }
    for (const std::uint32_t a : { f.t.v[kNextCorner[f.corner]], f.t.v[kPrevCorner[f.corner]] })
    {
      bool inU = false;
      for (const RingFace& g : ru.faces)
      {
        inU |= (g.t.v[0] == a) | (g.t.v[1] == a) | (g.t.v[2] == a);
      }
      clash |= inU & (a != opp[0]) & (a != o1);
    }
  }
  if (clash)
  {
    return false;
  }
  // A face (u, o1, o2) and a face (v, o1, o2) would become duplicates (tetrahedron).
  if (m == 2 && ru.HasFaceWith(opp[0], opp[1]) && rv.HasFaceWith(opp[0], opp[1]))
  {
    return false;
  }
  Views& w = this->W(s);
  for (const Ring* r : { &ru, &rv })
  {
    const std::uint32_t other = r == &ru ? v : u;
    for (const RingFace& f : r->faces)
    {
      if (Has(f.t, other))
      {
        continue;
      }
      Vec3 c[3] = { w.P.Get(f.t.v[0]), w.P.Get(f.t.v[1]), w.P.Get(f.t.v[2]) };
      if (!this->FaceOk(c, f.corner, p))
      {
        return false;
      }
    }
  }
  return true;
}

// Offers an edge to x: directly when x is this thread's, else queued for x's thread. The result
// does not depend on the order of offers (the best two by (cost, partner) are kept), so the
// parallel sweep in core and the sequential one out of core give identical candidates.
void Decimator::Offer(
  std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner, Scratch& s)
{
  if (x < s.lo || x >= s.hi)
  {
    std::size_t t = 0;
    while (t + 1 < this->partStart_.size() && x >= this->partStart_[t + 1])
    {
      ++t;
    }
    s.out[t].push_back({ x, partner, fromPartner, pl });
    return;
  }
  this->Apply(this->W(s), x, partner, pl, fromPartner);
}

void Decimator::Apply(
  Views& w, std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner)
{
  const float cost = float(pl.cost); // compared as stored
  if (const Cand* cp = w.C.Ptr(x))
  {
    if (!Before(cost, partner, cp->cost, cp->partner) && !Before(cost, partner, cp->cost2, cp->partner2))
    {
      return;
    }
  }
  Cand c = w.C.Get(x);
  if (Before(cost, partner, c.cost, c.partner))
  {
    c.cost2 = c.cost;
    c.partner2 = c.partner;
    c.cost = cost;
    c.p[0] = float(pl.p.x);
    c.p[1] = float(pl.p.y);
    c.p[2] = float(pl.p.z);
    c.partner = partner;
    c.t = float(fromPartner ? 1.0 - pl.t : pl.t);
  }
  else if (partner != c.partner && Before(cost, partner, c.cost2, c.partner2))
  {
    c.cost2 = cost;
    c.partner2 = partner;
  }
  else
  {
    return;
  }
  w.C.Set(x, c);
}

std::unique_ptr<DML> Decimator::ForkHelper(std::uint64_t nv, std::uint64_t mid,
  std::initializer_list<storage::BlockId> blocks, Views& w, const std::vector<DML::Range>& more)
{
  constexpr std::uint64_t kForkMin = 65536; // below, the sweeps are short
  const std::uint64_t budget = this->dml_.GetProfile().memoryBudget;
  if (this->threads_ < 2 || nv < kForkMin || budget == 0 || this->AllInCore())
  {
    return nullptr;
  }
  std::vector<DML::Range> ranges;
  for (storage::BlockId id : blocks)
  {
    ranges.push_back({ id, mid, nv - mid });
  }
  ranges.insert(ranges.end(), more.begin(), more.end());
  std::unique_ptr<DML> fork;
  try
  {
    fork = this->dml_.Fork(budget / 2, ranges);
  }
  catch (const storage::BudgetError&)
  {
    return nullptr; // too little room to share: one thread
  }
  if (fork)
  {
    this->BindViews(w, *fork);
  }
  return fork;
}

void Decimator::JoinHelper(std::unique_ptr<DML>& fork)
{
  if (this->scratch_.size() > 1)
  {
    this->scratch_[1].w = nullptr; // (the helper's views die with the fork)
  }
  if (fork)
  {
    std::unique_ptr<DML> f = std::move(fork);
    this->dml_.Join(*f);
  }
}

// Step 1 of a pass: every active vertex evaluates its edges. In core, the vertex range is split
// among threads_ threads; a thread writes only its own vertices' candidates and queues offers to
// the others', which their owners apply between barriers, one chunk of vertices at a time (the
// queues stay small). Out of core (the DML is single-threaded) one thread sweeps in order. Both
// give the same candidates: see Offer.
void Decimator::Sweep(std::uint64_t nv)
{
  constexpr std::uint64_t kChunk = 16384;
  constexpr std::uint64_t kParallelMin = 8192;
  auto sequential = [this, nv]() {
    Scratch& s = this->scratch_[0];
    s.lo = 0;
    s.hi = kNone;
    s.batch.n = 0;
    for (std::uint64_t u = 0; u < nv; ++u)
    {
      this->Tick(u, nv);
      this->PrefetchSweep(u, nv);
      this->Evaluate(std::uint32_t(u), s);
    }
    this->FlushEdges(s);
  };
  int T = (this->AllInCore() && nv >= kParallelMin) ? this->threads_ : 1;
  // Out of core on two threads: the second sweeps the upper half of the vertices through a
  // forked DML. Each thread writes only its own range's candidates (the others' offers are
  // queued, as in core), the only block the sweep writes.
  Views forkViews;
  std::unique_ptr<DML> fork =
    T == 1 ? this->ForkHelper(nv, nv / 2, { this->cand_.Id() }, forkViews) : nullptr;
  ForkGuard joinOnExit{ *this, fork };
  if (fork)
  {
    T = 2;
  }
  if (T <= 1)
  {
    sequential();
    return;
  }
  if (this->scratch_.size() < std::size_t(T))
  {
    this->scratch_.resize(std::size_t(T));
  }
  this->partStart_.assign(std::size_t(T) + 1, 0);
  for (int t = 0; t <= T; ++t)
  {
    this->partStart_[std::size_t(t)] = std::uint32_t(nv * std::uint64_t(t) / std::uint64_t(T));
  }
  if (fork)
  {
    this->scratch_[1].w = &forkViews; // (partStart_[1] is nv / 2)
  }
  std::uint64_t rounds = 0;
  for (int t = 0; t < T; ++t)
  {
    Scratch& s = this->scratch_[std::size_t(t)];
    s.lo = this->partStart_[std::size_t(t)];
    s.hi = this->partStart_[std::size_t(t) + 1];
    s.batch.n = 0;
    s.out.resize(std::size_t(T));
    for (auto& q : s.out)
    {
      q.clear();
    }
    rounds = std::max(rounds, (std::uint64_t(s.hi - s.lo) + kChunk - 1) / kChunk);
  }
  Barrier barrier(T);
  std::atomic<bool> stop{ false };
  std::vector<std::exception_ptr> errors(static_cast<std::size_t>(T));
  auto work = [&](int t) {
    Scratch& s = this->scratch_[std::size_t(t)];
    for (std::uint64_t r = 0; r < rounds; ++r)
    {
      try
      {
        const std::uint64_t b = std::min<std::uint64_t>(s.hi, s.lo + r * kChunk);
        const std::uint64_t e = std::min<std::uint64_t>(s.hi, b + kChunk);
        for (std::uint64_t u = b; u < e && !stop.load(std::memory_order_relaxed); ++u)
        {
          if (t == 0)
          {
            this->Tick(u - s.lo, s.hi - s.lo); // progress and abort: the calling thread only
          }
          this->PrefetchSweep(u, e);
          this->Evaluate(std::uint32_t(u), s);
        }
        this->FlushEdges(s); // (its offers to other threads go out at this barrier)
      }
      catch (...)
      {
        errors[std::size_t(t)] = std::current_exception();
        stop = true;
      }
      barrier.Wait();
      if (!stop)
      {
        try
        {
          for (int o = 0; o < T; ++o)
          {
            if (o != t)
            {
              for (const Deferred& d : this->scratch_[std::size_t(o)].out[std::size_t(t)])
              {
                this->Apply(this->W(s), d.x, d.partner, d.pl, d.fromPartner); // (may page)
              }
            }
          }
        }
        catch (...)
        {
          errors[std::size_t(t)] = std::current_exception();
          stop = true;
        }
      }
      // Everyone is done with the queues and agrees on stop.
      const bool quit = barrier.WaitAndAgree(stop);
      for (auto& q : s.out)
      {
        q.clear();
      }
      if (quit)
      {
        break;
      }
    }
  };
  // A thread that cannot be started: the others stop after their first chunk, and this thread
  // sweeps alone (evaluating a vertex twice gives the same candidates: offers are idempotent).
  const int started = RunOnThreads(T, work, [&](int n) {
    stop = true;
    for (int k = n; k < T; ++k)
    {
      barrier.Drop();
    }
  });
  this->JoinHelper(fork); // (on an exception, joinOnExit does)
  RethrowFirst(errors);
  if (started < T)
  {
    sequential();
  }
}

// The candidate sweep for vertex u: evaluates u's edges to higher neighbours once and offers
// them to both endpoints (light path: the ring's faces only, no neighbour table). An edge u-a is
// taken from the face where a follows u; an edge seen only with a before u is a boundary edge
// (or inconsistently oriented) and is taken from there.
void Decimator::Evaluate(std::uint32_t u, Scratch& s)
{
  Views& w = this->W(s);
  const State su = w.S.Get(u);
  if (su & kLocked)
  {
    return;
  }
  if (su & kNeedsLegal)
  {
    this->EvaluateFull(u, su, s);
    return;
  }
  if (!Active(su))
  {
    // Its candidate is exact (adjacent survivors offer their new edges), or its second best
    // was promoted: the placement of that edge is computed here.
    if (su & kPromote)
    {
      Cand c = w.C.Get(u);
      if (c.t < 0)
      {
        const std::uint32_t v = c.partner;
        Quadric Q = w.Q.Get(v);
        AddTo(Q, w.Q.Get(u));
        const Placement pl = this->Place(Q, w.P.Get(u), w.P.Get(v), su, w.S.Get(v));
        // c.cost stays: the same edge's cost as computed before (equal up to rounding), which
        // keeps the outcome independent of whether an offer to u came before or after this.
        c.p[0] = float(pl.p.x);
        c.p[1] = float(pl.p.y);
        c.p[2] = float(pl.p.z);
        c.t = float(pl.t);
        w.C.Set(u, c);
      }
    }
    return;
  }
  const std::uint32_t b = w.RO.Get(u), e = w.RO.Get(u + 1);
  const std::uint32_t* ids = w.RF.Ptr(b);
  if (!ids)
  {
    s.ids.resize(e - b);
    w.RF.GetRange(b, e - b, s.ids.data());
    ids = s.ids.data();
  }
  if (e - b > s.next.size())
  {
    s.next.resize(e - b);
    s.prev.resize(e - b);
  }
  std::uint32_t* next = s.next.data();
  std::uint32_t* prev = s.prev.data();
  // A vertex of very high valence takes long: the calling thread polls inside it.
  const bool poll = e - b > 65536 && &s == &this->scratch_[0];
  std::size_t n = 0;
  for (std::uint32_t k = 0; k < e - b; ++k)
  {
    if (poll && (k & 4095) == 4095)
    {
      this->progress_.Poll();
    }
    const Tri t = w.F.Get(ids[k]);
    if (!Alive(t))
    {
      continue;
    }
    // (no branches, as in CornerOf; masks rather than the corner tables: faster here)
    const std::uint32_t m0 = 0u - std::uint32_t(t.v[0] == u), m1 = 0u - std::uint32_t(t.v[1] == u),
                        m2 = 0u - std::uint32_t(t.v[2] == u);
    next[n] = (t.v[1] & m0) | (t.v[2] & m1) | (t.v[0] & m2);
    prev[n] = (t.v[2] & m0) | (t.v[0] & m1) | (t.v[1] & m2);
    ++n;
  }
  if (n == 0)
  {
    return;
  }
  if (const Quadric* qp = w.Q.Ptr(0))
  {
    // The neighbours' data is read (and their candidates written) below: fetch it in parallel.
    const State* sp = w.S.Ptr(0);
    const Vec3* pp = w.P.Ptr(0);
    const Cand* cp = w.C.Ptr(0);
    for (std::size_t i = 0; i < n; ++i)
    {
      const std::uint32_t a = next[i];
      Prefetch(qp + a);
      if (sp && pp && cp)
      {
        Prefetch(sp + a);
        Prefetch(pp + a);
        Prefetch(cp + a);
      }
    }
  }
  const Quadric Qu = w.Q.Get(u);
  const Vec3 pu = w.P.Get(u);
  auto in = [](const std::uint32_t* a, std::size_t m, std::uint32_t x) {
    bool found = false; // no early exit: a fixed trip count instead of a mispredicted branch
    for (std::size_t i = 0; i < m; ++i)
    {
      found |= a[i] == x;
    }
    return found;
  };
  if (n > LinkTally::kMinEntries)
  {
    const LinkTally& tally = s.tally;
    s.tally.Build(next, prev, n);
    for (std::size_t i = 0; i < n; ++i)
    {
      if (poll && (i & 4095) == 4095)
      {
        this->progress_.Poll();
      }
      if (tally.First(true, next[i], i))
      {
        this->EvaluateEdge(u, su, Qu, pu, next[i], next, prev, n, &tally, s);
      }
    }
    for (std::size_t i = 0; i < n; ++i)
    {
      if (poll && (i & 4095) == 4095)
      {
        this->progress_.Poll();
      }
      const std::uint32_t a = prev[i];
      if (tally.Count(true, a) == 0 && tally.First(false, a, i))
      {
        this->EvaluateEdge(u, su, Qu, pu, a, next, prev, n, &tally, s);
      }
    }
    s.tally.Release();
    ReleaseIfLarge(s.ids);
    if (n > 65536)
    {
      s.next.assign(64, 0);
      s.next.shrink_to_fit();
      s.prev.assign(64, 0);
      s.prev.shrink_to_fit();
    }
    return;
  }
  for (std::size_t i = 0; i < n; ++i)
  {
    const std::uint32_t a = next[i];
    if (!in(next, i, a))
    {
      this->EvaluateEdge(u, su, Qu, pu, a, next, prev, n, nullptr, s);
    }
  }
  for (std::size_t i = 0; i < n; ++i)
  {
    const std::uint32_t a = prev[i];
    if (!in(next, n, a) && !in(prev, i, a))
    {
      this->EvaluateEdge(u, su, Qu, pu, a, next, prev, n, nullptr, s);
    }
  }
}

void Decimator::EvaluateEdge(std::uint32_t u, State su, const Quadric& Qu, const Vec3& pu,
  std::uint32_t v, const std::uint32_t* next, const std::uint32_t* prev, std::size_t n,
  const LinkTally* tally, Scratch& s)
{
  Views& w = this->W(s);
  const State sv = w.S.Get(v);
  if (sv & kLocked)
  {
    return;
  }
  const bool activeV = Active(sv);
  if (activeV && v < u)
  {
    return; // done in v's sweep, and offered to u
  }
  // v needs the edge when its candidate is being recomputed, or when the edge changed (u
  // survived a collapse) and v keeps its cached candidate; kNeedsLegal vertices do their own.
  const bool offerV = !(sv & kNeedsLegal) && (activeV || (su & kSurvivor));
  if ((su & kFixed) && (sv & kFixed))
  {
    return;
  }
  const bool bothBoundary = (su & kBoundary) && (sv & kBoundary);
  if (bothBoundary || ((su | sv) & kComplex))
  {
    std::size_t count = 0;
    if (tally)
    {
      count = tally->Count(true, v) + tally->Count(false, v);
    }
    else
    {
      for (std::size_t i = 0; i < n; ++i)
      {
        count += (next[i] == v) + (prev[i] == v);
      }
    }
    if (bothBoundary && count != 1)
    {
      return; // a non-manifold edge, or it would pinch the surface across the interior
    }
  }
  const Quadric Qv = w.Q.Get(v);
  const Vec3 pv = w.P.Get(v);
  if ((su | sv) & kFixed)
  {
    Quadric Q = Qv;
    AddTo(Q, Qu);
    this->OfferEdge(u, v, this->Place(Q, pu, pv, su, sv), Trace(Q), offerV, s);
    return;
  }
  // Queued: placed in pairs (the offers do not depend on their order).
  EdgeBatch& b = s.batch;
  const int l = b.n;
  for (int k = 0; k < 10; ++k)
  {
    b.q[k][l] = Qv.q[k] + Qu.q[k]; // (AddTo's sum)
  }
  b.pu[0][l] = pu.x;
  b.pu[1][l] = pu.y;
  b.pu[2][l] = pu.z;
  b.pv[0][l] = pv.x;
  b.pv[1][l] = pv.y;
  b.pv[2][l] = pv.z;
  b.u[l] = u;
  b.v[l] = v;
  b.offerV[l] = offerV;
  if (++b.n == EdgeBatch::kLanes)
  {
    this->FlushEdges(s);
  }
}

// Places the queued edges of the sweep and offers them.
void Decimator::FlushEdges(Scratch& s)
{
  EdgeBatch& b = s.batch;
  const int n = b.n;
  if (n == 0)
  {
    return;
  }
  b.n = 0;
  // Unused lanes repeat the first edge (their results are ignored).
  for (int l = n; l < EdgeBatch::kLanes; ++l)
  {
    for (int k = 0; k < 10; ++k)
    {
      b.q[k][l] = b.q[k][0];
    }
    for (int k = 0; k < 3; ++k)
    {
      b.pu[k][l] = b.pu[k][0];
      b.pv[k][l] = b.pv[k][0];
    }
  }
  double cost[EdgeBatch::kLanes], px[EdgeBatch::kLanes], py[EdgeBatch::kLanes],
    pz[EdgeBatch::kLanes], t[EdgeBatch::kLanes];
#ifdef SIPMSS_LANES
  static_assert(EdgeBatch::kLanes == 2, "Lanes2 has two lanes");
  Lanes2 q[10], u[3], v[3];
  std::memcpy(q, b.q, sizeof(q));
  std::memcpy(u, b.pu, sizeof(u));
  std::memcpy(v, b.pv, sizeof(v));
  const PlaceOut<Lanes2> o = PlaceLanes<Lanes2>(q, u, v);
  std::memcpy(cost, &o.cost, sizeof(cost));
  std::memcpy(px, &o.px, sizeof(px));
  std::memcpy(py, &o.py, sizeof(py));
  std::memcpy(pz, &o.pz, sizeof(pz));
  std::memcpy(t, &o.t, sizeof(t));
#else
  for (int l = 0; l < n; ++l)
  {
    double q[10], u[3], v[3];
    for (int k = 0; k < 10; ++k)
    {
      q[k] = b.q[k][l];
    }
    for (int k = 0; k < 3; ++k)
    {
      u[k] = b.pu[k][l];
      v[k] = b.pv[k][l];
    }
    const PlaceOut<double> o = PlaceLanes<double>(q, u, v);
    cost[l] = o.cost;
    px[l] = o.px;
    py[l] = o.py;
    pz[l] = o.pz;
    t[l] = o.t;
  }
#endif
  for (int l = 0; l < n; ++l)
  {
    this->OfferEdge(b.u[l], b.v[l], { cost[l], { px[l], py[l], pz[l] }, t[l] },
      b.q[0][l] + b.q[4][l] + b.q[7][l], b.offerV[l], s);
  }
}

// Offers edge u-v with placement pl (summed quadric's trace `trace`) to u, and to v if offerV,
// unless it has no finite cost or exceeds maximumError.
void Decimator::OfferEdge(
  std::uint32_t u, std::uint32_t v, const Placement& pl, double trace, bool offerV, Scratch& s)
{
  if (!std::isfinite(pl.cost) ||
    (std::isfinite(this->opt_.maximumError) && pl.cost > this->opt_.maximumError * trace))
  {
    return;
  }
  this->Offer(u, v, pl, false, s);
  if (offerV)
  {
    this->Offer(v, u, pl, true, s);
  }
}

// The heavy path for a vertex whose cheapest collapse was illegal: all its edges, in cost
// order, the first legal one is its candidate. Edges to higher neighbours are still offered to
// them.
void Decimator::EvaluateFull(std::uint32_t u, State su, Scratch& s)
{
  Views& w = this->W(s);
  w.C.Set(u, this->none_);
  const std::uint32_t lengthU = this->RingLength(w, u);
  if (lengthU > kMaxCollapseRing)
  {
    return; // (no collapse of u is made in this pass: kMaxCollapseRing)
  }
  Ring& ru = s.ru;
  this->LoadRing(w, u, ru, true);
  if (ru.faces.empty())
  {
    return;
  }
  const Quadric Qu = w.Q.Get(u);
  const double maxErr = this->opt_.maximumError;
  const bool checkErr = std::isfinite(maxErr);
  s.edges.clear();
  for (std::uint32_t k = 0; k < ru.nbs.size(); ++k)
  {
    const Nb& nb = ru.nbs[k];
    const State sv = w.S.Get(nb.v);
    if (sv & kLocked)
    {
      continue;
    }
    if ((su & kBoundary) && (sv & kBoundary) && nb.count != 1)
    {
      continue;
    }
    if ((su & kFixed) && (sv & kFixed))
    {
      continue;
    }
    if (lengthU + this->RingLength(w, nb.v) > kMaxCollapseRing)
    {
      continue;
    }
    Quadric Q = w.Q.Get(nb.v);
    AddTo(Q, Qu);
    const Placement pl = this->Place(Q, ru.px, nb.p, su, sv);
    if (!std::isfinite(pl.cost) || (checkErr && pl.cost > maxErr * Trace(Q)))
    {
      continue;
    }
    // (Its neighbours get this edge from their own evaluation: u is neither active nor a
    // survivor.)
    s.edges.push_back({ pl.cost, nb.v, k, pl });
  }
  std::sort(s.edges.begin(), s.edges.end(), [](const EdgeCand& a, const EdgeCand& b) {
    return a.cost < b.cost || (a.cost == b.cost && a.v < b.v);
  });
  for (const EdgeCand& ec : s.edges)
  {
    if (this->Legal(u, ru.nbs[ec.nbIndex], ec.pl.p, s))
    {
      Cand c;
      c.cost = float(ec.cost);
      c.p[0] = float(ec.pl.p.x);
      c.p[1] = float(ec.pl.p.y);
      c.p[2] = float(ec.pl.p.z);
      c.partner = ec.v;
      c.t = float(ec.pl.t);
      c.cost2 = std::numeric_limits<float>::quiet_NaN();
      c.partner2 = kNone;
      w.C.Set(u, c);
      return;
    }
  }
}

void Decimator::InterpolateAttributes(std::uint32_t u, std::uint32_t v, double t, Scratch& s)
{
  Views& w = this->W(s);
  const std::size_t rec = this->recSize_;
  if (rec == 0 || t <= 0.0)
  {
    return;
  }
  s.abuf.resize(rec);
  s.abuf2.resize(rec);
  if (t >= 1.0)
  {
    w.A.GetRange(std::uint64_t(v) * rec, rec, s.abuf.data());
    w.A.SetRange(std::uint64_t(u) * rec, rec, s.abuf.data());
    return;
  }
  w.A.GetRange(std::uint64_t(u) * rec, rec, s.abuf.data());
  w.A.GetRange(std::uint64_t(v) * rec, rec, s.abuf2.data());
  float* a = reinterpret_cast<float*>(s.abuf.data());
  const float* b = reinterpret_cast<const float*>(s.abuf2.data());
  for (std::size_t i = 0; i < this->nFloats_; ++i)
  {
    a[i] = float(double(a[i]) + t * (double(b[i]) - double(a[i])));
  }
  if (this->layout_.normals)
  {
    double l = std::sqrt(double(a[0]) * a[0] + double(a[1]) * a[1] + double(a[2]) * a[2]);
    if (l > 0)
    {
      for (int i = 0; i < 3; ++i)
      {
        a[i] = float(a[i] / l);
      }
    }
  }
  if (this->layout_.colors)
  {
    std::uint8_t* ca = s.abuf.data() + this->nFloats_ * sizeof(float);
    const std::uint8_t* cb = s.abuf2.data() + this->nFloats_ * sizeof(float);
    for (int i = 0; i < 4; ++i)
    {
      double x = double(ca[i]) + t * (double(cb[i]) - double(ca[i]));
      ca[i] = std::uint8_t(std::min(255.0, std::max(0.0, std::floor(x + 0.5))));
    }
  }
  w.A.SetRange(std::uint64_t(u) * rec, rec, s.abuf.data());
}

// Collapses u and c.partner (their faces loaded in s.ru and s.rv) into u at c.p; returns the
// number of faces removed.
std::uint64_t Decimator::Collapse(std::uint32_t u, const Cand& c, Scratch& s)
{
  Views& w = this->W(s);
  const std::uint32_t v = c.partner;
  const Ring& ru = s.ru;
  const Ring& rv = s.rv;
  const State su = w.S.Get(u), sv = w.S.Get(v);
  std::uint64_t removed = 0;
  for (const RingFace& f : ru.faces)
  {
    if (Has(f.t, v))
    {
      w.F.Set(f.id, kDeadTri);
      ++removed;
    }
  }
  for (const RingFace& f : rv.faces)
  {
    if (!Has(f.t, u))
    {
      Tri t = f.t;
      t.v[f.corner] = u;
      w.F.Set(f.id, t);
    }
  }
  // Mark every vertex of the faces around u and v (the other two corners of each): no later
  // collapse of this pass touches them. (u and v are among them; they get their states below.)
  State* Sp = const_cast<State*>(w.S.Ptr(0));
  for (const Ring* r : { &ru, &rv })
  {
    for (const RingFace& f : r->faces)
    {
      const std::uint32_t a = f.t.v[kNextCorner[f.corner]], b = f.t.v[kPrevCorner[f.corner]];
      if (Sp)
      {
        Sp[a] |= kMarked;
        Sp[b] |= kMarked;
      }
      else
      {
        w.S.Set(a, State(w.S.Get(a) | kMarked));
        w.S.Set(b, State(w.S.Get(b) | kMarked));
      }
    }
  }
  w.P.Set(u, { c.p[0], c.p[1], c.p[2] });
  if (!this->lazySums_)
  {
    Quadric Q = w.Q.Get(u);
    AddTo(Q, w.Q.Get(v));
    w.Q.Set(u, Q);
  }
  this->InterpolateAttributes(u, v, double(c.t), s);
  w.S.Set(v, State(kRemoved | kMarked));
  w.S.Set(u, State(su | kMarked | kCollapsed | (sv & (kBoundary | kFixed | kComplex))));
  return removed;
}

inline std::uint32_t CostBin(double cost)
{
  float f = float(cost);
  std::uint32_t bits;
  std::memcpy(&bits, &f, 4);
  return bits >> 16; // non-negative floats order like their bits; 15 bits: ~0.8% wide bins
}

// One candidate of step 3: collapses u with its candidate's partner if both are free and the
// collapse is legal. With a vertex range [lo, hi) (a chunk), the collapse must stay inside it:
// u, the partner and every vertex of their rings in the range, else it is deferred. Collapses
// that stay inside disjoint ranges touch disjoint data (a face they change or a position they
// move has all its vertices in the range), so chunks can run at the same time.
Decimator::Try Decimator::TryCollapse(
  std::uint32_t u, Scratch& s, std::uint32_t lo, std::uint32_t hi, std::uint64_t& removed)
{
  Views& w = this->W(s);
  const State su = w.S.Get(u);
  if (su & kBusy)
  {
    return Try::Skip;
  }
  const Cand c = w.C.Get(u);
  const std::uint32_t v = c.partner;
  if (v < lo || v >= hi)
  {
    return Try::Defer;
  }
  if (w.S.Get(v) & kBusy)
  {
    return Try::Skip;
  }
  const bool chunked = lo != 0 || hi != kNone;
  // In a chunk: every vertex of the faces in it (u is), and with the face split on, only faces
  // on the chunk's side of the split.
  const bool split = chunked && this->splitOn_;
  const bool upper = lo >= this->splitMid_;
  auto outside = [&](const Ring& r) {
    bool out = false;
    for (const RingFace& f : r.faces)
    {
      for (const std::uint32_t x : f.t.v)
      {
        out |= x < lo || x >= hi;
      }
      out |= split && ((f.id >= this->splitFace_) != upper);
    }
    return out;
  };
  if (this->RingLength(w, u) + this->RingLength(w, v) > kMaxCollapseRing)
  {
    // Not made (kMaxCollapseRing). In a chunk, deferred: the verdict is the sequential one.
    if (chunked)
    {
      return Try::Defer;
    }
    w.S.Set(u, State(su | kNeedsLegal));
    return Try::Illegal;
  }
  // The faces only: the edge's faces and their third vertices come from u's.
  this->LoadFaces(w, u, s.ru);
  if (chunked && outside(s.ru))
  {
    return Try::Defer;
  }
  std::uint32_t m = 0, opp[2] = { kNone, kNone };
  for (const RingFace& f : s.ru.faces)
  {
    if (Has(f.t, v))
    {
      if (m < 2)
      {
        opp[m] = f.t.v[0] ^ f.t.v[1] ^ f.t.v[2] ^ u ^ v;
      }
      ++m;
    }
  }
  if (m > 0)
  {
    this->LoadFaces(w, v, s.rv);
    if (chunked && outside(s.rv))
    {
      return Try::Defer;
    }
  }
  const Vec3 p = { c.p[0], c.p[1], c.p[2] };
  bool legal = false; // (m == 0: v is no neighbour)
  if (m > 2 || (m > 0 && s.ru.faces.size() * s.rv.faces.size() > kLegalFacesMax))
  {
    // A non-manifold edge, or rings too large for LegalFaces' pairwise test: the sorted
    // neighbour tables.
    this->BuildNeighbours(w, s.ru, true);
    this->BuildNeighbours(w, s.rv, true);
    legal = this->Legal(u, *s.ru.Find(v), p, s, true);
  }
  else if (m > 0)
  {
    legal = this->LegalFaces(u, v, m, opp, p, s);
  }
  if (!legal)
  {
    w.S.Set(u, State(su | kNeedsLegal));
    return Try::Illegal;
  }
  removed += this->Collapse(u, c, s);
  return Try::Done;
}

// Runs TryCollapse on the candidates at positions [first, last) of the order until `budget`
// faces are removed; deferred ones get kDeferred (no list: the footprint stays in the DML).
// Returns where it stopped.
std::uint64_t Decimator::Step(std::uint64_t first, std::uint64_t last, std::uint32_t lo,
  std::uint32_t hi, std::uint64_t budget, Scratch& s, StepRun& run, std::int64_t tickAt,
  std::uint64_t tickScale)
{
  Views& w = this->W(s);
  // In core: prefetch the data of the candidates ahead, in stages, each reading what the one
  // before fetched: their state, candidate and ring offsets; for those still free, the
  // partner's, the ring's face ids and both positions; the ring's faces and the partner's face
  // ids; the positions of the ring's vertices and the partner's faces; the positions of the
  // partner's ring vertices and the states of both rings' vertices (the legality check reads
  // the positions, the collapse marks the states).
  const std::uint32_t* Op = w.O.Ptr(0);
  const State* Sp = w.S.Ptr(0);
  const Cand* Cp = w.C.Ptr(0);
  const std::uint32_t* ROp = w.RO.Ptr(0);
  const std::uint32_t* RFp = w.RF.Ptr(0);
  const Vec3* Pp = w.P.Ptr(0);
  const Tri* Fp = w.F.Ptr(0);
  const Quadric* Qp = this->lazySums_ ? nullptr : w.Q.Ptr(0);
  const bool prefetch = Op && Sp && Cp && ROp && RFp && Pp && Fp;
  constexpr std::uint64_t kAhead = 16;
  // (The loops over a ring's corners below are written out: through a shared generic lambda,
  // GCC 12 emitted half of these prefetches and the step ran 3-5% slower.)
  auto prefetchList = [&](std::uint32_t y) { // its face ids: the first and the last line
    const std::uint32_t b = ROp[y], e = ROp[y + 1];
    Prefetch(RFp + b);
    if (e > b)
    {
      Prefetch(RFp + e - 1);
    }
  };
  auto freePair = [&](std::uint32_t w, std::uint32_t& x) {
    x = Cp[w].partner;
    return !(Sp[w] & kBusy) && x >= lo && x < hi && !(Sp[x] & kBusy);
  };
  std::uint64_t i = first;
  for (; i < last && run.removed < budget; ++i)
  {
    if (tickAt >= 0 && ((i - first) & 1023) == 0)
    {
      this->progress_.Tick(
        double(std::uint64_t(tickAt) + tickScale * (i - first)) / double(this->stepTotal_));
    }
    if (prefetch)
    {
      std::uint32_t x;
      if (i + 2 * kAhead < last)
      {
        const std::uint32_t w = Op[i + 2 * kAhead];
        Prefetch(Sp + w);
        Prefetch(Cp + w);
        Prefetch(ROp + w);
      }
      if (i + kAhead < last)
      {
        const std::uint32_t w = Op[i + kAhead];
        x = Cp[w].partner;
        if (!(Sp[w] & kBusy) && x >= lo && x < hi)
        {
          Prefetch(Sp + x);
          Prefetch(ROp + x);
          prefetchList(w);
          Prefetch(Pp + w);
          Prefetch(Pp + x);
        }
      }
      if (i + kAhead / 2 < last)
      {
        const std::uint32_t w = Op[i + kAhead / 2];
        if (freePair(w, x))
        {
          for (std::uint32_t k = ROp[w], e = ROp[w + 1]; k < e; ++k)
          {
            Prefetch(Fp + RFp[k]);
          }
          prefetchList(x);
        }
      }
      if (i + kAhead / 4 < last)
      {
        const std::uint32_t w = Op[i + kAhead / 4];
        if (freePair(w, x))
        {
          for (std::uint32_t k = ROp[w], e = ROp[w + 1]; k < e; ++k)
          {
            for (const std::uint32_t y : Fp[RFp[k]].v)
            {
              PrefetchAt(Pp, y);
            }
          }
          for (std::uint32_t k = ROp[x], e = ROp[x + 1]; k < e; ++k)
          {
            Prefetch(Fp + RFp[k]);
          }
          if (Qp)
          {
            // The collapse adds the partner's quadric to w's (80 bytes: two cache lines each).
            for (const std::uint32_t y : { w, x })
            {
              Prefetch(Qp + y);
            }
          }
        }
      }
      if (i + kAhead / 8 < last)
      {
        const std::uint32_t w = Op[i + kAhead / 8];
        if (freePair(w, x))
        {
          for (std::uint32_t k = ROp[x], e = ROp[x + 1]; k < e; ++k)
          {
            for (const std::uint32_t y : Fp[RFp[k]].v)
            {
              PrefetchAt(Pp, y);
              PrefetchAt(Sp, y);
            }
          }
          for (std::uint32_t k = ROp[w], e = ROp[w + 1]; k < e; ++k)
          {
            for (const std::uint32_t y : Fp[RFp[k]].v)
            {
              PrefetchAt(Sp, y);
            }
          }
        }
      }
    }
    const std::uint32_t u = w.O.Get(i);
    switch (this->TryCollapse(u, s, lo, hi, run.removed))
    {
      case Try::Done:
        ++run.done;
        break;
      case Try::Illegal:
        ++run.illegal;
        break;
      case Try::Defer:
        w.S.Set(u, State(w.S.Get(u) | kDeferred));
        break;
      case Try::Skip:
        break;
    }
  }
  return i;
}

// One scan of the faces: the split point with the fewest faces on the wrong side (faces whose
// vertices all lie below the middle chunk boundary but sit at or after it, or all at or above
// it and before), in one pass: that count is (below faces) + min over f of (above faces before
// f - below faces before f).
void Decimator::FaceSplit(std::uint64_t nv)
{
  this->splitOn_ = false;
  const std::uint64_t size = this->StepChunkSize(nv);
  const std::uint64_t n = (nv + size - 1) / size;
  if (n < 2)
  {
    return;
  }
  const std::uint64_t mid = n / 2 * size;
  std::int64_t diff = 0, best = 0;
  std::uint64_t below = 0, bestAt = 0;
  for (std::uint64_t f = 0; f < this->nf_; ++f)
  {
    const Tri t = this->v_.F.Get(f);
    if (!Alive(t))
    {
      continue;
    }
    if (t.v[0] < mid && t.v[1] < mid && t.v[2] < mid)
    {
      ++below;
      --diff;
    }
    else if (t.v[0] >= mid && t.v[1] >= mid && t.v[2] >= mid)
    {
      ++diff;
    }
    else
    {
      continue;
    }
    if (diff < best)
    {
      best = diff;
      bestAt = f + 1;
    }
  }
  const std::uint64_t wrong = std::uint64_t(std::int64_t(below) + best);
  this->splitMid_ = mid;
  this->splitFace_ = bestAt;
  this->splitOn_ = wrong <= this->liveFaces_ / kSplitWrongShare;
}

// Step 3 for the candidates at positions [groupBegin, groupEnd) of the order, which are in
// vertex order. The vertices are cut into fixed chunks (their size depends on nv only). In
// rounds: every chunk runs its candidates up to a quota (a share of the faces still to remove
// this pass, by its candidates left), keeping only collapses inside the chunk (the chunks in
// parallel when in core, else one after the other: the same result); then the deferred ones run
// in order, one at a time, up to the pass's goal. Near the goal, the rest runs one at a time.
// Neither the thread count nor the storage mode changes the result.
void Decimator::StepChunks(std::uint64_t groupBegin, std::uint64_t groupEnd, std::uint64_t nv,
  std::uint64_t goal, StepRun& total)
{
  const std::uint64_t size = this->StepChunkSize(nv);
  const std::size_t n = std::size_t((nv + size - 1) / size);
  // The chunk boundaries in the group (it is in vertex order).
  std::vector<std::uint64_t> cursor(n + 1);
  for (std::size_t c = 0; c <= n; ++c)
  {
    const std::uint64_t vb = std::min<std::uint64_t>(nv, c * size);
    std::uint64_t l = groupBegin, h = groupEnd;
    while (l < h)
    {
      const std::uint64_t m = l + (h - l) / 2;
      if (this->v_.O.Get(m) < vb)
      {
        l = m + 1;
      }
      else
      {
        h = m;
      }
    }
    cursor[c] = l;
  }
  std::vector<std::uint64_t> end(cursor.begin() + 1, cursor.end());
  cursor.pop_back();
  const int T = (this->AllInCore() && (!this->recSize_ || this->v_.A.Ptr(0))) ? this->threads_ : 1;
  // Out of core: the two halves of the chunks on two threads (the second through a forked
  // DML) while the faces split with the vertices at the middle chunk boundary (FaceSplit).
  const std::size_t half = n / 2;
  const bool forkable =
    T == 1 && this->splitOn_ && half > 0 && std::uint64_t(half) * size == this->splitMid_;
  if (this->scratch_.size() < std::size_t(std::max(T, 2)))
  {
    this->scratch_.resize(std::size_t(std::max(T, 2)));
  }
  std::vector<std::uint64_t> roundStart(n);
  std::vector<StepRun> runs(n);
  // Progress: the step's position is that of the candidates consumed (those of the earlier
  // groups, whose rest is dropped when a group ends, then this group's).
  const std::uint64_t at = groupBegin;
  std::uint64_t done = 0;
  std::vector<std::uint64_t> quota(n);
  while (this->liveFaces_ > goal)
  {
    std::uint64_t left = 0;
    for (std::size_t c = 0; c < n; ++c)
    {
      left += end[c] - cursor[c];
    }
    const std::uint64_t R = this->liveFaces_ - goal;
    if (left == 0)
    {
      return;
    }
    if (R < kStepTail)
    {
      // The rest one at a time, in order.
      StepRun run;
      for (std::size_t c = 0; c < n && run.removed < R; ++c)
      {
        const std::uint64_t from = cursor[c];
        cursor[c] = this->Step(
          cursor[c], end[c], 0, kNone, R, this->scratch_[0], run, std::int64_t(at + done));
        done += cursor[c] - from;
      }
      this->liveFaces_ -= run.removed;
      total.done += run.done;
      total.illegal += run.illegal;
      return;
    }
    // A: the chunks, each up to its quota (9/10 of R shared by candidates left).
    for (std::size_t c = 0; c < n; ++c)
    {
      quota[c] = (end[c] - cursor[c]) * (R - R / 10) / left;
      runs[c] = StepRun();
      roundStart[c] = cursor[c];
    }
    // Progress (the calling thread): the candidates of its own chunks as it goes, everyone's
    // at the end of the round.
    std::uint64_t mine = 0;
    std::atomic<std::size_t> next{ 0 };
    std::atomic<bool> stop{ false };
    std::vector<std::exception_ptr> errors(static_cast<std::size_t>(T));
    auto work = [&](int t) {
      Scratch& s = this->scratch_[std::size_t(t)];
      try
      {
        for (std::size_t c; !stop.load(std::memory_order_relaxed) && (c = next++) < n;)
        {
          const std::uint32_t lo = std::uint32_t(c * size);
          const std::uint32_t hi = std::uint32_t(std::min<std::uint64_t>(nv, (c + 1) * size));
          // progress and abort: the calling thread only
          cursor[c] = this->Step(cursor[c], end[c], lo, hi, quota[c], s, runs[c],
            t == 0 ? std::int64_t(at + done + mine) : -1);
          if (t == 0)
          {
            mine += cursor[c] - roundStart[c];
          }
        }
      }
      catch (...)
      {
        errors[std::size_t(t)] = std::current_exception();
        stop = true;
      }
    };
    Views forkViews;
    std::unique_ptr<DML> fork;
    ForkGuard joinOnExit{ *this, fork };
    if (forkable)
    {
      const std::uint64_t mid = this->splitMid_;
      std::vector<DML::Range> more;
      more.push_back({ this->faces_.Id(), this->splitFace_,
        this->faces_.Size() - std::min(this->splitFace_, this->faces_.Size()) });
      if (this->recSize_)
      {
        more.push_back({ this->attr_.Id(), mid * this->recSize_,
          this->attr_.Size() - mid * this->recSize_ });
      }
      fork =
        this->ForkHelper(nv, mid, { this->state_.Id(), this->pos_.Id() }, forkViews, more);
    }
    if (fork)
    {
      // Each thread runs its half of the chunks in order (the same collapses as one after the
      // other: a chunk's collapses touch only its own vertices and faces).
      this->scratch_[1].w = &forkViews;
      ForRanges(
        2, 2,
        [&](int t, std::uint64_t gb, std::uint64_t ge, const std::atomic<bool>& halt) {
          for (std::uint64_t g = gb; g < ge; ++g)
          {
            Scratch& s = this->scratch_[std::size_t(t)];
            for (std::size_t c = g ? half : 0; c < (g ? n : half); ++c)
            {
              if (halt.load(std::memory_order_relaxed))
              {
                return;
              }
              const std::uint32_t lo = std::uint32_t(c * size);
              const std::uint32_t hi = std::uint32_t(std::min<std::uint64_t>(nv, (c + 1) * size));
              cursor[c] = this->Step(cursor[c], end[c], lo, hi, quota[c], s, runs[c],
                t == 0 ? std::int64_t(at + done + mine) : -1);
              if (t == 0)
              {
                mine += cursor[c] - roundStart[c];
              }
            }
          }
        },
        [&]() { this->JoinHelper(fork); });
      this->JoinHelper(fork);
    }
    // Chunks are taken from a shared counter: if a thread cannot start, the others take its share.
    else if (T > 1)
    {
      RunOnThreads(T, work, nullptr);
    }
    else
    {
      work(0);
    }
    RethrowFirst(errors);
    // B: the deferred ones, in order, one at a time. Each chunk's are moved to the front of
    // the part of the order it ran this round (done with), their flags cleared (all of them,
    // also past the goal), and go through Step (which prefetches ahead).
    StepRun b;
    for (std::size_t c = 0; c < n; ++c)
    {
      done += cursor[c] - roundStart[c];
    }
    for (std::size_t c = 0; c < n; ++c)
    {
      this->liveFaces_ -= runs[c].removed;
      total.done += runs[c].done;
      total.illegal += runs[c].illegal;
    }
    for (std::size_t c = 0; c < n; ++c)
    {
      std::uint64_t k = roundStart[c];
      for (std::uint64_t i = roundStart[c]; i < cursor[c]; ++i)
      {
        const std::uint32_t u = this->v_.O.Get(i);
        const State su = this->v_.S.Get(u);
        if (su & kDeferred)
        {
          this->v_.S.Set(u, State(su & ~kDeferred));
          this->v_.O.Set(k++, u);
        }
      }
      if (this->liveFaces_ > goal + b.removed)
      {
        this->Step(roundStart[c], k, 0, kNone, this->liveFaces_ - goal, this->scratch_[0], b,
          std::int64_t(at + done), 0); // (polls only: these candidates were counted)
      }
    }
    this->liveFaces_ -= std::min(b.removed, this->liveFaces_);
    total.done += b.done;
    total.illegal += b.illegal;
  }
}

bool Decimator::Pass(std::uint64_t goal, bool exact, double workAfter)
{
  const std::uint64_t nv = this->nv_;
  this->BindViews();
  // Progress: the pass's steps by their work (kWork), then the rest of the run.
  const double wantGuess = double(2 * (this->liveFaces_ - std::min(goal, this->liveFaces_)) + 16);
  const double wStep = kWork::kStep * wantGuess;
  const double wCompact = kWork::kCompact * double(this->nf_ + nv);
  const double wOrder = kWork::kOrder * double(nv);
  // 1. Every vertex's cheapest collapse.
  this->progress_.BeginPhase(
    "collapse", kWork::kSweep * double(nv), wOrder + wStep + wCompact + workAfter);
  this->Sweep(nv);
  // 2. Counting sort of the cheapest candidates on their cost's float bits: enough bins for
  // about four times the collapses the goal needs (a collapse removes 2 faces, and both
  // endpoints may propose it). Ties in order of vertex index.
  this->progress_.BeginPhase("collapse", wOrder, wStep + wCompact + workAfter);
  std::fill(this->hist_.begin(), this->hist_.end(), 0u);
  std::uint64_t candidates = 0;
  for (std::uint64_t u = 0; u < nv; ++u)
  {
    this->Tick(u, 2 * nv);
    const Cand c = this->v_.C.Get(u);
    if (c.partner != kNone)
    {
      ++this->hist_[CostBin(c.cost)];
      ++candidates;
    }
  }
  if (candidates == 0)
  {
    return false;
  }
  const std::uint64_t want = 2 * (this->liveFaces_ - goal) + 16;
  std::uint64_t taken = 0;
  std::uint32_t lastBin = 0;
  for (std::uint32_t b = 0; b < std::uint32_t(kCostBins); ++b)
  {
    taken += this->hist_[b];
    lastBin = b;
    if (taken >= want)
    {
      break;
    }
  }
  // Processing order. A pass that may end on a level (or the final target) goes in exact cost
  // order (bins 0.8% wide, ties by vertex index), so that the last collapses are the cheapest.
  // Other passes take the ordered candidates in kGroups cost quantiles, each in vertex order: a
  // forward sweep over the blocks (cache and page friendly, which matters out of core) with the
  // same quality in tests against a strict order.
  const int groups = exact ? 0 : kGroups;
  const std::size_t keys = groups ? std::size_t(groups) : std::size_t(lastBin) + 1;
  std::vector<std::uint64_t>& start = this->starts_; // start of each key (group or bin)
  start.assign(keys, 0);
  std::uint64_t cum = 0;
  for (std::uint32_t b = 0; b <= lastBin; ++b)
  {
    const std::uint64_t n = this->hist_[b];
    const std::uint32_t key = std::uint32_t(
      groups ? std::min<std::uint64_t>(groups - 1, cum * std::uint64_t(groups) / taken) : b);
    this->hist_[b] = key; // bin -> key
    start[key] += n;
    cum += n;
  }
  std::uint64_t sum = 0;
  for (std::uint64_t& x : start)
  {
    const std::uint64_t n = x;
    x = sum;
    sum += n;
  }
  this->BindViews();
  for (std::uint64_t u = 0; u < nv; ++u)
  {
    this->Tick(nv + u, 2 * nv);
    const Cand c = this->v_.C.Get(u);
    if (c.partner == kNone)
    {
      continue;
    }
    const std::uint32_t b = CostBin(c.cost);
    if (b <= lastBin)
    {
      this->v_.O.Set(start[this->hist_[b]]++, std::uint32_t(u));
    }
  }
  // 3. Collapse in cost order, endpoints of earlier collapses excluded. Legality is checked
  // here, on the current faces and positions (the costs of pairs with no busy endpoint are as in
  // step 1). A vertex whose cheapest collapse is illegal evaluates all its edges with legality
  // in the next passes. A pass that may end on a level goes strictly in order, one collapse at
  // a time; the others go group by group through StepChunks (in parallel when in core).
  this->stepTotal_ = std::max<std::uint64_t>(taken, 1);
  this->progress_.BeginPhase("collapse", kWork::kStep * double(taken), wCompact + workAfter);
  this->lazySums_ = !this->AllInCore(); // (the mode does not change before Compact)
  StepRun run;
  if (groups && nv >= 2 * this->StepChunkSize(nv))
  {
    this->FaceSplit(nv);
    for (std::size_t g = 0; g < keys && this->liveFaces_ > goal; ++g)
    {
      this->StepChunks(g ? start[g - 1] : 0, start[g], nv, goal, run);
    }
    this->splitOn_ = false;
  }
  else
  {
    this->Step(0, taken, 0, kNone, this->liveFaces_ - goal, this->scratch_[0], run, 0);
    this->liveFaces_ -= run.removed;
  }
  const std::uint64_t done = run.done, illegal = run.illegal;
  // 4. Compact into fresh blocks.
  this->progress_.BeginPhase("collapse", wCompact, workAfter);
  this->Compact();
  // Flagged vertices always get a legal candidate (or none) in the next pass: progress is made
  // as long as some candidate exists.
  return done > 0 || illegal > 0;
}

// Renumbers the live vertices and faces after a pass, in place: compaction keeps the order, so
// every element moves to an index <= its own and ascending loops never overwrite what they still
// have to read. The blocks then shrink (Resize: no copy) and the DML re-evaluates its mode with
// the smaller cost. The rings are rebuilt (degrees, offsets, reverse fill). In place rather than
// into fresh blocks: half the peak memory, and no first-touch page faults on every pass.
void Decimator::Compact()
{
  const std::uint64_t nv = this->nv_, nf = this->nf_;
  const std::uint64_t nf2 = this->liveFaces_;
  const std::uint64_t total = 4 * nf + 2 * nv;
  this->remap_.Resize(std::max<std::uint64_t>(nv, 1));
  this->BindViews();
  View<std::uint32_t> R(this->dml_, this->remap_);
  // In core on several threads: the degrees (CountDegrees), the rings by vertex range (each
  // thread scans all faces and writes only its own vertices), the moves (in place, downwards)
  // one array group per thread. Same result either way.
  const int T = (nv >= kParallelCompactMin && this->AllInCore() && R.Ptr(0) &&
                  (!this->recSize_ || this->v_.A.Ptr(0)))
    ? this->threads_
    : 1;
  // 1. Degrees of the live faces, counted in the old ring offsets (the rings are done with);
  // the candidate order is free until the next pass: CountDegrees' second counter array.
  FillBlock(this->dml_, this->ringOff_, std::uint32_t(0));
  this->CountDegrees(nf, T, 0, total, const_cast<std::uint32_t*>(this->v_.O.Ptr(0)));
  // 2. New vertex numbers; RO[k] = end of k's ring (k <= v: RO[k] was read already). R holds the
  // new number, with the top bit for the survivors of this pass (their old state is overwritten
  // below before their neighbours look at it).
  constexpr std::uint32_t kTop = 0x80000000u;
  std::uint64_t k = 0;
  std::uint32_t end = 0;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    this->Tick(nf + v, total);
    const std::uint32_t deg = this->v_.RO.Get(v);
    if (deg == 0)
    {
      R.Set(v, kNone);
      continue;
    }
    end += deg;
    this->v_.RO.Set(k, end);
    const bool survivor = (this->v_.S.Get(v) & kCollapsed) != 0;
    R.Set(v, std::uint32_t(k) | (survivor ? kTop : 0u));
    if (survivor && this->lazySums_)
    {
      // Its collapse's partner (its candidate's) is still in place: nothing moved yet.
      Quadric Q = this->v_.Q.Get(v);
      AddTo(Q, this->v_.Q.Get(this->v_.C.Get(v).partner));
      this->v_.Q.Set(v, Q);
    }
    ++k;
  }
  this->lazySums_ = false;
  const std::uint64_t nv2 = k;
  this->v_.RO.Set(nv2, end);
  // 3. Vertex data, and the candidates carried to the next pass.
  auto carry = [this, kTop](Views& wv, const View<std::uint32_t>& R, std::uint64_t v, State& flags,
                 Cand& c) {
    const State sv = wv.S.Get(v);
    flags = State(sv & (kBoundary | kLocked | kFixed | kNeedsLegal | kComplex));
    c = this->none_;
    if (sv & kCollapsed)
    {
      flags = State((flags & ~kNeedsLegal) | kSurvivor); // every edge changed
    }
    else if ((sv & kMarked) && (sv & kNeedsLegal))
    {
      flags = State((flags & ~kNeedsLegal) | kRecompute); // touched: a fresh start
    }
    else
    {
      // The edges of an untouched vertex are unchanged; a touched one lost or changed only its
      // edges to the collapsed pairs (the survivors offer the new ones): its best and second
      // best stay exact unless they pointed at one of them. A lost best is replaced by the
      // second best when that one is known and still valid.
      c = wv.C.Get(v);
      auto valid = [&R, kTop](std::uint32_t partner, std::uint32_t& mapped) {
        mapped = partner == kNone ? kNone : R.Get(partner);
        return partner == kNone || (mapped != kNone && !(mapped & kTop));
      };
      std::uint32_t x = kNone, x2 = kNone;
      const bool bestOk = c.partner != kNone && valid(c.partner, x);
      const bool secondOk = c.cost2 == c.cost2 && valid(c.partner2, x2); // not NaN
      if (bestOk)
      {
        c.partner = x;
        if (secondOk)
        {
          c.partner2 = x2;
        }
        else
        {
          c.cost2 = std::numeric_limits<float>::quiet_NaN();
          c.partner2 = kNone;
        }
      }
      else if (c.partner != kNone && secondOk && !(flags & kNeedsLegal))
      {
        // Promote (no second best is known after it); kNone: no other edge at all.
        c.cost = c.cost2;
        c.partner = x2;
        c.t = -1.0f;
        c.cost2 = std::numeric_limits<float>::quiet_NaN();
        c.partner2 = kNone;
        if (x2 == kNone)
        {
          c = this->none_;
        }
        else
        {
          flags |= kPromote;
        }
      }
      else
      {
        c = this->none_;
        if (!(flags & kNeedsLegal))
        {
          flags |= kRecompute;
        }
      }
    }
  };
  const std::size_t rec = this->recSize_;
  std::uint64_t f2 = 0;
  // 4. Faces, ascending: new index f2 <= f (in core on several threads: on the quadrics'
  // thread, below; out of core on the calling thread, after the quadrics).
  auto moveFaces = [&]() {
    for (std::uint64_t f = 0; f < nf; ++f)
    {
      this->Tick(nf + 2 * nv + f, total);
      Tri t = this->v_.F.Get(f);
      if (!Alive(t))
      {
        continue;
      }
      for (int c = 0; c < 3; ++c)
      {
        t.v[c] = R.Get(t.v[c]) & ~kTop;
      }
      this->v_.F.Set(f2++, t);
    }
  };
  bool facesMoved = T > 1;
  if (T > 1)
  {
    // In place and downwards (carry reads only the vertex's own records and R): the arrays are
    // independent, so one thread moves the quadrics and another carries the states and
    // candidates and moves them, the positions and the point data (memory-bound: one thread per
    // stream).
    const std::uint32_t* Rp = R.Ptr(0);
    Quadric* Qp = const_cast<Quadric*>(this->v_.Q.Ptr(0));
    Vec3* Pp = const_cast<Vec3*>(this->v_.P.Ptr(0));
    State* Sp = const_cast<State*>(this->v_.S.Ptr(0));
    Cand* Cp = const_cast<Cand*>(this->v_.C.Ptr(0));
    std::uint8_t* Ap = rec ? const_cast<std::uint8_t*>(this->v_.A.Ptr(0)) : nullptr;
    // Group 0 runs on the calling thread, which ticks the progress (and so checks for an abort;
    // the other group then finishes its loop before the exception is passed on).
    ForRanges(std::min(T, 2), 2, [&](int, std::uint64_t gb, std::uint64_t ge, const std::atomic<bool>&) {
      for (std::uint64_t g = gb; g < ge; ++g)
      {
        for (std::uint64_t v = 0; v < nv; ++v)
        {
          const std::uint32_t rv = Rp[v];
          const std::uint64_t w = rv & ~kTop;
          if (g == 0 && (v & 4095) == 0)
          {
            this->progress_.Tick(double(nf + nv + v) / double(total));
          }
          if (rv == kNone)
          {
            continue;
          }
          if (g == 0)
          {
            if (w != v)
            {
              Qp[w] = Qp[v];
            }
            continue;
          }
          State flags;
          Cand c;
          carry(this->v_, R, v, flags, c); // (reads v's records: not in place)
          Sp[w] = flags;
          Cp[w] = c;
          if (w == v)
          {
            continue;
          }
          Pp[w] = Pp[v];
          if (Ap)
          {
            std::memcpy(Ap + w * rec, Ap + v * rec, rec);
          }
        }
        if (g == 0)
        {
          moveFaces(); // step 4 too (it reads only R and the faces)
        }
      }
    });
  }
  else
  {
    // Out of core, on two threads when the budget can be shared: this thread moves the
    // quadrics and then the faces, a helper carries and moves the states, candidates, positions
    // and point data through a forked DML (the same two groups as in core).
    Views forkViews;
    std::vector<DML::Range> attrRange;
    if (rec)
    {
      attrRange.push_back({ this->attr_.Id(), 0, nv * rec });
    }
    std::unique_ptr<DML> fork = this->ForkHelper(
      nv, 0, { this->state_.Id(), this->cand_.Id(), this->pos_.Id() }, forkViews, attrRange);
    ForkGuard joinOnExit{ *this, fork };
    auto moveRest = [&](Views& wv, const View<std::uint32_t>& RR, std::vector<std::uint8_t>& buf,
                      bool moveQ, bool tick) {
      buf.resize(rec);
      for (std::uint64_t v = 0; v < nv; ++v)
      {
        if (tick)
        {
          this->Tick(nf + nv + v, total);
        }
        const std::uint32_t rv = RR.Get(v);
        if (rv == kNone)
        {
          continue;
        }
        const std::uint64_t w = rv & ~kTop;
        State flags;
        Cand c;
        carry(wv, RR, v, flags, c);
        wv.S.Set(w, flags);
        wv.C.Set(w, c);
        if (w != v)
        {
          wv.P.Set(w, wv.P.Get(v));
          if (moveQ)
          {
            wv.Q.Set(w, wv.Q.Get(v));
          }
          if (rec)
          {
            wv.A.GetRange(v * rec, rec, buf.data());
            wv.A.SetRange(w * rec, rec, buf.data());
          }
        }
      }
    };
    if (!fork)
    {
      moveRest(this->v_, R, this->abuf_, true, true);
    }
    else
    {
      const View<std::uint32_t> forkR(*fork, this->remap_);
      ForRanges(
        2, 2,
        [&](int t, std::uint64_t gb, std::uint64_t ge, const std::atomic<bool>&) {
          for (std::uint64_t g = gb; g < ge; ++g)
          {
            if (g == 0)
            {
              // The quadrics, then the faces (which read only R and the faces).
              for (std::uint64_t v = 0; v < nv; ++v)
              {
                this->Tick(nf + nv + v, total);
                const std::uint32_t rv = R.Get(v);
                const std::uint64_t w = rv & ~kTop;
                if (rv != kNone && w != v)
                {
                  this->v_.Q.Set(w, this->v_.Q.Get(v));
                }
              }
              moveFaces();
            }
            else if (fork && t == 1)
            {
              std::vector<std::uint8_t> buf;
              moveRest(forkViews, forkR, buf, false, false);
            }
            else
            {
              moveRest(this->v_, R, this->abuf_, false, false); // (the helper did not start)
            }
          }
        },
        [&]() { this->JoinHelper(fork); });
      this->JoinHelper(fork);
      facesMoved = true;
    }
  }
  if (!facesMoved)
  {
    moveFaces();
  }
  // 5. Shrink, then the rings (faces in reverse: each list ascending, RO[k] ends at its start).
  const std::uint64_t nvb = std::max<std::uint64_t>(nv2, 1);
  this->pos_.Resize(nvb);
  this->quad_.Resize(nvb);
  if (rec)
  {
    this->attr_.Resize(nvb * rec);
  }
  this->state_.Resize(nvb);
  this->cand_.Resize(nvb);
  this->faces_.Resize(std::max<std::uint64_t>(nf2, 1));
  this->ringOff_.Resize(nv2 + 1);
  this->ringFace_.Resize(std::max<std::uint64_t>(3 * nf2, 1));
  this->nv_ = nv2;
  this->nf_ = nf2;
  this->BindViews();
  this->FillRings(nf2, 2 * nf + 2 * nv, total);
  this->remap_.Resize(nvb);
  this->order_.Resize(nvb);
  this->dml_.Reconfigure();
  this->BindViews();
}

// ---------------------------------------------------------------------------------------------
// output

void Decimator::Emit(io::MeshSink& sink)
{
  io::MeshHeader h;
  h.format = io::Format::Unknown;
  h.vertexCount = this->nv_;
  h.faceCount = this->nf_;
  h.layout = this->layout_;
  sink.Begin(h);
  this->BindViews();
  const std::size_t rec = this->recSize_;
  const std::size_t ns = this->layout_.scalars.size();
  // Chunks of at most 16K vertices and about 1 MiB of buffers, whatever the number of vertex
  // properties (the output's size does not depend on the chunking).
  const std::size_t perVertex = sizeof(Vec3) + 12 + (this->layout_.normals ? 12 : 0) +
    (this->layout_.texcoords ? 8 : 0) + 4 * ns + rec + (this->layout_.colors ? 4 : 0);
  const std::size_t chunk = std::clamp<std::size_t>((std::size_t(1) << 20) / perVertex, 1, 1 << 14);
  std::vector<Vec3> p(chunk);
  std::vector<float> xyz(3 * chunk), normals, tex, scalars;
  std::vector<std::uint8_t> raw, rgba;
  if (this->layout_.normals)
  {
    normals.resize(3 * chunk);
  }
  if (this->layout_.texcoords)
  {
    tex.resize(2 * chunk);
  }
  if (ns)
  {
    scalars.resize(ns * chunk);
  }
  if (this->layout_.colors)
  {
    rgba.resize(4 * chunk);
  }
  raw.resize(rec * chunk);
  const std::uint64_t total = this->nv_ + this->nf_;
  for (std::uint64_t first = 0; first < this->nv_; first += chunk)
  {
    this->progress_.Tick(total ? double(first) / double(total) : 1.0);
    const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, this->nv_ - first));
    this->v_.P.GetRange(first, n, p.data());
    for (std::size_t i = 0; i < n; ++i)
    {
      xyz[3 * i] = float(p[i].x + this->origin_.x);
      xyz[3 * i + 1] = float(p[i].y + this->origin_.y);
      xyz[3 * i + 2] = float(p[i].z + this->origin_.z);
    }
    io::VertexChunk vc;
    vc.first = first;
    vc.count = n;
    vc.xyz = xyz.data();
    if (rec)
    {
      this->v_.A.GetRange(first * rec, n * rec, raw.data());
      for (std::size_t i = 0; i < n; ++i)
      {
        const float* f = reinterpret_cast<const float*>(raw.data() + i * rec);
        std::size_t k = 0;
        if (this->layout_.normals)
        {
          for (int j = 0; j < 3; ++j)
          {
            normals[3 * i + j] = f[k++];
          }
        }
        if (this->layout_.texcoords)
        {
          for (int j = 0; j < 2; ++j)
          {
            tex[2 * i + j] = f[k++];
          }
        }
        for (std::size_t j = 0; j < ns; ++j)
        {
          scalars[ns * i + j] = f[k++];
        }
        if (this->layout_.colors)
        {
          std::memcpy(&rgba[4 * i], raw.data() + i * rec + this->nFloats_ * sizeof(float), 4);
        }
      }
      vc.normals = this->layout_.normals ? normals.data() : nullptr;
      vc.texcoords = this->layout_.texcoords ? tex.data() : nullptr;
      vc.scalars = ns ? scalars.data() : nullptr;
      vc.rgba = this->layout_.colors ? rgba.data() : nullptr;
    }
    sink.Vertices(vc);
  }
  std::vector<Tri> tris(chunk);
  for (std::uint64_t first = 0; first < this->nf_; first += chunk)
  {
    this->progress_.Tick(total ? double(this->nv_ + first) / double(total) : 1.0);
    const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, this->nf_ - first));
    this->v_.F.GetRange(first, n, tris.data());
    sink.Triangles(reinterpret_cast<const std::uint32_t*>(tris.data()), n);
  }
  io::ReadStats rs;
  rs.vertices = this->nv_;
  rs.triangles = this->nf_;
  rs.polygons = this->nf_;
  sink.End(rs);
}

// ---------------------------------------------------------------------------------------------

std::vector<std::uint64_t> Decimator::Levels(std::uint64_t F0) const
{
  std::uint64_t target = this->opt_.targetTriangles;
  if (target == 0)
  {
    double r = std::min(1.0, std::max(0.0, this->opt_.targetReduction));
    target = std::uint64_t(std::llround(double(F0) * (1.0 - r)));
  }
  const int K = std::max(1, this->opt_.levelsOfDetail);
  std::vector<std::uint64_t> levels(K);
  for (int i = 0; i < K; ++i)
  {
    if (i == K - 1 || F0 <= target || target == 0)
    {
      levels[i] = target;
    }
    else
    {
      double x = double(F0) * std::pow(double(target) / double(F0), double(i + 1) / double(K));
      levels[i] = std::max<std::uint64_t>(target, std::uint64_t(std::llround(x)));
    }
  }
  return levels;
}

// Run's pass loop, on counts only: each pass removes its planned share (a pass that removes
// fewer makes the next estimates larger: the progress then moves more slowly, never back).
std::uint64_t Decimator::PassGoal(std::uint64_t T, std::uint64_t level) const
{
  const double fraction = std::min(0.9, std::max(0.01, this->opt_.passFraction));
  const double farFraction = std::min(0.9, std::max(fraction, this->opt_.farPassFraction));
  // Far from the level, the cheapest collapses cost orders of magnitude less than the level's
  // error and their exact order matters less: larger passes (fewer sweeps).
  const bool far = double(T) > this->opt_.farRatio * double(std::max<std::uint64_t>(level, 1));
  const std::uint64_t step =
    std::max<std::uint64_t>(1, std::uint64_t(double(T) * (far ? farFraction : fraction)));
  return std::max(level, T > step ? T - step : 0);
}

double Decimator::PassesWork(
  std::uint64_t T, std::size_t level, const std::vector<std::uint64_t>& levels) const
{
  const double vpf = this->VerticesPerFace();
  double work = 0;
  double nf = double(T), nv = vpf * double(T);
  for (int guard = 0; level < levels.size() && guard < 10000; ++guard)
  {
    if (T <= levels[level])
    {
      if (this->emitsLevels_)
      {
        work += kWork::kWrite * double(T) * (1.0 + vpf);
      }
      ++level;
      continue;
    }
    const std::uint64_t goal = this->PassGoal(T, levels[level]);
    work += (kWork::kSweep + kWork::kOrder) * nv + kWork::kStep * double(2 * (T - goal) + 16) +
      kWork::kCompact * (nf + nv);
    T = goal;
    nf = double(T);
    nv = vpf * double(T);
  }
  return work + kWork::kWrite * double(T) * (1.0 + vpf);
}

double Decimator::RestWork(int stage, std::uint64_t V, std::uint64_t F) const
{
  double work = 0;
  if (stage <= 0 && this->opt_.weldDistance >= 0)
  {
    work += kWork::kWeld * double(V + F);
  }
  if (stage <= 1)
  {
    work += kWork::kRings * double(F);
  }
  if (stage <= 2)
  {
    work += kWork::kQuadrics * double(F);
  }
  // The passes from F faces (nv_ and nf_ are those of the input until the first pass).
  return work + this->PassesWork(F, 0, this->Levels(F));
}

void Decimator::Run(const MeshSource& input, io::MeshSink& output,
  const std::function<void(int, const std::function<void(io::MeshSink&)>&)>& onLevel)
{
  this->emitsLevels_ = bool(onLevel);
  this->Read(input);
  if (this->opt_.weldDistance >= 0)
  {
    PhaseTimer timer(this->stats_, this->dml_, "weld");
    this->progress_.BeginPhase("weld", kWork::kWeld * double(this->nv_ + this->nf_),
      this->RestWork(1, this->nv_, this->nf_));
    this->Weld();
  }
  this->BuildRings();
  this->BuildQuadrics();
  if (this->opt_.sourceConsumed)
  {
    this->opt_.sourceConsumed();
    this->dml_.Reconfigure();
  }

  const std::uint64_t F0 = this->liveFaces_;
  const std::vector<std::uint64_t> levels = this->Levels(F0);
  const int K = int(levels.size());
  auto emitLevel = [&](int level) {
    if (onLevel)
    {
      // (the final write follows the last level's: this phase never ends the run)
      this->progress_.BeginPhase("write", kWork::kWrite * double(this->nv_ + this->nf_),
        this->PassesWork(this->liveFaces_, std::size_t(level) + 1, levels));
      onLevel(level, [this](io::MeshSink& sink) { this->Emit(sink); });
    }
  };
  {
    PhaseTimer timer(this->stats_, this->dml_, "collapse");
    int level = 0;
    bool compacted = false;
    while (level < K)
    {
      if (this->liveFaces_ <= levels[level])
      {
        if (!compacted)
        {
          this->Compact();
          compacted = true;
        }
        emitLevel(level);
        ++level;
        continue;
      }
      const std::uint64_t goal = this->PassGoal(this->liveFaces_, levels[level]);
      if (!this->Pass(goal, goal == levels[level], this->PassesWork(goal, std::size_t(level), levels)))
      {
        // No legal collapse under maximumError remains: this is the final level.
        if (!compacted)
        {
          this->Compact();
        }
        emitLevel(level);
        break;
      }
      compacted = true;
    }
  }
  {
    PhaseTimer timer(this->stats_, this->dml_, "write");
    this->progress_.BeginPhase("write", kWork::kWrite * double(this->nv_ + this->nf_), 0.0);
    this->Emit(output);
  }
  this->progress_.Finish();
  this->stats_.outputVertices = this->nv_;
  this->stats_.outputTriangles = this->nf_;
  this->stats_.droppedInputFaces = this->dropped_ + this->readerDropped_;
  this->stats_.storage = this->dml_.GetStats();
}

} // namespace

namespace
{
// The bytes of a decimation's structures on V vertices and F faces (without point data): the
// table Decimator declares (Loader::Begin).
double DecimateBytes(std::uint64_t V, std::uint64_t F)
{
  return double(V) *
    double(sizeof(Vec3) + sizeof(Quadric) + sizeof(State) + sizeof(Cand) + 4 * sizeof(std::uint32_t)) +
    double(F) * double(sizeof(Tri) + 3 * sizeof(std::uint32_t));
}

// The layout step, then the decimation of the reordered copy (in the same DML, freed as soon as
// the decimation has built its own structures).
RunStats DecimateReordered(const MeshSource& input, io::MeshSink& output,
  const DecimateOptions& options, Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  DML dml;
  dml.Config(options.storage);
  RunStats before;
  detail::StoredMesh mesh(dml);
  detail::ReadAndReorder(input, mesh, dml, options.storage,
    [](storage::Profile& p, std::uint64_t v, std::uint64_t f) {
      p.structures.push_back({ "decimate", 1, std::uint64_t(DecimateBytes(v, f)), 0.0 });
    },
    [&options](std::uint64_t v, std::uint64_t f) { return EstimateDecimateWork(v, f, options); },
    progress, before, options.threads);
  DecimateOptions o = options;
  o.dml = &dml;
  o.layout = LayoutPolicy::Keep;
  o.sourceConsumed = [&mesh, &options] {
    mesh.Release();
    if (options.sourceConsumed)
    {
      options.sourceConsumed();
    }
  };
  RunStats stats;
  {
    Decimator d(o, progress, stats);
    d.Run([&mesh](io::MeshSink& sink, const io::ReadOptions& ro) { return mesh.Replay(sink, ro); },
      output, onLevel);
  }
  stats.phases.insert(stats.phases.begin(), before.phases.begin(), before.phases.end());
  stats.reordered = true;
  stats.layoutFarFraction = mesh.Layout().FarFraction();
  stats.storage = dml.GetStats();
  return stats;
}
} // namespace

RunStats Decimate(const MeshSource& input, io::MeshSink& output, const DecimateOptions& options,
  Progress& progress,
  const std::function<void(int level, const std::function<void(io::MeshSink&)>& emit)>& onLevel)
{
  return TranslateOutOfMemory(progress, options.storage, [&] {
    if (!options.dml && options.layout == LayoutPolicy::Reorder)
    {
      return DecimateReordered(input, output, options, progress, onLevel);
    }
    try
    {
      RunStats stats;
      Decimator d(options, progress, stats);
      d.Run(input, output, onLevel);
      return stats;
    }
    catch (const detail::ReorderNeeded&)
    {
      // (the loader found the first faces far apart: the run starts again on a reordered copy)
      return DecimateReordered(input, output, options, progress, onLevel);
    }
  });
}
double EstimateDecimateWork(std::uint64_t V, std::uint64_t F, const DecimateOptions& options)
{
  NullProgress none;
  RunStats stats;
  DecimateOptions o = options;
  o.dml = nullptr;
  Decimator d(o, none, stats);
  return d.Plan(V, F);
}

} // namespace sipmss::algorithms
