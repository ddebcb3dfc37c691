// Algorithm I: compaction after a pass, and the output.
// (Part of Decimate.cpp's translation unit; the map of the passes: Decimator.h.)
namespace sipmss::algorithms
{
namespace
{
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
  // On several threads (Workers): the degrees (CountDegrees), the rings by vertex range (each
  // thread scans all faces and writes only its own vertices), the moves (in place, downwards)
  // one array group per thread. Same result either way.
  // 1. Degrees of the live faces, counted in the old ring offsets (the rings are done with);
  // the candidate order is free until the next pass: CountDegrees' second counter array.
  FillBlock(this->dml_, this->ringOff_, std::uint32_t(0));
  this->CountDegrees(nf, kParallelCompactMin, 0, total, &this->order_);
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
  // (S, C, R: access of either kind, see WithAccess)
  auto carry = [this, kTop](const auto& S, const auto& C, const auto& R, std::uint64_t v,
                 State& flags, Cand& c) {
    const State sv = S.Get(v);
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
      c = C.Get(v);
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
  // 4. Faces, ascending: new index f2 <= f (they read only R and the faces).
  auto moveFaces = [&](Views& wv, const View<std::uint32_t>& RR, bool tick) {
    for (std::uint64_t f = 0; f < nf; ++f)
    {
      if (tick)
      {
        this->Tick(nf + 2 * nv + f, total);
      }
      Tri t = wv.F.Get(f);
      if (!Alive(t))
      {
        continue;
      }
      for (int c = 0; c < 3; ++c)
      {
        t.v[c] = RR.Get(t.v[c]) & ~kTop;
      }
      wv.F.Set(f2++, t);
    }
  };
  // The quadrics, in place and downwards.
  auto moveQuadrics = [&](Views& wv, const View<std::uint32_t>& RR, bool tick, bool poll) {
    WithAccess(
      [&](auto Q, auto RA) {
        for (std::uint64_t v = 0; v < nv; ++v)
        {
          if (tick)
          {
            this->Tick(nf + nv + v, total);
          }
          else if (poll && (v & 4095) == 0)
          {
            this->progress_.Poll();
          }
          const std::uint32_t rv = RA.Get(v);
          const std::uint64_t w = rv & ~kTop;
          if (rv != kNone && w != v)
          {
            Q.Set(w, Q.Get(v));
          }
        }
      },
      wv.Q, RR);
  };
  // The states and candidates (carried), the positions and the point data, in place and
  // downwards (carry reads only the vertex's own records and R).
  auto moveRest = [&](Views& wv, const View<std::uint32_t>& RR, bool tick) {
    std::vector<std::uint8_t> buf(rec);
    WithAccess(
      [&](auto S, auto C, auto P, auto A, auto RA) {
        for (std::uint64_t v = 0; v < nv; ++v)
        {
          if (tick)
          {
            this->Tick(nf + nv + v, total);
          }
          const std::uint32_t rv = RA.Get(v);
          if (rv == kNone)
          {
            continue;
          }
          const std::uint64_t w = rv & ~kTop;
          State flags;
          Cand c;
          carry(S, C, RA, v, flags, c); // (reads v's records: not in place)
          S.Set(w, flags);
          C.Set(w, c);
          if (w != v)
          {
            P.Set(w, P.Get(v));
            if (rec)
            {
              A.GetRange(v * rec, rec, buf.data());
              A.SetRange(w * rec, rec, buf.data());
            }
          }
        }
      },
      wv.S, wv.C, wv.P, wv.A, RR);
  };
  // The arrays are independent: on two threads one moves the quadrics and then the faces, the
  // other carries and moves the rest (memory-bound: one thread per stream; out of core the
  // second through a forked DML).
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = std::min(this->threads_, 2);
  phase.inCoreMin = kParallelCompactMin;
  phase.helperFirst = 0; // (the second task writes every vertex of its blocks)
  phase.writes = { this->state_.Id(), this->cand_.Id(), this->pos_.Id() };
  if (rec)
  {
    phase.helperWrites.push_back({ this->attr_.Id(), 0, nv * rec });
  }
  phase.mainWrites = { this->quad_.Id(), this->faces_.Id() };
  Workers workers(this->dml_, phase);
  // (Progress: on one thread the quadrics only poll, the rest ticks, then the faces.)
  const bool split = workers.Count() > 1;
  workers.RunTasks(2, [&](int t, int task, const std::atomic<bool>&) {
    Views wv;
    this->BindViews(wv, workers, t);
    const View<std::uint32_t> RR = workers.Bind(t, this->remap_);
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
    this->BindViews();
    moveFaces(this->v_, R, true);
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

} // namespace
} // namespace sipmss::algorithms
