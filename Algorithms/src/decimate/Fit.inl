// Algorithm I: the final fit of the output's vertices to the input's surface
// (DecimateOptions::fitSurface). (Part of Decimate.cpp's translation unit; the map of the
// passes: Passes.h.)
//
// The quadrics place a merged vertex where its squared distance to the input's planes is least.
// Between the vertices the output's faces are flat, so where the input is curved a face lies on
// one side of it, and the distance is largest in the face's middle. The fit moves each merged
// vertex along its normal by t so that the faces pass through a sample of the input's vertices
// in the least-squares sense: a sample p, nearest to the point q = sum_c b_c x_c of a face of
// the vertex that stands for it, with the face's unit normal n, has the residual
// n.(q - p) + sum_c b_c (n.m_c) t_c. The normal equations, damped (kFitDamping times their
// diagonal, for vertices with few samples), are solved by a few steps of conjugate gradients
// with a diagonal preconditioner. Measured (docs/benchmarks.md): RMS and Hausdorff distance to
// the input both lower, Lucy-size to 10K by 13%.
//
// Samples: every stride-th vertex of the input that has faces (kFitSamplesPerVertex per vertex
// of the finest level's estimated output), in a DML block; Compact follows each sample to the
// vertex that stands for it (a collapsed vertex's candidate names its survivor). The fit is
// one thread and deterministic, so the output does not depend on threads or storage mode.
namespace sipmss::algorithms
{
namespace
{
constexpr double kFitSamplesPerVertex = 16;
constexpr double kFitDamping = 0.25;
constexpr int kFitIterations = 6;

// One sample's row of the least-squares system: its face's corners, their coefficients and the
// residual at t = 0.
struct FitRow
{
  std::uint32_t v[3];
  float j[3];
  float r;
};
// A vertex of the fit: its normal (0: it does not move), the normal equations' diagonal and
// right-hand side, and the conjugate gradients' vectors.
struct FitVertex
{
  Vec3 m;
  double d, g, t, r, p, q;
};

// The vertices that may move: merged by a collapse, not fixed.
inline bool Movable(State s)
{
  return (s & kMerged) && !(s & kFixed);
}

void SampleInput(RunContext& ctx, MeshState& mesh, const std::vector<std::uint64_t>& levels)
{
  mesh.nSamples = 0;
  const bool exported = bool(ctx.opt.finalSamples);
  if ((!ctx.opt.fitSurface && !exported) || mesh.nv == 0 || levels.empty() ||
    (levels.back() >= mesh.liveFaces && !exported))
  {
    return; // (no fit, or no collapse will be made)
  }
  if (ctx.opt.initialSamples)
  {
    // The caller's samples, each with its input vertex (kNone when that has no faces).
    mesh.samples = Array<FitSample>(mesh.dml, 1024);
    mesh.BindViews();
    std::uint64_t n = 0;
    ctx.opt.initialSamples([&](const double p[3], std::uint64_t v) {
      if ((n & 4095) == 0)
      {
        ctx.progress.Poll();
      }
      if (n == mesh.samples.Size())
      {
        mesh.samples.Resize(2 * n);
        mesh.BindViews();
      }
      const bool faces = v < mesh.nv && RingLength(mesh.views, std::uint32_t(v)) > 0;
      const FitSample s = { { float(p[0] - mesh.origin.x), float(p[1] - mesh.origin.y),
                              float(p[2] - mesh.origin.z) },
        faces ? std::uint32_t(v) : kNone };
      mesh.samples.Write(n++, 1, &s);
    });
    mesh.nSamples = n;
    mesh.samples.Resize(std::max<std::uint64_t>(n, 1));
    mesh.BindViews();
    return;
  }
  // The finest level's output, about half as many vertices as triangles (a bound alone: unknown,
  // every second vertex).
  const std::uint64_t sized = ctx.opt.fitSampleTriangles ? ctx.opt.fitSampleTriangles : levels.front();
  const double outV = std::max(1.0, double(sized ? sized : mesh.liveFaces) / 2);
  const std::uint64_t stride = std::max<std::uint64_t>(
    2, std::uint64_t(double(mesh.nv) / (kFitSamplesPerVertex * outV)));
  const std::uint64_t cap = (mesh.nv + stride - 1) / stride;
  mesh.samples = Array<FitSample>(mesh.dml, std::max<std::uint64_t>(cap, 1));
  View<FitSample> out(mesh.dml, mesh.samples);
  mesh.BindViews();
  std::uint64_t n = 0;
  for (std::uint64_t v = 0; v < mesh.nv; v += stride)
  {
    if ((v & 4095) < stride)
    {
      ctx.progress.Poll();
    }
    if (RingLength(mesh.views, std::uint32_t(v)) == 0)
    {
      continue;
    }
    const Vec3 p = mesh.views.P.Get(v);
    out.Set(n++, { { float(p.x), float(p.y), float(p.z) }, std::uint32_t(v) });
  }
  mesh.nSamples = n;
  mesh.samples.Resize(std::max<std::uint64_t>(n, 1));
  mesh.BindViews();
}

// Compact, once R holds the new numbers (top bit: a survivor) and before anything moves: each
// sample's vertex becomes its new number, or, when it was removed, its survivor's.
void TrackSamples(MeshState& mesh, const View<std::uint32_t>& R)
{
  if (mesh.nSamples == 0)
  {
    return;
  }
  constexpr std::uint32_t kTop = 0x80000000u;
  View<FitSample> S(mesh.dml, mesh.samples);
  for (std::uint64_t i = 0; i < mesh.nSamples; ++i)
  {
    FitSample s = S.Get(i);
    if (s.owner == kNone)
    {
      continue;
    }
    std::uint32_t r = R.Get(s.owner);
    if (r == kNone && (mesh.views.S.Get(s.owner) & kRemoved))
    {
      const std::uint32_t u = mesh.views.C.Get(s.owner).partner; // (Collapse: the survivor)
      r = u == kNone ? kNone : R.Get(u);
    }
    const std::uint32_t owner = r == kNone ? kNone : (r & ~kTop);
    if (owner != s.owner)
    {
      s.owner = owner;
      S.Set(i, s);
    }
  }
}

// The samples with the output vertices that stand for them (DecimateOptions::finalSamples).
void ExportSamples(RunContext& ctx, MeshState& mesh)
{
  if (!ctx.opt.finalSamples)
  {
    return;
  }
  // (copied out a chunk at a time: the callback may grow a block of the same DML, which can move
  // it out of core, so no view is held across it)
  constexpr std::size_t kRun = 1 << 12;
  std::vector<FitSample> run(kRun);
  for (std::uint64_t first = 0; first < mesh.nSamples; first += kRun)
  {
    ctx.progress.Poll();
    const std::size_t n = std::size_t(std::min<std::uint64_t>(kRun, mesh.nSamples - first));
    mesh.samples.Read(first, n, run.data());
    for (std::size_t i = 0; i < n; ++i)
    {
      const FitSample& s = run[i];
      if (s.owner != kNone)
      {
        const double p[3] = { double(s.p[0]) + mesh.origin.x, double(s.p[1]) + mesh.origin.y,
          double(s.p[2]) + mesh.origin.z };
        ctx.opt.finalSamples(p, s.owner);
      }
    }
  }
  mesh.BindViews();
}

void Fit(RunContext& ctx, MeshState& mesh)
{
  if (mesh.nSamples == 0 || mesh.nv == 0 || !ctx.opt.fitSurface)
  {
    mesh.fittedValid = false;
    return;
  }
  if (mesh.fittedValid)
  {
    return; // (the last level, written again as the final output; Compact clears it)
  }
  const std::uint64_t nv = mesh.nv;
  mesh.fittedValid = false; // (until the new positions are all written)
#if defined(__GLIBC__)
  // The passes' freed memory (the page cache's buffers when the run moved in core, the rings'
  // scratch) stays in the heap's arenas, resident; the fit's blocks would come on top of it.
  ::malloc_trim(0);
#endif
  // (every block opens before any view is bound: opening one may move the DML out of core)
  Array<FitVertex> vertsBlock(mesh.dml, nv);
  Array<FitRow> rowsBlock(mesh.dml, std::max<std::uint64_t>(mesh.nSamples, 1));
  mesh.fitted = Array<Vec3>(mesh.dml, nv);
  mesh.BindViews();
  Views& w = mesh.views;
  View<FitVertex> V(mesh.dml, vertsBlock);
  View<FitRow> rows(mesh.dml, rowsBlock);
  View<FitSample> samples(mesh.dml, mesh.samples);
  View<Vec3> out(mesh.dml, mesh.fitted);
  auto poll = [&ctx](std::uint64_t i) {
    if ((i & 4095) == 0)
    {
      ctx.progress.Poll();
    }
  };
  // 1. The movable vertices' normals: their faces' area-weighted normals; and the largest
  // geometric error of a vertex (its quadric's per unit of trace: with attributes, the
  // achieved error counts theirs too), which no move may exceed.
  bool any = false;
  double largest = 0;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    poll(v);
    FitVertex x{};
    {
      const Quadric Q = w.Q.Get(v);
      const Vec3 p = w.P.Get(v);
      const double trace = Trace(Q);
      if (trace > 0)
      {
        largest = std::max(largest, QuadricValue(Q.q, p.x, p.y, p.z) / trace);
      }
    }
    if (Movable(w.S.Get(v)))
    {
      Vec3 sum{ 0, 0, 0 };
      for (std::uint32_t k = w.RO.Get(v), e = w.RO.Get(v + 1); k < e; ++k)
      {
        const Tri t = w.F.Get(w.RF.Get(k));
        const Vec3 a = w.P.Get(t.v[0]), b = w.P.Get(t.v[1]), c = w.P.Get(t.v[2]);
        sum = sum + Cross(b - a, c - a);
      }
      const double l = std::sqrt(Dot(sum, sum));
      if (l > 0 && std::isfinite(l))
      {
        x.m = (1.0 / l) * sum;
        any = true;
      }
    }
    V.Set(v, x);
  }
  if (!any)
  {
    mesh.fittedValid = false;
    mesh.fitted = Array<Vec3>();
    mesh.BindViews();
    return;
  }
  // 2. Each sample's row: the nearest point of the faces of the vertex that stands for it.
  std::uint64_t nRows = 0;
  for (std::uint64_t i = 0; i < mesh.nSamples; ++i)
  {
    poll(i);
    const FitSample s = samples.Get(i);
    if (s.owner == kNone || s.owner >= nv)
    {
      continue;
    }
    const Vec3 p{ s.p[0], s.p[1], s.p[2] };
    double best = std::numeric_limits<double>::infinity();
    Tri bt{};
    std::array<double, 3> bb{};
    Vec3 bc[3], bd{ 0, 0, 0 }; // (the nearest face's corners, the nearest point minus p)
    for (std::uint32_t k = w.RO.Get(s.owner), e = w.RO.Get(s.owner + 1); k < e; ++k)
    {
      const Tri t = w.F.Get(w.RF.Get(k));
      const Vec3 c[3] = { w.P.Get(t.v[0]), w.P.Get(t.v[1]), w.P.Get(t.v[2]) };
      const std::array<double, 3> bw = ClosestPointBarycentric(p, c[0], c[1], c[2]);
      const Vec3 dq = bw[0] * c[0] + bw[1] * c[1] + bw[2] * c[2] - p;
      const double d2 = Dot(dq, dq);
      if (d2 < best)
      {
        best = d2;
        bt = t;
        bb = bw;
        bd = dq;
        bc[0] = c[0], bc[1] = c[1], bc[2] = c[2];
      }
    }
    if (!(best < std::numeric_limits<double>::infinity()))
    {
      continue;
    }
    const Vec3 n0 = Cross(bc[1] - bc[0], bc[2] - bc[0]);
    const double l = std::sqrt(Dot(n0, n0));
    if (!(l > 0) || !std::isfinite(l))
    {
      continue;
    }
    const Vec3 n = (1.0 / l) * n0;
    FitRow row;
    row.r = float(Dot(n, bd));
    bool moves = false;
    for (int c = 0; c < 3; ++c)
    {
      row.v[c] = bt.v[c];
      const FitVertex x = V.Get(bt.v[c]);
      row.j[c] = float(bb[c] * Dot(n, x.m));
      moves |= row.j[c] != 0.0f;
    }
    if (!moves)
    {
      continue;
    }
    for (int c = 0; c < 3; ++c)
    {
      if (row.j[c] != 0.0f)
      {
        FitVertex x = V.Get(row.v[c]);
        x.d += double(row.j[c]) * double(row.j[c]);
        x.g -= double(row.j[c]) * double(row.r);
        V.Set(row.v[c], x);
      }
    }
    rows.Set(nRows++, row);
  }
  // 3. Conjugate gradients on (J^T J + kFitDamping diag) t = -J^T r, from t = 0, with the
  // diagonal as preconditioner: r = g, p = z = r / M.
  auto precond = [](const FitVertex& x) { return (1.0 + kFitDamping) * x.d; };
  double rz = 0;
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    poll(v);
    FitVertex x = V.Get(v);
    if (x.d > 0)
    {
      x.r = x.g;
      x.p = x.r / precond(x);
      rz += x.r * x.p;
      V.Set(v, x);
    }
  }
  for (int it = 0; it < kFitIterations && rz > 0; ++it)
  {
    // q = A p
    for (std::uint64_t v = 0; v < nv; ++v)
    {
      poll(v);
      FitVertex x = V.Get(v);
      if (x.d > 0)
      {
        x.q = kFitDamping * x.d * x.p;
        V.Set(v, x);
      }
    }
    for (std::uint64_t i = 0; i < nRows; ++i)
    {
      poll(i);
      const FitRow row = rows.Get(i);
      double jp = 0;
      for (int c = 0; c < 3; ++c)
      {
        if (row.j[c] != 0.0f)
        {
          jp += double(row.j[c]) * V.Get(row.v[c]).p;
        }
      }
      for (int c = 0; c < 3; ++c)
      {
        if (row.j[c] != 0.0f)
        {
          FitVertex y = V.Get(row.v[c]); // (corners may repeat in a degenerate face)
          y.q += double(row.j[c]) * jp;
          V.Set(row.v[c], y);
        }
      }
    }
    double pq = 0;
    for (std::uint64_t v = 0; v < nv; ++v)
    {
      poll(v);
      const FitVertex x = V.Get(v);
      if (x.d > 0)
      {
        pq += x.p * x.q;
      }
    }
    if (!(pq > 0))
    {
      break;
    }
    const double alpha = rz / pq;
    double rz2 = 0;
    for (std::uint64_t v = 0; v < nv; ++v)
    {
      poll(v);
      FitVertex x = V.Get(v);
      if (x.d > 0)
      {
        x.t += alpha * x.p;
        x.r -= alpha * x.q;
        rz2 += x.r * x.r / precond(x);
        V.Set(v, x);
      }
    }
    const double beta = rz2 / rz;
    rz = rz2;
    for (std::uint64_t v = 0; v < nv; ++v)
    {
      poll(v);
      FitVertex x = V.Get(v);
      if (x.d > 0)
      {
        x.p = x.r / precond(x) + beta * x.p;
        V.Set(v, x);
      }
    }
  }
  // 4. The fitted positions. A move that would raise the vertex's quadric error (per unit of
  // its trace) above the larger of the largest vertex's and its own is halved up to four times,
  // else not made.
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    poll(v);
    const FitVertex x = V.Get(v);
    const Vec3 p = w.P.Get(v);
    Vec3 fitted = p;
    const Quadric Q = w.Q.Get(v);
    const double trace = Trace(Q);
    if (x.d > 0 && x.t != 0 && std::isfinite(x.t) && trace > 0) // (no quadric: no limit, no move)
    {
      const double limit = std::max(
        std::min(ctx.achievedErr2, largest) * trace, QuadricValue(Q.q, p.x, p.y, p.z));
      double t = x.t;
      for (int halve = 0; halve <= 4; ++halve, t *= 0.5)
      {
        const Vec3 y = p + t * x.m;
        if (QuadricValue(Q.q, y.x, y.y, y.z) <= limit)
        {
          fitted = y;
          break;
        }
      }
    }
    out.Set(v, fitted);
  }
  mesh.fittedValid = true;
  // (the fit's blocks close here)
}

} // namespace
} // namespace sipmss::algorithms
