// Algorithm I: compaction after a pass, and the output.
// (Part of Decimate.cpp's translation unit; the map of the passes: Passes.h.)
namespace sipmss::algorithms
{
namespace
{
// The sums a pass with lazy sums left to the compaction (PassState::lazySums), while every
// record is still in place: each survivor of the pass (a live vertex, its degree in the old
// ring offsets) adds its partner's quadric, and extension, to its own, and the collapse's error
// is measured as Collapse measures it without lazy sums (its cost per unit of the summed
// quadric's trace). On the vertex ranges of up to two threads (out of core the upper one
// through a forked DML): a survivor writes only its own records, and reads its partner's,
// which nothing writes here (a partner is removed by its collapse, in no other one).
void LazySums(RunContext& ctx, MeshState& mesh, std::uint64_t nv)
{
  const std::size_t xs = mesh.xSize;
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = std::min(ctx.threads, 2);
  phase.inCoreMin = kParallelCompactMin;
  phase.writes = { mesh.quad.Id() };
  if (xs)
  {
    const std::uint64_t mid = nv / 2; // (Phase::helperFirst's default)
    phase.helperWrites.push_back({ mesh.extra.Id(), mid * xs, (nv - mid) * xs });
  }
  std::vector<double> err(2, 0.0); // each worker's largest error
  Workers workers(mesh.dml, phase);
  workers.Run([&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
    Views w;
    mesh.BindViews(w, workers, t);
    std::vector<double> xsum, xa, xb;
    double e = 0;
    for (std::uint64_t v = lo; v < hi; ++v)
    {
      if ((v & 4095) == 0)
      {
        if (stop.load(std::memory_order_relaxed))
        {
          return;
        }
        if (t == 0)
        {
          ctx.progress.Poll();
        }
      }
      if (!(w.S.Get(v) & kCollapsed) || w.RO.Get(v) == 0)
      {
        continue;
      }
      const Cand c = w.C.Get(v);
      Quadric Q = w.Q.Get(v);
      AddTo(Q, w.Q.Get(c.partner));
      w.Q.Set(v, Q);
      if (xs)
      {
        SumExtension(w.X, xs, v, c.partner, xsum, xa, xb);
        w.X.SetRange(v * xs, xs, xsum.data());
      }
      const double trace = Trace(Q);
      if (trace > 0)
      {
        e = std::max(e, KeyError(xs, double(c.cost), trace));
      }
    }
    err[std::size_t(t)] = std::max(err[std::size_t(t)], e); // (t < 2)
  });
  for (const double e : err)
  {
    ctx.achievedErr2 = std::max(ctx.achievedErr2, e);
  }
}

// Packs the live ones of a run's elements i0..n-1 (r[i] != kNone), `per` items each in
// `items` from the run's element i0 on, to the front of `items`; returns how many. In place
// and forwards: an element only moves down.
template <class T>
std::size_t PackLive(
  const std::uint32_t* r, std::size_t i0, std::size_t n, T* items, std::size_t per)
{
  std::size_t m = 0;
  for (std::size_t i = i0; i < n; ++i)
  {
    if (r[i] != kNone)
    {
      std::copy_n(items + (i - i0) * per, per, items + m * per);
      ++m;
    }
  }
  return m;
}

// Renumbers the live vertices and faces after a pass, in place: compaction keeps the order, so
// every element moves to an index <= its own and ascending loops never overwrite what they still
// have to read. The blocks then shrink (Resize: no copy) and the DML re-evaluates its mode with
// the smaller cost. The rings are rebuilt (degrees, offsets, reverse fill). In place rather than
// into fresh blocks: half the peak memory, and no first-touch page faults on every pass.
void Compact(RunContext& ctx, MeshState& mesh, PassState& pass)
{
  const std::uint64_t nv = mesh.nv, nf = mesh.nf;
  const std::uint64_t nf2 = mesh.liveFaces;
  const std::uint64_t total = 4 * nf + 2 * nv;
  // (a level's fitted positions are written: the next level fits its own)
  mesh.fitted = Array<Vec3>();
  mesh.fittedValid = false;
  mesh.remap.Resize(std::max<std::uint64_t>(nv, 1));
  mesh.BindViews();
  View<std::uint32_t> R(mesh.dml, mesh.remap);
  // On several threads (Workers): the degrees (CountDegrees), out of core the lazy sums by
  // vertex range (LazySums), the rings by vertex range (each thread scans all faces and writes
  // only its own vertices), the moves (in place, downwards) one array group per thread. Same
  // result either way.
  // 1. Degrees of the live faces, counted in the old ring offsets (the rings are done with);
  // the candidate order is free until the next pass: CountDegrees' second counter array.
  FillBlock(mesh.dml, mesh.ringOff, std::uint32_t(0));
  CountDegrees(ctx, mesh, nf, kParallelCompactMin, 0, total, &mesh.order);
  // 2. New vertex numbers; RO[k] = end of k's ring (k <= v: RO[k] was read already). R holds the
  // new number, with the top bit for the survivors of this pass (their old state is overwritten
  // below before their neighbours look at it).
  constexpr std::uint32_t kTop = 0x80000000u;
  if (pass.lazySums)
  {
    LazySums(ctx, mesh, nv);
    pass.lazySums = false;
  }
  // (by runs of kRenumberRun vertices read and written as ranges: a run's new offsets land at
  // or below its vertices, which it has read)
  constexpr std::uint64_t kRenumberRun = 256;
  std::uint64_t k = 0;
  std::uint32_t end = 0;
  {
    std::vector<std::uint32_t> deg(kRenumberRun), ends(kRenumberRun), r(kRenumberRun);
    std::vector<State> st(kRenumberRun);
    for (std::uint64_t v0 = 0; v0 < nv; v0 += kRenumberRun)
    {
      if ((v0 & 1023) == 0)
      {
        ctx.progress.Tick(double(nf + v0) / double(total));
      }
      const std::size_t n = std::size_t(std::min(kRenumberRun, nv - v0));
      mesh.views.RO.GetRange(v0, n, deg.data());
      mesh.views.S.GetRange(v0, n, st.data());
      const std::uint64_t k0 = k;
      for (std::size_t i = 0; i < n; ++i)
      {
        if (deg[i] == 0)
        {
          r[i] = kNone;
          continue;
        }
        end += deg[i];
        ends[k - k0] = end;
        const bool survivor = (st[i] & kCollapsed) != 0;
        r[i] = std::uint32_t(k) | (survivor ? kTop : 0u);
        ++k;
      }
      mesh.views.RO.SetRange(k0, k - k0, ends.data());
      R.SetRange(v0, n, r.data());
    }
  }
  for (Scratch& s : pass.scratch)
  {
    ctx.achievedErr2 = std::max(ctx.achievedErr2, s.achievedErr2);
    s.achievedErr2 = 0;
  }
  const std::uint64_t nv2 = k;
  mesh.views.RO.Set(nv2, end);
  TrackSamples(mesh, R); // (the removed vertices' candidates still name their survivors)
  // 3. Vertex data, and the candidates carried to the next pass: a vertex's state sv and
  // candidate cv give its new flags and candidate c (R: its partners' new numbers).
  auto carry = [&, kTop](const View<std::uint32_t>& R, State sv, const Cand& cv, State& flags,
                 Cand& c) {
    flags = State(sv & (kBoundary | kLocked | kFixed | kNeedsLegal | kComplex | kMerged));
    c = kNoCandidate;
    if (sv & kCollapsed)
    {
      flags = State((flags & ~kNeedsLegal) | kSurvivor | kMerged); // every edge changed
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
      c = cv;
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
          c = kNoCandidate;
        }
        else
        {
          flags |= kPromote;
        }
      }
      else
      {
        c = kNoCandidate;
        if (!(flags & kNeedsLegal))
        {
          flags |= kRecompute;
        }
      }
    }
  };
  const std::size_t rec = mesh.recSize;
  const std::size_t xs = mesh.xSize;
  std::uint64_t f2 = 0;
  // The moves go by runs of up to kMoveRun elements, read and written as ranges (a table
  // lookup per run and page, not per element). A run's live elements land next to each other,
  // at or below their old indices (the order is kept), and what a run writes is read first.
  // Those that do not move (all before the first removed one) come first in a run: their
  // quadrics, positions and point data are neither read nor written; every live vertex's state
  // and candidate are written (carried), and every live face (renumbered).
  constexpr std::uint64_t kMoveRun = 256;
  // (vertex runs are shorter with large records: their point data or extensions in a run take
  // about kMoveBytes at most, outside the budget like any scratch; one record may take 160 KB,
  // 40,000 properties)
  constexpr std::size_t kMoveBytes = std::size_t(64) << 10;
  const std::uint64_t vRun = std::clamp<std::uint64_t>(
    kMoveBytes / std::max<std::size_t>({ rec, xs * sizeof(double), 1 }), 1, kMoveRun);
  // (once per 1,024 elements: i advances by at most step <= 1,024)
  auto progressAt = [&](std::uint64_t at, std::uint64_t i, std::uint64_t step) {
    if ((i & 1023) < step)
    {
      ctx.progress.Tick(double(at + i) / double(total));
    }
  };
  // 4. Faces, ascending: new index f2 <= f (they read only R and the faces).
  auto moveFaces = [&](Views& wv, const View<std::uint32_t>& RR, bool tick) {
    std::vector<Tri> buf, out(kMoveRun);
    for (std::uint64_t f0 = 0; f0 < nf; f0 += kMoveRun)
    {
      if (tick)
      {
        progressAt(nf + 2 * nv, f0, kMoveRun);
      }
      const std::size_t n = std::size_t(std::min(kMoveRun, nf - f0));
      const Tri* in = wv.F.Run(f0, n, buf); // (read whole before the run's faces are written)
      std::size_t m = 0;
      for (std::size_t i = 0; i < n; ++i)
      {
        Tri t = in[i];
        if (!Alive(t))
        {
          continue;
        }
        for (int c = 0; c < 3; ++c)
        {
          t.v[c] = RR.Get(t.v[c]) & ~kTop;
        }
        out[m++] = t;
      }
      // (faces that stay are written too: their corners are renumbered)
      wv.F.SetRange(f2, m, out.data());
      f2 += m;
    }
  };
  // The live vertices of the run [v0, v0 + n) with new numbers r: the first one's new number
  // (wLive, kNone for none) and the first moved one's index in the run (n for none).
  auto runOf = [kTop](const std::uint32_t* r, std::uint64_t v0, std::size_t n,
                 std::uint64_t& wLive, std::size_t& firstMoved) {
    wLive = kNone;
    firstMoved = n;
    for (std::size_t i = 0; i < n; ++i)
    {
      if (r[i] == kNone)
      {
        continue;
      }
      const std::uint64_t w = r[i] & ~kTop;
      if (wLive == kNone)
      {
        wLive = w;
      }
      if (w != v0 + i)
      {
        firstMoved = i;
        return;
      }
    }
  };
  // The quadrics (and attribute extensions), in place and downwards.
  auto moveQuadrics = [&](Views& wv, const View<std::uint32_t>& RR, bool tick, bool poll) {
    std::vector<std::uint32_t> r(vRun);
    std::vector<Quadric> q(vRun);
    std::vector<double> x(vRun * xs);
    for (std::uint64_t v0 = 0; v0 < nv; v0 += vRun)
    {
      if (tick)
      {
        progressAt(nf + nv, v0, vRun);
      }
      else if (poll && (v0 & 4095) < vRun)
      {
        ctx.progress.Poll();
      }
      const std::size_t n = std::size_t(std::min(vRun, nv - v0));
      RR.GetRange(v0, n, r.data());
      std::uint64_t wLive;
      std::size_t i0;
      runOf(r.data(), v0, n, wLive, i0);
      if (i0 == n)
      {
        continue; // nothing moves
      }
      wv.Q.GetRange(v0 + i0, n - i0, q.data());
      if (xs)
      {
        wv.X.GetRange((v0 + i0) * xs, (n - i0) * xs, x.data());
      }
      const std::uint64_t w0 = r[i0] & ~kTop;
      const std::size_t m = PackLive(r.data(), i0, n, q.data(), 1);
      wv.Q.SetRange(w0, m, q.data());
      if (xs)
      {
        PackLive(r.data(), i0, n, x.data(), xs);
        wv.X.SetRange(w0 * xs, m * xs, x.data());
      }
    }
  };
  // The states and candidates (carried: every live vertex's change), the positions and the
  // point data (the moved ones), in place and downwards.
  auto moveRest = [&](Views& wv, const View<std::uint32_t>& RR, bool tick) {
    std::vector<std::uint32_t> r(vRun);
    std::vector<State> sIn(vRun), sOut(vRun);
    std::vector<Cand> cIn(vRun), cOut(vRun);
    std::vector<Vec3> p(vRun);
    std::vector<std::uint8_t> a(vRun * rec);
    for (std::uint64_t v0 = 0; v0 < nv; v0 += vRun)
    {
      if (tick)
      {
        progressAt(nf + nv, v0, vRun);
      }
      const std::size_t n = std::size_t(std::min(vRun, nv - v0));
      RR.GetRange(v0, n, r.data());
      std::uint64_t wLive;
      std::size_t i0;
      runOf(r.data(), v0, n, wLive, i0);
      if (wLive == kNone)
      {
        continue; // no live vertex
      }
      wv.S.GetRange(v0, n, sIn.data());
      wv.C.GetRange(v0, n, cIn.data());
      std::size_t m = 0;
      for (std::size_t i = 0; i < n; ++i)
      {
        if (r[i] != kNone)
        {
          carry(RR, sIn[i], cIn[i], sOut[m], cOut[m]);
          ++m;
        }
      }
      wv.S.SetRange(wLive, m, sOut.data());
      wv.C.SetRange(wLive, m, cOut.data());
      if (i0 == n)
      {
        continue; // no position or point data moves
      }
      wv.P.GetRange(v0 + i0, n - i0, p.data());
      if (rec)
      {
        wv.A.GetRange((v0 + i0) * rec, (n - i0) * rec, a.data());
      }
      const std::uint64_t w0 = r[i0] & ~kTop;
      const std::size_t k2 = PackLive(r.data(), i0, n, p.data(), 1);
      wv.P.SetRange(w0, k2, p.data());
      if (rec)
      {
        PackLive(r.data(), i0, n, a.data(), rec);
        wv.A.SetRange(w0 * rec, k2 * rec, a.data());
      }
    }
  };
  // The arrays are independent: on two threads one moves the quadrics and then the faces, the
  // other carries and moves the rest (memory-bound: one thread per stream; out of core the
  // second through a forked DML).
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = std::min(ctx.threads, 2);
  phase.inCoreMin = kParallelCompactMin;
  phase.helperFirst = 0; // (the second task writes every vertex of its blocks)
  phase.writes = { mesh.state.Id(), mesh.cand.Id(), mesh.pos.Id() };
  if (rec)
  {
    phase.helperWrites.push_back({ mesh.attr.Id(), 0, nv * rec });
  }
  phase.mainWrites = { mesh.quad.Id(), mesh.faces.Id() };
  phase.record = &pass.compactFork;
  if (mesh.xSize)
  {
    phase.mainWrites.push_back(mesh.extra.Id());
  }
  Workers workers(mesh.dml, phase);
  // (Progress: on one thread the quadrics only poll, the rest ticks, then the faces.)
  const bool split = workers.Count() > 1;
  workers.RunTasks(2, [&](int t, int task, const std::atomic<bool>&) {
    Views wv;
    mesh.BindViews(wv, workers, t);
    const View<std::uint32_t> RR = workers.Bind(t, mesh.remap);
    if (task == 0)
    {
      moveQuadrics(wv, RR, t == 0 && split, t == 0);
      if (split)
      {
        moveFaces(wv, RR, t == 0);
      }
    }
    else
    {
      moveRest(wv, RR, t == 0 && !split);
    }
  });
  if (!split)
  {
    mesh.BindViews();
    moveFaces(mesh.views, R, true);
  }
  // 5. Shrink, then the rings (faces in reverse: each list ascending, RO[k] ends at its start).
  const std::uint64_t nvb = std::max<std::uint64_t>(nv2, 1);
  mesh.pos.Resize(nvb);
  mesh.quad.Resize(nvb);
  if (mesh.xSize)
  {
    mesh.extra.Resize(nvb * mesh.xSize);
  }
  if (rec)
  {
    mesh.attr.Resize(nvb * rec);
  }
  mesh.state.Resize(nvb);
  mesh.cand.Resize(nvb);
  mesh.faces.Resize(std::max<std::uint64_t>(nf2, 1));
  mesh.ringOff.Resize(nv2 + 1);
  mesh.ringFace.Resize(std::max<std::uint64_t>(3 * nf2, 1));
  mesh.nv = nv2;
  mesh.nf = nf2;
  mesh.BindViews();
  FillRings(ctx, mesh, nf2, 2 * nf + 2 * nv, total);
  mesh.remap.Resize(nvb);
  mesh.order.Resize(nvb);
  mesh.dml.Reconfigure();
  mesh.BindViews();
}

