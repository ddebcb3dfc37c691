// Algorithm I: reading the input into the DML, and the optional weld.
// (Part of Decimate.cpp's translation unit; the map of the passes: Passes.h.)
namespace sipmss::algorithms
{
namespace
{
void Loader::Tick()
{
  try
  {
    this->ctx_.progress.Tick(ReadFraction(this->mesh_));
  }
  catch (const AbortedError&)
  {
    this->aborted_ = true;
    throw;
  }
}
void Loader::Begin(const io::MeshHeader& header)
{
  BeginInput(this->ctx_, this->mesh_, header);
  // (a face selection is read with the faces: the reordered copy would not carry it)
  if (MeasuresLayout(this->ctx_) && !this->mesh_.faceSelect)
  {
    this->MeasureLayout(header.vertexCount);
  }
}
void Loader::Vertices(const io::VertexChunk& chunk)
{
  this->Tick();
  AddVertices(this->mesh_, chunk);
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
  AddTriangles(this->mesh_, indices, count);
  if (this->mesh_.faceSelect)
  {
    this->mesh_.lastTris.assign(indices, indices + 3 * count);
    this->mesh_.trianglesRead += count;
  }
}
void Loader::TriangleFlags(const std::uint8_t* flags, std::size_t count)
{
  MeshState& mesh = this->mesh_;
  if (!mesh.faceSelect)
  {
    return;
  }
  if (count * 3 != mesh.lastTris.size())
  {
    throw std::logic_error("decimate: the source sent flags for " + std::to_string(count) +
      " triangles after " + std::to_string(mesh.lastTris.size() / 3));
  }
  mesh.trianglesFlagged += count;
  // (faces may come before their vertices, as in a PLY whose face element is first: the
  // readers have checked the indices against the vertex count)
  std::uint32_t top = 0;
  for (std::size_t t = 0; t < count; ++t)
  {
    if (flags[t] == 0)
    {
      top = std::max({ top, mesh.lastTris[3 * t], mesh.lastTris[3 * t + 1], mesh.lastTris[3 * t + 2] });
    }
  }
  EnsureVertexCapacity(mesh, std::uint64_t(top) + 1);
  View<std::uint8_t> out(mesh.dml, mesh.outside);
  for (std::size_t t = 0; t < count; ++t)
  {
    if (flags[t] == 0)
    {
      for (int k = 0; k < 3; ++k)
      {
        out.Set(mesh.lastTris[3 * t + std::size_t(k)], 1);
      }
    }
  }
}
void Loader::End(const io::ReadStats& stats)
{
  if (this->measure_)
  {
    this->Measured();
  }
  this->mesh_.readerDropped = stats.droppedFaces;
}

// ---------------------------------------------------------------------------------------------
// read

void BeginInput(RunContext& ctx, MeshState& mesh, const io::MeshHeader& header)
{
  if (mesh.begun)
  {
    return;
  }
  mesh.begun = true;
  mesh.layout = header.layout;
  mesh.nFloats = (mesh.layout.normals ? 3 : 0) + (mesh.layout.texcoords ? 2 : 0) +
    mesh.layout.scalars.size();
  mesh.recSize = mesh.nFloats * sizeof(float) + (mesh.layout.colors ? 4 : 0);
  // The lock and selection scalars: their place among the record's floats (after the normals
  // and the texture coordinates); a selection may also name a face (cell) scalar.
  auto joined = [](const std::vector<std::string>& names) {
    std::string have;
    for (const std::string& n : names)
    {
      have += (have.empty() ? "" : ", ") + n;
    }
    return have.empty() ? std::string("none") : have;
  };
  const std::vector<std::string>& points = mesh.layout.scalars;
  const std::vector<std::string>& faces = header.faceScalars;
  auto scalarFloat = [&](const std::string& name) {
    const auto it = std::find(points.begin(), points.end(), name);
    return it == points.end() ? -1
                              : int((mesh.layout.normals ? 3 : 0) +
                                  (mesh.layout.texcoords ? 2 : 0) + (it - points.begin()));
  };
  const std::string& lock = ctx.opt.lockArray;
  const std::string& selection = ctx.opt.selectionArray;
  mesh.lockFloat = lock.empty() ? -1 : scalarFloat(lock);
  if (!lock.empty() && mesh.lockFloat < 0)
  {
    throw MissingArrayError("the input has no point array '" + lock +
      "' to use as the lock array (its point arrays: " + joined(points) + ")");
  }
  mesh.selectFloat = selection.empty() ? -1 : scalarFloat(selection);
  mesh.faceSelect = !selection.empty() && mesh.selectFloat < 0 &&
    std::find(faces.begin(), faces.end(), selection) != faces.end();
  if (!selection.empty() && mesh.selectFloat < 0 && !mesh.faceSelect)
  {
    throw MissingArrayError("the input has no point or cell array '" + selection +
      "' to use as the selection array (its point arrays: " + joined(points) +
      "; its cell arrays: " + joined(faces) + ")");
  }
  // The attribute channels.
  mesh.channels = AttributeChannels(mesh.layout, ctx.opt.attributes);
  mesh.xSize = AttributeExtraSize(mesh.channels.size());
  mesh.announcedV = header.vertexCount;
  mesh.announcedF = header.faceCount;
  if (header.vertexCount + header.faceCount > 0)
  {
    ctx.progress.Sized(header.vertexCount, header.faceCount);
    ctx.progress.BeginPhase("read", kWork::kRead * double(header.vertexCount + header.faceCount),
      WorkAfterRead(ctx, mesh, header.vertexCount, header.faceCount));
  }

  // The profile: the structures of the run, sized from the header (0 when unknown: the blocks
  // then grow with Resize and the DML re-evaluates the mode as they do).
  storage::Profile profile = ctx.opt.storage;
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
  add("decimate.attributes", mesh.recSize, V);
  add("decimate.quadrics", sizeof(Quadric), V);
  add("decimate.attributeQuadrics", mesh.xSize * sizeof(double), V);
  add("decimate.vertexState", sizeof(State), V);
  add("decimate.faces", sizeof(Tri), F);
  add("decimate.ringOffsets", sizeof(std::uint32_t), V + 1);
  add("decimate.ringFaces", sizeof(std::uint32_t), 3 * F);
  add("decimate.candidates", sizeof(Cand), V);
  add("decimate.order", sizeof(std::uint32_t), V);
  add("decimate.remap", sizeof(std::uint32_t), V);
  // The final fit's samples: at most every second vertex (Fit.inl).
  add("decimate.fitSamples",
    (ctx.opt.fitSurface || ctx.opt.finalSamples) && !ctx.opt.initialSamples ? sizeof(FitSample) : 0,
    (V + 1) / 2);
  if (!ctx.opt.dml)
  {
    mesh.dml.Config(profile);
  }

  mesh.vCap = std::max<std::uint64_t>(V, 1);
  mesh.fCap = std::max<std::uint64_t>(F, 1);
  mesh.pos = Array<Vec3>(mesh.dml, mesh.vCap);
  if (mesh.recSize)
  {
    mesh.attr = Array<std::uint8_t>(mesh.dml, mesh.vCap * mesh.recSize);
  }
  mesh.faces = Array<Tri>(mesh.dml, mesh.fCap);
  if (mesh.faceSelect)
  {
    mesh.outside = Array<std::uint8_t>(mesh.dml, mesh.vCap);
  }
  // In core, the reader's first touches of these blocks go to another core, in the order the
  // reader fills them (a PLY's vertices come first). On one thread, as asked, none.
  if (ctx.threads > 1 && V > 0 && F > 0)
  {
    std::vector<storage::Prefaulter::Range> ranges;
    auto add = [&](BlockId id, std::uint64_t bytes) {
      if (void* base = mesh.dml.BasePointer(id))
      {
        ranges.push_back({ base, std::size_t(bytes) });
      }
    };
    add(mesh.pos.Id(), mesh.vCap * sizeof(Vec3));
    if (mesh.recSize)
    {
      add(mesh.attr.Id(), mesh.vCap * mesh.recSize);
    }
    add(mesh.faces.Id(), mesh.fCap * sizeof(Tri));
    mesh.prefault.Start(std::move(ranges));
  }
}

void EnsureVertexCapacity(MeshState& mesh, std::uint64_t n)
{
  if (n <= mesh.vCap)
  {
    return;
  }
  std::uint64_t cap = std::max<std::uint64_t>({ n, mesh.vCap * 2, 1024 });
  mesh.prefault.Stop(); // (the blocks may move)
  mesh.pos.Resize(cap);
  if (mesh.recSize)
  {
    mesh.attr.Resize(cap * mesh.recSize);
  }
  if (mesh.faceSelect)
  {
    mesh.outside.Resize(cap);
  }
  mesh.vCap = cap;
}

void EnsureFaceCapacity(MeshState& mesh, std::uint64_t n)
{
  if (n <= mesh.fCap)
  {
    return;
  }
  std::uint64_t cap = std::max<std::uint64_t>({ n, mesh.fCap * 2, 1024 });
  mesh.prefault.Stop(); // (the blocks may move)
  mesh.faces.Resize(cap);
  mesh.fCap = cap;
}

void AddVertices(MeshState& mesh, const io::VertexChunk& c)
{
  if (!mesh.begun)
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
  EnsureVertexCapacity(mesh, end);
  if (!mesh.haveOrigin)
  {
    mesh.origin = { double(c.xyz[0]), double(c.xyz[1]), double(c.xyz[2]) };
    mesh.haveOrigin = true;
  }
  mesh.vbuf.resize(c.count);
  Vec3 lo = mesh.lo, hi = mesh.hi;
  for (std::size_t i = 0; i < c.count; ++i)
  {
    const Vec3 p = { double(c.xyz[3 * i]) - mesh.origin.x,
      double(c.xyz[3 * i + 1]) - mesh.origin.y, double(c.xyz[3 * i + 2]) - mesh.origin.z };
    mesh.vbuf[i] = p;
    lo = { std::min(lo.x, p.x), std::min(lo.y, p.y), std::min(lo.z, p.z) };
    hi = { std::max(hi.x, p.x), std::max(hi.y, p.y), std::max(hi.z, p.z) };
  }
  mesh.lo = lo;
  mesh.hi = hi;
  View<Vec3>(mesh.dml, mesh.pos).SetRange(c.first, c.count, mesh.vbuf.data());
  if (mesh.recSize)
  {
    const std::size_t rec = mesh.recSize;
    const std::size_t ns = mesh.layout.scalars.size();
    mesh.abuf.assign(c.count * rec, 0);
    for (std::size_t i = 0; i < c.count; ++i)
    {
      float* f = reinterpret_cast<float*>(mesh.abuf.data() + i * rec);
      std::size_t k = 0;
      if (mesh.layout.normals)
      {
        for (int j = 0; j < 3; ++j)
        {
          f[k++] = c.normals ? c.normals[3 * i + j] : 0.0f;
        }
      }
      if (mesh.layout.texcoords)
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
      if (mesh.layout.colors)
      {
        std::uint8_t* rgba = mesh.abuf.data() + i * rec + mesh.nFloats * sizeof(float);
        for (int j = 0; j < 4; ++j)
        {
          rgba[j] = c.rgba ? c.rgba[4 * i + j] : std::uint8_t(255);
        }
      }
    }
    View<std::uint8_t>(mesh.dml, mesh.attr)
      .SetRange(c.first * rec, c.count * rec, mesh.abuf.data());
  }
  mesh.nv = std::max(mesh.nv, end);
}

void AddTriangles(MeshState& mesh, const std::uint32_t* idx, std::size_t count)
{
  if (!mesh.begun)
  {
    throw io::MeshIOError("decimate: the source sent triangles before Begin()");
  }
  mesh.tbuf.clear();
  for (std::size_t i = 0; i < count; ++i)
  {
    Tri t = { { idx[3 * i], idx[3 * i + 1], idx[3 * i + 2] } };
    if (t.v[0] == t.v[1] || t.v[1] == t.v[2] || t.v[0] == t.v[2])
    {
      ++mesh.dropped;
      continue;
    }
    mesh.tbuf.push_back(t);
  }
  if (mesh.tbuf.empty())
  {
    return;
  }
  EnsureFaceCapacity(mesh, mesh.nf + mesh.tbuf.size());
  View<Tri>(mesh.dml, mesh.faces).SetRange(mesh.nf, mesh.tbuf.size(), mesh.tbuf.data());
  mesh.nf += mesh.tbuf.size();
}

void Read(RunContext& ctx, MeshState& mesh, const MeshSource& input)
{
  PhaseTimer timer(ctx.stats, mesh.dml, "read");
  ctx.progress.BeginPhase("read", 0.0, 1.0); // (its share once the header gives the sizes)
  Loader loader(ctx, mesh);
  io::ReadOptions ro;
  ro.faceFlag = ctx.opt.selectionArray; // (used when it names a face scalar)
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
  mesh.prefault.Stop(); // (the blocks shrink to their counts below)
  if (loader.Aborted())
  {
    throw AbortedError();
  }
  if (loader.Layout().Faces() > 0)
  {
    ctx.stats.layoutFarFraction = loader.Layout().FarFraction();
  }
  if (mesh.faceSelect && mesh.trianglesFlagged != mesh.trianglesRead)
  {
    // (a source that does not pass ReadOptions::faceFlag on, e.g. a reordered copy)
    throw std::runtime_error("decimate: the cell array '" + ctx.opt.selectionArray +
      "' did not come with the faces (" + std::to_string(mesh.trianglesFlagged) + " of " +
      std::to_string(mesh.trianglesRead) + " triangles): this source cannot select cells");
  }
  ctx.progress.Poll(); // (the exact sizes and the mode's re-evaluation follow: storage calls)
  if (!mesh.begun)
  {
    io::MeshHeader h;
    BeginInput(ctx, mesh, h);
  }
  ctx.stats.inputVertices = mesh.nv;
  ctx.stats.inputTriangles = mesh.nf + mesh.dropped;
  mesh.readerDropped = std::max(mesh.readerDropped, rs.droppedFaces);
  // Exact sizes, then let the DML re-evaluate the mode.
  mesh.vCap = std::max<std::uint64_t>(mesh.nv, 1);
  mesh.fCap = std::max<std::uint64_t>(mesh.nf, 1);
  mesh.pos.Resize(mesh.vCap);
  if (mesh.recSize)
  {
    mesh.attr.Resize(mesh.vCap * mesh.recSize);
  }
  mesh.faces.Resize(mesh.fCap);
  ctx.progress.Poll();
  mesh.dml.Reconfigure();
}

// Greedy welding: each vertex joins the lowest-index representative within weldDistance (a
// spatial hash of cells of that size in the DML), else becomes a representative.
void Weld(RunContext& ctx, MeshState& mesh)
{
  const double d = ctx.opt.weldDistance;
  const std::uint64_t nv = mesh.nv;
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
  Array<std::uint32_t> head(mesh.dml, tableSize);
  Array<std::uint32_t> next(mesh.dml, nv);
  Array<std::uint32_t> rep(mesh.dml, nv);
  FillBlock(mesh.dml, head, kNone);
  View<std::uint32_t> H(mesh.dml, head), N(mesh.dml, next), R(mesh.dml, rep);
  View<Vec3> P(mesh.dml, mesh.pos);
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
    ctx.Tick(v, nv);
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
  View<Tri> F(mesh.dml, mesh.faces);
  for (std::uint64_t f = 0; f < mesh.nf; ++f)
  {
    ctx.Tick(f, mesh.nf);
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
      ++mesh.dropped;
    }
    else if (w.v[0] != t.v[0] || w.v[1] != t.v[1] || w.v[2] != t.v[2])
    {
      F.Set(f, w);
    }
  }
}

} // namespace
} // namespace sipmss::algorithms
