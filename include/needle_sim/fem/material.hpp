#pragma once
// Isotropic linear elastic material (small strain in the corotated frame).
#include <Eigen/Core>

namespace needle_sim {

// How a hexahedron integrates the material (doc/method.md "Element"); every one is computed
// once at rest into the element's K0 and strain operator (hex8.hpp), so they cost the same
// per step.
//   Trilinear          full 2x2x2 Gauss (the paper's element): locks in bending and as nu -> 0.5
//   Bbar               the volumetric strain replaced by its element mean (Hughes 1980; Q1-P0)
//   IncompatibleModes  nine condensed incompatible modes (Wilson et al. 1973, Taylor et al. 1976)
//   IncompatibleModesBbar  both: B-bar on the compatible strain, the modes added whole
enum class HexFormulation { Trilinear, Bbar, IncompatibleModes, IncompatibleModesBbar };

struct LinearElasticMaterial {
  double young = 1.0;    // E [Pa]
  double poisson = 0.3;  // nu, in (-1, 0.5)
  double density = 1.0;  // rho [kg/m^3]
  HexFormulation element = HexFormulation::IncompatibleModesBbar;  // how the hexahedra integrate it (#37)

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
