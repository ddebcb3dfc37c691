// Algorithm I: the candidate sweep (each vertex's cheapest collapse) and the placement.
// (Part of Decimate.cpp's translation unit; the map of the passes: Passes.h.)
namespace sipmss::algorithms
{
namespace
{
// ---------------------------------------------------------------------------------------------
// collapse

// The placement of a collapse with summed quadric Q (PlaceLanes for one edge); a fixed endpoint
// stays where it is.
Placement Place(const Quadric& Q, const Vec3& pu, const Vec3& pv, State su, State sv)
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

// Q, the sum of u's and v's quadrics: returns its trace (the error bound's unit) and, with
// attributes (mesh.xSize > 0), adds the attribute error of the summed extensions to it
// (Attributes.h), which s.xbuf then holds.
double EdgeQuadric(const MeshState& mesh, const Views& w, std::uint32_t u, std::uint32_t v,
  Quadric& Q, Scratch& s)
{
  const double trace = Trace(Q);
  if (mesh.xSize)
  {
    AddEdgeAttributeError(mesh, w, u, v, Q, s);
  }
  return trace;
}

// (Out of line: a run without attributes keeps the sweep's code as it was.)
SIPMSS_COLD void AddEdgeAttributeError(const MeshState& mesh, const Views& w, std::uint32_t u,
  std::uint32_t v, Quadric& Q, Scratch& s)
{
  SumExtension(w.X, mesh.xSize, u, v, s.xbuf, s.xbuf2, s.xbuf3);
  AddAttributeError(s.xbuf.data(), mesh.channels.size(), Q);
}

// Offers an edge to x: directly when x is this thread's, else queued for x's thread. The result
// does not depend on the order of offers (the best two by (cost, partner) are kept), so the
// parallel sweep in core and the sequential one out of core give identical candidates.
void Offer(MeshState& mesh, PassState& pass, 
  std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner, Scratch& s)
{
  if (x < s.lo || x >= s.hi)
  {
    std::size_t t = 0;
    while (t + 1 < pass.partStart.size() && x >= pass.partStart[t + 1])
    {
      ++t;
    }
    s.out[t].push_back({ x, partner, fromPartner, pl });
    return;
  }
  Apply(mesh.W(s), x, partner, pl, fromPartner);
}

void Apply(
  Views& w, std::uint32_t x, std::uint32_t partner, const Placement& pl, bool fromPartner)
{
  const float cost = float(pl.cost); // compared as stored
  Cand c = w.C.Get(x);
  if (!Before(cost, partner, c.cost, c.partner) && !Before(cost, partner, c.cost2, c.partner2))
  {
    return;
  }
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

// Step 1 of a pass: every active vertex evaluates its edges. In core, the vertex range is split
// among threads_ threads; a thread writes only its own vertices' candidates and queues offers to
// the others', which their owners apply between barriers, one chunk of vertices at a time (the
// queues stay small). Out of core (the DML is single-threaded) one thread sweeps in order. Both
// give the same candidates: see Offer.
void Sweep(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint64_t nv)
{
  constexpr std::uint64_t kChunk = 16384;
  constexpr std::uint64_t kParallelMin = 8192;
  auto sequential = [&, nv]() {
    Scratch& s = pass.scratch[0];
    s.lo = 0;
    s.hi = kNone;
    s.batch.n = 0;
    WithAccess(
      [&](auto S, auto RO, auto RF, auto F) {
        for (std::uint64_t u = 0; u < nv; ++u)
        {
          ctx.Tick(u, nv);
          PrefetchSweep(S, RO, RF, F, u, nv);
          Evaluate(ctx, mesh, pass, std::uint32_t(u), s);
        }
      },
      mesh.views.S, mesh.views.RO, mesh.views.RF, mesh.views.F);
    FlushEdges(ctx, mesh, pass, s);
  };
  // Out of core on two threads: the second sweeps the upper half of the vertices through a
  // forked DML. Each thread writes only its own range's candidates (the others' offers are
  // queued, as in core), the only block the sweep writes.
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = ctx.threads;
  phase.inCoreMin = kParallelMin;
  phase.writes = { mesh.cand.Id() };
  phase.record = &pass.sweepFork;
  Workers workers(mesh.dml, phase);
  const int T = workers.Count();
  if (T <= 1)
  {
    sequential();
    return;
  }
  if (pass.scratch.size() < std::size_t(T))
  {
    pass.scratch.resize(std::size_t(T));
  }
  pass.partStart.assign(std::size_t(T) + 1, 0);
  for (int t = 0; t <= T; ++t)
  {
    pass.partStart[std::size_t(t)] = std::uint32_t(workers.Begin(t));
  }
  std::vector<Views> views(static_cast<std::size_t>(T));
  for (int t = 0; t < T; ++t)
  {
    mesh.BindViews(views[std::size_t(t)], workers, t);
  }
  std::uint64_t rounds = 0;
  for (int t = 0; t < T; ++t)
  {
    Scratch& s = pass.scratch[std::size_t(t)];
    s.lo = pass.partStart[std::size_t(t)];
    s.hi = pass.partStart[std::size_t(t) + 1];
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
  // Out of core, a helper whose half of the budget cannot hold its window of pages makes both
  // threads evict each other's pages (a sweep can then read its blocks hundreds of times over):
  // each thread counts its misses, and once they pass ForkRecord::kThrash reads of its share of
  // the files (Workers declines the helper of a phase that misses that much), the forked sweep
  // stops. It then runs on one thread from the start (the offers are idempotent, as below;
  // its progress starts over too) and the record keeps the following passes' sweeps on one
  // thread.
  std::atomic<bool> thrash{ false };
  const bool guard = workers.Forked();
  auto work = [&](int t) {
    Scratch& s = pass.scratch[std::size_t(t)];
    ScratchViews use(s, views[std::size_t(t)]);
    const std::uint64_t missesAtStart = guard ? workers.Dml(t).GetStats().misses : 0;
    const double missLimit = guard ? workers.MissLimit(s.hi - s.lo) : 0.0;
    for (std::uint64_t r = 0; r < rounds; ++r)
    {
      try
      {
        const std::uint64_t b = std::min<std::uint64_t>(s.hi, s.lo + r * kChunk);
        const std::uint64_t e = std::min<std::uint64_t>(s.hi, b + kChunk);
        const Views& w = views[std::size_t(t)];
        WithAccess(
          [&](auto S, auto RO, auto RF, auto F) {
            for (std::uint64_t u = b; u < e && !stop.load(std::memory_order_relaxed); ++u)
            {
              if (t == 0)
              {
                ctx.Tick(u - s.lo, s.hi - s.lo); // progress and abort: the calling thread only
              }
              PrefetchSweep(S, RO, RF, F, u, e);
              Evaluate(ctx, mesh, pass, std::uint32_t(u), s);
            }
          },
          w.S, w.RO, w.RF, w.F);
        FlushEdges(ctx, mesh, pass, s); // (its offers to other threads go out at this barrier)
        if (guard)
        {
          const std::uint64_t misses = workers.Dml(t).GetStats().misses - missesAtStart;
          if (double(misses) > missLimit)
          {
            thrash = true;
            stop = true;
          }
        }
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
              for (const Deferred& d : pass.scratch[std::size_t(o)].out[std::size_t(t)])
              {
                Apply(mesh.W(s), d.x, d.partner, d.pl, d.fromPartner); // (may page)
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
  workers.Join(); // (on an exception, its destructor does)
  RethrowFirst(errors);
  if (thrash)
  {
    workers.DeclineHelper();
  }
  if (started < T || thrash)
  {
    // (the sequential sweep evaluates every vertex again: what the stopped threads counted of
    // the pass's vertices and edges goes, but for the promoted placements they made, which
    // stay made)
    for (Scratch& s : pass.scratch)
    {
      s.active = 0;
      s.placed = s.promoted;
    }
    sequential();
  }
}

// The candidate sweep for vertex u: evaluates u's edges to higher neighbours once and offers
// them to both endpoints (light path: the ring's faces only, no neighbour table). An edge u-a is
// taken from the face where a follows u; an edge seen only with a before u is a boundary edge
// (or inconsistently oriented) and is taken from there.
void Evaluate(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint32_t u, Scratch& s)
{
  Views& w = mesh.W(s);
  const State su = w.S.Get(u);
  if (su & kLocked)
  {
    return;
  }
  if (su & kNeedsLegal)
  {
    EvaluateFull(ctx, mesh, u, su, s);
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
        EdgeQuadric(mesh, w, u, v, Q, s);
        ++s.placed;
        ++s.promoted;
        const Placement pl = Place(Q, w.P.Get(u), w.P.Get(v), su, w.S.Get(v));
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
  ++s.active;
  const std::uint32_t b = w.RO.Get(u), e = w.RO.Get(u + 1);
  const std::uint32_t* ids = w.RF.Run(b, e - b, s.ids);
  if (e - b > s.next.size())
  {
    s.next.resize(e - b);
    s.prev.resize(e - b);
  }
  std::uint32_t* next = s.next.data();
  std::uint32_t* prev = s.prev.data();
  // A vertex of very high valence takes long: the calling thread polls inside it.
  const bool poll = e - b > 65536 && &s == &pass.scratch[0];
  std::size_t n = 0;
  for (std::uint32_t k = 0; k < e - b; ++k)
  {
    if (poll && (k & 4095) == 4095)
    {
      ctx.progress.Poll();
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
  // The neighbours' data is read (and their candidates written) below: fetch it in parallel.
  for (std::size_t i = 0; i < n; ++i)
  {
    const std::uint32_t a = next[i];
    w.Q.Prefetch(a);
    w.S.Prefetch(a);
    w.P.Prefetch(a);
    w.C.Prefetch(a);
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
        ctx.progress.Poll();
      }
      if (tally.First(true, next[i], i))
      {
        EvaluateEdge(ctx, mesh, pass, u, su, Qu, pu, next[i], next, prev, n, &tally, s);
      }
    }
    for (std::size_t i = 0; i < n; ++i)
    {
      if (poll && (i & 4095) == 4095)
      {
        ctx.progress.Poll();
      }
      const std::uint32_t a = prev[i];
      if (tally.Count(true, a) == 0 && tally.First(false, a, i))
      {
        EvaluateEdge(ctx, mesh, pass, u, su, Qu, pu, a, next, prev, n, &tally, s);
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
      EvaluateEdge(ctx, mesh, pass, u, su, Qu, pu, a, next, prev, n, nullptr, s);
    }
  }
  for (std::size_t i = 0; i < n; ++i)
  {
    const std::uint32_t a = prev[i];
    if (!in(next, n, a) && !in(prev, i, a))
    {
      EvaluateEdge(ctx, mesh, pass, u, su, Qu, pu, a, next, prev, n, nullptr, s);
    }
  }
}

void EvaluateEdge(RunContext& ctx, MeshState& mesh, PassState& pass, std::uint32_t u, State su,
  const Quadric& Qu, const Vec3& pu, std::uint32_t v, const std::uint32_t* next,
  const std::uint32_t* prev, std::size_t n, const LinkTally* tally, Scratch& s)
{
  Views& w = mesh.W(s);
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
    const double trace = EdgeQuadric(mesh, w, u, v, Q, s);
    ++s.placed;
    OfferEdge(ctx, mesh, pass, u, v, Place(Q, pu, pv, su, sv), trace, offerV, s);
    return;
  }
  // Queued: placed in pairs (the offers do not depend on their order).
  EdgeBatch& b = s.batch;
  const int l = b.n;
  for (int k = 0; k < 10; ++k)
  {
    b.q[k][l] = Qv.q[k] + Qu.q[k]; // (AddTo's sum)
  }
  b.trace[l] = b.q[0][l] + b.q[4][l] + b.q[7][l];
  if (mesh.xSize)
  {
    Quadric Q;
    for (int k = 0; k < 10; ++k)
    {
      Q.q[k] = b.q[k][l];
    }
    AddEdgeAttributeError(mesh, w, u, v, Q, s);
    for (int k = 0; k < 10; ++k)
    {
      b.q[k][l] = Q.q[k];
    }
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
    FlushEdges(ctx, mesh, pass, s);
  }
}

// Places the queued edges of the sweep and offers them.
void FlushEdges(RunContext& ctx, MeshState& mesh, PassState& pass, Scratch& s)
{
  EdgeBatch& b = s.batch;
  const int n = b.n;
  if (n == 0)
  {
    return;
  }
  b.n = 0;
  s.placed += std::uint64_t(n);
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
    OfferEdge(ctx, mesh, pass, b.u[l], b.v[l], { cost[l], { px[l], py[l], pz[l] }, t[l] },
      b.trace[l], b.offerV[l], s);
  }
}

// Offers edge u-v with placement pl (summed quadric's trace `trace`) to u, and to v if offerV,
// unless it has no finite cost or exceeds the error bound.
void OfferEdge(RunContext& ctx, MeshState& mesh, PassState& pass, 
  std::uint32_t u, std::uint32_t v, const Placement& pl, double trace, bool offerV, Scratch& s)
{
  if (!std::isfinite(pl.cost) || pl.cost > ctx.maxErr2 * trace)
  {
    return;
  }
  Placement ranked = pl;
  ranked.cost = RankKey(mesh.xSize, pl.cost, trace);
  Offer(mesh, pass, u, v, ranked, false, s);
  if (offerV)
  {
    Offer(mesh, pass, v, u, ranked, true, s);
  }
}

// The heavy path for a vertex whose cheapest collapse was illegal: all its edges, in cost
// order, the first legal one is its candidate. Edges to higher neighbours are still offered to
// them.
void EvaluateFull(RunContext& ctx, MeshState& mesh, std::uint32_t u, State su, Scratch& s)
{
  Views& w = mesh.W(s);
  ++s.active;
  w.C.Set(u, kNoCandidate);
  const std::uint32_t lengthU = RingLength(w, u);
  if (lengthU > kMaxCollapseRing)
  {
    return; // (no collapse of u is made in this pass: kMaxCollapseRing)
  }
  Ring& ru = s.ru;
  LoadRing(w, u, ru, true);
  if (ru.faces.empty())
  {
    return;
  }
  const Quadric Qu = w.Q.Get(u);
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
    if (lengthU + RingLength(w, nb.v) > kMaxCollapseRing)
    {
      continue;
    }
    Quadric Q = w.Q.Get(nb.v);
    AddTo(Q, Qu);
    const double trace = EdgeQuadric(mesh, w, u, nb.v, Q, s);
    ++s.placed;
    const Placement pl = Place(Q, ru.px, nb.p, su, sv);
    if (!std::isfinite(pl.cost) || pl.cost > ctx.maxErr2 * trace)
    {
      continue;
    }
    // (Its neighbours get this edge from their own evaluation: u is neither active nor a
    // survivor.)
    s.edges.push_back({ RankKey(mesh.xSize, pl.cost, trace), nb.v, k, pl });
  }
  std::sort(s.edges.begin(), s.edges.end(), [](const EdgeCand& a, const EdgeCand& b) {
    return a.cost < b.cost || (a.cost == b.cost && a.v < b.v);
  });
  for (const EdgeCand& ec : s.edges)
  {
    if (Legal(ctx, mesh, u, ru.nbs[ec.nbIndex], ec.pl.p, s))
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

} // namespace
} // namespace sipmss::algorithms
