#pragma once
// Zienkiewicz-Zhu superconvergent patch recovery (SPR) error estimate (doc/method.md,
// paper §2.3).
//
//  1. Stresses at element centroids (the superconvergent point of a trilinear hex), from
//     the corotated displacement and rotated to the global frame: sigma_e = R (D B_c u) R^T.
//  2. Per node, a least-squares linear polynomial in (x, y, z) through the centroid stresses
//     of its element patch (rest coordinates). Boundary nodes, whose patches are too small
//     or flat for a 3D linear fit, take the average of the polynomials of the interior
//     patches they belong to; a node in no interior patch uses the minimum-norm fit of its
//     own patch (a constant when the patch is a single element).
//  3. Recovered field sigma* = sum_a N_a sigma*_a; element error in the energy norm
//     eta_e^2 = int_e (sigma_h - sigma*)^T D^-1 (sigma_h - sigma*) dV (2x2x2 Gauss, sigma_h
//     at the Gauss points), and the global estimate eta = sqrt(sum eta_e^2).
// Computed only when asked for: adaptivity, or an error output.
#include <array>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/corotational_hex_model.hpp"

namespace needle_sim {

using Stress = Eigen::Matrix<double, 6, 1>;  // Voigt: xx, yy, zz, xy, yz, zx

struct ErrorEstimate {
  std::vector<double> eta;              // per element
  std::vector<Stress> centroid_stress;  // per element, global frame
  std::vector<Stress> recovered;        // per node
  double global = 0;                    // sqrt(sum eta_e^2)
  double max = 0;
  double energy = 0;                    // sqrt(int sigma_h^T D^-1 sigma_h), for relative errors
  // sigma* - sigma_h at each element's 2x2x2 Gauss points (the goal estimate's duals pair
  // with it: SprEstimator::dual).
  std::vector<std::array<Stress, 8>> gauss_error;
};

class SprEstimator {
 public:
  explicit SprEstimator(const CorotationalHexModel& model);
  // Estimate for positions x (3n) with the model's current rotations.
  ErrorEstimate estimate(const VecX& x) const { return estimate(x, nullptr); }
  // Estimate of the stress change from positions `reference` to x (SPR is linear in the
  // stress field): after a preload such as the brain shift, the error of the response to
  // what came after it, which the preload's own large stresses would otherwise mask.
  ErrorEstimate estimate(const VecX& x, const VecX* reference) const { return estimate(x, reference, nullptr); }
  // The same, the rotations extracted from the given starting rotations (a copy of the
  // model's rotationGuesses() at the step x is of) instead of the model's current ones: an
  // estimate made on another thread while the model steps on (Simulation, estimate_delay).
  ErrorEstimate estimate(const VecX& x, const VecX* reference, const std::vector<Eigen::Quaterniond>* guesses) const;

  // Stress of element e at natural coordinates xi, global frame, for positions x (the
  // element's rotation is extracted from x).
  Stress elementStress(const VecX& x, int e, const Vec3& xi) const;
  Stress elementStress(const VecX& x, int e, const Vec3& xi, const Mat3& R) const;
  static double vonMises(const Stress& s);

  // The recovered nodal field (SPR patch fits) of given element-centroid stresses.
  std::vector<Stress> recover(const std::vector<Stress>& centroid) const;

  // A displacement increment dz (3n), linear about the rotations of x (the dual field of a
  // goal-oriented estimate, adapt/goal_estimator.hpp): its element error indicators in the
  // energy norm, and per element the product with the primal field's error,
  //     mixed_e = int_e (sigma*_u - sigma_u)^T D^-1 (sigma*_z - sigma_z) dV,
  // the primal field (x, reference) with its recovery `primal` (estimate()'s result).
  struct DualIndicators {
    std::vector<double> eta;    // per element
    std::vector<double> mixed;  // per element
    double global = 0;          // sqrt(sum eta^2)
    double mixed_total = 0;     // sum mixed
  };
  DualIndicators dual(const VecX& x, const VecX* reference, const ErrorEstimate& primal, const VecX& dz) const;

 private:
  // Element displacement in its corotated frame, relative to the centroid.
  Eigen::Matrix<double, 24, 1> corotatedDisplacement(const VecX& x, int e, const Mat3& R) const;

 public:

 private:
  // Per rest shape (the model's shapes: the volume fraction, which its references include,
  // plays no part): B at the centroid and at the 2x2x2 Gauss points with det J there. An
  // immersed grid has a few cell shapes but hundreds of references (10 kB each here).
  struct ShapeTables {
    Eigen::Matrix<double, 6, 24> centroid_B;
    std::array<Eigen::Matrix<double, 6, 24>, 8> gauss_B;
    std::array<double, 8> gauss_detJ{};
  };
  const ShapeTables& shape(int e) const { return shapes_[model_.shapeIndex(e)]; }
  // Element rotations of positions x, kept for the last two position vectors asked (the
  // primal's and the reference's: the duals of a pass ask for the same ones again).
  const std::vector<Mat3>& rotations(const VecX& x, const std::vector<Eigen::Quaterniond>* guesses = nullptr) const;

  const CorotationalHexModel& model_;
  std::vector<std::vector<int>> node_elements_;
  std::vector<Vec3> centroids_;
  std::vector<char> interior_;  // node has a full 3D patch
  // Interior nodes: the linear fit as a map from the patch's centroid values to the
  // coefficients (4 x patch size; coefficients = fit * values), made once per mesh.
  std::vector<Eigen::Matrix<double, 4, Eigen::Dynamic>> fit_;
  std::vector<ShapeTables> shapes_;
  struct RotationCache {
    VecX x;
    std::vector<Mat3> R;
  };
  mutable std::array<RotationCache, 2> rotation_cache_;
  mutable int rotation_next_ = 0;
};

}  // namespace needle_sim
