// Algorithm I: the collapse step (legality, collapse, the chunked rounds) and a pass.
// (Part of Decimate.cpp's translation unit; the map of the passes: Passes.h.)
namespace sipmss::algorithms
{
namespace
{
// x's live faces only (r.faces; no neighbour table, no positions).
void LoadFaces(Views& w, std::uint32_t x, Ring& r)
{
  r.x = x;
  r.faces.clear();
  r.nbs.clear();
  r.keys.clear();
  const std::uint32_t b = w.RO.Get(x), e = w.RO.Get(x + 1);
  const std::uint32_t* ids = w.RF.Run(b, e - b, r.ids);
  for (std::uint32_t k = 0; k < e - b; ++k)
  {
    w.F.Prefetch(ids[k]);
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

void LoadRing(Views& w, std::uint32_t x, Ring& r, bool positions)
{
  LoadFaces(w, x, r);
  BuildNeighbours(w, r, positions);
}

// The sorted neighbour table of a ring whose faces are loaded (and their positions).
void BuildNeighbours(Views& w, Ring& r, bool positions)
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
    for (const Nb& n : r.nbs)
    {
      w.P.Prefetch(n.v);
    }
    r.px = w.P.Get(r.x);
    for (Nb& n : r.nbs)
    {
      n.p = w.P.Get(n.v);
    }
  }
}

bool FaceOk(const RunContext& ctx, const Ring& r, std::size_t slot, const Vec3& p)
{
  Vec3 c[3];
  r.Corners(slot, c);
  return FaceOk(ctx, c, r.faces[slot].corner, p);
}

// Face with corners c (overwritten) when corner `corner` moves to p.
bool FaceOk(const RunContext& ctx, Vec3 c[3], int corner, const Vec3& p)
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
  const double dot = Dot(n0, n1), k = ctx.cosThreshold;
  const double bound2 = k * k * l0 * l1;
  return k >= 0 ? (dot >= 0 && dot * dot >= bound2) : (dot >= 0 || dot * dot <= bound2);
}

// Is collapsing u (ring in s.ru, with its neighbour table and positions) and nb.v to p legal?
// Loads s.rv the same way unless rvLoaded.
bool Legal(RunContext& ctx, MeshState& mesh, std::uint32_t u, const Nb& nb, const Vec3& p,
  Scratch& s, bool rvLoaded)
{
  const std::uint32_t v = nb.v;
  const std::uint32_t m = nb.count;
  Ring& ru = s.ru;
  Ring& rv = s.rv;
  if (!rvLoaded)
  {
    LoadRing(mesh.W(s), v, rv, true);
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
    if (!Has(ru.faces[s].t, v) && !FaceOk(ctx, ru, s, p))
    {
      return false;
    }
  }
  for (std::size_t s = 0; s < rv.faces.size(); ++s)
  {
    if (!Has(rv.faces[s].t, u) && !FaceOk(ctx, rv, s, p))
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
bool LegalFaces(RunContext& ctx, MeshState& mesh, std::uint32_t u, std::uint32_t v, std::uint32_t m,
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
  Views& w = mesh.W(s);
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
      if (!FaceOk(ctx, c, f.corner, p))
      {
        return false;
      }
    }
  }
  return true;
}

void InterpolateAttributes(MeshState& mesh, std::uint32_t u, std::uint32_t v, double t, Scratch& s)
{
  Views& w = mesh.W(s);
  const std::size_t rec = mesh.recSize;
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
  for (std::size_t i = 0; i < mesh.nFloats; ++i)
  {
    a[i] = float(double(a[i]) + t * (double(b[i]) - double(a[i])));
  }
  if (mesh.layout.normals)
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
  if (mesh.layout.colors)
  {
    std::uint8_t* ca = s.abuf.data() + mesh.nFloats * sizeof(float);
    const std::uint8_t* cb = s.abuf2.data() + mesh.nFloats * sizeof(float);
    for (int i = 0; i < 4; ++i)
    {
      double x = double(ca[i]) + t * (double(cb[i]) - double(ca[i]));
      ca[i] = std::uint8_t(std::min(255.0, std::max(0.0, std::floor(x + 0.5))));
    }
  }
  w.A.SetRange(std::uint64_t(u) * rec, rec, s.abuf.data());
}

// With attributes: u's and v's extensions summed into s.xbuf, and into u's unless the sums are
// lazy (the optimal values need the sum even then: u's and v's are current until Compact).
SIPMSS_COLD void SumExtensions(
  MeshState& mesh, PassState& pass, std::uint32_t u, std::uint32_t v, Scratch& s)
{
  Views& w = mesh.W(s);
  SumExtension(w.X, mesh.xSize, u, v, s.xbuf, s.xbuf2, s.xbuf3);
  if (!pass.lazySums)
  {
    w.X.SetRange(std::uint64_t(u) * mesh.xSize, mesh.xSize, s.xbuf.data());
  }
}

// With attributes: the weighted channels of u's record take their optimal values at u's (new)
// position from the summed extension in s.xbuf (Attributes.h); normals are renormalized.
SIPMSS_COLD void OptimalAttributes(MeshState& mesh, std::uint32_t u, Scratch& s)
{
  Views& w = mesh.W(s);
  const std::size_t rec = mesh.recSize;
  if (!(s.xbuf[0] > 0))
  {
    return; // no face around it: no fit
  }
  s.abuf.resize(rec);
  w.A.GetRange(std::uint64_t(u) * rec, rec, s.abuf.data());
  const Vec3 p = w.P.Get(u);
  bool normals = false;
  for (std::size_t j = 0; j < mesh.channels.size(); ++j)
  {
    const AttributeChannel& c = mesh.channels[j];
    SetChannelValue(c, OptimalAttribute(s.xbuf.data(), j, p.x, p.y, p.z), s.abuf.data());
    normals |= c.normal;
  }
  if (normals)
  {
    float* a = reinterpret_cast<float*>(s.abuf.data());
    const double l = std::sqrt(double(a[0]) * a[0] + double(a[1]) * a[1] + double(a[2]) * a[2]);
    if (l > 0)
    {
      for (int i = 0; i < 3; ++i)
      {
        a[i] = float(a[i] / l);
      }
    }
  }
  w.A.SetRange(std::uint64_t(u) * rec, rec, s.abuf.data());
}

// Collapses u and c.partner (their faces loaded in s.ru and s.rv) into u at c.p; returns the
// number of faces removed.
std::uint64_t Collapse(MeshState& mesh, PassState& pass, std::uint32_t u, const Cand& c, Scratch& s)
{
  Views& w = mesh.W(s);
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
  for (const Ring* r : { &ru, &rv })
  {
    for (const RingFace& f : r->faces)
    {
      const std::uint32_t a = f.t.v[kNextCorner[f.corner]], b = f.t.v[kPrevCorner[f.corner]];
      w.S.Set(a, State(w.S.Get(a) | kMarked));
      w.S.Set(b, State(w.S.Get(b) | kMarked));
    }
  }
  // A fixed endpoint (a lock, a locked boundary, outside a selection) keeps its exact position:
  // the survivor stays where it is, or takes the removed one's (the candidate's float position
  // would round it).
  if (sv & kFixed)
  {
    w.P.Set(u, w.P.Get(v));
  }
  else if (!(su & kFixed))
  {
    w.P.Set(u, { c.p[0], c.p[1], c.p[2] });
  }
  if (mesh.xSize)
  {
    SumExtensions(mesh, pass, u, v, s);
  }
  if (!pass.lazySums)
  {
    Quadric Q = w.Q.Get(u);
    AddTo(Q, w.Q.Get(v));
    w.Q.Set(u, Q);
    // The collapse's error (RunStats::achievedError): its cost per unit of the summed quadric's
    // (geometric) trace. (With lazy sums Compact measures it, where it adds the quadrics.)
    const double trace = Trace(Q);
    if (trace > 0)
    {
      s.achievedErr2 = std::max(s.achievedErr2, KeyError(mesh.xSize, double(c.cost), trace));
    }
  }
  InterpolateAttributes(mesh, u, v, double(c.t), s);
  if (mesh.xSize && !((su | sv) & kFixed))
  {
    OptimalAttributes(mesh, u, s);
  }
  w.S.Set(v, State(kRemoved | kMarked));
  w.S.Set(u, State(su | kMarked | kCollapsed | (sv & (kBoundary | kFixed | kComplex))));
  // The removed vertex's candidate names its survivor (nothing reads a removed vertex's
  // candidate otherwise): Compact follows the final fit's samples with it.
  Cand link = kNoCandidate;
  link.partner = u;
  w.C.Set(v, link);
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
Try TryCollapse(RunContext& ctx, MeshState& mesh, PassState& pass, 
  std::uint32_t u, Scratch& s, std::uint32_t lo, std::uint32_t hi, std::uint64_t& removed)
{
  Views& w = mesh.W(s);
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
  const bool split = chunked && pass.splitOn;
  const bool upper = lo >= pass.splitMid;
  auto outside = [&](const Ring& r) {
    bool out = false;
    for (const RingFace& f : r.faces)
    {
      for (const std::uint32_t x : f.t.v)
      {
        out |= x < lo || x >= hi;
      }
      out |= split && ((f.id >= pass.splitFace) != upper);
    }
    return out;
  };
  if (RingLength(w, u) + RingLength(w, v) > kMaxCollapseRing)
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
  LoadFaces(w, u, s.ru);
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
    LoadFaces(w, v, s.rv);
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
    BuildNeighbours(w, s.ru, true);
    BuildNeighbours(w, s.rv, true);
    legal = Legal(ctx, mesh, u, *s.ru.Find(v), p, s, true);
  }
  else if (m > 0)
  {
    legal = LegalFaces(ctx, mesh, u, v, m, opp, p, s);
  }
  if (!legal)
  {
    w.S.Set(u, State(su | kNeedsLegal));
    return Try::Illegal;
  }
  removed += Collapse(mesh, pass, u, c, s);
  return Try::Done;
}

// Runs TryCollapse on the candidates at positions [first, last) of the order until `budget`
// faces are removed; deferred ones get kDeferred (no list: the footprint stays in the DML).
// Returns where it stopped.
std::uint64_t Step(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t first,
  std::uint64_t last, std::uint32_t lo, std::uint32_t hi, std::uint64_t budget, Scratch& s,
  StepRun& run, std::int64_t tickAt, std::uint64_t tickScale)
{
  Views& w = mesh.W(s);
  // In core: prefetch the data of the candidates ahead, in stages, each reading what the one
  // before fetched: their state, candidate and ring offsets; for those still free, the
  // partner's, the ring's face ids and both positions; the ring's faces and the partner's face
  // ids; the positions of the ring's vertices and the partner's faces; the positions of the
  // partner's ring vertices and the states of both rings' vertices (the legality check reads
  // the positions, the collapse marks the states).
  // (A template over the access kind: the prefetches need the in-core addresses.)
  auto loop = [&](auto O, auto S, auto C, auto RO, auto RF, auto P, auto F, auto Q) {
  constexpr bool prefetch = decltype(O)::kInCore;
  (void)S, (void)C, (void)RO, (void)RF, (void)P, (void)F, (void)Q;
  const std::uint32_t* Op = nullptr;
  const State* Sp = nullptr;
  const Cand* Cp = nullptr;
  const std::uint32_t* ROp = nullptr;
  const std::uint32_t* RFp = nullptr;
  const Vec3* Pp = nullptr;
  const Tri* Fp = nullptr;
  const Quadric* Qp = nullptr;
  if constexpr (prefetch)
  {
    Op = O.Data();
    Sp = S.Data();
    Cp = C.Data();
    ROp = RO.Data();
    RFp = RF.Data();
    Pp = P.Data();
    Fp = F.Data();
    Qp = pass.lazySums ? nullptr : Q.Data();
  }
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
      ctx.progress.Tick(
        double(std::uint64_t(tickAt) + tickScale * (i - first)) / double(pass.stepTotal));
    }
    if constexpr (prefetch)
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
    const std::uint32_t u = O.Get(i);
    switch (TryCollapse(ctx, mesh, pass, u, s, lo, hi, run.removed))
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
  };
  return WithAccess(loop, w.O, w.S, w.C, w.RO, w.RF, w.P, w.F, w.Q);
}

