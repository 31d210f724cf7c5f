// needle_sim_amg_baseline: the static solve of a scene (solver.mode static, no contact) two
// ways, side by side at equal error (issue #18, doc/benchmarks.md "Static solves"):
//  - needle_sim's own: Newton with CG preconditioned by a CHOLMOD factor of an earlier
//    tangent (TissueBody::solveStatic, as `needle_sim run` does it);
//  - the baseline: the same Newton iteration (corotational forces and tangent, inexact
//    Newton to the same tolerance) with CG preconditioned by HYPRE's BoomerAMG, an algebraic
//    multigrid for elasticity (3 unknowns per node), its hierarchy built
//    for the first tangent and reused (as the factor is) or rebuilt at every Newton step.
// Both are measured against a reference solved tightly with the direct method; each is
// timed on its own (no warm-up beyond the first run). Built with -DNEEDLE_SIM_AMG_BASELINE=ON
// (scripts/amg_baseline.sh installs HYPRE and runs it); not part of the package's tools.
#include <HYPRE.h>
#include <HYPRE_parcsr_ls.h>
#include <mpi.h>

#include <CLI/CLI.hpp>
#include <Eigen/Sparse>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <memory>
#include <numeric>
#include <string>
#include <vector>

#include "needle_sim/core/stopwatch.hpp"
#include "needle_sim/scene/scene_loader.hpp"
#include "needle_sim/sim/simulation.hpp"

using namespace needle_sim;

namespace {

// The settings are the fastest of a sweep on the 32x16x16 box (doc/benchmarks.md, "Static
// solves": strength 0.25-0.9, relaxation 6/8, HMIS/PMIS/Falgout coarsening, interpolation,
// aggressive coarsening on 0-2 levels).
struct AmgOptions {
  bool nodal = false;         // nodal coarsening (the three unknowns of a node coarsened together)
  bool rebuild = false;       // a new hierarchy at every Newton step
  double strong = 0.5;        // strength threshold (3D elasticity: 0.5 and up)
  int max_iterations = 500;   // CG iterations per Newton step
};

struct NewtonResult {
  VecX x;
  int newton = 0, cg = 0;
  double setup_ms = 0, solve_ms = 0, assemble_ms = 0, forces_ms = 0, total_ms = 0;
  bool converged = false;
};

// A HYPRE IJ matrix and vectors over the free DOFs of one process.
class HypreSystem {
 public:
  explicit HypreSystem(int n) : n_(n), rows_(n) {
    std::iota(rows_.begin(), rows_.end(), 0);
    HYPRE_IJVectorCreate(MPI_COMM_WORLD, 0, n - 1, &b_);
    HYPRE_IJVectorSetObjectType(b_, HYPRE_PARCSR);
    HYPRE_IJVectorInitialize(b_);
    HYPRE_IJVectorCreate(MPI_COMM_WORLD, 0, n - 1, &x_);
    HYPRE_IJVectorSetObjectType(x_, HYPRE_PARCSR);
    HYPRE_IJVectorInitialize(x_);
  }
  ~HypreSystem() {
    if (A_) HYPRE_IJMatrixDestroy(A_);
    HYPRE_IJVectorDestroy(b_);
    HYPRE_IJVectorDestroy(x_);
  }
  // A full symmetric matrix in compressed rows.
  void setMatrix(const Eigen::SparseMatrix<double, Eigen::RowMajor, HYPRE_BigInt>& K) {
    if (A_) HYPRE_IJMatrixDestroy(A_);
    HYPRE_IJMatrixCreate(MPI_COMM_WORLD, 0, n_ - 1, 0, n_ - 1, &A_);
    HYPRE_IJMatrixSetObjectType(A_, HYPRE_PARCSR);
    std::vector<HYPRE_Int> sizes(n_);
    for (int i = 0; i < n_; ++i) sizes[i] = static_cast<HYPRE_Int>(K.outerIndexPtr()[i + 1] - K.outerIndexPtr()[i]);
    HYPRE_IJMatrixSetRowSizes(A_, sizes.data());
    HYPRE_IJMatrixInitialize(A_);
    std::vector<HYPRE_BigInt> rows(rows_.begin(), rows_.end());
    HYPRE_IJMatrixSetValues(A_, n_, sizes.data(), rows.data(), K.innerIndexPtr(), K.valuePtr());
    HYPRE_IJMatrixAssemble(A_);
    HYPRE_IJMatrixGetObject(A_, reinterpret_cast<void**>(&parA_));
  }
  void setVectors(const VecX& b, const VecX& x0) {
    std::vector<HYPRE_BigInt> rows(rows_.begin(), rows_.end());
    HYPRE_IJVectorSetValues(b_, n_, rows.data(), b.data());
    HYPRE_IJVectorSetValues(x_, n_, rows.data(), x0.data());
    HYPRE_IJVectorAssemble(b_);
    HYPRE_IJVectorAssemble(x_);
    HYPRE_IJVectorGetObject(b_, reinterpret_cast<void**>(&parb_));
    HYPRE_IJVectorGetObject(x_, reinterpret_cast<void**>(&parx_));
  }
  VecX solution() const {
    VecX out(n_);
    std::vector<HYPRE_BigInt> rows(rows_.begin(), rows_.end());
    HYPRE_IJVectorGetValues(x_, n_, rows.data(), out.data());
    return out;
  }
  HYPRE_ParCSRMatrix A() const { return parA_; }
  HYPRE_ParVector b() const { return parb_; }
  HYPRE_ParVector x() const { return parx_; }

