// Algorithm I: pruning the small disconnected pieces of the input (DecimateOptions::pruneSize).
// Part of Decimate.cpp's translation unit (decimate/Passes.h says why).

namespace sipmss::algorithms
{
namespace
{
// A component's bounds and flags, kept at its root vertex.
struct PruneBox
{
  Float3 lo, hi;
  std::uint32_t flags; // kPruneFixed, kPruneCounted
  std::uint32_t pad;
};
static_assert(sizeof(PruneBox) == 32, "PruneBox layout");
constexpr std::uint32_t kPruneFixed = 1;   // holds a vertex that must stay (lock, selection)
constexpr std::uint32_t kPruneCounted = 2; // counted among the pruned components

// The root of x in the union-find forest (path halving).
std::uint32_t PruneRoot(View<std::uint32_t>& parent, std::uint32_t x)
{
  std::uint32_t p = parent.Get(x);
  while (p != x)
  {
    const std::uint32_t g = parent.Get(p);
    if (g != p)
    {
      parent.Set(x, g);
    }
    x = p;
    p = g;
  }
  return x;
}

// Removes every connected component (vertices joined by live faces) whose bounding box has a
// diagonal below pruneSize times the input's, unless it holds a locked vertex or one outside
// the selection. Its faces die here, before the quadrics, so the rest of the run never sees
// them (and compaction drops their vertices). Union-find over the faces in a vertex array of
// the DML, then the bounds at the roots, then the faces: three sequential passes and the
// lookups of the roots, within the budget; the same result in every mode.
void Prune(RunContext& ctx, MeshState& mesh)
{
  PhaseTimer timer(ctx.stats, mesh.dml, "prune");
  const std::uint64_t nv = mesh.nv, nf = mesh.nf;
  ctx.progress.BeginPhase("prune", kWork::kPrune * double(nf + nv),
    kWork::kQuadrics * double(mesh.liveFaces) + RestWork(ctx, mesh, 3, nv, mesh.liveFaces));
  const std::uint64_t total = 3 * nf + 2 * nv;
  Array<std::uint32_t> parentArray(mesh.dml, std::max<std::uint64_t>(nv, 1));
  Array<PruneBox> boxArray(mesh.dml, std::max<std::uint64_t>(nv, 1));
  View<std::uint32_t> parent(mesh.dml, parentArray);
  View<PruneBox> box(mesh.dml, boxArray);
  View<Tri> F(mesh.dml, mesh.faces);
  View<Vec3> P(mesh.dml, mesh.pos);
  View<std::uint8_t> A(mesh.dml, mesh.attr);
  const bool arrays = mesh.lockFloat >= 0 || mesh.selectFloat >= 0;
  View<std::uint8_t> outside;
  if (mesh.faceSelect)
  {
    outside = View<std::uint8_t>(mesh.dml, mesh.outside);
  }
  // 1. The components: each face joins its corners' trees (the lower root stays the root).
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    parent.Set(v, std::uint32_t(v));
  }
  for (std::uint64_t f = 0; f < nf; ++f)
  {
    ctx.Tick(f, total);
    const Tri t = F.Get(f);
    if (!Alive(t))
    {
      continue;
    }
    std::uint32_t r = PruneRoot(parent, t.v[0]);
    for (int k = 1; k < 3; ++k)
    {
      const std::uint32_t s = PruneRoot(parent, t.v[k]);
      if (s != r)
      {
        parent.Set(std::max(r, s), std::min(r, s));
        r = std::min(r, s);
      }
    }
  }
  // 2. Each component's bounds (and whether it must stay), at its root.
  const float inf = std::numeric_limits<float>::infinity();
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    box.Set(v, PruneBox{ { inf, inf, inf }, { -inf, -inf, -inf }, 0, 0 });
  }
  for (std::uint64_t v = 0; v < nv; ++v)
  {
    ctx.Tick(nf + v, total);
    const std::uint32_t r = PruneRoot(parent, std::uint32_t(v));
    PruneBox b = box.Get(r);
    const Vec3 p = P.Get(v);
    const Float3 q = { float(p.x), float(p.y), float(p.z) };
    b.lo = { std::min(b.lo.x, q.x), std::min(b.lo.y, q.y), std::min(b.lo.z, q.z) };
    b.hi = { std::max(b.hi.x, q.x), std::max(b.hi.y, q.y), std::max(b.hi.z, q.z) };
    if ((arrays && FixedByArrays(mesh, A, std::uint32_t(v))) ||
      (mesh.faceSelect && outside.Get(v) != 0))
    {
      b.flags |= kPruneFixed;
    }
    box.Set(r, b);
  }
  // 3. The faces of the small components die.
  const double size = ctx.opt.pruneSize * ctx.diagonal;
  std::uint64_t faces = 0, components = 0;
  for (std::uint64_t f = 0; f < nf; ++f)
  {
    ctx.Tick(nf + nv + f, total);
    const Tri t = F.Get(f);
    if (!Alive(t))
    {
      continue;
    }
    const std::uint32_t r = PruneRoot(parent, t.v[0]);
    PruneBox b = box.Get(r);
    if (b.flags & kPruneFixed)
    {
      continue;
    }
    const Vec3 d = { double(b.hi.x) - b.lo.x, double(b.hi.y) - b.lo.y, double(b.hi.z) - b.lo.z };
    if (Dot(d, d) >= size * size)
    {
      continue;
    }
    F.Set(f, kDeadTri);
    ++faces;
    if (!(b.flags & kPruneCounted))
    {
      b.flags |= kPruneCounted;
      box.Set(r, b);
      ++components;
    }
  }
  mesh.liveFaces -= faces;
  ctx.stats.prunedComponents += components;
  ctx.stats.prunedTriangles += faces;
}
} // namespace
} // namespace sipmss::algorithms
