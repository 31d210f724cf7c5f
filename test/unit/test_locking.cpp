// Volumetric locking (#37, doc/verification.md "Nearly incompressible tissue"): the shipped
// locking scenes with each hexahedron formulation against converged references computed
// outside the product (deal.II Taylor-Hood Q2-Q1, Richardson-extrapolated:
// test/data/locking_reference.json, tools/reference/). The trilinear element must be seen to
// lock (the benchmark can fail), the locking-free one must not.
#include <gtest/gtest.h>
#include <yaml-cpp/yaml.h>

#include <cstdio>
#include <string>

#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"
#include "fixtures.hpp"

using namespace needle_sim;

namespace {

const YAML::Node& reference() {
  static const YAML::Node r = YAML::LoadFile(std::string(NEEDLE_SIM_SOURCE_DIR) + "/test/data/locking_reference.json");
  return r;
}

// The extrapolated value of a quantity at nu; its error estimate in *err.
double referenceValue(const std::string& benchmark, double nu, const std::string& quantity, double* err) {
  for (const auto& kv : reference()["benchmarks"][benchmark]["by_nu"]) {
    if (std::abs(kv.first.as<double>() - nu) > 1e-12) continue;
    const YAML::Node q = kv.second["quantities"][quantity];
    *err = q["error_estimate"].as<double>();
    return q["extrapolated"].as<double>();
  }
  ADD_FAILURE() << benchmark << ": no reference at nu " << nu;
  return 0;
}

// One static step of a shipped scene; a probe's displacement component.
double staticProbe(const std::string& scene, const std::string& element, double nu, const std::string& cells, int probe,
                   int component) {
  Simulation sim(loadScene(needle_sim_test::sceneFile(scene), {"tissue.element=" + element, "tissue.material.poisson=" + std::to_string(nu),
                                              "tissue.grid.cells=" + cells}));
  sim.step();
  return sim.probeDisplacement(probe)[component];
}

struct Case {
  double nu;
  const char* cells;
  double bound;  // |relative error| allowed to incompatible_modes_bbar
};

}  // namespace

// The paper's block under gravity: the free end's sag. incompatible_modes_bbar within a few per
// cent on the paper's coarse meshes at every nu, and closer on the finer one; trilinear locks
// (more than half too stiff at 0.499 on 8x4x4, the 60-72 %).
TEST(Locking, PhantomBlockSagAgainstTheDealIIReference) {
  const Case cases[] = {{0.3, "[8,4,4]", 0.03},    {0.3, "[16,8,8]", 0.015},  {0.45, "[8,4,4]", 0.05},
                        {0.499, "[8,4,4]", 0.06},  {0.499, "[16,8,8]", 0.03}, {0.4999, "[8,4,4]", 0.06},
                        {0.4999, "[16,8,8]", 0.03}};
  for (const Case& c : cases) {
    double ref_err = 0;
    const double ref = referenceValue("phantom_box_mixed_Q2Q1", c.nu, "tip_uz", &ref_err);
    ASSERT_LT(ref_err, 0.005 * std::abs(ref));
    const double u = staticProbe("locking_box.yaml", "incompatible_modes_bbar", c.nu, c.cells, 0, 2);
    const double t = staticProbe("locking_box.yaml", "trilinear", c.nu, c.cells, 0, 2);
    std::printf("nu %.4f %-9s reference %.5e: incompatible_modes_bbar %+.2f %%, trilinear %+.2f %%\n", c.nu, c.cells, ref,
                100 * (u - ref) / ref, 100 * (t - ref) / ref);
    EXPECT_LT(std::abs(u - ref), c.bound * std::abs(ref)) << "nu " << c.nu << " " << c.cells;
    EXPECT_LT(std::abs(u - ref), std::abs(t - ref)) << "nu " << c.nu << " " << c.cells;  // never worse than trilinear
    if (c.nu >= 0.499 && std::string(c.cells) == "[8,4,4]") {
      EXPECT_LT(t / ref, 0.5) << "trilinear does not lock?";
    }
  }
}

// Cook's membrane in plane strain at nu = 0.4999, the classic locking test: the loaded corner.
TEST(Locking, CookMembranePlaneStrainAgainstTheDealIIReference) {
  const double scale = 1e-4;  // the scene's load is the reference's times this
  for (double nu : {0.3, 0.4999}) {
    double ref_err = 0;
    const double ref = referenceValue("cook_membrane_plane_strain_mixed_Q2Q1", nu, "corner_uy", &ref_err);
    for (const char* cells : {"[16,16,1]", "[32,32,1]"}) {
      const double u = staticProbe("cook_membrane_plane_strain.yaml", "incompatible_modes_bbar", nu, cells, 0, 1) / scale;
      const double t = staticProbe("cook_membrane_plane_strain.yaml", "trilinear", nu, cells, 0, 1) / scale;
      std::printf("nu %.4f %-10s reference %.4f: incompatible_modes_bbar %.4f, trilinear %.4f\n", nu, cells, ref, u, t);
      EXPECT_LT(std::abs(u - ref), (std::string(cells) == "[16,16,1]" ? 0.02 : 0.01) * ref) << "nu " << nu << " " << cells;
      EXPECT_LT(std::abs(u - ref), std::abs(t - ref)) << "nu " << nu << " " << cells;
      if (nu > 0.49) {
        EXPECT_LT(t / ref, 0.5) << "trilinear does not lock?";
      }
    }
  }
}

// The hex8 cantilever (bending): incompatible_modes_bbar bends as the beam does (u_y / (P L^3 /
// 3 E I); Timoshenko's beam with shear: 1.008 at nu 0.3), where trilinear locks in shear (0.648
// on 10x1x1) and, at nu = 0.4999, volumetrically too. A pure mean under the modes would bend 3.5
// times too far on 10x1x1 (doc/method.md "Tissue").
TEST(Locking, CantileverBendsAsTheBeam) {
  auto ratio = [](const std::string& element, double nu, const std::string& cells) {
    return staticProbe("cantilever_hex8.yaml", element, nu, cells, 0, 1) / (4.0 * 1e-3);
  };
  for (const char* cells : {"[10,1,1]", "[20,2,2]", "[40,4,4]"}) {
    const double r = ratio("incompatible_modes_bbar", 0.3, cells);
    std::printf("nu 0.3    %-9s incompatible_modes_bbar %.4f\n", cells, r);
    EXPECT_NEAR(r, 1.0, 0.01) << cells;
  }
  for (const char* cells : {"[20,2,2]", "[40,4,4]"}) {
    const double r = ratio("incompatible_modes_bbar", 0.4999, cells), t = ratio("trilinear", 0.4999, cells);
    std::printf("nu 0.4999 %-9s incompatible_modes_bbar %.4f, trilinear %.4f\n", cells, r, t);
    EXPECT_NEAR(r, 1.0, 0.02) << cells;
    EXPECT_LT(t, 0.6) << cells;
  }
}
