#pragma once
// Eigen aliases used across the library. Positions and displacements of n nodes are
// stored as one flat vector of length 3n (x0,y0,z0,x1,...), the layout the sparse
// solvers need.
#include <Eigen/Core>
#include <Eigen/Geometry>
#include <Eigen/SparseCore>
#include <array>
#include <vector>

namespace needle_sim {

using Vec3 = Eigen::Vector3d;
using Mat3 = Eigen::Matrix3d;
using VecX = Eigen::VectorXd;
using Vec3i = Eigen::Vector3i;
using SparseMatrix = Eigen::SparseMatrix<double, Eigen::ColMajor, int>;

inline Eigen::Map<Vec3> node3(VecX& v, int node) { return Eigen::Map<Vec3>(v.data() + 3 * node); }
inline Eigen::Map<const Vec3> node3(const VecX& v, int node) {
  return Eigen::Map<const Vec3>(v.data() + 3 * node);
}

}  // namespace needle_sim
