// Metro-style mesh comparison: two-sided surface-to-surface distances between two triangle
// meshes, estimated from area-uniform samples and exact point-to-triangle distances.
//
// Sampling. Each side gets the same number of samples S. Samples are stratified along the
// cumulative area table: sample k falls in the area stratum [k, k+1) * A/S (jittered uniformly
// inside it). The table runs over the triangles in a canonical order, not the file's: by the
// Morton code of their centroids (21 bits an axis over the centroids' bounds), then by their
// corners' coordinates; and each triangle's corners are taken in the order of their coordinates
// (x, then y, then z). So neighbouring strata are neighbouring pieces of the surface, and a copy
// of a mesh with its points, triangles or corners listed in another order (a shuffled file, a
// tool that writes its triangles in another order) gets the same samples and the same numbers,
// bit for bit. (Only the attribute values can still follow the file's order: triangles on the
// same three points keep it between them, so do coincident corners of a zero-area triangle, and
// when two triangles of the other mesh are equally near a sample, the one the search returns
// gives the values there.) Each sample so lands on a triangle with probability proportional to
// its area, and a triangle with area share f gets between floor(f * S) - 1 and ceil(f * S) + 1
// samples (less variance than independent draws). The point inside the triangle is uniform (barycentric with
// the sqrt trick). Zero-area triangles are never sampled but are still distance targets.
// Vertices are NOT added as extra samples: every sample carries the same weight, so mean and rms
// are unbiased area averages. The Hausdorff value is therefore a sampled (lower) estimate of the
// true one, as in Metro.
//
// Distances. The target surface is indexed by a bounding volume hierarchy (MeshDistanceIndex);
// the nearest search is exact: branch and bound with a conservative prune, so it returns the same
// value as a brute-force minimum of PointTriangleDistanceSquared over all triangles, bit for bit.
// A BVH rather than a uniform grid: its cost grows far less with the distance between the
// surfaces (a grid shell search visits O((d / cell)^3) cells) and its memory does not depend on
// how much of the bounding box the surface fills. Its boxes are oriented along the patches' mean
// normals, which keeps queries far from a finely tessellated surface cheap. The worst case is
// inherent to an exact search: a point (nearly) equidistant from much of the surface, like the
// center of a sphere, visits all of it.
//
// Determinism. Samples are split into fixed-size chunks, each with its own RNG seeded from
// (seed, side, chunk); per-chunk sums are combined in chunk order. Results are bitwise identical
// for a given seed whatever the thread count. The forward side of CompareMeshes draws exactly the
// samples of SampleDistance(reference, candidate, samples, seed, ...).
//
// Thread safety: all functions are reentrant; MeshDistanceIndex is immutable after construction
// and may be queried from any number of threads.
#pragma once

#include "sipmss/algorithms/Vector.h"

#include <array>
#include <cstddef>
#include <cstdint>
#include <vector>

namespace sipmss::algorithms
{

// A plain in-memory indexed triangle mesh.
struct TriangleMesh
{
  std::vector<float> points;             // 3 per vertex
  std::vector<std::uint32_t> triangles;  // 3 per triangle
  // Optional per-vertex attribute values (attributeStride per vertex; CompareOptions::
  // attributeGroups), interpolated linearly over the triangles.
  std::vector<float> attributes;
  std::size_t attributeStride = 0;

