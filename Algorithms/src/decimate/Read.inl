// Algorithm I: reading the input into the DML, and the optional weld.
// (Part of Decimate.cpp's translation unit; the map of the passes: Decimator.h.)
namespace sipmss::algorithms
{
namespace
{
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

} // namespace
} // namespace sipmss::algorithms
