#pragma once
// Isotropic linear elastic material (small strain in the corotated frame).
#include <Eigen/Core>

namespace needle_sim {

struct LinearElasticMaterial {
  double young = 1.0;    // E [Pa]
  double poisson = 0.3;  // nu, in (-1, 0.5)
  double density = 1.0;  // rho [kg/m^3]

  double lameLambda() const { return young * poisson / ((1 + poisson) * (1 - 2 * poisson)); }
  double lameMu() const { return young / (2 * (1 + poisson)); }

  // Voigt elasticity matrix for (xx, yy, zz, xy, yz, zx) with engineering shear strains.
  Eigen::Matrix<double, 6, 6> elasticity() const {
    const double l = lameLambda(), m = lameMu();
    Eigen::Matrix<double, 6, 6> D = Eigen::Matrix<double, 6, 6>::Zero();
    D.topLeftCorner<3, 3>().setConstant(l);
    D.topLeftCorner<3, 3>().diagonal().array() += 2 * m;
    D.bottomRightCorner<3, 3>().diagonal().setConstant(m);
    return D;
  }
};

}  // namespace needle_sim