// One scan of the faces: the split point with the fewest faces on the wrong side (faces whose
// vertices all lie below the middle chunk boundary but sit at or after it, or all at or above
// it and before), in one pass: that count is (below faces) + min over f of (above faces before
// f - below faces before f).
void FaceSplit(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t nv)
{
  pass.splitOn = false;
  const std::uint64_t size = StepChunkSize(ctx, nv);
  const std::uint64_t n = (nv + size - 1) / size;
  if (n < 2)
  {
    return;
  }
  const std::uint64_t mid = n / 2 * size;
  std::int64_t diff = 0, best = 0;
  std::uint64_t below = 0, bestAt = 0;
  std::vector<Tri> buf;
  for (std::uint64_t f0 = 0; f0 < mesh.nf; f0 += kFaceRun)
  {
    const std::size_t count = std::size_t(std::min(kFaceRun, mesh.nf - f0));
    const Tri* run = mesh.views.F.Run(f0, count, buf);
    for (std::size_t j = 0; j < count; ++j)
    {
      const Tri& t = run[j];
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
        bestAt = f0 + j + 1;
      }
    }
  }
  const std::uint64_t wrong = std::uint64_t(std::int64_t(below) + best);
  pass.splitMid = mid;
  pass.splitFace = bestAt;
  pass.splitOn = wrong <= mesh.liveFaces / kSplitWrongShare;
}