 private:
  int n_;
  std::vector<int> rows_;
  HYPRE_IJMatrix A_ = nullptr;
  HYPRE_IJVector b_, x_;
  HYPRE_ParCSRMatrix parA_ = nullptr;
  HYPRE_ParVector parb_ = nullptr, parx_ = nullptr;
};

// The hierarchy kept across Newton steps: PCG's call to the preconditioner's setup is skipped.
HYPRE_Int noSetup(HYPRE_Solver, HYPRE_Matrix, HYPRE_Vector, HYPRE_Vector) { return 0; }

// The tangent K(x) over the free DOFs (no hanging DOFs: checked by the caller), full storage.
Eigen::SparseMatrix<double, Eigen::RowMajor, HYPRE_BigInt> tangent(const CorotationalHexModel& model, const DofMap& dofs) {
  std::vector<Eigen::Triplet<double, HYPRE_BigInt>> t;
  t.reserve(static_cast<size_t>(model.numElements()) * 576);
  hex8::Mat24 Ke;
  int fi[24];
  for (int e = 0; e < model.numElements(); ++e) {
    model.elementStiffness(e, Ke);
    const auto& el = model.mesh().element(e);
    for (int a = 0; a < 8; ++a)
      for (int c = 0; c < 3; ++c) fi[3 * a + c] = dofs.freeIndex(3 * el[a] + c);
    for (int i = 0; i < 24; ++i) {
      if (fi[i] < 0) continue;
      for (int j = 0; j < 24; ++j)
        if (fi[j] >= 0) t.emplace_back(fi[i], fi[j], Ke(i, j));
    }
  }
  Eigen::SparseMatrix<double, Eigen::RowMajor, HYPRE_BigInt> K(dofs.numFree(), dofs.numFree());
  K.setFromTriplets(t.begin(), t.end());
  K.makeCompressed();
  return K;
}

// Static Newton as TissueBody::solveStatic does it without extra terms (same convergence test,
// same forcing terms), the linear steps by BoomerAMG-preconditioned CG.
NewtonResult amgNewton(const TissueBody& body, double tol, int max_newton, double lin_tol, const AmgOptions& o) {
  const auto t_all = steadyNow();
  NewtonResult res;
  CorotationalHexModel model(body.model(), body.mesh());
  const DofMap& dofs = body.dofs();
  const int n = dofs.numFree();
  VecX x = body.mesh().restPositions(), r_full, r, dx_free, dx;
  const VecX rest = x;
  VecX fe;
  dofs.gather(body.externalForce(), fe);
  const double ref = fe.norm();
  auto residual = [&]() {
    const auto t0 = steadyNow();
    model.updateRotations(x);
    r_full = body.externalForce();
    model.addInternalForce(x, r_full);
    dofs.gather(r_full, r);
    res.forces_ms += msSince(t0);
    return r.norm();
  };
  // Component of each free DOF (x, y, z), for the systems AMG.
  std::vector<HYPRE_Int> dof_func(n);
  for (int i = 0; i < n; ++i) dof_func[i] = dofs.freeToFull()[i] % 3;
  HypreSystem sys(n);
  HYPRE_Solver amg = nullptr, pcg = nullptr;
  auto makeAmg = [&]() {
    if (amg) HYPRE_BoomerAMGDestroy(amg);
    HYPRE_BoomerAMGCreate(&amg);
    HYPRE_BoomerAMGSetPrintLevel(amg, 0);
    HYPRE_BoomerAMGSetMaxIter(amg, 1);  // one V-cycle per application
    HYPRE_BoomerAMGSetTol(amg, 0.0);
    HYPRE_BoomerAMGSetNumFunctions(amg, 3);
    // dof_func is owned by the caller's vector; BoomerAMG frees what it is given: a copy.
    HYPRE_Int* f = static_cast<HYPRE_Int*>(malloc(sizeof(HYPRE_Int) * n));
    std::copy(dof_func.begin(), dof_func.end(), f);
    HYPRE_BoomerAMGSetDofFunc(amg, f);
    if (o.nodal) HYPRE_BoomerAMGSetNodal(amg, 4);
    HYPRE_BoomerAMGSetStrongThreshold(amg, o.strong);
    HYPRE_BoomerAMGSetCoarsenType(amg, 10);  // HMIS
    HYPRE_BoomerAMGSetInterpType(amg, 6);    // extended+i
    HYPRE_BoomerAMGSetPMaxElmts(amg, 4);
    HYPRE_BoomerAMGSetRelaxType(amg, 6);     // symmetric hybrid Gauss-Seidel (CG needs symmetry)
    HYPRE_BoomerAMGSetNumSweeps(amg, 1);
    HYPRE_BoomerAMGSetAggNumLevels(amg, 1);  // aggressive coarsening on the first level
  };
  double rn = residual();
  const double rn0 = rn;
  double dxn = 0;
  for (int it = 0; it <= max_newton; ++it) {
    const double un = (x - rest).norm();
    const double refn = std::max(ref, rn0);
    if (rn <= tol * refn || (it > 0 && dxn <= tol * un)) {
      res.newton = it;
      res.converged = true;
      break;
    }
    if (it == max_newton) break;
    const double rel = refn > 0 ? rn / refn : 0;
    const double eta = rel > 0 ? std::clamp(std::max(std::min(1e-2, rel), 0.5 * tol / rel), lin_tol, std::max(1e-1, lin_tol)) : lin_tol;
    auto t0 = steadyNow();
    const auto K = tangent(model, dofs);
    sys.setMatrix(K);
    dx_free.setZero(n);
    sys.setVectors(r, dx_free);
    res.assemble_ms += msSince(t0);
    t0 = steadyNow();
    if (pcg) HYPRE_ParCSRPCGDestroy(pcg);
    HYPRE_ParCSRPCGCreate(MPI_COMM_WORLD, &pcg);
    HYPRE_PCGSetTol(pcg, eta);
    HYPRE_PCGSetTwoNorm(pcg, 1);  // ||b - A x|| <= tol ||b||, the test of needle_sim's CG
    HYPRE_PCGSetMaxIter(pcg, o.max_iterations);
    const bool setup = o.rebuild || !amg;
    if (setup) makeAmg();
    HYPRE_PCGSetPrecond(pcg, reinterpret_cast<HYPRE_PtrToSolverFcn>(HYPRE_BoomerAMGSolve),
                        setup ? reinterpret_cast<HYPRE_PtrToSolverFcn>(HYPRE_BoomerAMGSetup)
                              : reinterpret_cast<HYPRE_PtrToSolverFcn>(noSetup),
                        amg);
    HYPRE_ParCSRPCGSetup(pcg, sys.A(), sys.b(), sys.x());
    res.setup_ms += msSince(t0);
    t0 = steadyNow();
    HYPRE_ParCSRPCGSolve(pcg, sys.A(), sys.b(), sys.x());
    HYPRE_Int its = 0;
    HYPRE_PCGGetNumIterations(pcg, &its);
    res.cg += its;
    dx_free = sys.solution();
    res.solve_ms += msSince(t0);
    dofs.scatter(dx_free, dx);
    x += dx;
    dxn = dx.norm();
    rn = residual();
  }
  if (pcg) HYPRE_ParCSRPCGDestroy(pcg);
  if (amg) HYPRE_BoomerAMGDestroy(amg);
  res.x = x;
  res.total_ms = msSince(t_all);
  return res;
}

}  // namespace

