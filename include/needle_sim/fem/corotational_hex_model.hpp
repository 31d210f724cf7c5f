#pragma once
// Corotational trilinear hexahedra (doc/method.md "Tissue").
//
// Per element a rotation R is extracted from the deformation gradient at the centroid;
// the element then behaves linearly in its rotated frame:
//   internal force   f_e = -R K0 (R^T x_e - X_e)
//   tangent          K_e =  R K0 R^T          (the dynamic steps' and the preconditioners')
// plus, for static Newton, the part from the rotation's own change (RotationTerms below).
// K0 is computed once at rest by 2x2x2 Gauss and shared between elements of identical
// shape (a uniform grid stores a single 24x24 matrix).
//
// R is the rotation of the polar decomposition F = R U, found by the quaternion
// iteration of Mueller et al. (2016), warm-started from the previous step's rotation.
// It always returns a proper rotation, also for flat or inverted elements, where an
// SVD-based polar decomposition needs explicit reflection handling.
#include <Eigen/Geometry>
#include <vector>

#include "needle_sim/core/types.hpp"
#include <atomic>

#include "needle_sim/fem/hex8.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/fem/material.hpp"

namespace needle_sim {

class CorotationalHexModel {
 public:
  CorotationalHexModel(const HexMesh& mesh, const LinearElasticMaterial& material);
  // A copy (rotations included) over `mesh`, a copy of other's mesh.
  CorotationalHexModel(const CorotationalHexModel& other, const HexMesh& mesh);
  CorotationalHexModel(const CorotationalHexModel&) = delete;
  CorotationalHexModel& operator=(const CorotationalHexModel&) = delete;

  const HexMesh& mesh() const { return mesh_; }
  // The material the references were computed for (the scene's).
  const LinearElasticMaterial& material() const { return material_; }
  // A factor on every element's stiffness: Young's modulus adopted during a run (Simulation::
  // adopt) is material().young times it. K0 is linear in E at a fixed nu (every formulation:
  // hex8.hpp), so scaling the products is exact. Atomic: a background factor refresh reads it.
  double stiffnessScale() const { return stiffness_scale_.load(std::memory_order_relaxed); }
  void setStiffnessScale(double s) { stiffness_scale_.store(s, std::memory_order_relaxed); }
  // material() with the adopted Young's modulus: what stresses and estimates use.
  LinearElasticMaterial materialInUse() const {
    LinearElasticMaterial m = material_;
    m.young *= stiffnessScale();
    return m;
  }
  int numElements() const { return mesh_.numElements(); }
  // Number of distinct element references (rest shape and volume fraction), i.e. K0 matrices stored.
  int numReferences() const { return static_cast<int>(refs_.size()); }
  const hex8::ElementReference& reference(int e) const { return refs_[ref_of_[e]]; }
  int referenceIndex(int e) const { return ref_of_[e]; }  // elements of one rest shape and fraction share it
  // Distinct rest shapes (hex8::shapeKey, the fraction left out): what depends on the
  // geometry alone is shared by the elements of one shape (the SPR estimator's B tables).
  int numShapes() const { return num_shapes_; }
  int shapeIndex(int e) const { return shape_of_[e]; }

  // Integral of N_a over the mesh, per node: the lumped mass is density times this.
  const VecX& nodalVolume() const { return nodal_volume_; }

  // Extracts every element's rotation from the current positions x (3n).
  void updateRotations(const VecX& x);
  const Mat3& rotation(int e) const { return rot_[e]; }
  const std::vector<Mat3>& rotations() const { return rot_; }
  // Sets the rotations the forces and the stiffness take (lagged rotations: those of the factor
  // in use, SystemSolver::factorRotations); the extraction's warm start stays as it was.
  void setRotations(const std::vector<Mat3>& r) { rot_ = r; }
  // Rotation of element e for positions x, without changing the model (warm-started from
  // the stored one): for outputs computed after a step (stresses, error estimates).
  Mat3 computeRotation(int e, const VecX& x) const;
  // The same from a given starting rotation (the extraction iterates from it): with a copy of
  // rotationGuesses() taken at a step, another thread computes what computeRotation would
  // have then, while this model steps on.
  Mat3 computeRotation(int e, const VecX& x, const Eigen::Quaterniond& guess) const;
  const std::vector<Eigen::Quaterniond>& rotationGuesses() const { return quat_; }
  // Sets all rotations to the identity (the linear, small-displacement model).
  void resetRotations();
  // Elements whose deformation gradient at the centroid has det F <= 0 at the last update.
  int invertedElements() const { return inverted_; }

  // f += internal elastic force for positions x with the current rotations.
  void addInternalForce(const VecX& x, VecX& f) const;
  // out += s * K v, with K = sum_e R K0 R^T (matrix-free).
  void addStiffnessProduct(const VecX& v, double s, VecX& out) const;
  // Rotated element stiffness R K0 R^T of element e.
  void elementStiffness(int e, hex8::Mat24& Ke) const { elementStiffness(e, rot_[e], Ke); }
  // The same with a given rotation (reads the element's reference only: another thread may
  // assemble from rotations captured earlier).
  void elementStiffness(int e, const Mat3& R, hex8::Mat24& Ke) const;
  // The rest of the consistent tangent, from the rotation's change with x (doc/method.md
  // "Static solves"): with dR = [w]x R and w = H^-1 sum_a (R g_a) x dx_a (the polar
  // decomposition's derivative, H = tr(S) I - S, S = F R^T, g_a = dN_a/dX at the centroid),
  //   K_rot dx = w x (R K0 u)_a - R K0 R^T (w x x~_b)_a      (x~: positions about the centroid).
  // It is not symmetric (the polar rotation is not the energy's minimiser): static Newton
  // takes it in the operator of a GMRES step, preconditioned by the factor of R K0 R^T.
  // Without it Newton converges only linearly once the elements have turned.
  struct RotationTerms {
    std::vector<Mat3> h_inv;                                 // per element (0: skipped)
    std::vector<Eigen::Matrix<double, 24, 1>> force;         // R K0 u, world frame
    std::vector<Eigen::Matrix<double, 24, 1>> centred;       // x~
  };
  // At positions x with the rotations of updateRotations(x).
  void rotationTerms(const VecX& x, RotationTerms& t) const;
  // out += s * K_rot v.
  void addRotationStiffnessProduct(const RotationTerms& t, const VecX& v, double s, VecX& out) const;
  // Elastic energy 1/2 sum_e u_e^T K0 u_e in the corotated frames.
  double elasticEnergy(const VecX& x) const;

 private:
  // F = sum_a x_a (dN_a/dX)^T at element e's centroid: what its rotation is extracted from.
  Mat3 deformationGradient(int e, const VecX& x) const;
  // Local (corotated) displacement R^T x_e - X_e of element e.
  Eigen::Matrix<double, 24, 1> localDisplacement(int e, const VecX& x) const;

  const HexMesh& mesh_;
  LinearElasticMaterial material_;
  std::atomic<double> stiffness_scale_{1.0};
  std::vector<hex8::ElementReference> refs_;
  std::vector<int> ref_of_;
  std::vector<int> shape_of_;
  int num_shapes_ = 0;
  std::vector<Eigen::Quaterniond> quat_;
  std::vector<Mat3> rot_;
  VecX nodal_volume_;
  int inverted_ = 0;
};

}  // namespace needle_sim
