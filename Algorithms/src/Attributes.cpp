#include "sipmss/algorithms/Attributes.h"

#include "sipmss/algorithms/Common.h"

#include <algorithm>
#include <cctype>
#include <charconv>
#include <limits>
#include <system_error>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <sstream>

namespace sipmss::algorithms
{

std::string ParseAttributeWeights(const std::string& text, std::vector<AttributeWeight>& out)
{
  out.clear();
  const auto notSpace = [](unsigned char c) { return !std::isspace(c); };
  const auto trim = [&notSpace](std::string x) {
    x.erase(x.begin(), std::find_if(x.begin(), x.end(), notSpace));
    x.erase(std::find_if(x.rbegin(), x.rend(), notSpace).base(), x.end());
    return x;
  };
  if (std::find_if(text.begin(), text.end(), notSpace) == text.end())
  {
    return {}; // an empty list
  }
  std::size_t at = 0;
  while (at <= text.size())
  {
    const std::size_t comma = std::min(text.find(',', at), text.size());
    const std::string item = trim(text.substr(at, comma - at));
    at = comma + 1;
    if (item.empty())
    {
      return "has an empty entry in '" + text + "' (expected NAME[:WEIGHT],...)";
    }
    AttributeWeight a;
    const std::size_t colon = item.rfind(':');
    a.name = trim(item.substr(0, colon));
    if (colon != std::string::npos)
    {
      // (std::from_chars: the C locale's number syntax whatever the process's locale)
      std::string w = trim(item.substr(colon + 1));
      if (w.size() > 1 && w[0] == '+' && w[1] != '+' && w[1] != '-')
      {
        w.erase(0, 1); // (one leading '+', as strtod and the readers take it)
      }
      const auto r = std::from_chars(w.data(), w.data() + w.size(), a.weight);
      if (w.empty() || r.ptr != w.data() + w.size() ||
        (r.ec != std::errc() && r.ec != std::errc::result_out_of_range))
      {
        return "has a weight that is not a number in '" + item + "' (expected NAME[:WEIGHT])";
      }
      if (r.ec == std::errc::result_out_of_range)
      {
        return "has a weight out of range in '" + item + "'";
      }
    }
    if (a.name.empty())
    {
      return "has an entry without a name: '" + item + "'";
    }
    if (!std::isfinite(a.weight) || a.weight <= 0)
    {
      std::ostringstream s;
      s << "needs a finite weight above 0 for '" << a.name << "', not " << a.weight;
      return s.str();
    }
    for (const AttributeWeight& b : out)
    {
      if (b.name == a.name)
      {
        return "names '" + a.name + "' twice";
      }
    }
    out.push_back(std::move(a));
  }
  return {};
}

std::string FormatAttributeWeights(const std::vector<AttributeWeight>& list)
{
  std::ostringstream s;
  s.precision(17);
  for (std::size_t i = 0; i < list.size(); ++i)
  {
    s << (i ? "," : "") << list[i].name << ':' << list[i].weight;
  }
  return s.str();
}

std::vector<AttributeChannel> AttributeChannels(
  const io::VertexLayout& layout, const std::vector<AttributeWeight>& weights)
{
  std::vector<AttributeChannel> out;
  const int texBase = layout.normals ? 3 : 0;
  const int scalarBase = texBase + (layout.texcoords ? 2 : 0);
  const int colorBase = (scalarBase + int(layout.scalars.size())) * int(sizeof(float));
  auto have = [&]() {
    std::string s;
    auto add = [&s](const std::string& n) { s += (s.empty() ? "" : ", ") + n; };
    if (layout.normals)
    {
      add("normals");
    }
    if (layout.colors)
    {
      add("colors (rgb, rgba)");
    }
    if (layout.texcoords)
    {
      add("texcoords (uv)");
    }
    for (const std::string& n : layout.scalars)
    {
      add(n);
    }
    return s.empty() ? std::string("none") : s;
  };
  for (const AttributeWeight& a : weights)
  {
    const double scale = a.weight;
    std::vector<AttributeChannel> mine;
    // A scalar's own name first, then NAME for NAME_0, NAME_1, ... (the components of a VTK
    // array, in order), then the keywords in any case (the VTK readers' arrays are Normals, RGBA
    // and TCoords): a scalar array called like a keyword is that array.
    const auto it = std::find(layout.scalars.begin(), layout.scalars.end(), a.name);
    if (it != layout.scalars.end())
    {
      mine.push_back({ scalarBase + int(it - layout.scalars.begin()), -1, scale, false });
    }
    else
    {
      for (int c = 0;; ++c)
      {
        const auto ic = std::find(
          layout.scalars.begin(), layout.scalars.end(), a.name + "_" + std::to_string(c));
        if (ic == layout.scalars.end())
        {
          break;
        }
        mine.push_back({ scalarBase + int(ic - layout.scalars.begin()), -1, scale, false });
      }
    }
    std::string key = a.name;
    std::transform(key.begin(), key.end(), key.begin(),
      [](unsigned char c) { return char(std::tolower(c)); });
    if (!mine.empty())
    {
      // (a scalar's)
    }
    else if (key == "normals" && layout.normals)
    {
      for (int i = 0; i < 3; ++i)
      {
        mine.push_back({ i, -1, scale, true });
      }
    }
    else if ((key == "colors" || key == "rgb" || key == "rgba") && layout.colors)
    {
      for (int i = 0; i < (key == "rgba" ? 4 : 3); ++i)
      {
        mine.push_back({ -1, colorBase + i, scale / 255.0, false });
      }
    }
    else if ((key == "texcoords" || key == "uv" || key == "tcoords") && layout.texcoords)
    {
      for (int i = 0; i < 2; ++i)
      {
        mine.push_back({ texBase + i, -1, scale, false });
      }
    }
    if (mine.empty())
    {
      throw MissingArrayError("the input has no point attribute '" + a.name +
        "' to weigh in the error (its point attributes: " + have() + ")");
    }
    for (const AttributeChannel& c : mine)
    {
      for (const AttributeChannel& o : out)
      {
        if (o.floatIndex == c.floatIndex && o.colorByte == c.colorByte)
        {
          throw MissingArrayError("the attribute list names a channel of '" + a.name +
            "' twice (e.g. colors and rgba)");
        }
      }
      out.push_back(c);
    }
  }
  return out;
}

std::size_t RecordSize(const io::VertexLayout& layout)
{
  return ((layout.normals ? 3 : 0) + (layout.texcoords ? 2 : 0) + layout.scalars.size()) *
    sizeof(float) + (layout.colors ? 4 : 0);
}

void PackRecord(const io::VertexLayout& layout, const io::VertexChunk& c, std::size_t i,
  std::uint8_t* record)
{
  std::size_t at = 0;
  auto put = [&](float f) {
    std::memcpy(record + at, &f, sizeof(float));
    at += sizeof(float);
  };
  if (layout.normals)
  {
    for (int d = 0; d < 3; ++d)
    {
      put(c.normals ? c.normals[3 * i + d] : 0.0f);
    }
  }
  if (layout.texcoords)
  {
    for (int d = 0; d < 2; ++d)
    {
      put(c.texcoords ? c.texcoords[2 * i + d] : 0.0f);
    }
  }
  const std::size_t ns = layout.scalars.size();
  for (std::size_t d = 0; d < ns; ++d)
  {
    put(c.scalars ? c.scalars[ns * i + d] : 0.0f);
  }
  if (layout.colors)
  {
    for (int d = 0; d < 4; ++d)
    {
      record[at + std::size_t(d)] = c.rgba ? c.rgba[4 * i + std::size_t(d)] : 255;
    }
  }
}

double ChannelValue(const AttributeChannel& c, const std::uint8_t* record)
{
  if (c.floatIndex >= 0)
  {
    float f;
    std::memcpy(&f, record + std::size_t(c.floatIndex) * sizeof(float), sizeof(float));
    return double(f) * c.scale;
  }
  return double(record[c.colorByte]) * c.scale;
}

void SetChannelValue(const AttributeChannel& c, double s, std::uint8_t* record)
{
  const double raw = c.scale != 0 ? s / c.scale : 0.0;
  if (c.floatIndex >= 0)
  {
    const float f = float(raw);
    std::memcpy(record + std::size_t(c.floatIndex) * sizeof(float), &f, sizeof(float));
    return;
  }
  record[c.colorByte] = std::uint8_t(std::min(255.0, std::max(0.0, std::floor(raw + 0.5))));
}

void AddFaceAttributes(const double p0[3], const double p1[3], const double p2[3],
  const double* s0, const double* s1, const double* s2, std::size_t k, double w, double* extra)
{
  const double e1[3] = { p1[0] - p0[0], p1[1] - p0[1], p1[2] - p0[2] };
  const double e2[3] = { p2[0] - p0[0], p2[1] - p0[1], p2[2] - p0[2] };
  const double a = e1[0] * e1[0] + e1[1] * e1[1] + e1[2] * e1[2];
  const double b = e1[0] * e2[0] + e1[1] * e2[1] + e1[2] * e2[2];
  const double c = e2[0] * e2[0] + e2[1] * e2[1] + e2[2] * e2[2];
  const double det = a * c - b * b;
  // |e1 x e2|^2 = det is the product of any two squared edge lengths times the squared sine of
  // their angle; with the two longest, of the smallest angle.
  const double e3 = a + c - 2 * b; // |p2 - p1|^2
  const double longest = std::max({ a, c, e3 });
  const double second = a + c + e3 - longest - std::min({ a, c, e3 });
  if (!(det > 1e-10 * longest * second) || !(w > 0))
  {
    // A degenerate face has no plane to fit over; a sliver (the squared sine of its smallest
    // angle below 1e-10) would fit a gradient of unbounded size and pin its corners: neither
    // counts.
    return;
  }
  extra[0] += w;
  for (std::size_t j = 0; j < k; ++j)
  {
    // The gradient in the face's plane: g = x e1 + y e2 with g.e1 = s1 - s0, g.e2 = s2 - s0.
    const double d1 = s1[j] - s0[j], d2 = s2[j] - s0[j];
    const double x = (c * d1 - b * d2) / det, y = (a * d2 - b * d1) / det;
    const double g[3] = { x * e1[0] + y * e2[0], x * e1[1] + y * e2[1], x * e1[2] + y * e2[2] };
    const double d = s0[j] - (g[0] * p0[0] + g[1] * p0[1] + g[2] * p0[2]);
    // w (g.p + d - s)^2: the p terms as a plane quadric (g need not be a unit vector), then the
    // cross terms.
    const Quadric P = PlaneQuadric(g[0], g[1], g[2], d, w);
    for (int i = 0; i < 10; ++i)
    {
      extra[1 + i] += P.q[i];
    }
    double* bj = extra + kAttributeB + 4 * j;
    bj[0] -= w * g[0];
    bj[1] -= w * g[1];
    bj[2] -= w * g[2];
    bj[3] -= w * d;
  }
}

void AddAttributeError(const double* extra, std::size_t k, Quadric& Q)
{
  const double alpha = extra[0];
  if (!(alpha > 0))
  {
    return;
  }
  for (int i = 0; i < 10; ++i)
  {
    Q.q[i] += alpha * extra[1 + i];
  }
  for (std::size_t j = 0; j < k; ++j)
  {
    const double* b = extra + kAttributeB + 4 * j;
    const double x = b[0], y = b[1], z = b[2], e = b[3];
    Q.q[0] -= b[0] * x;
    Q.q[1] -= b[0] * y;
    Q.q[2] -= b[0] * z;
    Q.q[3] -= b[0] * e;
    Q.q[4] -= b[1] * y;
    Q.q[5] -= b[1] * z;
    Q.q[6] -= b[1] * e;
    Q.q[7] -= b[2] * z;
    Q.q[8] -= b[2] * e;
    Q.q[9] -= b[3] * e;
  }
}

} // namespace sipmss::algorithms
