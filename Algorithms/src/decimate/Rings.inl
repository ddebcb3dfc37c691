// Algorithm I: the vertex rings (face lists per vertex) and the quadrics.
// (Part of Decimate.cpp's translation unit; the map of the passes: Passes.h.)
namespace sipmss::algorithms
{
namespace
{
// ---------------------------------------------------------------------------------------------
// rings

// Faces are read by runs of kFaceRun (the accessors' Run: in place in core, else one table lookup
// per run and page instead of one per face).
constexpr std::uint64_t kFaceRun = 256;

// Adds the live faces [0, nf) to the degrees in the ring offsets (zero before), on the workers
// of a phase over the vertices (from parallelMin vertices in core): each worker scans every face
// and counts only its own vertices (no atomics; a worker never writes another's counter, not
// even adding zero). With a `spare` block of nv counters and workers that share memory, two of
// them count half of the faces each instead, the second into `spare`, which is then added.
void CountDegrees(RunContext& ctx, MeshState& mesh, std::uint64_t nf, std::uint64_t parallelMin,
  std::uint64_t tickBase, std::uint64_t tickTotal, const Array<std::uint32_t>* spare)
{
  mesh.BindViews();
  const std::uint64_t nv = mesh.nv;
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
      ctx.progress.Tick(double(tickBase + f) / double(tickTotal));
    }
    return true;
  };
  if (spare)
  {
    storage::Phase halves;
    halves.elements = nv;
    halves.threads = std::min(ctx.threads, 2);
    halves.inCoreMin = parallelMin;
    halves.helper = false;
    halves.helperFirst = 0; // (worker 1 writes all of the spare counters)
    halves.writes = { spare->Id() };
    halves.mainWrites = { mesh.ringOff.Id() };
    Workers workers(mesh.dml, halves);
    if (workers.Shared())
    {
      workers.RunTasks(2, [&](int t, int task, const std::atomic<bool>& stop) {
        const View<Tri> F = workers.Bind(t, mesh.faces);
        const View<std::uint32_t> counts =
          workers.Bind(t, task == 0 ? mesh.ringOff : *spare);
        WithAccess(
          [&](auto Fa, auto Ca) {
            if (task == 1)
            {
              for (std::uint64_t v = 0; v < nv; ++v)
              {
                Ca.Set(v, 0u);
              }
            }
            std::vector<Tri> buf(kFaceRun);
            const std::uint64_t fEnd = task == 0 ? nf / 2 : nf;
            for (std::uint64_t f0 = task == 0 ? 0 : nf / 2; f0 < fEnd; f0 += kFaceRun)
            {
              const std::size_t n = std::size_t(std::min(kFaceRun, fEnd - f0));
              const Tri* run = Fa.Run(f0, n, buf);
              for (std::size_t j = 0; j < n; ++j)
              {
                if (!tick(t, f0 + j, stop))
                {
                  return;
                }
                const Tri& t3 = run[j];
                if (Alive(t3))
                {
                  for (int c = 0; c < 3; ++c)
                  {
                    Ca.Set(t3.v[c], Ca.Get(t3.v[c]) + 1);
                  }
                }
              }
            }
          },
          F, counts);
      });
      // The sum, by vertex range on the same threads.
      storage::Phase add;
      add.elements = nv;
      add.threads = halves.threads;
      add.helper = false;
      add.writes = { mesh.ringOff.Id() };
      Workers adders(mesh.dml, add);
      adders.Run([&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>&) {
        WithAccess(
          [&](auto ROa, auto Ea) {
            for (std::uint64_t v = lo; v < hi; ++v)
            {
              ROa.Set(v, ROa.Get(v) + Ea.Get(v));
            }
          },
          adders.Bind(t, mesh.ringOff), adders.Bind(t, *spare));
      });
      return;
    }
  }
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = ctx.threads;
  phase.inCoreMin = parallelMin;
  phase.writes = { mesh.ringOff.Id() };
  Workers workers(mesh.dml, phase);
  workers.Run([&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
    const View<Tri> F = workers.Bind(t, mesh.faces);
    const View<std::uint32_t> RO = workers.Bind(t, mesh.ringOff);
    WithAccess(
      [&](auto Fa, auto ROa) {
        std::vector<Tri> buf(kFaceRun);
        for (std::uint64_t f0 = 0; f0 < nf; f0 += kFaceRun)
        {
          const std::size_t n = std::size_t(std::min(kFaceRun, nf - f0));
          const Tri* run = Fa.Run(f0, n, buf);
          for (std::size_t j = 0; j < n; ++j)
          {
            if (!tick(t, f0 + j, stop))
            {
              return;
            }
            const Tri& t3 = run[j];
            if (Alive(t3))
            {
              for (int c = 0; c < 3; ++c)
              {
                const std::uint32_t x = t3.v[c];
                if (x >= lo && x < hi)
                {
                  ROa.Set(x, ROa.Get(x) + 1);
                }
              }
            }
          }
        }
      },
      F, RO);
  });
}

