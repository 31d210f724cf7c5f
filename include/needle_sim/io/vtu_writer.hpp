#pragma once
// The tissue mesh as a VTK unstructured grid (.vtu, ASCII XML), for ParaView: rest and
// current node positions (the points are the current ones), nodal displacement, and per
// element the von Mises stress at the centroid, the refinement level and, when given, the
// SPR error estimate eta.
#include <string>
#include <utility>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/geometry/triangle_mesh.hpp"

namespace needle_sim {

struct VtuCellData {
  std::vector<double> von_mises;  // per element (empty: omitted)
  std::vector<double> eta;        // per element (empty: omitted)
  std::vector<int> level;         // per element (empty: all 0)
};

// Writes atomically (temporary file, then rename). Throws std::runtime_error on I/O errors.
void writeVtu(const std::string& path, const HexMesh& mesh, const VecX& positions, const VtuCellData& cells);

// An organ surface (immersed geometry) as VTK polydata (.vtp): current vertex positions,
// triangles, and the vertex displacement from the rest surface.
void writeSurfaceVtp(const std::string& path, const TriangleMesh& rest, const std::vector<Vec3>& positions);
// Needle centre lines as VTK polydata (.vtp): one polyline per needle, cell data `needle`.
void writeCentreLinesVtp(const std::string& path, const std::vector<std::vector<Vec3>>& lines);
// A ParaView collection (.pvd) of time steps: (time, file relative to the .pvd).
void writePvd(const std::string& path, const std::vector<std::pair<double, std::string>>& steps);

}  // namespace needle_sim