int main(int argc, char** argv) {
  CLI::App app{"needle_sim's static solve against an algebraic-multigrid baseline (HYPRE BoomerAMG), at equal error"};
  std::string scene_path;
  std::vector<std::string> overrides;
  int repeat = 3;
  app.add_option("scene", scene_path, "scene file (its tissue solved statically, no needles)")->required();
  app.add_option("--set", overrides, "scene override key=value (repeatable)");
  app.add_option("--repeat", repeat, "timed runs of each method (the table gives the fastest and slowest)")->check(CLI::Range(1, 100));
  CLI11_PARSE(app, argc, argv);
  MPI_Init(&argc, &argv);
  HYPRE_Init();
  int status = 0;
  try {
    overrides.insert(overrides.begin(), "solver.mode=static");
    const Scene scene = loadScene(scene_path, overrides);
    const double tol = scene.solver.static_tolerance;
    const double lin_tol = scene.solver.linear.tolerance;
    // Reference: the direct method (a fresh factor every Newton step), 1e-4 of the tolerance.
    std::vector<std::string> tight = overrides;
    tight.push_back("solver.linear.method=direct");
    char tight_tol[64];
    std::snprintf(tight_tol, sizeof tight_tol, "solver.static.tolerance=%.3g", std::max(tol * 1e-4, 1e-14));
    tight.push_back(tight_tol);
    Simulation ref_sim(loadScene(scene_path, tight));
    if (ref_sim.tissue().dofs().numFree() != static_cast<int>(ref_sim.tissue().dofs().freeToFull().size()))
      throw std::runtime_error("unexpected DOF map");
    for (int d = 0; d < ref_sim.tissue().dofs().numFull(); ++d)
      if (ref_sim.tissue().dofs().hanging(d)) throw std::runtime_error("hanging DOFs are not supported by the baseline");
    ref_sim.step();
    const VecX u_ref = ref_sim.tissue().displacements();
    auto error = [&](const VecX& x) { return (x - ref_sim.tissue().mesh().restPositions() - u_ref).norm() / u_ref.norm(); };

    std::printf("needle_sim_amg_baseline: %s, %d free DOFs, static tolerance %.0e, CG tolerance %.0e, %d runs each\n",
                scene_path.c_str(), ref_sim.tissue().dofs().numFree(), tol, lin_tol, repeat);
    std::printf("| method | total ms (min-max) | setup or factor ms | CG ms | Newton | CG iterations | error vs reference |\n");
    std::printf("|---|---|---|---|---|---|---|\n");
    auto row = [](const char* name, std::vector<double> total, double setup, double solve, int newton, int cg, double err) {
      std::sort(total.begin(), total.end());
      std::printf("| %s | %.0f-%.0f | %.0f | %.0f | %d | %d | %.1e |\n", name, total.front(), total.back(), setup, solve, newton, cg,
                  err);
    };
    {
      std::vector<double> total;
      StepStats s;
      double err = 0;
      for (int k = 0; k < repeat; ++k) {
        Simulation sim(scene);  // made before the clock starts: the mesh, the model
        sim.tissue().model();
        const auto t0 = steadyNow();
        s = sim.step();
        total.push_back(msSince(t0));
        err = error(sim.tissue().positions());
      }
      row("needle_sim: CG + CHOLMOD factor of an earlier tangent", total, s.assemble_ms + s.factor_ms, s.solve_ms,
          s.newton_iterations, s.linear_iterations, err);
    }
    for (int variant = 0; variant < 3; ++variant) {
      AmgOptions o;
      o.nodal = variant == 2;
      o.rebuild = variant == 1;
      std::vector<double> total;
      NewtonResult r;
      for (int k = 0; k < repeat; ++k) {
        Simulation sim(scene);
        r = amgNewton(sim.tissue(), tol, scene.solver.static_max_iterations, lin_tol, o);
        if (!r.converged) throw std::runtime_error("AMG Newton did not converge");
        total.push_back(r.total_ms);
      }
      const char* name = variant == 0   ? "BoomerAMG-CG, unknown-based, hierarchy of the first tangent"
                         : variant == 1 ? "BoomerAMG-CG, unknown-based, hierarchy rebuilt every Newton step"
                                        : "BoomerAMG-CG, nodal coarsening, hierarchy of the first tangent";
      row(name, total, r.setup_ms, r.solve_ms, r.newton, r.cg, error(r.x));
    }
  } catch (const std::exception& e) {
    std::fprintf(stderr, "needle_sim_amg_baseline: %s\n", e.what());
    status = 1;
  }
  HYPRE_Finalize();
  MPI_Finalize();
  return status;
}
