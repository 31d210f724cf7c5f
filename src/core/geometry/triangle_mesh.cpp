#include "needle_sim/geometry/triangle_mesh.hpp"

#include <assimp/Importer.hpp>
#include <assimp/postprocess.h>
#include <assimp/scene.h>

#include <algorithm>
#include <array>
#include <cctype>
#include <charconv>
#include <cstdlib>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <map>
#include <sstream>
#include <vector>

#include "needle_sim/core/error.hpp"

namespace needle_sim {

TriangleMesh::TriangleMesh(std::vector<Vec3> vertices, std::vector<Triangle> triangles)
    : vertices_(std::move(vertices)), triangles_(std::move(triangles)) {
  updateBounds();
}

void TriangleMesh::updateBounds() {
  lo_ = Vec3::Constant(std::numeric_limits<double>::infinity());
  hi_ = -lo_;
  for (const auto& v : vertices_) {
    lo_ = lo_.cwiseMin(v);
    hi_ = hi_.cwiseMax(v);
  }
  if (vertices_.empty()) lo_ = hi_ = Vec3::Zero();
}

double TriangleMesh::volume() const {
  double v = 0;
  for (const auto& t : triangles_) v += vertices_[t[0]].dot(vertices_[t[1]].cross(vertices_[t[2]]));
  return v / 6;
}

Vec3 TriangleMesh::centroid() const {
  // Relative to the bounding-box centre, to avoid cancellation far from the origin.
  const Vec3 o = 0.5 * (lo_ + hi_);
  double v = 0;
  Vec3 c = Vec3::Zero();
  for (const auto& t : triangles_) {
    const Vec3 a = vertices_[t[0]] - o, b = vertices_[t[1]] - o, d = vertices_[t[2]] - o;
    const double w = a.dot(b.cross(d));  // 6 x the tetrahedron (o, a, b, d)
    v += w;
    c += w * (a + b + d) / 4;
  }
  return o + c / v;
}

double TriangleMesh::area() const {
  double a = 0;
  for (const auto& t : triangles_)
    a += 0.5 * (vertices_[t[1]] - vertices_[t[0]]).cross(vertices_[t[2]] - vertices_[t[0]]).norm();
  return a;
}

Vec3 TriangleMesh::normal(int t) const {
  const auto& tr = triangles_[t];
  return (vertices_[tr[1]] - vertices_[tr[0]]).cross(vertices_[tr[2]] - vertices_[tr[0]]).normalized();
}

void TriangleMesh::vertexNormals(std::vector<Vec3>& normals, std::vector<double>& areas) const {
  normals.assign(vertices_.size(), Vec3::Zero());
  areas.assign(vertices_.size(), 0.0);
  for (const auto& t : triangles_) {
    const Vec3 n2 = (vertices_[t[1]] - vertices_[t[0]]).cross(vertices_[t[2]] - vertices_[t[0]]);  // 2 A n
    for (int k = 0; k < 3; ++k) {
      normals[t[k]] += n2;
      areas[t[k]] += n2.norm() / 6;
    }
  }
  for (auto& n : normals) {
    const double l = n.norm();
    if (l > 0) n /= l;
  }
}

long TriangleMesh::unmatchedEdges(std::array<int, 2>* example) const {
  // Net count of directed edges per undirected edge: a->b counts +1, b->a counts -1.
  std::map<std::pair<int, int>, int> net;
  for (const auto& t : triangles_)
    for (int k = 0; k < 3; ++k) {
      const int a = t[k], b = t[(k + 1) % 3];
      if (a < b) ++net[{a, b}];
      else --net[{b, a}];
    }
  long bad = 0;
  for (const auto& [e, n] : net)
    if (n != 0) {
      if (bad == 0 && example) *example = {e.first, e.second};
      bad += std::abs(n);
    }
  return bad;
}

void TriangleMesh::flip() {
  for (auto& t : triangles_) std::swap(t[1], t[2]);
}

void TriangleMesh::transform(const SurfaceTransform& t) {
  for (auto& v : vertices_) v = t.apply(v);
  if (t.scale * t.rotation.determinant() < 0) flip();
  updateBounds();
}

Vec3 closestPointOnTriangle(const Vec3& p, const Vec3& a, const Vec3& b, const Vec3& c) {
  const Vec3 ab = b - a, ac = c - a, ap = p - a;
  const double d1 = ab.dot(ap), d2 = ac.dot(ap);
  if (d1 <= 0 && d2 <= 0) return a;
  const Vec3 bp = p - b;
  const double d3 = ab.dot(bp), d4 = ac.dot(bp);
  if (d3 >= 0 && d4 <= d3) return b;
  const double vc = d1 * d4 - d3 * d2;
  if (vc <= 0 && d1 >= 0 && d3 <= 0) return a + ab * (d1 / (d1 - d3));
  const Vec3 cp = p - c;
  const double d5 = ab.dot(cp), d6 = ac.dot(cp);
  if (d6 >= 0 && d5 <= d6) return c;
  const double vb = d5 * d2 - d1 * d6;
  if (vb <= 0 && d2 >= 0 && d6 <= 0) return a + ac * (d2 / (d2 - d6));
  const double va = d3 * d6 - d5 * d4;
  if (va <= 0 && (d4 - d3) >= 0 && (d5 - d6) >= 0) return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
  const double denom = 1 / (va + vb + vc);
  return a + ab * (vb * denom) + ac * (vc * denom);
}

double TriangleMesh::distance(const Vec3& p, const std::vector<int>& subset) const {
  double best = std::numeric_limits<double>::infinity();
  auto visit = [&](int t) {
    const auto& tr = triangles_[t];
    best = std::min(best, (closestPointOnTriangle(p, vertices_[tr[0]], vertices_[tr[1]], vertices_[tr[2]]) - p).norm());
  };
  if (subset.empty())
    for (int t = 0; t < numTriangles(); ++t) visit(t);
  else
    for (int t : subset) visit(t);
  return best;
}

namespace {
double widen(float f) {
  char buf[64];
  const auto r = std::to_chars(buf, buf + sizeof buf - 1, f);
  *r.ptr = '\0';
  return std::strtod(buf, nullptr);
}

// A mesh as read: vertices and polygons (vertex indices, unchecked).
struct RawMesh {
  std::vector<std::array<double, 3>> vertices;
  std::vector<std::vector<long long>> faces;
};

// OFF ("OFF", counts "nv nf ne", nv vertices, nf faces "n i1 ... in"; '#' comments). Read
// here rather than by assimp, whose OFF importer aborts or reads out of bounds on malformed
// files (found by fuzz_mesh). Returns an empty string or the problem.
std::string readOff(const std::string& path, RawMesh& out) {
  std::ifstream in(path);
  std::stringstream tokens;
  std::string line;
  while (std::getline(in, line)) tokens << line.substr(0, line.find('#')) << '\n';
  std::string head;
  if (!(tokens >> head) || head != "OFF") return "not an OFF file (no 'OFF' header; NOFF/COFF are not read)";
  long long nv = 0, nf = 0, ne = 0;
  if (!(tokens >> nv >> nf >> ne)) return "OFF: missing vertex/face/edge counts";
  constexpr long long kMax = 100000000;
  if (nv < 0 || nf < 0 || nv > kMax || nf > kMax) return "OFF: implausible vertex or face count";
  out.vertices.reserve(static_cast<size_t>(std::min(nv, 1000000LL)));
  for (long long i = 0; i < nv; ++i) {
    std::array<double, 3> v{};
    if (!(tokens >> v[0] >> v[1] >> v[2])) return "OFF: vertex " + std::to_string(i) + " is missing or not numeric";
    out.vertices.push_back(v);
  }
  for (long long f = 0; f < nf; ++f) {
    long long n = 0;
    if (!(tokens >> n) || n < 0 || n > 1000) return "OFF: face " + std::to_string(f) + " has no valid vertex count";
    std::vector<long long> face(static_cast<size_t>(n));
    for (auto& i : face)
      if (!(tokens >> i)) return "OFF: face " + std::to_string(f) + " is missing vertex indices";
    out.faces.push_back(std::move(face));
    std::getline(tokens, line);  // per-face colour, if any
  }
  return "";
}
}  // namespace

TriangleMesh loadTriangleMesh(const std::string& path, const SurfaceTransform& t, const std::string& scene_file,
                              const std::string& key) {
  auto fail = [&](const std::string& problem) { throw InputError(scene_file, key, "'" + path + "': " + problem); };
  if (!std::filesystem::is_regular_file(path)) fail("no such mesh file");
  if (!std::ifstream(path)) fail("cannot open the mesh file");
  // Read: OFF by hand, the rest by assimp (faces only; no post-processing that could abort).
  std::vector<RawMesh> raw;
  std::string ext = std::filesystem::path(path).extension().string();
  std::transform(ext.begin(), ext.end(), ext.begin(), [](unsigned char c) { return std::tolower(c); });
  if (ext == ".off") {
    raw.emplace_back();
    const std::string problem = readOff(path, raw.back());
    if (!problem.empty()) fail("cannot read the mesh: " + problem);
  } else {
    Assimp::Importer importer;
    importer.SetPropertyInteger(AI_CONFIG_PP_RVC_FLAGS, aiComponent_NORMALS | aiComponent_TEXCOORDS |
                                                            aiComponent_COLORS | aiComponent_MATERIALS |
                                                            aiComponent_TANGENTS_AND_BITANGENTS);
    // No aiProcess_Triangulate: on malformed polygons Debian's assimp aborts the process in
    // an assertion of that step (found by fuzz_mesh); polygons are fanned below instead.
    const aiScene* sc = importer.ReadFile(path, aiProcess_RemoveComponent | aiProcess_PreTransformVertices);
    if (!sc || !sc->mRootNode) fail(std::string("cannot read the mesh: ") + importer.GetErrorString());
    for (unsigned m = 0; m < sc->mNumMeshes; ++m) {
      const aiMesh* mesh = sc->mMeshes[m];
      RawMesh r;
      for (unsigned i = 0; i < mesh->mNumVertices; ++i) {
        // assimp stores single precision; the shortest decimal of each float recovers what
        // the file said (0.04, not 0.0399999991) whenever it had at most 7 digits.
        const auto& v = mesh->mVertices[i];
        r.vertices.push_back({widen(v.x), widen(v.y), widen(v.z)});
      }
      for (unsigned f = 0; f < mesh->mNumFaces; ++f)
        r.faces.emplace_back(mesh->mFaces[f].mIndices, mesh->mFaces[f].mIndices + mesh->mFaces[f].mNumIndices);
      raw.push_back(std::move(r));
    }
  }
  // Vertices with equal positions are welded (across the file's meshes) so that edges match;
  // points and lines are skipped; a polygon (planar, convex: quads of OBJ/OFF files) becomes
  // a fan of triangles.
  std::vector<Vec3> V;
  std::vector<Triangle> T;
  std::map<std::array<double, 3>, int> weld;
  for (const RawMesh& r : raw) {
    std::vector<int> id(r.vertices.size());
    for (size_t i = 0; i < r.vertices.size(); ++i) {
      for (double c : r.vertices[i])  // before the map: NaN keys would break its ordering
        if (!std::isfinite(c)) fail("has non-finite vertex coordinates");
      auto it = weld.find(r.vertices[i]);
      if (it == weld.end()) {
        it = weld.emplace(r.vertices[i], static_cast<int>(V.size())).first;
        V.emplace_back(r.vertices[i][0], r.vertices[i][1], r.vertices[i][2]);
      }
      id[i] = it->second;
    }
    const auto n = static_cast<long long>(id.size());
    for (const auto& face : r.faces)
      for (size_t k = 1; k + 1 < face.size(); ++k) {
        const long long a = face[0], b = face[k], c = face[k + 1];
        if (a < 0 || b < 0 || c < 0 || a >= n || b >= n || c >= n) fail("has a face with a vertex index out of range");
        const Triangle tr{id[a], id[b], id[c]};
        if (tr[0] == tr[1] || tr[1] == tr[2] || tr[0] == tr[2]) continue;  // collapsed by welding
        T.push_back(tr);
      }
  }
  if (T.empty()) fail("contains no triangles");
  TriangleMesh mesh(std::move(V), std::move(T));
  std::array<int, 2> e{};
  const long open = mesh.unmatchedEdges(&e);
  if (open > 0)
  {
    std::ostringstream m;
    m << "not a closed surface: " << open
      << " edges without a matching opposite edge (an open mesh or inconsistent orientation), e.g. the edge from ("
      << mesh.vertex(e[0]).transpose() << ") to (" << mesh.vertex(e[1]).transpose() << ")";
    fail(m.str());
  }
  mesh.transform(t);
  if (mesh.volume() < 0) mesh.flip();
  if (!(mesh.volume() > 0)) fail("encloses no volume");
  return mesh;
}

}  // namespace needle_sim