// Fills the incident face lists of faces [0, nf) (dead ones skipped) from the ring offsets, which
// hold the end of each list: faces in reverse, so each list ends up in increasing face order and
// RO[v] at its start. In core on all cores, each thread owns a range of vertices and scans every
// face (the reads are sequential, the writes it splits are not): the same lists.
void FillRings(RunContext& ctx, MeshState& mesh, std::uint64_t nf, std::uint64_t tickBase,
  std::uint64_t tickTotal)
{
  const std::uint64_t nv = mesh.nv;
  // Out of core: the upper half of the vertices (their offsets and lists) on a helper thread
  // through a forked DML.
  const std::uint64_t mid = nv / 2;
  const std::uint64_t rfBegin = mid > 0 ? mesh.views.RO.Get(mid - 1) : 0;
  const std::uint64_t rfEnd = mid > 0 ? mesh.views.RO.Get(nv) : 0;
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = ctx.threads;
  phase.inCoreThreads = nf >= kParallelRingsMin;
  phase.helper = rfBegin < rfEnd;
  phase.writes = { mesh.ringOff.Id() };
  phase.helperWrites = { { mesh.ringFace.Id(), rfBegin, rfEnd - rfBegin } };
  Workers workers(mesh.dml, phase);
  workers.Run([&](int th, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
    const View<Tri> F = workers.Bind(th, mesh.faces);
    const View<std::uint32_t> RO = workers.Bind(th, mesh.ringOff);
    const View<std::uint32_t> RF = workers.Bind(th, mesh.ringFace);
    WithAccess(
      [&](auto Fa, auto ROa, auto RFa) {
        std::vector<Tri> buf(kFaceRun);
        for (std::uint64_t f1 = nf; f1 > 0;)
        {
          const std::size_t n = std::size_t(std::min(kFaceRun, f1));
          const std::uint64_t f0 = f1 - n;
          const Tri* run = Fa.Run(f0, n, buf);
          for (std::size_t j = n; j-- > 0;)
          {
            const std::uint64_t i = f0 + j;
            if ((i & 4095) == 0)
            {
              if (stop.load(std::memory_order_relaxed))
              {
                return;
              }
              if (th == 0 && tickTotal)
              {
                // (strided: Tick's own 1-in-1024 filter would miss; abort is checked here too)
                ctx.progress.Tick(double(tickBase + (nf - i)) / double(tickTotal));
              }
            }
            const Tri& t = run[j];
            if (!Alive(t))
            {
              continue;
            }
            for (int k = 0; k < 3; ++k)
            {
              const std::uint32_t x = t.v[k];
              if (x >= lo && x < hi)
              {
                const std::uint32_t e = ROa.Get(x) - 1;
                ROa.Set(x, e);
                RFa.Set(e, std::uint32_t(i));
              }
            }
          }
          f1 = f0;
        }
      },
      F, RO, RF);
  });
}

