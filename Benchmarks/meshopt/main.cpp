// sipmss-bench-meshopt (Debian's meshoptimizer 0.18) and sipmss-bench-meshopt12 (meshoptimizer
// 1.2 built from ../shared/peers at bench time): the meshoptimizer peers of the decimation
// benchmarks. Reads a mesh into memory, runs one simplifier to a target triangle count, writes
// the result, and prints JSON with the read and simplify times and meshoptimizer's result_error.
//   sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES [simplify|sloppy|update|attributes]
//   sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES attributes-of|update-of NAME:W[,NAME:W]
// update (meshopt_simplifyWithUpdate: positions placed optimally) and attributes
// (meshopt_simplifyWithAttributes with area-weighted vertex normals, weight 0.5 each) need 1.2.
// attributes-of and update-of weigh the input's own normals and colors (NAME normals or colors,
// colors from 0 to 1, as sipmss simplify --attributes takes them) in simplifyWithAttributes or
// simplifyWithUpdate (which also updates them), and write them with the output.
#include "../peers/PeerMesh.h"

#include <meshoptimizer.h>

#include <cmath>
#include <cstdlib>
#include <cstring>
#include <stdexcept>

namespace
{
// Area-weighted vertex normals, normalized (3 floats per vertex).
std::vector<float> VertexNormals(const sipmss::bench::PeerMesh& m)
{
  std::vector<float> n(m.p.size(), 0.f);
  for (std::size_t f = 0; f < m.t.size(); f += 3)
  {
    const float* a = &m.p[3 * m.t[f]];
    const float* b = &m.p[3 * m.t[f + 1]];
    const float* c = &m.p[3 * m.t[f + 2]];
    const float u[3] = { b[0] - a[0], b[1] - a[1], b[2] - a[2] };
    const float v[3] = { c[0] - a[0], c[1] - a[1], c[2] - a[2] };
    const float x[3] = { u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0] };
    for (int k = 0; k < 3; ++k)
    {
      for (int d = 0; d < 3; ++d)
      {
        n[3 * m.t[f + k] + d] += x[d];
      }
    }
  }
  for (std::size_t i = 0; i < n.size(); i += 3)
  {
    const float l = std::sqrt(n[i] * n[i] + n[i + 1] * n[i + 1] + n[i + 2] * n[i + 2]);
    for (int d = 0; d < 3 && l > 0; ++d)
    {
      n[i + d] /= l;
    }
  }
  return n;
}
// The attribute list "normals:0.5,colors:1" of attributes-of / update-of: the per-vertex
// floats meshoptimizer weighs (3 per name) and their weights.
void AttributeFloats(const sipmss::bench::PeerMesh& m, const std::string& list,
  std::vector<float>& values, std::vector<float>& weights)
{
  struct Entry
  {
    bool normals;
    float weight;
  };
  std::vector<Entry> entries;
  std::size_t at = 0;
  while (at < list.size())
  {
    const std::size_t comma = std::min(list.find(',', at), list.size());
    const std::string item = list.substr(at, comma - at);
    at = comma + 1;
    const std::size_t colon = item.find(':');
    const std::string name = item.substr(0, colon);
    const float w = colon == std::string::npos ? 1.0f : std::strtof(item.c_str() + colon + 1, nullptr);
    if (name == "normals" && !m.n.empty())
    {
      entries.push_back({ true, w });
    }
    else if (name == "colors" && !m.rgba.empty())
    {
      entries.push_back({ false, w });
    }
    else
    {
      throw std::runtime_error("the input has no attribute '" + name + "' (normals, colors)");
    }
  }
  const std::size_t nv = m.p.size() / 3, k = 3 * entries.size();
  values.resize(nv * k);
  weights.clear();
  for (const Entry& e : entries)
  {
    weights.insert(weights.end(), 3, e.weight);
  }
  for (std::size_t i = 0; i < nv; ++i)
  {
    for (std::size_t j = 0; j < entries.size(); ++j)
    {
      for (int d = 0; d < 3; ++d)
      {
        values[i * k + 3 * j + d] =
          entries[j].normals ? m.n[3 * i + d] : float(m.rgba[4 * i + d]) / 255.0f;
      }
    }
  }
}

