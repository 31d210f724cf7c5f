#include "needle_sim/io/vtu_writer.hpp"

#include <cstdio>
#include <filesystem>
#include <fstream>
#include <iomanip>
#include <stdexcept>

namespace needle_sim {

namespace {
// Writes through a temporary file renamed into place, so a reader never sees half a file.
template <class Body>
void writeAtomically(const std::string& path, Body body) {
  const std::string tmp = path + ".tmp";
  {
    std::ofstream o(tmp);
    if (!o) throw std::runtime_error("cannot write " + tmp);
    o << std::setprecision(10);
    body(o);
    if (!o) throw std::runtime_error("error writing " + tmp);
  }
  std::filesystem::rename(tmp, path);
}
}  // namespace

void writeVtu(const std::string& path, const HexMesh& mesh, const VecX& x, const VtuCellData& cells) {
  writeAtomically(path, [&](std::ofstream& o) {
    const int nn = mesh.numNodes(), ne = mesh.numElements();
    o << "<?xml version=\"1.0\"?>\n<VTKFile type=\"UnstructuredGrid\" version=\"0.1\" byte_order=\"LittleEndian\">\n"
      << "<UnstructuredGrid>\n<Piece NumberOfPoints=\"" << nn << "\" NumberOfCells=\"" << ne << "\">\n";
    o << "<PointData Vectors=\"displacement\">\n<DataArray type=\"Float64\" Name=\"displacement\" NumberOfComponents=\"3\" format=\"ascii\">\n";
    for (int i = 0; i < nn; ++i) {
      const Vec3 u = node3(x, i) - mesh.node(i);
      o << u[0] << ' ' << u[1] << ' ' << u[2] << '\n';
    }
    o << "</DataArray>\n</PointData>\n<CellData Scalars=\"von_mises\">\n";
    auto scalars = [&](const char* name, const auto& v) {
      o << "<DataArray type=\"Float64\" Name=\"" << name << "\" format=\"ascii\">\n";
      for (const auto& s : v) o << s << '\n';
      o << "</DataArray>\n";
    };
    if (!cells.von_mises.empty()) scalars("von_mises", cells.von_mises);
    if (!cells.eta.empty()) scalars("eta", cells.eta);
    if (mesh.hasFractions()) {
      std::vector<double> f(ne);
      for (int e = 0; e < ne; ++e) f[e] = mesh.fraction(e);
      scalars("volume_fraction", f);
    }
    o << "<DataArray type=\"Int32\" Name=\"level\" format=\"ascii\">\n";
    for (int e = 0; e < ne; ++e) o << (cells.level.empty() ? 0 : cells.level[e]) << '\n';
    o << "</DataArray>\n</CellData>\n<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n";
    for (int i = 0; i < nn; ++i) o << x[3 * i] << ' ' << x[3 * i + 1] << ' ' << x[3 * i + 2] << '\n';
    o << "</DataArray>\n</Points>\n<Cells>\n<DataArray type=\"Int32\" Name=\"connectivity\" format=\"ascii\">\n";
    for (int e = 0; e < ne; ++e) {
      for (int a : mesh.element(e)) o << a << ' ';
      o << '\n';
    }
    o << "</DataArray>\n<DataArray type=\"Int32\" Name=\"offsets\" format=\"ascii\">\n";
    for (int e = 1; e <= ne; ++e) o << 8 * e << '\n';
    o << "</DataArray>\n<DataArray type=\"UInt8\" Name=\"types\" format=\"ascii\">\n";
    for (int e = 0; e < ne; ++e) o << "12\n";  // VTK_HEXAHEDRON
    o << "</DataArray>\n</Cells>\n</Piece>\n</UnstructuredGrid>\n</VTKFile>\n";
  });
}

void writeSurfaceVtp(const std::string& path, const TriangleMesh& rest, const std::vector<Vec3>& p) {
  writeAtomically(path, [&](std::ofstream& o) {
    const int nv = rest.numVertices(), nt = rest.numTriangles();
    o << "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"0.1\" byte_order=\"LittleEndian\">\n<PolyData>\n"
      << "<Piece NumberOfPoints=\"" << nv << "\" NumberOfPolys=\"" << nt << "\">\n";
    o << "<PointData Vectors=\"displacement\">\n<DataArray type=\"Float64\" Name=\"displacement\" "
         "NumberOfComponents=\"3\" format=\"ascii\">\n";
    for (int i = 0; i < nv; ++i) {
      const Vec3 u = p[i] - rest.vertex(i);
      o << u[0] << ' ' << u[1] << ' ' << u[2] << '\n';
    }
    o << "</DataArray>\n</PointData>\n<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n";
    for (const auto& v : p) o << v[0] << ' ' << v[1] << ' ' << v[2] << '\n';
    o << "</DataArray>\n</Points>\n<Polys>\n<DataArray type=\"Int32\" Name=\"connectivity\" format=\"ascii\">\n";
    for (const auto& t : rest.triangles()) o << t[0] << ' ' << t[1] << ' ' << t[2] << '\n';
    o << "</DataArray>\n<DataArray type=\"Int32\" Name=\"offsets\" format=\"ascii\">\n";
    for (int t = 1; t <= nt; ++t) o << 3 * t << '\n';
    o << "</DataArray>\n</Polys>\n</Piece>\n</PolyData>\n</VTKFile>\n";
  });
}

void writeCentreLinesVtp(const std::string& path, const std::vector<std::vector<Vec3>>& lines) {
  writeAtomically(path, [&](std::ofstream& o) {
    int np = 0;
    for (const auto& l : lines) np += static_cast<int>(l.size());
    o << "<?xml version=\"1.0\"?>\n<VTKFile type=\"PolyData\" version=\"0.1\" byte_order=\"LittleEndian\">\n<PolyData>\n"
      << "<Piece NumberOfPoints=\"" << np << "\" NumberOfLines=\"" << lines.size() << "\">\n";
    o << "<CellData Scalars=\"needle\">\n<DataArray type=\"Int32\" Name=\"needle\" format=\"ascii\">\n";
    for (size_t k = 0; k < lines.size(); ++k) o << k << '\n';
    o << "</DataArray>\n</CellData>\n<Points>\n<DataArray type=\"Float64\" NumberOfComponents=\"3\" format=\"ascii\">\n";
    for (const auto& l : lines)
      for (const auto& v : l) o << v[0] << ' ' << v[1] << ' ' << v[2] << '\n';
    o << "</DataArray>\n</Points>\n<Lines>\n<DataArray type=\"Int32\" Name=\"connectivity\" format=\"ascii\">\n";
    int next = 0;
    for (const auto& l : lines) {
      for (size_t i = 0; i < l.size(); ++i) o << next++ << ' ';
      o << '\n';
    }
    o << "</DataArray>\n<DataArray type=\"Int32\" Name=\"offsets\" format=\"ascii\">\n";
    int off = 0;
    for (const auto& l : lines) o << (off += static_cast<int>(l.size())) << '\n';
    o << "</DataArray>\n</Lines>\n</Piece>\n</PolyData>\n</VTKFile>\n";
  });
}

void writePvd(const std::string& path, const std::vector<std::pair<double, std::string>>& steps) {
  writeAtomically(path, [&](std::ofstream& o) {
    o << "<?xml version=\"1.0\"?>\n<VTKFile type=\"Collection\" version=\"0.1\">\n<Collection>\n";
    for (const auto& [t, file] : steps) o << "<DataSet timestep=\"" << t << "\" file=\"" << file << "\"/>\n";
    o << "</Collection>\n</VTKFile>\n";
  });
}

}  // namespace needle_sim