// Restricts a collapse chunk's views to what its collapses write: the records of the vertices
// [lo, hi) (states, positions, quadrics, point data, candidates) and any face; nothing else.
void ChunkBounds(
  Views& w, std::uint64_t lo, std::uint64_t hi, std::size_t recSize, std::size_t xSize)
{
  const storage::WriteBounds vertices{ lo, hi, 0, 0 };
  w.S.Restrict(vertices);
  w.P.Restrict(vertices);
  w.Q.Restrict(vertices);
  w.A.Restrict({ lo * recSize, hi * recSize, 0, 0 });
  w.X.Restrict({ lo * xSize, hi * xSize, 0, 0 });
  for (View<std::uint32_t>* v : { &w.RO, &w.RF, &w.O })
  {
    v->Restrict(storage::WriteBounds::None());
  }
  w.C.Restrict(vertices); // (a removed vertex's candidate names its survivor: Collapse)
}

// Step 3 for the candidates at positions [groups.front(), groups.back()) of the order, in
// groups: group g at [groups[g], groups[g + 1]), each in vertex order. The vertices are cut
// into fixed chunks (their size depends on nv only) and the chunks into parts of kStepPart
// vertices. In rounds: every chunk runs its candidates part by part, in each part group by
// group, up to a quota (a share of the faces still to remove this pass, by its candidates
// left), keeping only collapses inside the chunk (the chunks in parallel when in core, else
// one after the other: the same result); then the deferred ones run in order, one at a time,
// up to the pass's goal. Near the goal, the rest runs one at a time. Neither the thread count
// nor the storage mode changes the result. With several groups, a part's records are read
// once for all of them (out of core they stay in the cache from one group to the next).
void StepChunks(RunContext& ctx, MeshState& mesh, PassState& pass,
  const std::vector<std::uint64_t>& groups, std::uint64_t nv, std::uint64_t goal, StepRun& total)
{
  const std::uint64_t size = StepChunkSize(ctx, nv);
  const std::size_t n = std::size_t((nv + size - 1) / size);
  const std::size_t G = groups.size() - 1;
  const std::uint64_t part = std::min<std::uint64_t>(size, kStepPart);
  const std::size_t partsPerChunk = std::size_t((size + part - 1) / part);
  // The parts: part k of chunk c starts at vertex c * size + k * part.
  std::vector<std::uint32_t> partLo;
  std::vector<std::size_t> chunkPart(n + 1);
  for (std::size_t c = 0; c < n; ++c)
  {
    chunkPart[c] = partLo.size();
    const std::uint64_t hi = std::min<std::uint64_t>(nv, (c + 1) * size);
    for (std::size_t k = 0; k < partsPerChunk && c * size + k * part < hi; ++k)
    {
      partLo.push_back(std::uint32_t(c * size + k * part));
    }
  }
  chunkPart[n] = partLo.size();
  const std::size_t P = partLo.size();
  // The parts' boundaries in each group (they are in vertex order): cursor[g * P + k] to
  // end[g * P + k].
  std::vector<std::uint64_t> cursor(G * P), end(G * P);
  for (std::size_t g = 0; g < G; ++g)
  {
    for (std::size_t k = 0; k <= P; ++k)
    {
      const std::uint64_t vb = k < P ? partLo[k] : nv;
      std::uint64_t l = groups[g], h = groups[g + 1];
      while (l < h)
      {
        const std::uint64_t m = l + (h - l) / 2;
        if (mesh.views.O.Get(m) < vb)
        {
          l = m + 1;
        }
        else
        {
          h = m;
        }
      }
      if (k < P)
      {
        cursor[g * P + k] = l;
      }
      if (k > 0)
      {
        end[g * P + k - 1] = l;
      }
    }
  }
  // In core: the chunks on every thread, taken from a shared counter. Out of core: the two
  // halves of the chunks on two threads (the second through a forked DML) while the faces split
  // with the vertices at the middle chunk boundary (FaceSplit).
  const std::size_t half = n / 2;
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = ctx.threads;
  phase.helper = pass.splitOn && half > 0 && std::uint64_t(half) * size == pass.splitMid;
  phase.helperFirst = pass.splitMid;
  phase.writes = { mesh.state.Id(), mesh.pos.Id(), mesh.cand.Id() };
  phase.record = &pass.stepFork;
  phase.minBytes = kStepWindowBytes;
  phase.helperWrites.push_back({ mesh.faces.Id(), pass.splitFace,
    mesh.faces.Size() - std::min(pass.splitFace, mesh.faces.Size()) });
  if (mesh.recSize)
  {
    phase.helperWrites.push_back({ mesh.attr.Id(), pass.splitMid * mesh.recSize,
      mesh.attr.Size() - pass.splitMid * mesh.recSize });
  }
  if (mesh.xSize)
  {
    phase.helperWrites.push_back({ mesh.extra.Id(), pass.splitMid * mesh.xSize,
      mesh.extra.Size() - pass.splitMid * mesh.xSize });
  }
  if (pass.scratch.size() < std::size_t(std::max(ctx.threads, 2)))
  {
    pass.scratch.resize(std::size_t(std::max(ctx.threads, 2)));
  }
  std::vector<std::uint64_t> roundStart(G * P);
  std::vector<StepRun> runs(n);
  // Progress: the step's position is that of the candidates consumed (those of the earlier
  // groups, whose rest is dropped when a group ends, then these).
  const std::uint64_t at = groups.front();
  std::uint64_t done = 0;
  std::vector<std::uint64_t> quota(n);
  // Progress in a round (the calling thread, t == 0): the candidates of its own chunks as it
  // goes (mine), everyone's at the end of the round.
  std::uint64_t mine = 0;
  // Chunk c's vertices [lo, hi).
  auto range = [&](std::size_t c) {
    return std::pair<std::uint32_t, std::uint32_t>(
      std::uint32_t(c * size), std::uint32_t(std::min<std::uint64_t>(nv, (c + 1) * size)));
  };
  // Chunk c's parts, group by group in each, up to its quota, on thread t.
  auto runChunk = [&](std::size_t c, Scratch& s, int t) {
    const auto [lo, hi] = range(c);
    for (std::size_t k = chunkPart[c]; k < chunkPart[c + 1] && runs[c].removed < quota[c]; ++k)
    {
      for (std::size_t g = 0; g < G && runs[c].removed < quota[c]; ++g)
      {
        const std::size_t i = g * P + k;
        const std::uint64_t from = cursor[i];
        cursor[i] = Step(ctx, mesh, pass, cursor[i], end[i], lo, hi, quota[c], s, runs[c],
          t == 0 ? std::int64_t(at + done + mine) : -1);
        if (t == 0)
        {
          mine += cursor[i] - from;
        }
      }
    }
  };
  while (mesh.liveFaces > goal)
  {
    std::uint64_t left = 0;
    for (std::size_t i = 0; i < G * P; ++i)
    {
      left += end[i] - cursor[i];
    }
    const std::uint64_t R = mesh.liveFaces - goal;
    if (left == 0)
    {
      return;
    }
    if (R < kStepTail)
    {
      // The rest one at a time, in order.
      StepRun run;
      for (std::size_t i = 0; i < G * P && run.removed < R; ++i)
      {
        const std::uint64_t from = cursor[i];
        cursor[i] = Step(ctx, mesh, pass, cursor[i], end[i], 0, kNone, R, pass.scratch[0], run,
          std::int64_t(at + done));
        done += cursor[i] - from;
      }
      mesh.liveFaces -= run.removed;
      total.done += run.done;
      total.illegal += run.illegal;
      return;
    }
    // A: the chunks, each up to its quota (9/10 of R shared by candidates left).
    for (std::size_t c = 0; c < n; ++c)
    {
      std::uint64_t mineLeft = 0;
      for (std::size_t g = 0; g < G; ++g)
      {
        for (std::size_t k = chunkPart[c]; k < chunkPart[c + 1]; ++k)
        {
          mineLeft += end[g * P + k] - cursor[g * P + k];
        }
      }
      quota[c] = mineLeft * (R - R / 10) / left;
      runs[c] = StepRun();
    }
    roundStart = cursor;
    mine = 0;
    std::atomic<std::size_t> next{ 0 };
    std::atomic<bool> stop{ false };
    Workers workers(mesh.dml, phase);
    const int T = workers.Count();
    std::vector<std::exception_ptr> errors(static_cast<std::size_t>(T));
    auto work = [&](int t) {
      Scratch& s = pass.scratch[std::size_t(t)];
      try
      {
        for (std::size_t c; !stop.load(std::memory_order_relaxed) && (c = next++) < n;)
        {
          const auto [lo, hi] = range(c);
          // The chunk's views: its collapses write only its vertices' records (and faces of its
          // vertices, whose ids are anywhere); checked in builds with SIPMSS_CHECK_WRITES.
          Views chunk;
          mesh.BindViews(chunk, mesh.dml);
          ChunkBounds(chunk, lo, hi, mesh.recSize, mesh.xSize);
          ScratchViews use(s, chunk);
          runChunk(c, s, t); // (progress and abort: the calling thread only)
        }
      }
      catch (...)
      {
        errors[std::size_t(t)] = std::current_exception();
        stop = true;
      }
    };
    if (workers.Forked())
    {
      // Each thread runs its half of the chunks in order (the same collapses as one after the
      // other: a chunk's collapses touch only its own vertices and faces).
      workers.Run([&](int t, std::uint64_t vb, std::uint64_t ve, const std::atomic<bool>& halt) {
        Scratch& s = pass.scratch[std::size_t(t)];
        Views views;
        mesh.BindViews(views, workers, t);
        ScratchViews use(s, views);
        for (std::size_t c = vb / size; c < (ve + size - 1) / size; ++c)
        {
          if (halt.load(std::memory_order_relaxed))
          {
            return;
          }
          runChunk(c, s, t);
        }
      });
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
    // B: the deferred ones, in order, one at a time. Each part's are moved to the front of
    // the part of the order it ran this round (done with), their flags cleared (all of them,
    // also past the goal), and go through Step (which prefetches ahead).
    StepRun b;
    for (std::size_t i = 0; i < G * P; ++i)
    {
      done += cursor[i] - roundStart[i];
    }
    for (std::size_t c = 0; c < n; ++c)
    {
      mesh.liveFaces -= runs[c].removed;
      total.done += runs[c].done;
      total.illegal += runs[c].illegal;
    }
    for (std::size_t i = 0; i < G * P; ++i)
    {
      std::uint64_t k = roundStart[i];
      for (std::uint64_t j = roundStart[i]; j < cursor[i]; ++j)
      {
        const std::uint32_t u = mesh.views.O.Get(j);
        const State su = mesh.views.S.Get(u);
        if (su & kDeferred)
        {
          mesh.views.S.Set(u, State(su & ~kDeferred));
          mesh.views.O.Set(k++, u);
        }
      }
      if (k > roundStart[i] && mesh.liveFaces > goal + b.removed)
      {
        Step(ctx, mesh, pass, roundStart[i], k, 0, kNone, mesh.liveFaces - goal, pass.scratch[0], b,
          std::int64_t(at + done), 0); // (polls only: these candidates were counted)
      }
    }
    mesh.liveFaces -= std::min(b.removed, mesh.liveFaces);
    total.done += b.done;
    total.illegal += b.illegal;
  }
}

// Pass's statistics: the sizes at its start, the laps of its steps (time and the DML's I/O),
// the step-1 counts of the threads' scratch, added to RunStats::passes when the pass ends (also
// by an early return; not when it throws).
class PassRecord
{
public:
  PassStat stat;
  PassRecord(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t goal)
    : ctx_(ctx)
    , mesh_(mesh)
    , pass_(pass)
    , io_(mesh.dml.GetStats())
    , lap_(std::chrono::steady_clock::now())
  {
    this->arrays_ = this->ArraysNow();
    this->stat.vertices = mesh.nv;
    this->stat.triangles = mesh.liveFaces;
    this->stat.goal = goal;
    for (Scratch& s : pass.scratch)
    {
      s.active = s.placed = s.promoted = 0;
    }
  }
  ~PassRecord()
  {
    if (std::uncaught_exceptions() > 0)
    {
      return;
    }
    for (const Scratch& s : this->pass_.scratch)
    {
      this->stat.activeVertices += s.active;
      this->stat.edgesPlaced += s.placed;
    }
    this->stat.trianglesAfter = this->mesh_.liveFaces;
    try
    {
      this->stat.mode = this->mesh_.dml.GetMode();
      this->ctx_.stats.passes.push_back(this->stat);
    }
    catch (...)
    {
      // (a destructor must not throw: without memory for it, the pass goes unrecorded)
    }
  }
  PassRecord(const PassRecord&) = delete;
  PassRecord& operator=(const PassRecord&) = delete;
  // Adds the time and the DML's I/O since the last lap to `step`.
  void Lap(PassStat::Step& step)
  {
    const auto now = std::chrono::steady_clock::now();
    const storage::Stats io = this->mesh_.dml.GetStats();
    step.seconds += std::chrono::duration<double>(now - this->lap_).count();
    step.bytesRead += io.bytesRead - this->io_.bytesRead;
    step.bytesWritten += io.bytesWritten - this->io_.bytesWritten;
    step.misses += io.misses - this->io_.misses;
    // By array (out of core): each named block's I/O since the last lap, the rest as "other".
    const Snapshots arrays = this->ArraysNow();
    if (io.misses != this->io_.misses || io.bytesRead != this->io_.bytesRead ||
      io.bytesWritten != this->io_.bytesWritten)
    {
      storage::BlockStats other{ io.misses - this->io_.misses, io.bytesRead - this->io_.bytesRead,
        io.bytesWritten - this->io_.bytesWritten };
      for (std::size_t i = 0; i < arrays.size(); ++i)
      {
        const Snapshot &a = arrays[i], &b = this->arrays_[i];
        if (a.id < 0)
        {
          continue;
        }
        // (the same block as at the last lap, else one opened since: all of its I/O is new)
        const bool same = b.id == a.id && b.io.misses <= a.io.misses &&
          b.io.bytesRead <= a.io.bytesRead && b.io.bytesWritten <= a.io.bytesWritten;
        const storage::BlockStats d{ a.io.misses - (same ? b.io.misses : 0),
          a.io.bytesRead - (same ? b.io.bytesRead : 0),
          a.io.bytesWritten - (same ? b.io.bytesWritten : 0) };
        if (d.misses + d.bytesRead + d.bytesWritten == 0)
        {
          continue;
        }
        Add(step, kArrayNames[i], d);
        other.misses -= std::min(other.misses, d.misses);
        other.bytesRead -= std::min(other.bytesRead, d.bytesRead);
        other.bytesWritten -= std::min(other.bytesWritten, d.bytesWritten);
      }
      if (other.misses + other.bytesRead + other.bytesWritten > 0)
      {
        Add(step, "other", other);
      }
    }
    this->arrays_ = std::move(arrays);
    this->lap_ = now;
    this->io_ = io;
  }

private:
  // The pass's named blocks (PassStat::ArrayIo's names, in order) and the I/O so far of those
  // open now (id -1: not open).
  static constexpr const char* kArrayNames[] = { "positions", "quadrics", "faces",
    "ring offsets", "ring faces", "states", "candidates", "order", "remap", "attributes",
    "attribute terms", "fit samples", "face selection", "fitted positions" };
  struct Snapshot
  {
    storage::BlockId id = -1;
    storage::BlockStats io;
  };
  using Snapshots = std::array<Snapshot, std::size(kArrayNames)>;
  Snapshots ArraysNow() const
  {
    const MeshState& m = this->mesh_;
    const std::pair<storage::BlockId, bool> blocks[] = { { m.pos.Id(), m.pos.IsOpen() },
      { m.quad.Id(), m.quad.IsOpen() }, { m.faces.Id(), m.faces.IsOpen() },
      { m.ringOff.Id(), m.ringOff.IsOpen() }, { m.ringFace.Id(), m.ringFace.IsOpen() },
      { m.state.Id(), m.state.IsOpen() }, { m.cand.Id(), m.cand.IsOpen() },
      { m.order.Id(), m.order.IsOpen() }, { m.remap.Id(), m.remap.IsOpen() },
      { m.attr.Id(), m.attr.IsOpen() }, { m.extra.Id(), m.extra.IsOpen() },
      { m.samples.Id(), m.samples.IsOpen() }, { m.outside.Id(), m.outside.IsOpen() },
      { m.fitted.Id(), m.fitted.IsOpen() } };
    static_assert(std::size(blocks) == std::size(kArrayNames), "one name per block");
    Snapshots out;
    for (std::size_t i = 0; i < out.size(); ++i)
    {
      if (blocks[i].second)
      {
        out[i] = { blocks[i].first, m.dml.GetBlockStats(blocks[i].first) };
      }
    }
    return out;
  }
  // Adds d to step's entry `name` (a step lapped again adds to what it has).
  static void Add(PassStat::Step& step, const std::string& name, const storage::BlockStats& d)
  {
    for (PassStat::ArrayIo& a : step.arrays)
    {
      if (a.name == name)
      {
        a.misses += d.misses;
        a.bytesRead += d.bytesRead;
        a.bytesWritten += d.bytesWritten;
        return;
      }
    }
    step.arrays.push_back({ name, d.misses, d.bytesRead, d.bytesWritten });
  }
  Snapshots arrays_;
  RunContext& ctx_;
  MeshState& mesh_;
  PassState& pass_;
  storage::Stats io_;
  std::chrono::steady_clock::time_point lap_;
};

bool Pass(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t goal, bool exact,
  bool far, double workAfter)
{
  const std::uint64_t nv = mesh.nv;
  mesh.BindViews();
  // This pass's statistics (RunStats::passes): recorded however the pass ends.
  PassRecord record(ctx, mesh, pass, goal);
  // Progress: the pass's steps by their work (kWork), then the rest of the run.
  const double wantGuess = double(2 * (mesh.liveFaces - std::min(goal, mesh.liveFaces)) + 16);
  const double wStep = kWork::kStep * wantGuess;
  const double wCompact = kWork::kCompact * double(mesh.nf + nv);
  const double wOrder = kWork::kOrder * double(nv);
  // 1. Every vertex's cheapest collapse.
  ctx.progress.BeginPhase(
    "collapse", kWork::kSweep * double(nv), wOrder + wStep + wCompact + workAfter);
  Sweep(ctx, mesh, pass, nv);
  record.Lap(record.stat.sweep);
  // 2. Counting sort of the cheapest candidates on their cost's float bits: enough bins for
  // about four times the collapses the goal needs (a collapse removes 2 faces, and both
  // endpoints may propose it). Ties in order of vertex index.
  ctx.progress.BeginPhase("collapse", wOrder, wStep + wCompact + workAfter);
  std::fill(pass.hist.begin(), pass.hist.end(), 0u);
  std::uint64_t candidates = 0;
  // (the candidates by runs: in place in core, else one table lookup per run and page)
  constexpr std::uint64_t kOrderRun = 256;
  std::vector<Cand> buf;
  for (std::uint64_t u0 = 0; u0 < nv; u0 += kOrderRun)
  {
    if ((u0 & 1023) == 0)
    {
      ctx.progress.Tick(double(u0) / double(2 * nv));
    }
    const std::size_t n = std::size_t(std::min(kOrderRun, nv - u0));
    const Cand* cands = mesh.views.C.Run(u0, n, buf);
    for (std::size_t j = 0; j < n; ++j)
    {
      if (cands[j].partner != kNone)
      {
        ++pass.hist[CostBin(cands[j].cost)];
        ++candidates;
      }
    }
  }
  if (candidates == 0)
  {
    record.Lap(record.stat.order);
    return false;
  }
  const std::uint64_t want = 2 * (mesh.liveFaces - goal) + 16;
  std::uint64_t taken = 0;
  std::uint32_t lastBin = 0;
  for (std::uint32_t b = 0; b < std::uint32_t(kCostBins); ++b)
  {
    taken += pass.hist[b];
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
  std::vector<std::uint64_t>& start = pass.starts; // start of each key (group or bin)
  start.assign(keys, 0);
  std::uint64_t cum = 0;
  for (std::uint32_t b = 0; b <= lastBin; ++b)
  {
    const std::uint64_t n = pass.hist[b];
    const std::uint32_t key = std::uint32_t(
      groups ? std::min<std::uint64_t>(groups - 1, cum * std::uint64_t(groups) / taken) : b);
    pass.hist[b] = key; // bin -> key
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
  mesh.BindViews();
  for (std::uint64_t u0 = 0; u0 < nv; u0 += kOrderRun)
  {
    if ((u0 & 1023) == 0)
    {
      ctx.progress.Tick(double(nv + u0) / double(2 * nv));
    }
    const std::size_t n = std::size_t(std::min(kOrderRun, nv - u0));
    const Cand* cands = mesh.views.C.Run(u0, n, buf);
    for (std::size_t j = 0; j < n; ++j)
    {
      if (cands[j].partner == kNone)
      {
        continue;
      }
      const std::uint32_t b = CostBin(cands[j].cost);
      if (b <= lastBin)
      {
        mesh.views.O.Set(start[pass.hist[b]]++, std::uint32_t(u0 + j));
      }
    }
  }
  // 3. Collapse in cost order, endpoints of earlier collapses excluded. Legality is checked
  // here, on the current faces and positions (the costs of pairs with no busy endpoint are as in
  // step 1). A vertex whose cheapest collapse is illegal evaluates all its edges with legality
  // in the next passes. A pass that may end on a level goes strictly in order, one collapse at
  // a time; the others go through StepChunks (in parallel when in core): far from the level
  // (`far`: halving passes, whose quotas hardly ever stop a chunk) every group at once, each
  // chunk part by part with the groups in turn in each part; nearer, group by group.
  record.Lap(record.stat.order);
  record.stat.candidates = taken;
  pass.stepTotal = std::max<std::uint64_t>(taken, 1);
  ctx.progress.BeginPhase("collapse", kWork::kStep * double(taken), wCompact + workAfter);
  // (the page policy's choice, see lazySums_; the mode does not change before Compact)
  pass.lazySums = !mesh.views.Q.InCore();
  StepRun run;
  if (groups && nv >= 2 * StepChunkSize(ctx, nv))
  {
    FaceSplit(ctx, mesh, pass, nv);
    std::vector<std::uint64_t> bounds(keys + 1, 0);
    std::copy(start.begin(), start.end(), bounds.begin() + 1);
    if (far)
    {
      StepChunks(ctx, mesh, pass, bounds, nv, goal, run);
    }
    else
    {
      for (std::size_t g = 0; g < keys && mesh.liveFaces > goal; ++g)
      {
        StepChunks(ctx, mesh, pass, { bounds[g], bounds[g + 1] }, nv, goal, run);
      }
    }
    pass.splitOn = false;
  }
  else
  {
    Step(ctx, mesh, pass, 0, taken, 0, kNone, mesh.liveFaces - goal, pass.scratch[0], run, 0);
    mesh.liveFaces -= run.removed;
  }
  const std::uint64_t done = run.done, illegal = run.illegal;
  record.Lap(record.stat.step);
  record.stat.collapses = done;
  record.stat.illegal = illegal;
  // 4. Compact into fresh blocks.
  ctx.progress.BeginPhase("collapse", wCompact, workAfter);
  Compact(ctx, mesh, pass);
  record.Lap(record.stat.compact);
  // Flagged vertices always get a legal candidate (or none) in the next pass: progress is made
  // as long as some candidate exists.
  return done > 0 || illegal > 0;
}

} // namespace
} // namespace sipmss::algorithms