// Writes meshoptimizer's updated attribute floats back into the mesh's normals and colors.
void StoreAttributes(sipmss::bench::PeerMesh& m, const std::string& list,
  const std::vector<float>& values)
{
  const std::size_t nv = m.p.size() / 3;
  const std::size_t k = values.size() / std::max<std::size_t>(nv, 1);
  std::size_t j = 0, at = 0;
  while (at < list.size())
  {
    const std::size_t comma = std::min(list.find(',', at), list.size());
    const bool normals = list.compare(at, 7, "normals") == 0;
    at = comma + 1;
    for (std::size_t i = 0; i < nv; ++i)
    {
      const float* v = &values[i * k + 3 * j];
      if (normals)
      {
        const float l = std::sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]);
        for (int d = 0; d < 3; ++d)
        {
          m.n[3 * i + d] = l > 0 ? v[d] / l : v[d];
        }
      }
      else
      {
        for (int d = 0; d < 3; ++d)
        {
          m.rgba[4 * i + d] =
            std::uint8_t(std::lround(std::min(255.0f, std::max(0.0f, v[d] * 255.0f))));
        }
      }
    }
    ++j;
  }
}
} // namespace

int main(int argc, char** argv)
{
  using namespace sipmss::bench;
  if (argc < 4)
  {
    std::fprintf(stderr,
      "usage: sipmss-bench-meshopt INPUT OUTPUT TARGET_TRIANGLES [simplify|sloppy|update|attributes]\n");
    return 2;
  }
  try
  {
    const auto t0 = Clock::now();
    const std::string mode = argc > 4 ? argv[4] : "simplify";
    const bool own = mode == "attributes-of" || mode == "update-of";
    const std::string list = argc > 5 ? argv[5] : "";
    PeerMesh m = ReadPeerMesh(argv[1], own);
    std::vector<float> values, weights;
    if (own)
    {
      AttributeFloats(m, list, values, weights);
    }
    const auto t1 = Clock::now();
    const std::size_t target = std::strtoull(argv[3], nullptr, 10) * 3;
    const std::size_t nv = m.p.size() / 3;
    std::vector<unsigned int> out(m.t.size());
    float err = 0;
    std::size_t n = 0;
    if (mode == "simplify")
    {
      n = meshopt_simplify(out.data(), m.t.data(), m.t.size(), m.p.data(), nv, 3 * sizeof(float),
        target, 1e9f, 0, &err);
    }
    else if (mode == "sloppy")
    {
      n = meshopt_simplifySloppy(out.data(), m.t.data(), m.t.size(), m.p.data(), nv,
        3 * sizeof(float), target, 1e9f, &err);
    }
#if MESHOPTIMIZER_VERSION >= 1000
    else if (mode == "update")
    {
      out.assign(m.t.begin(), m.t.end());
      n = meshopt_simplifyWithUpdate(out.data(), out.size(), m.p.data(), nv, 3 * sizeof(float),
        nullptr, 0, nullptr, 0, nullptr, target, 1e9f, 0, &err);
    }
    else if (mode == "attributes")
    {
      const std::vector<float> normals = VertexNormals(m);
      const float weights[3] = { 0.5f, 0.5f, 0.5f };
      n = meshopt_simplifyWithAttributes(out.data(), m.t.data(), m.t.size(), m.p.data(), nv,
        3 * sizeof(float), normals.data(), 3 * sizeof(float), weights, 3, nullptr, target, 1e9f,
        0, &err);
    }
    else if (mode == "attributes-of")
    {
      n = meshopt_simplifyWithAttributes(out.data(), m.t.data(), m.t.size(), m.p.data(), nv,
        3 * sizeof(float), values.data(), weights.size() * sizeof(float), weights.data(),
        weights.size(), nullptr, target, 1e9f, 0, &err);
    }
    else if (mode == "update-of")
    {
      out.assign(m.t.begin(), m.t.end());
      n = meshopt_simplifyWithUpdate(out.data(), out.size(), m.p.data(), nv, 3 * sizeof(float),
        values.data(), weights.size() * sizeof(float), weights.data(), weights.size(), nullptr,
        target, 1e9f, 0, &err);
      StoreAttributes(m, list, values);
    }
#endif
    else
    {
      throw std::runtime_error("unknown or unsupported mode " + mode + " (meshoptimizer " +
        std::to_string(MESHOPTIMIZER_VERSION) + ")");
    }
    out.resize(n);
    const auto t2 = Clock::now();
    WriteUsed(argv[2], m.p, std::vector<std::uint32_t>(out.begin(), out.end()), own ? &m : nullptr);
    PrintResult(Seconds(t0, t1), Seconds(t1, t2), out.size() / 3, err);
  }
  catch (const std::exception& e)
  {
    std::fprintf(stderr, "sipmss-bench-meshopt: error: %s\n", e.what());
    return 1;
  }
  return 0;
}
