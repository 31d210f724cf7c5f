#pragma once
// Corotational 3D Euler-Bernoulli beam (doc/method.md "Needle").
//
// The needle is a chain of 2-node elements with 6 DOF per node: a position p_i and an
// orientation q_i, the rotation carrying the node's rest material frame to its current
// one. Orientations are unit quaternions updated multiplicatively, q <- exp(dphi) q, with
// dphi a spin in the world frame, so they never drift off the rotation group.
//
// Each element carries a frame R_e: first axis along the chord p_b - p_a, twist from the
// mean of the two node rotations. In that frame the element is a linear Hermite beam
// loaded only by its deformational quantities: stretch l - L0, twist and the end
// rotations relative to the chord, theta_a, theta_b = log(R_e^T R_i E0). The internal
// force is the exact gradient of the local energy through those quantities (chord spin
// included), so rigid motions of any size produce no force, and constant curvature is
// represented exactly at the nodes. Tangent for dynamics: the linear 12x12 stiffness
// rotated into R_e; for static equilibrium under large loads a consistent tangent by
// central differences of the element force (the needle has tens of elements).
#include <Eigen/Geometry>
#include <vector>

#include "needle_sim/core/types.hpp"

namespace needle_sim {

struct BeamSection {
  double outer_radius = 1e-3;
  double inner_radius = 0.0;  // 0: solid
  double area() const;
  double secondMoment() const;  // I about a diameter
  double polarMoment() const;   // J = 2 I
};

struct BeamMaterial {
  double young = 2e11;
  double poisson = 0.3;
  double density = 8000;
  double shearModulus() const { return young / (2 * (1 + poisson)); }
};

using Mat12 = Eigen::Matrix<double, 12, 12>;
using Vec12 = Eigen::Matrix<double, 12, 1>;

// Positions and orientations of all nodes.
struct BeamState {
  std::vector<Vec3> p;
  std::vector<Eigen::Quaterniond> q;
};

class CorotationalBeam {
 public:
  // A straight beam of `elements` equal elements from `base` along unit `direction`.
  CorotationalBeam(int elements, double length, const BeamSection& section, const BeamMaterial& material,
                   const Vec3& base, const Vec3& direction);

  int numNodes() const { return static_cast<int>(rest_.size()); }
  int numElements() const { return numNodes() - 1; }
  int numDofs() const { return 6 * numNodes(); }
  double length() const { return length_; }
  double elementLength() const { return L0_; }
  const BeamSection& section() const { return section_; }
  const BeamMaterial& material() const { return material_; }
  const Vec3& restPosition(int i) const { return rest_[i]; }
  const Vec3& restDirection() const { return dir0_; }
  // Rest material frame E0: columns (axis, normal, binormal).
  const Eigen::Quaterniond& restFrame() const { return qE0_; }
  BeamState restState() const;

  // Internal force vector (6 per node: force, then moment, world frame).
  void internalForce(const BeamState& s, VecX& f) const;
  // Internal force of one element on its two nodes (12 entries).
  Vec12 elementForce(const BeamState& s, int e) const;
  // Linear beam stiffness rotated into the element frame (the dynamic tangent).
  void elementStiffness(const BeamState& s, int e, Mat12& K) const;
  // Consistent tangent -d f_e / d(dp, dphi) by central differences, symmetrised.
  void elementConsistentStiffness(const BeamState& s, int e, Mat12& K) const;
  double elasticEnergy(const BeamState& s) const;

  // Lumped mass per DOF: rho A L/2 per element end for translations, rho J L/2 for
  // rotations (isotropic rotary inertia; gyroscopic terms are neglected).
  VecX lumpedMass() const;

  // Applies increments: p += dp, q <- exp(dphi) q, for a 6n vector.
  static void applyIncrement(BeamState& s, const VecX& d);

 private:
  struct Local {
    Eigen::Quaterniond qe;  // element frame
    Vec3 e1;
    double l;
    Vec3 ta, tb;  // end rotations in the element frame
  };
  Local local(const BeamState& s, int e) const;
  Local local(const Vec3& pa, const Eigen::Quaterniond& qa, const Vec3& pb, const Eigen::Quaterniond& qb) const;
  Vec12 elementForce(const Local& o) const;
  Eigen::Matrix<double, 12, 12> localStiffness() const;

  double length_, L0_;
  BeamSection section_;
  BeamMaterial material_;
  Vec3 dir0_;
  Eigen::Quaterniond qE0_;
  std::vector<Vec3> rest_;
  double EA_, GJ_, EI_;
  Mat12 Kloc_;
};

// Rotation vector of a unit quaternion (log map), accurate for small angles.
Vec3 quaternionLog(const Eigen::Quaterniond& q);
// Unit quaternion of a rotation vector (exp map).
Eigen::Quaterniond quaternionExp(const Vec3& v);

}  // namespace needle_sim
