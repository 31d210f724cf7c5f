#pragma once
// Closed triangle surfaces: organ boundaries (immersed geometry), targets such as the
// subthalamic nucleus, skull surfaces and clamp patches (doc/method.md "Immersed geometry").
//
// Files are read with assimp (OBJ, STL, PLY, ...; OFF with our own reader: assimp's overread on malformed files). Identical vertices are welded, and
// the mesh must be closed with a consistent orientation: every edge a->b is matched by an
// edge b->a. Non-manifold edges (four triangles on one edge, as in the demo brain) pass this
// test and are harmless to the winding-number inside test. An inside-out mesh is flipped.
#include <array>
#include <string>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

// p -> rotation * (scale * p) + translation: file units and frame to the scene's (metres).
struct SurfaceTransform {
  double scale = 1.0;
  Mat3 rotation = Mat3::Identity();
  Vec3 translation = Vec3::Zero();
  Vec3 apply(const Vec3& p) const { return rotation * (scale * p) + translation; }
};

using Triangle = std::array<int, 3>;

class TriangleMesh {
 public:
  TriangleMesh() = default;
  TriangleMesh(std::vector<Vec3> vertices, std::vector<Triangle> triangles);

  int numVertices() const { return static_cast<int>(vertices_.size()); }
  int numTriangles() const { return static_cast<int>(triangles_.size()); }
  const std::vector<Vec3>& vertices() const { return vertices_; }
  const std::vector<Triangle>& triangles() const { return triangles_; }
  const Vec3& vertex(int i) const { return vertices_[i]; }
  const Triangle& triangle(int t) const { return triangles_[t]; }
  Vec3 boundsMin() const { return lo_; }
  Vec3 boundsMax() const { return hi_; }

  // Enclosed volume and its centroid (divergence theorem; exact for a closed mesh).
  double volume() const;
  Vec3 centroid() const;
  double area() const;
  // Unit normal of triangle t (outward for a closed, outward-oriented mesh).
  Vec3 normal(int t) const;
  // Area-weighted unit vertex normals and the area attributed to each vertex (1/3 of its
  // triangles').
  void vertexNormals(std::vector<Vec3>& normals, std::vector<double>& areas) const;

  // Edges a->b without a matching b->a: 0 for a closed, consistently oriented mesh.
  // `example` receives one such edge when there is any.
  long unmatchedEdges(std::array<int, 2>* example = nullptr) const;
  // Reverses every triangle (an inside-out mesh).
  void flip();
  void transform(const SurfaceTransform& t);

  // Distance from p to the nearest point of the given triangles (all when empty).
  double distance(const Vec3& p, const std::vector<int>& subset = {}) const;

 private:
  void updateBounds();
  std::vector<Vec3> vertices_;
  std::vector<Triangle> triangles_;
  Vec3 lo_ = Vec3::Zero(), hi_ = Vec3::Zero();
};

// Nearest point of triangle (a, b, c) to p (Ericson, Real-Time Collision Detection 5.1.5).
Vec3 closestPointOnTriangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c);

// Loads a closed surface and applies `t`. Throws InputError naming `file` of the scene and
// `key` when the mesh file is missing, unreadable, empty or not closed.
TriangleMesh loadTriangleMesh(const std::string& path, const SurfaceTransform& t, const std::string& scene_file,
                              const std::string& key);

}  // namespace needle_sim