void BuildRings(RunContext& ctx, MeshState& mesh)
{
  PhaseTimer timer(ctx.stats, mesh.dml, "rings");
  ctx.progress.BeginPhase(
    "rings", kWork::kRings * double(mesh.nf), RestWork(ctx, mesh, 2, mesh.nv, mesh.nf));
  const std::uint64_t nv = mesh.nv, nf = mesh.nf;
  if (3 * nf >= kNone)
  {
    throw std::runtime_error("decimate: more than 1.4 billion triangles");
  }
  mesh.ringOff = Array<std::uint32_t>(mesh.dml, nv + 1);
  FillBlock(mesh.dml, mesh.ringOff, std::uint32_t(0));
  View<Tri> F(mesh.dml, mesh.faces);
  View<Vec3> P(mesh.dml, mesh.pos);
  View<std::uint32_t> RO(mesh.dml, mesh.ringOff);
  // Passes 1 and 3 run on the workers of a phase (each on its own faces), the degrees and
  // pass 2 by vertex range (CountDegrees, FillRings); same result.
  // Pass 1 over the faces: validate, drop zero-area faces, count the degrees. The first bad
  // face is reported, whatever the threads. On several workers the degrees are counted after
  // (CountDegrees).
  std::uint64_t live = 0;
  {
    storage::Phase phase;
    phase.elements = nf;
    phase.threads = ctx.threads;
    phase.inCoreThreads = nf >= kParallelRingsMin;
    phase.writes = { mesh.faces.Id() };
    Workers workers(mesh.dml, phase);
    const int T1 = workers.Count();
    std::vector<std::uint64_t> lives(std::size_t(T1), 0), drops(std::size_t(T1), 0);
    std::vector<std::uint64_t> bad(std::size_t(T1), ~std::uint64_t(0));
    auto pass1 = [&](int th, std::uint64_t fb, std::uint64_t fe, const std::atomic<bool>& stop) {
      View<Tri> Fv = workers.Bind(th, mesh.faces);
      const View<Vec3> Pv = workers.Bind(th, mesh.pos);
      // (counted here, stored at the end: the threads' counters share a cache line)
      std::uint64_t liveHere = 0, dropsHere = 0;
      for (std::uint64_t f = fb; f < fe && !stop.load(std::memory_order_relaxed); ++f)
      {
        if (th == 0 && ((f - fb) & 1023) == 0)
        {
          ctx.progress.Tick(double((f - fb) * T1) / double(4 * nf));
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
          ++dropsHere;
          continue;
        }
        if (T1 <= 1)
        {
          for (int k = 0; k < 3; ++k)
          {
            RO.Set(t.v[k], RO.Get(t.v[k]) + 1);
          }
        }
        ++liveHere;
      }
      lives[std::size_t(th)] += liveHere; // (+=: a fallback range runs as worker 0 again)
      drops[std::size_t(th)] += dropsHere;
    };
    workers.Run(pass1);
    F.Refresh();
    P.Refresh();
    RO.Refresh();
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
      mesh.dropped += drops[std::size_t(th)];
    }
    if (T1 > 1)
    {
      CountDegrees(ctx, mesh, nf, 0, nf, 4 * nf);
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
  mesh.ringFace = Array<std::uint32_t>(mesh.dml, std::max<std::uint32_t>(sum, 1));
  F.Refresh();
  P.Refresh();
  RO.Refresh();
  View<std::uint32_t> RF(mesh.dml, mesh.ringFace);
  // Pass 2: the incident face lists.
  mesh.BindViews();
  FillRings(ctx, mesh, nf, 2 * nf, 4 * nf);
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
  storage::Phase phase3;
  phase3.elements = nv;
  phase3.threads = ctx.threads;
  phase3.inCoreThreads = nf >= kParallelRingsMin;
  Workers workers3(mesh.dml, phase3);
  const int T3 = workers3.Count();
  std::vector<std::vector<std::uint64_t>> found(static_cast<std::size_t>(T3));
  auto pass3 = [&](int th, std::uint64_t vb, std::uint64_t ve, const std::atomic<bool>& stop) {
    const View<Tri> Fv = workers3.Bind(th, mesh.faces);
    const View<std::uint32_t> ROv = workers3.Bind(th, mesh.ringOff);
    const View<std::uint32_t> RFv = workers3.Bind(th, mesh.ringFace);
    std::vector<std::uint32_t> list;
    std::vector<std::pair<std::uint64_t, std::uint32_t>> keyed; // (other two vertices, face)
    std::uint64_t work = 0; // ring entries since the last poll
    for (std::uint64_t x = vb; x < ve && !stop.load(std::memory_order_relaxed); ++x)
    {
      if (th == 0 && work >= 4096)
      {
        work = 0;
        ctx.progress.Tick(double(3 * nf) / double(4 * nf) +
          double((x - vb) * std::uint64_t(T3)) / double(4 * std::max<std::uint64_t>(nv, 1)));
      }
      const std::uint32_t b = ROv.Get(x), e = ROv.Get(x + 1);
      work += 1 + (e - b);
      if (e - b < 2)
      {
        continue;
      }
      const std::uint32_t* faceIds = RFv.Run(b, e - b, list);
      keyed.clear();
      for (std::uint32_t k = 0; k < e - b; ++k)
      {
        if ((k & 4095) == 4095)
        {
          if (th == 0)
          {
            ctx.progress.Poll(); // (a vertex of very high valence)
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
  workers3.Run(pass3, [&]() { ctx.progress.Poll(); });
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
      ctx.progress.Tick(1.0);
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
      ++mesh.dropped;
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
      ++mesh.dropped;
      --live;
    }
  }
  mesh.liveFaces = live;
}

// ---------------------------------------------------------------------------------------------
// rings of single vertices

void MeshState::BindViews()
{
  this->BindViews(this->views, this->dml);
}

// (bind(array) makes one view; blocks not open, or attributes absent, get an unbound one)
template <class Bind>
void BindEach(Views& w, const Bind& bind, const Array<Vec3>& pos, const Array<Quadric>& quad,
  const Array<std::uint8_t>& attr, bool attributes, const Array<double>& extra,
  const Array<State>& state,
  const Array<Tri>& faces, const Array<std::uint32_t>& ringOff,
  const Array<std::uint32_t>& ringFace, const Array<Cand>& cand, const Array<std::uint32_t>& order)
{
  w.P = bind(pos);
  w.Q = quad.IsOpen() ? bind(quad) : View<Quadric>();
  w.A = attributes ? bind(attr) : View<std::uint8_t>();
  w.X = extra.IsOpen() ? bind(extra) : View<double>();
  w.S = state.IsOpen() ? bind(state) : View<State>();
  w.F = bind(faces);
  w.RO = bind(ringOff);
  w.RF = bind(ringFace);
  w.C = cand.IsOpen() ? bind(cand) : View<Cand>();
  w.O = order.IsOpen() ? bind(order) : View<std::uint32_t>();
}

void MeshState::BindViews(Views& w, DML& on) const
{
  BindEach(w, [&on](const auto& a) { return storage::View(on, a); }, this->pos, this->quad,
    this->attr, this->recSize != 0, this->extra, this->state, this->faces, this->ringOff, this->ringFace,
    this->cand, this->order);
}

void MeshState::BindViews(Views& w, const Workers& workers, int t) const
{
  BindEach(w, [&workers, t](const auto& a) { return workers.Bind(t, a); }, this->pos,
    this->quad, this->attr, this->recSize != 0, this->extra, this->state, this->faces, this->ringOff,
    this->ringFace, this->cand, this->order);
}

// ---------------------------------------------------------------------------------------------
// quadrics

// Whether the lock or selection array keeps vertex u where it is (a lock not 0, or outside the
// selection: 0). A is the attribute records' view.
bool FixedByArrays(const MeshState& mesh, const View<std::uint8_t>& A, std::uint32_t u)
{
  auto scalar = [&](int index) {
    float value = 0.0f;
    A.GetRange(std::uint64_t(u) * mesh.recSize + std::uint64_t(index) * sizeof(float),
      sizeof(float), reinterpret_cast<std::uint8_t*>(&value));
    return value;
  };
  return (mesh.lockFloat >= 0 && scalar(mesh.lockFloat) != 0.0f) ||
    (mesh.selectFloat >= 0 && scalar(mesh.selectFloat) == 0.0f);
}

// Scratch of the attribute terms of one vertex: its extension and the corners' scaled values.
struct AttributeScratch
{
  explicit AttributeScratch(const MeshState& mesh)
    : x(mesh.xSize)
    , s(3 * mesh.channels.size())
    , rec(mesh.recSize)
  {
  }
  std::vector<double> x, s;
  std::vector<std::uint8_t> rec;
};

// Adds face t's attribute terms (Attributes.h) to a vertex's extension as.x.
void FaceAttributes(const MeshState& mesh, const Views& w, const Tri& t, AttributeScratch& as)
{
  const std::size_t k = mesh.channels.size();
  Vec3 q[3];
  double p[3][3];
  for (int c = 0; c < 3; ++c)
  {
    q[c] = w.P.Get(t.v[c]);
    p[c][0] = q[c].x;
    p[c][1] = q[c].y;
    p[c][2] = q[c].z;
    const std::uint8_t* rec = w.A.Run(std::uint64_t(t.v[c]) * mesh.recSize, mesh.recSize, as.rec);
    for (std::size_t j = 0; j < k; ++j)
    {
      as.s[c * k + j] = ChannelValue(mesh.channels[j], rec);
    }
  }
  const Vec3 n = Cross(q[1] - q[0], q[2] - q[0]);
  AddFaceAttributes(p[0], p[1], p[2], as.s.data(), as.s.data() + k, as.s.data() + 2 * k, k,
    0.5 * std::sqrt(Dot(n, n)), as.x.data());
}

// BuildQuadrics' cache of face planes (each face is gathered by its three corners, nearby in
// the vertex order of a scan or of a clustered mesh): direct-mapped by face id, per thread.
struct FacePlane
{
  std::uint32_t face = kNone;
  Vec3 n{ 0, 0, 0 };
  double d = 0;
  double area = 0; // 0: no plane (a degenerate face)
};
constexpr std::size_t kFacePlanes = 4096; // (192 KiB a thread)

void BuildQuadrics(RunContext& ctx, MeshState& mesh)
{
  PhaseTimer timer(ctx.stats, mesh.dml, "quadrics");
  ctx.progress.BeginPhase("quadrics", kWork::kQuadrics * double(mesh.liveFaces),
    RestWork(ctx, mesh, 3, mesh.nv, mesh.liveFaces));
  const std::uint64_t nv = mesh.nv;
  mesh.quad = Array<Quadric>(mesh.dml, std::max<std::uint64_t>(nv, 1));
  if (mesh.xSize)
  {
    mesh.extra = Array<double>(mesh.dml, std::max<std::uint64_t>(nv, 1) * mesh.xSize);
  }
  mesh.state = Array<State>(mesh.dml, std::max<std::uint64_t>(nv, 1));
  mesh.cand = Array<Cand>(mesh.dml, std::max<std::uint64_t>(nv, 1));
  mesh.order = Array<std::uint32_t>(mesh.dml, std::max<std::uint64_t>(nv, 1));
  mesh.remap = Array<std::uint32_t>(mesh.dml, std::max<std::uint64_t>(nv, 1));
  mesh.BindViews();
  // One gather per vertex over its ring (faces in increasing order, so the sums are those of a
  // scatter in face order, whatever the threads): the area-weighted face plane quadrics, the edge
  // multiplicities (topology flags, boundary constraint planes), the initial quadric, and the
  // empty candidate. Every vertex writes only its own records: in core the vertex range is split
  // among threads (not with initialQuadric, a caller's callback).
  const double bw = ctx.opt.boundaryWeight;
  auto vertex = [&, bw](Views& w, std::uint32_t u, std::vector<Tri>& tris,
                  std::vector<std::uint32_t>& next, std::vector<std::uint32_t>& prev,
                  LinkTally& tally, const std::atomic<bool>& stop, bool caller,
                  AttributeScratch& as, std::vector<FacePlane>& planes) {
    // A vertex of very high valence takes long: the calling thread polls inside it (an abort
    // throws), another thread stops early when the run is being stopped.
    auto stopped = [&, caller](std::size_t i) {
      if ((i & 4095) != 4095)
      {
        return false;
      }
      if (caller)
      {
        ctx.progress.Poll();
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
      const std::uint32_t f = w.RF.Get(k);
      const Tri t = w.F.Get(f);
      if (!Alive(t))
      {
        continue;
      }
      const int c = CornerOf(t, u);
      tris.push_back(t);
      next.push_back(t.v[kNextCorner[c]]);
      prev.push_back(t.v[kPrevCorner[c]]);
      // The face's plane, computed by the first of its corners that comes here (the same
      // doubles for the other two, whatever the cache holds).
      FacePlane& plane = planes[f & (kFacePlanes - 1)];
      if (plane.face != f)
      {
        const Vec3 a = w.P.Get(t.v[0]);
        Vec3 nn = Cross(w.P.Get(t.v[1]) - a, w.P.Get(t.v[2]) - a);
        const double len = std::sqrt(Dot(nn, nn));
        plane.face = f;
        plane.area = 0;
        if (len > 0)
        {
          nn = (1.0 / len) * nn;
          plane.n = nn;
          plane.d = -Dot(nn, a);
          plane.area = 0.5 * len;
        }
      }
      if (plane.area > 0)
      {
        AddPlane(Q, plane.n, plane.d, plane.area);
      }
    }
    // (a caller's quadric replaces the face planes: set aside, added back if it has none)
    const bool replaceable = ctx.opt.initialQuadricReplacesFaces && ctx.opt.initialQuadric;
    Quadric faceQ = Q;
    if (replaceable)
    {
      Q = Quadric{ { 0, 0, 0, 0, 0, 0, 0, 0, 0, 0 } };
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
      if (ctx.opt.lockBoundary)
      {
        flags |= kFixed;
      }
    }
    if ((mesh.lockFloat >= 0 || mesh.selectFloat >= 0) && FixedByArrays(mesh, w.A, u))
    {
      flags |= kFixed; // a lock (not 0) or outside the selection (0): never moves, never removed
    }
    if (ctx.opt.initialQuadric)
    {
      double iq[10] = { 0 };
      const bool given = ctx.opt.initialQuadric(u, iq);
      if (replaceable && !given)
      {
        AddTo(Q, faceQ);
      }
      if (given)
      {
        // World to local coordinates: x = y + o.
        const Vec3 o = mesh.origin;
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
    if (mesh.xSize)
    {
      // The attribute terms of its faces.
      std::fill(as.x.begin(), as.x.end(), 0.0);
      for (const Tri& t : tris)
      {
        FaceAttributes(mesh, w, t, as);
      }
      w.X.SetRange(std::uint64_t(u) * mesh.xSize, mesh.xSize, as.x.data());
    }
    w.Q.Set(u, Q);
    w.S.Set(u, flags);
    w.C.Set(u, kNoCandidate);
    if (useTally)
    {
      tally.Release();
      ReleaseIfLarge(tris);
      ReleaseIfLarge(next);
      ReleaseIfLarge(prev);
    }
  };
  // On the workers of a phase over the vertices (not with initialQuadric, a caller's callback):
  // in core on all cores, out of core the upper half on a helper thread through a forked DML.
  storage::Phase phase;
  phase.elements = nv;
  phase.threads = ctx.opt.initialQuadric ? 1 : ctx.threads;
  phase.inCoreMin = 8192;
  phase.writes = { mesh.quad.Id(), mesh.state.Id(), mesh.cand.Id() };
  if (mesh.xSize)
  {
    // (the extension has xSize doubles per vertex: the helper's vertices [nv / 2, nv))
    phase.helperFirst = nv / 2;
    phase.helperWrites.push_back(
      { mesh.extra.Id(), nv / 2 * mesh.xSize, (nv - nv / 2) * mesh.xSize });
  }
  Workers workers(mesh.dml, phase);
  workers.Run(
    [&](int t, std::uint64_t lo, std::uint64_t hi, const std::atomic<bool>& stop) {
      Views w;
      mesh.BindViews(w, workers, t);
      std::vector<Tri> tris;
      std::vector<std::uint32_t> next, prev;
      LinkTally tally;
      AttributeScratch as(mesh);
      std::vector<FacePlane> planes(kFacePlanes);
      WithAccess(
        [&](auto RO, auto RF, auto F, auto P) {
          for (std::uint64_t u = lo; u < hi && !stop.load(std::memory_order_relaxed); ++u)
          {
            if (t == 0)
            {
              ctx.Tick(u - lo, hi - lo); // progress and abort: the calling thread only
            }
            if constexpr (decltype(RO)::kInCore)
            {
              // The faces of the vertices 8 ahead, the corner positions of those 4 ahead.
              const std::uint32_t* ROp = RO.Data();
              const std::uint32_t* RFp = RF.Data();
              const Tri* Fp = F.Data();
              const Vec3* Pp = P.Data();
              if (u + 8 < hi)
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
            }
            else if (u + 8 < hi)
            {
              // Out of core the same, from the pages at hand (Peek: no read for a hint).
              PrefetchRingFaces(RO, RF, F, std::uint32_t(u + 8));
              for (auto [k, end] = RingAtHand(RO, std::uint32_t(u + 4)); k < end; ++k)
              {
                const std::uint32_t* id = RF.Peek(k);
                if (const Tri* t = id ? F.Peek(*id) : nullptr)
                {
                  for (const std::uint32_t y : t->v)
                  {
                    P.Prefetch(y); // (nothing for a dead face's corner: past the block)
                  }
                }
              }
            }
            vertex(w, std::uint32_t(u), tris, next, prev, tally, stop, t == 0, as, planes);
          }
        },
        w.RO, w.RF, w.F, w.P);
    },
    [&]() { ctx.progress.Poll(); });
  if (mesh.faceSelect)
  {
    // A corner of a face outside a face selection never moves or goes (as a vertex outside a
    // point selection): every such face keeps its corners.
    mesh.BindViews();
    View<std::uint8_t> out(mesh.dml, mesh.outside);
    for (std::uint64_t u = 0; u < nv; ++u)
    {
      if (out.Get(u))
      {
        mesh.views.S.Set(u, State(mesh.views.S.Get(u) | kFixed));
      }
    }
    mesh.outside.Close();
  }
}

} // namespace
} // namespace sipmss::algorithms