// ---------------------------------------------------------------------------------------------
// output

void Emit(RunContext& ctx, MeshState& mesh, io::MeshSink& sink)
{
  io::MeshHeader h;
  h.format = io::Format::Unknown;
  h.vertexCount = mesh.nv;
  h.faceCount = mesh.nf;
  h.layout = mesh.layout;
  sink.Begin(h);
  mesh.BindViews();
  const std::size_t rec = mesh.recSize;
  const std::size_t ns = mesh.layout.scalars.size();
  // Chunks of at most 16K vertices and about 1 MiB of buffers, whatever the number of vertex
  // properties (the output's size does not depend on the chunking).
  const std::size_t perVertex = sizeof(Vec3) + 12 + (mesh.layout.normals ? 12 : 0) +
    (mesh.layout.texcoords ? 8 : 0) + 4 * ns + rec + (mesh.layout.colors ? 4 : 0);
  const std::size_t chunk = std::clamp<std::size_t>((std::size_t(1) << 20) / perVertex, 1, 1 << 14);
  std::vector<Vec3> p(chunk);
  std::vector<float> xyz(3 * chunk), normals, tex, scalars;
  std::vector<std::uint8_t> raw, rgba;
  if (mesh.layout.normals)
  {
    normals.resize(3 * chunk);
  }
  if (mesh.layout.texcoords)
  {
    tex.resize(2 * chunk);
  }
  if (ns)
  {
    scalars.resize(ns * chunk);
  }
  if (mesh.layout.colors)
  {
    rgba.resize(4 * chunk);
  }
  raw.resize(rec * chunk);
  const std::uint64_t total = mesh.nv + mesh.nf;
  std::vector<Quadric> quadrics;
  for (std::uint64_t first = 0; first < mesh.nv; first += chunk)
  {
    ctx.progress.Tick(total ? double(first) / double(total) : 1.0);
    // (bound for each chunk: the finalQuadric callback may grow a block of the same DML, which
    // can move it out of core)
    mesh.BindViews();
    const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, mesh.nv - first));
    (mesh.fittedValid ? View<Vec3>(mesh.dml, mesh.fitted) : mesh.views.P)
      .GetRange(first, n, p.data());
    for (std::size_t i = 0; i < n; ++i)
    {
      xyz[3 * i] = float(p[i].x + mesh.origin.x);
      xyz[3 * i + 1] = float(p[i].y + mesh.origin.y);
      xyz[3 * i + 2] = float(p[i].z + mesh.origin.z);
    }
    io::VertexChunk vc;
    vc.first = first;
    vc.count = n;
    vc.xyz = xyz.data();
    if (rec)
    {
      mesh.views.A.GetRange(first * rec, n * rec, raw.data());
      for (std::size_t i = 0; i < n; ++i)
      {
        const float* f = reinterpret_cast<const float*>(raw.data() + i * rec);
        std::size_t k = 0;
        if (mesh.layout.normals)
        {
          for (int j = 0; j < 3; ++j)
          {
            normals[3 * i + j] = f[k++];
          }
        }
        if (mesh.layout.texcoords)
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
        if (mesh.layout.colors)
        {
          std::memcpy(&rgba[4 * i], raw.data() + i * rec + mesh.nFloats * sizeof(float), 4);
        }
      }
      vc.normals = mesh.layout.normals ? normals.data() : nullptr;
      vc.texcoords = mesh.layout.texcoords ? tex.data() : nullptr;
      vc.scalars = ns ? scalars.data() : nullptr;
      vc.rgba = mesh.layout.colors ? rgba.data() : nullptr;
    }
    sink.Vertices(vc);
    if (ctx.opt.finalQuadric)
    {
      const double o[3] = { mesh.origin.x, mesh.origin.y, mesh.origin.z };
      quadrics.resize(n);
      mesh.views.Q.GetRange(first, n, quadrics.data()); // (before any callback)
      for (std::size_t i = 0; i < n; ++i)
      {
        // (local to input coordinates: E(x - origin))
        const Quadric q = Translated(quadrics[i], o);
        ctx.opt.finalQuadric(first + i, q.q);
      }
    }
  }
  std::vector<Tri> tris(chunk);
  mesh.BindViews();
  for (std::uint64_t first = 0; first < mesh.nf; first += chunk)
  {
    ctx.progress.Tick(total ? double(mesh.nv + first) / double(total) : 1.0);
    const std::size_t n = std::size_t(std::min<std::uint64_t>(chunk, mesh.nf - first));
    mesh.views.F.GetRange(first, n, tris.data());
    sink.Triangles(reinterpret_cast<const std::uint32_t*>(tris.data()), n);
  }
  io::ReadStats rs;
  rs.vertices = mesh.nv;
  rs.triangles = mesh.nf;
  rs.polygons = mesh.nf;
  sink.End(rs);
}

} // namespace
} // namespace sipmss::algorithms