  std::size_t NumberOfPoints() const { return points.size() / 3; }
  std::size_t NumberOfTriangles() const { return triangles.size() / 3; }
  // xmin,xmax,ymin,ymax,zmin,zmax over all points; {1,-1,1,-1,1,-1} (min > max) when empty.
  std::array<double, 6> Bounds() const;
};

struct CompareOptions
{
  // Samples per side. 0: max(1e5, 2 * triangles of the larger mesh), capped at 2e6.
  std::uint64_t samples = 0;
  std::uint64_t seed = 1;
  int threads = 0; // <= 0: every core (storage::ResolveThreads)
  // Attribute errors: each group (first component, count) of both meshes' attributes (the same
  // stride) is compared at every sample: the value interpolated at the sample against the value
  // interpolated at its nearest point on the other mesh (barycentric), as a Euclidean distance.
  std::vector<std::array<std::size_t, 2>> attributeGroups;
};

struct CompareResult
{
  // Two-sided values relative to the REFERENCE bounding-box diagonal. mean and rms run over the
  // samples of both sides (each side has `samples` of them); hausdorff is the larger maximum.
  double mean = 0, rms = 0, hausdorff = 0;
  double diagonal = 0;       // the reference bounding-box diagonal
  std::uint64_t samples = 0; // samples per side (2 * samples distances in all)
  // The same values in model units.
  double meanAbsolute = 0, rmsAbsolute = 0, hausdorffAbsolute = 0;
  // One-sided parts for the record, relative to the reference diagonal:
  // forward = reference samples against the candidate, backward = candidate samples against the
  // reference.
  double forwardRms = 0, backwardRms = 0;
  // Per attribute group (CompareOptions::attributeGroups), two-sided over the same samples: the
  // RMS and the largest difference, in the attribute's units.
  std::vector<double> attributeRms, attributeMax;
};

// Two-sided comparison. Throws std::invalid_argument when a mesh is empty, has zero total area,
// a triangle index out of range, a coordinate that is not finite, or a size not a multiple of 3.
CompareResult CompareMeshes(const TriangleMesh& reference, const TriangleMesh& candidate,
  const CompareOptions& options = {});

// One-sided: distances (model units) from `samples` area-uniform samples on `from` to the surface
// `to`. `from` must have positive area; `to` needs at least one triangle (zero-area triangles are
// fine). samples == 0 returns all zeros. threads <= 0: hardware concurrency.
struct OneSided
{
  double mean = 0, rms = 0, max = 0;
  std::uint64_t samples = 0;
};
OneSided SampleDistance(const TriangleMesh& from, const TriangleMesh& to, std::uint64_t samples,
  std::uint64_t seed, int threads);

// Exact squared distance from p to the triangle (a, b, c): Ericson's closest-point region test,
// on the corners in the order of their coordinates (the same value, bit for bit, whichever order
// they are given in). Degenerate triangles (collinear vertices, coincident vertices, a single
// point) are handled as the union of their edges.
double PointTriangleDistanceSquared(
  const double p[3], const double a[3], const double b[3], const double c[3]);
// The barycentric coordinates (of a, b, c) of the point of triangle (a, b, c) nearest to p
// (Ericson's regions; a degenerate triangle: its nearest edge's).
std::array<double, 3> ClosestPointBarycentric(
  const double p[3], const double a[3], const double b[3], const double c[3]);
std::array<double, 3> ClosestPointBarycentric(
  const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c);

// The spatial index behind the distance queries, public for tests and other algorithms.
class MeshDistanceIndex
{
public:
  struct Hit
  {
    double distanceSquared = 0;
    std::uint32_t triangle = 0; // index into the mesh's triangles
  };

  // Indexes every triangle of `mesh` (degenerate ones too). Throws std::invalid_argument for a
  // mesh without triangles or with more than 2^29 - 1, an out-of-range index or a non-finite
  // coordinate. The mesh is copied;
  // it need not outlive the index. threads <= 0: hardware concurrency (the build result does not
  // depend on it).
  explicit MeshDistanceIndex(const TriangleMesh& mesh, int threads = 1);

  // Exact nearest triangle: the distance equals min over all triangles of
  // PointTriangleDistanceSquared. `hint` (a triangle index, or kNoHint) only speeds the search.
  static constexpr std::uint32_t kNoHint = 0xffffffffu;
  Hit Nearest(const double p[3], std::uint32_t hint = kNoHint) const;

  std::size_t NumberOfTriangles() const { return this->Original.size(); }
  std::size_t NumberOfNodes() const { return this->Nodes.size(); }

private:
  // A child of an inner node, bounded by an oriented box (center, three unit axes u, v, w, half
  // extents along them). ref = (index << 3) | count: count == 0 is an inner node (index = node),
  // else a leaf (index = first triangle in leaf order, count = number of triangles).
  struct Child
  {
    float center[3];
    float axis[3][3];
    float half[3];
    std::uint32_t ref;
  };
  struct alignas(64) Node
  {
    Child child[2];
  };
  struct Builder;

  Child Root{};
  std::vector<Node> Nodes;
  std::vector<float> Triangles;        // 9 floats per triangle, in leaf order
  std::vector<std::uint8_t> Degenerate; // per triangle in leaf order: use the edge distance
  std::vector<std::uint32_t> Original; // leaf order -> mesh triangle index
  std::vector<std::uint32_t> Position; // mesh triangle index -> leaf order
  double Scale = 0;                    // max |coordinate| of the indexed triangles
};

} // namespace sipmss::algorithms
