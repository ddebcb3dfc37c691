// Attribute-aware quadrics (Garland-Heckbert 1998, Hoppe 1999 in its memory-efficient form, with
// meshoptimizer's weighting): chosen point-data channels (normals, colors, texture coordinates,
// scalars), each with a weight, join the error of the decimation and of the clustering.
// docs/architecture.md, "Attribute-aware error".
//
// Each face f (area w) fits every channel j linearly over its plane: s_j(p) = g_j.p + d_j takes
// the (weighted) corner values at the corners. Its attribute error at (p, s_1..s_k) is
//   w sum_j (s_j - g_j.p - d_j)^2,
// whose s-s block is w times the identity. Summed over faces (a vertex's extension, `extra`):
// alpha = sum w, the p-p, p and constant terms as a quadric Qa, and per channel
// B_j = -sum w g_j and e_j = -sum w d_j:
//   Ea(p, s) = Qa(p) + sum_j [ alpha s_j^2 + 2 s_j (B_j.p + e_j) ].
// Minimizing over s gives s_j(p) = -(B_j.p + e_j) / alpha (the merged vertex's attributes: the
// quadric-optimal values) and Qa(p) - sum_j (B_j.p + e_j)^2 / alpha.
//
// Weight (meshoptimizer's simplifyWithAttributes: its position error is a mean squared distance,
// its attribute error an area-weighted sum, "so that a change of 1 in a weighted attribute across
// a distance d costs about as much as a change of position of d"): our geometric cost is the
// area-weighted sum Q(p), i.e. alpha times a mean, so the attribute error enters times alpha:
//   cost(p) = Q(p) + alpha Qa(p) - sum_j (B_j.p + e_j)^2     (AddAttributeError),
// a plain quadric in p that the placement minimizes as any other (the same kernel, Placement.h).
// The decimation ranks attribute runs' collapses by this cost per unit of the geometric trace
// (a mean squared distance plus the summed attribute error, meshoptimizer's ranking; RankKey in
// decimate/Passes.h).
// Channels are multiplied by their weight (colors first go to [0, 1]); equal weights mean the
// same as meshoptimizer's. The errors the runs report (RunStats::achievedError) include the
// attribute term; the error bound's unit stays the geometric quadric's trace.
#pragma once

#include "sipmss/algorithms/Quadric.h"
#include "sipmss/io/MeshIO.h"

#include <cstddef>
#include <string>
#include <vector>

namespace sipmss::algorithms
{

// One entry of an attribute list: a name (AttributeChannels) and its weight (> 0).
struct AttributeWeight
{
  std::string name;
  double weight = 1.0;
};

// Parses "normals:0.5,colors:1,height" (a weight defaults to 1) into `out`; returns what is
// wrong (empty when nothing). Every front end takes this one syntax.
std::string ParseAttributeWeights(const std::string& text, std::vector<AttributeWeight>& out);
// The canonical text of a list (ParseAttributeWeights of it gives the list back).
std::string FormatAttributeWeights(const std::vector<AttributeWeight>& list);

// One channel of a vertex's attribute record (the decimation's and the clustering's packed
// record: the normals' 3 floats, the texture coordinates' 2, the scalars', then 4 color bytes):
// either a float (floatIndex >= 0) or a color byte (colorByte >= 0: its offset in the record).
// scaled = raw * scale.
struct AttributeChannel
{
  int floatIndex = -1;
  int colorByte = -1;
  double scale = 1.0;
  bool normal = false; // a component of the normals (renormalized after a merge)
};

// The channels of `weights` in `layout`, scaled by their weight (colors also by 1/255). A name is,
// in this order: a scalar of the layout; NAME for the scalars NAME_0, NAME_1, ... (a VTK array of
// several components); or a keyword in any case, "normals" (3 channels), "colors" or "rgb" (3),
// "rgba" (4), "texcoords", "uv" or "tcoords" (2). An unknown name, or a channel named twice (e.g. colors
// and rgba), throws MissingArrayError (the message lists the names the input has).
std::vector<AttributeChannel> AttributeChannels(
  const io::VertexLayout& layout, const std::vector<AttributeWeight>& weights);

// The attribute extension of a vertex for k channels: alpha, Qa (10, Quadric.h's layout), then
// B_j (3) and e_j (1) per channel: AttributeExtraSize(k) doubles.
constexpr std::size_t kAttributeB = 11;
inline std::size_t AttributeExtraSize(std::size_t k)
{
  return k ? kAttributeB + 4 * k : 0;
}

// Bytes of the packed record of a layout, and vertex i of a chunk packed into `record`.
std::size_t RecordSize(const io::VertexLayout& layout);
void PackRecord(const io::VertexLayout& layout, const io::VertexChunk& chunk, std::size_t i,
  std::uint8_t* record);

// The scaled value of channel c in a packed record.
double ChannelValue(const AttributeChannel& c, const std::uint8_t* record);
// Writes scaled value s of channel c into a packed record (colors rounded and clamped).
void SetChannelValue(const AttributeChannel& c, double s, std::uint8_t* record);

// Adds face (p0, p1, p2) with weight w (its area) and weighted corner values s0/s1/s2 (k
// channels each) to the extension `extra` (AttributeExtraSize(k) doubles). Positions in the
// caller's (local) coordinates. A degenerate face or a sliver (the squared sine of its smallest
// angle below 1e-10) adds nothing.
void AddFaceAttributes(const double p0[3], const double p1[3], const double p2[3],
  const double* s0, const double* s1, const double* s2, std::size_t k, double w, double* extra);
// Adds the attribute error of an extension (the attributes minimized out) to the geometric
// quadric Q: Q + alpha Qa - sum_j (B_j.p + e_j)^2.
void AddAttributeError(const double* extra, std::size_t k, Quadric& Q);
// The optimal scaled value of channel j at p.
inline double OptimalAttribute(const double* extra, std::size_t j, double x, double y, double z)
{
  const double* b = extra + kAttributeB + 4 * j;
  return extra[0] > 0 ? -(b[0] * x + b[1] * y + b[2] * z + b[3]) / extra[0] : 0.0;
}

} // namespace sipmss::algorithms
