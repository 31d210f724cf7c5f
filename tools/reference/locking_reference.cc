// Reference solutions for needle_sim's locking benchmarks, computed with
// deal.II (Debian's 9.4.1) outside the product's build.
//
// Linear isotropic elasticity, two formulations:
//   mixed        Taylor-Hood Q2-Q1 displacement/pressure, p = lambda div u:
//                  (2 mu eps(u), eps(v)) + (p, div v)          = (f, v) + (t, v)_N
//                  (div u, q)            - (1/lambda) (p, q)    = 0
//                stable (inf-sup) and uniform in lambda, up to nu = 0.5.
//   displacement plain Q2 displacement (the step-8 form):
//                  (2 mu eps(u), eps(v)) + (lambda div u, div v) = (f, v) + (t, v)_N
//
// Tasks (see README.md):
//   verify                      solver checks with exactly representable solutions
//   box   --nu NU --n N         phantom box, N x N/2 x N/2 hexahedra
//   cook  --nu NU --n N         Cook's membrane (plane strain or --plane-stress)
// Each run prints one JSON object on stdout; progress goes to stderr.

#include <deal.II/base/function.h>
#include <deal.II/base/mpi.h>
#include <deal.II/base/quadrature_lib.h>
#include <deal.II/base/timer.h>
#include <deal.II/base/utilities.h>

#include <deal.II/dofs/dof_handler.h>
#include <deal.II/dofs/dof_renumbering.h>
#include <deal.II/dofs/dof_tools.h>

#include <deal.II/fe/fe_q.h>
#include <deal.II/fe/fe_system.h>
#include <deal.II/fe/fe_values.h>
#include <deal.II/fe/mapping_q1.h>

#include <deal.II/grid/grid_generator.h>
#include <deal.II/grid/grid_tools.h>
#include <deal.II/grid/tria.h>

#include <deal.II/lac/affine_constraints.h>
#include <deal.II/lac/block_sparse_matrix.h>
#include <deal.II/lac/block_sparsity_pattern.h>
#include <deal.II/lac/block_vector.h>
#include <deal.II/lac/dynamic_sparsity_pattern.h>
#include <deal.II/lac/solver_cg.h>
#include <deal.II/lac/solver_control.h>
#include <deal.II/lac/solver_minres.h>
#include <deal.II/lac/sparse_matrix.h>
#include <deal.II/lac/sparse_direct.h>
#include <deal.II/lac/trilinos_precondition.h>

#include <deal.II/numerics/vector_tools.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <functional>
#include <iomanip>
#include <iostream>
#include <limits>
#include <map>
#include <set>
#include <sstream>
#include <stdexcept>
#include <string>
#include <vector>

using namespace dealii;

namespace ref
{
  // ------------------------------------------------------------------ utils

  std::string
  num(const double x)
  {
    if (!std::isfinite(x))
      return "null";
    std::ostringstream s;
    s << std::setprecision(15) << x;
    return s.str();
  }

  template <int dim>
  std::string
  vec_json(const Tensor<1, dim> &v)
  {
    std::string s = "[";
    for (unsigned int d = 0; d < dim; ++d)
      s += (d ? ", " : "") + num(v[d]);
    return s + "]";
  }

  template <int dim>
  std::string
  point_json(const Point<dim> &v)
  {
    std::string s = "[";
    for (unsigned int d = 0; d < dim; ++d)
      s += (d ? ", " : "") + num(v[d]);
    return s + "]";
  }

  double
  wall_seconds()
  {
    return std::chrono::duration<double>(
             std::chrono::steady_clock::now().time_since_epoch())
      .count();
  }

  // ------------------------------------------------------------ material

  struct Material
  {
    double E      = 1.0;
    double nu     = 0.3;
    double mu     = 0.0;
    double lambda = 0.0; // may be +inf at nu = 0.5 (then 1/lambda = 0)

    // plane_stress (2D only): the in-plane response of a thin plate,
    // lambda* = 2 lambda mu / (lambda + 2 mu).
    static Material
    from_E_nu(const double E, const double nu, const bool plane_stress = false)
    {
      Material m;
      m.E  = E;
      m.nu = nu;
      m.mu = E / (2.0 * (1.0 + nu));
      if (plane_stress)
        m.lambda = E * nu / (1.0 - nu * nu);
      else if (nu >= 0.5)
        m.lambda = std::numeric_limits<double>::infinity();
      else
        m.lambda = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
      return m;
    }

    double
    inv_lambda() const
    {
      return std::isinf(lambda) ? 0.0 : 1.0 / lambda;
    }
  };

  // ---------------------------------------------------- problem definition

  template <int dim>
  using VectorField = std::function<Tensor<1, dim>(const Point<dim> &)>;

  template <int dim>
  using TractionField =
    std::function<Tensor<1, dim>(const Point<dim> &, const Tensor<1, dim> &)>;

  template <int dim>
  struct ProblemSpec
  {
    Material                                       material;
    std::set<types::boundary_id>                   dirichlet_ids;
    // symmetry planes: boundary id -> the displacement component (the
    // plane's normal) that is zero there; the others are free
    std::map<types::boundary_id, unsigned>         symmetry_ids;
    VectorField<dim>                               dirichlet_value; // null: 0
    VectorField<dim>                               body_force;      // null: 0
    std::map<types::boundary_id, TractionField<dim>> tractions;
  };

  enum class Formulation
  {
    mixed,
    displacement
  };

  enum class SolverKind
  {
    direct,
    iterative
  };

  struct SolveInfo
  {
    std::string method;
    unsigned    iterations        = 0;
    bool        converged         = true; // iterative: reached the tolerance
    double      relative_residual = 0.0; // ||K x - b|| / ||b|| (true residual)
    double      seconds_setup     = 0.0;
    double      seconds_solve     = 0.0;
  };

  // A Function<dim> with dim+1 (or dim) components from a VectorField, for
  // interpolate_boundary_values. The extra (pressure) component is 0.
  template <int dim>
  class FieldFunction : public Function<dim>
  {
  public:
    FieldFunction(const VectorField<dim> &f, const unsigned n_components)
      : Function<dim>(n_components)
      , f(f)
    {}

    double
    value(const Point<dim> &p, const unsigned int component) const override
    {
      if (component >= dim || !f)
        return 0.0;
      return f(p)[component];
    }

  private:
    VectorField<dim> f;
  };

  // ---------------------------------------------------------- the solver

  template <int dim>
  class ElasticitySolver
  {
  public:
    ElasticitySolver(const Triangulation<dim> &tria,
                     const ProblemSpec<dim> &  spec,
                     const Formulation         formulation)
      : tria(tria)
      , spec(spec)
      , formulation(formulation)
      , fe(make_fe(formulation))
      , dof_handler(tria)
      , quadrature(3)
      , face_quadrature(3)
    {}

    void
    setup_and_assemble();
    SolveInfo
    solve(SolverKind kind, double tolerance = 1e-12);

    // u (and p) at a point; throws if the point is outside the mesh.
    Vector<double>
    value_at(const Point<dim> &p) const;

    Tensor<1, dim>
    displacement_at(const Point<dim> &p) const
    {
      const Vector<double> v = value_at(p);
      Tensor<1, dim>       u;
      for (unsigned d = 0; d < dim; ++d)
        u[d] = v[d];
      return u;
    }

    // External work of the loads, int f.u dV + int t.u dA (= compliance)
    double
    external_work() const;
    // Strain energy 1/2 (2 mu eps:eps + lambda (div u)^2); in the mixed form
    // the volumetric part is 1/2 p^2/lambda (p the discrete pressure).
    double
    strain_energy() const;

    // max over the nodes of |u_h - u| (displacement components) and of
    // |p_h - p| (pressure, mixed only) against exact fields.
    std::pair<double, double>
    nodal_errors(const VectorField<dim> &            u_exact,
                 const std::function<double(const Point<dim> &)> &p_exact) const;

    // L2 norm of u_h - u over the domain.
    double
    l2_error(const VectorField<dim> &u_exact) const;

    types::global_dof_index
    n_dofs() const
    {
      return dof_handler.n_dofs();
    }
    std::vector<types::global_dof_index> dofs_per_block;

  private:
    static std::unique_ptr<FESystem<dim>>
    make_fe(const Formulation f)
    {
      if (f == Formulation::mixed)
        return std::make_unique<FESystem<dim>>(FE_Q<dim>(2), dim, FE_Q<dim>(1), 1);
      return std::make_unique<FESystem<dim>>(FE_Q<dim>(2), dim);
    }

    bool
    mixed() const
    {
      return formulation == Formulation::mixed;
    }

    const Triangulation<dim> &      tria;
    const ProblemSpec<dim> &        spec;
    const Formulation               formulation;
    std::unique_ptr<FESystem<dim>>  fe;
    DoFHandler<dim>                 dof_handler;
    const QGauss<dim>               quadrature;
    const QGauss<dim - 1>           face_quadrature;
    MappingQ1<dim>                  mapping;
    AffineConstraints<double>       constraints;
    BlockSparsityPattern            sparsity;
    BlockSparseMatrix<double>       K;
    SparseMatrix<double>            P; // pressure block: (1/mu + 1/lambda) M_p
    BlockVector<double>             rhs;
    BlockVector<double>             solution;
  };

  template <int dim>
  void
  ElasticitySolver<dim>::setup_and_assemble()
  {
    dof_handler.distribute_dofs(*fe);
    DoFRenumbering::Cuthill_McKee(dof_handler);
    std::vector<unsigned int> block_component(fe->n_components(), 0);
    if (mixed())
      block_component[dim] = 1;
    DoFRenumbering::component_wise(dof_handler, block_component);
    dofs_per_block =
      DoFTools::count_dofs_per_fe_block(dof_handler, block_component);
    const unsigned n_blocks = dofs_per_block.size();

    constraints.clear();
    const FEValuesExtractors::Vector u_ex(0);
    const FieldFunction<dim> bc(spec.dirichlet_value, fe->n_components());
    for (const auto id : spec.dirichlet_ids)
      VectorTools::interpolate_boundary_values(
        mapping, dof_handler, id, bc, constraints, fe->component_mask(u_ex));
    for (const auto &sym : spec.symmetry_ids)
      VectorTools::interpolate_boundary_values(
        mapping, dof_handler, sym.first,
        Functions::ZeroFunction<dim>(fe->n_components()), constraints,
        fe->component_mask(FEValuesExtractors::Scalar(sym.second)));
    constraints.close();

    {
      BlockDynamicSparsityPattern dsp(dofs_per_block, dofs_per_block);
      DoFTools::make_sparsity_pattern(dof_handler, dsp, constraints, false);
      sparsity.copy_from(dsp);
    }
    K.reinit(sparsity);
    if (mixed())
      P.reinit(sparsity.block(1, 1));
    rhs.reinit(dofs_per_block);
    solution.reinit(dofs_per_block);
    (void)n_blocks;

    const double mu        = spec.material.mu;
    const double lambda    = spec.material.lambda;
    const double inv_lam   = spec.material.inv_lambda();
    const double schur_fac = 1.0 / mu + inv_lam;

    FEValues<dim>     fv(mapping, *fe, quadrature,
                     update_values | update_gradients | update_quadrature_points |
                       update_JxW_values);
    FEFaceValues<dim> ffv(mapping, *fe, face_quadrature,
                          update_values | update_quadrature_points |
                            update_normal_vectors | update_JxW_values);
    const FEValuesExtractors::Scalar p_ex(dim);

    const unsigned int dpc = fe->n_dofs_per_cell();
    FullMatrix<double> cell_K(dpc, dpc), cell_P(dpc, dpc);
    Vector<double>     cell_rhs(dpc);
    std::vector<types::global_dof_index> local_dofs(dpc);
    std::vector<SymmetricTensor<2, dim>> eps(dpc);
    std::vector<double>                  div(dpc), q(dpc);
    std::vector<Tensor<1, dim>>          phi(dpc);

    for (const auto &cell : dof_handler.active_cell_iterators())
      {
        fv.reinit(cell);
        cell_K   = 0;
        cell_P   = 0;
        cell_rhs = 0;
        for (unsigned int k = 0; k < quadrature.size(); ++k)
          {
            const double JxW = fv.JxW(k);
            for (unsigned int i = 0; i < dpc; ++i)
              {
                eps[i] = fv[u_ex].symmetric_gradient(i, k);
                div[i] = fv[u_ex].divergence(i, k);
                phi[i] = fv[u_ex].value(i, k);
                q[i]   = mixed() ? fv[p_ex].value(i, k) : 0.0;
              }
            const Tensor<1, dim> f =
              spec.body_force ? spec.body_force(fv.quadrature_point(k)) :
                                Tensor<1, dim>();
            for (unsigned int i = 0; i < dpc; ++i)
              {
                for (unsigned int j = 0; j < dpc; ++j)
                  {
                    double a = 2.0 * mu * (eps[i] * eps[j]);
                    if (mixed())
                      {
                        a += div[i] * q[j] + q[i] * div[j] - inv_lam * q[i] * q[j];
                        cell_P(i, j) += schur_fac * q[i] * q[j] * JxW;
                      }
                    else
                      a += lambda * div[i] * div[j];
                    cell_K(i, j) += a * JxW;
                  }
                cell_rhs(i) += (f * phi[i]) * JxW;
              }
          }
        for (const auto face : cell->face_indices())
          if (cell->at_boundary(face))
            {
              const auto it = spec.tractions.find(cell->face(face)->boundary_id());
              if (it == spec.tractions.end())
                continue;
              ffv.reinit(cell, face);
              for (unsigned int k = 0; k < face_quadrature.size(); ++k)
                {
                  const Tensor<1, dim> t =
                    it->second(ffv.quadrature_point(k), ffv.normal_vector(k));
                  for (unsigned int i = 0; i < dpc; ++i)
                    cell_rhs(i) += (t * ffv[u_ex].value(i, k)) * ffv.JxW(k);
                }
            }
        cell->get_dof_indices(local_dofs);
        constraints.distribute_local_to_global(cell_K, cell_rhs, local_dofs, K, rhs);
        // the pressure has no constraints: add the pressure-pressure entries
        // directly (P holds only that block)
        if (mixed())
          for (unsigned int i = 0; i < dpc; ++i)
            if (fe->system_to_component_index(i).first == dim)
              for (unsigned int j = 0; j < dpc; ++j)
                if (fe->system_to_component_index(j).first == dim)
                  P.add(local_dofs[i] - dofs_per_block[0],
                        local_dofs[j] - dofs_per_block[0],
                        cell_P(i, j));
      }
  }

  // Block-diagonal, symmetric positive definite preconditioner for MINRES:
  // diag( AMG(A), [(1/mu + 1/lambda) M_p]^{-1} ).
  class BlockDiagonalPreconditioner
  {
  public:
    BlockDiagonalPreconditioner(const TrilinosWrappers::PreconditionAMG &amg,
                                const SparseDirectUMFPACK &              schur)
      : amg(amg)
      , schur(schur)
    {}
    void
    vmult(BlockVector<double> &dst, const BlockVector<double> &src) const
    {
      amg.vmult(dst.block(0), src.block(0));
      schur.vmult(dst.block(1), src.block(1));
    }

  private:
    const TrilinosWrappers::PreconditionAMG &amg;
    const SparseDirectUMFPACK &              schur;
  };

  template <int dim>
  SolveInfo
  ElasticitySolver<dim>::solve(const SolverKind kind, const double tolerance)
  {
    SolveInfo info;
    double    t0 = wall_seconds();
    if (kind == SolverKind::direct)
      {
        info.method = "UMFPACK (SparseDirectUMFPACK on the whole system)";
        SparseDirectUMFPACK direct;
        direct.initialize(K);
        info.seconds_setup = wall_seconds() - t0;
        t0                 = wall_seconds();
        direct.vmult(solution, rhs);
        info.seconds_solve = wall_seconds() - t0;
      }
    else
      {
        // AMG on the displacement block with the translations as near null
        // space (deal.II 9.4 takes constant modes only).
        const FEValuesExtractors::Vector u_ex(0);
        std::vector<std::vector<bool>>   constant_modes;
        DoFTools::extract_constant_modes(dof_handler,
                                         fe->component_mask(u_ex),
                                         constant_modes);
        TrilinosWrappers::PreconditionAMG                 amg;
        TrilinosWrappers::PreconditionAMG::AdditionalData data;
        data.elliptic              = true;
        data.higher_order_elements = true;
        data.smoother_sweeps       = 2;
        data.aggregation_threshold = 0.02;
        data.constant_modes        = constant_modes;
        amg.initialize(K.block(0, 0), data);

        const double  b_norm = rhs.l2_norm();
        SolverControl control(20000, tolerance * b_norm, false, false);
        if (mixed())
          {
            info.method = "MINRES, block-diagonal preconditioner "
                          "diag(ML AMG(A), UMFPACK((1/mu+1/lambda) M_p))";
            SparseDirectUMFPACK schur;
            schur.initialize(P);
            info.seconds_setup = wall_seconds() - t0;
            t0                 = wall_seconds();
            BlockDiagonalPreconditioner prec(amg, schur);
            SolverMinRes<BlockVector<double>> minres(control);
            try
              {
                minres.solve(K, solution, rhs, prec);
              }
            catch (const SolverControl::NoConvergence &)
              {
                info.converged = false;
              }
          }
        else
          {
            info.method        = "CG, ML AMG preconditioner";
            info.seconds_setup = wall_seconds() - t0;
            t0                 = wall_seconds();
            SolverCG<Vector<double>> cg(control);
            try
              {
                cg.solve(K.block(0, 0), solution.block(0), rhs.block(0), amg);
              }
            catch (const SolverControl::NoConvergence &)
              {
                info.converged = false;
              }
          }
        info.iterations    = control.last_step();
        info.seconds_solve = wall_seconds() - t0;
      }
    // true residual of the system as solved (constrained rows included)
    BlockVector<double> r(rhs);
    K.vmult(r, solution);
    r -= rhs;
    info.relative_residual = r.l2_norm() / std::max(rhs.l2_norm(), 1e-300);
    constraints.distribute(solution);
    return info;
  }

  template <int dim>
  Vector<double>
  ElasticitySolver<dim>::value_at(const Point<dim> &p) const
  {
    const auto cell_and_point =
      GridTools::find_active_cell_around_point(mapping, dof_handler, p);
    const Quadrature<dim> q(
      GeometryInfo<dim>::project_to_unit_cell(cell_and_point.second));
    FEValues<dim> fv(mapping, *fe, q, update_values);
    fv.reinit(cell_and_point.first);
    std::vector<Vector<double>> v(1, Vector<double>(fe->n_components()));
    fv.get_function_values(solution, v);
    return v[0];
  }

  template <int dim>
  double
  ElasticitySolver<dim>::external_work() const
  {
    const QGauss<dim>     qc(4);
    const QGauss<dim - 1> qf(4);
    FEValues<dim> fv(mapping, *fe, qc,
                     update_values | update_quadrature_points | update_JxW_values);
    FEFaceValues<dim> ffv(mapping, *fe, qf,
                          update_values | update_quadrature_points |
                            update_normal_vectors | update_JxW_values);
    const FEValuesExtractors::Vector u_ex(0);
    std::vector<Tensor<1, dim>>      u(qc.size()), uf(qf.size());
    double                           W = 0.0;
    for (const auto &cell : dof_handler.active_cell_iterators())
      {
        if (spec.body_force)
          {
            fv.reinit(cell);
            fv[u_ex].get_function_values(solution, u);
            for (unsigned k = 0; k < qc.size(); ++k)
              W += spec.body_force(fv.quadrature_point(k)) * u[k] * fv.JxW(k);
          }
        for (const auto face : cell->face_indices())
          if (cell->at_boundary(face))
            {
              const auto it = spec.tractions.find(cell->face(face)->boundary_id());
              if (it == spec.tractions.end())
                continue;
              ffv.reinit(cell, face);
              ffv[u_ex].get_function_values(solution, uf);
              for (unsigned k = 0; k < qf.size(); ++k)
                W += it->second(ffv.quadrature_point(k), ffv.normal_vector(k)) *
                     uf[k] * ffv.JxW(k);
            }
      }
    return W;
  }

  template <int dim>
  double
  ElasticitySolver<dim>::strain_energy() const
  {
    const QGauss<dim> qc(4);
    FEValues<dim>     fv(mapping, *fe, qc,
                     update_values | update_gradients | update_JxW_values);
    const FEValuesExtractors::Vector     u_ex(0);
    const FEValuesExtractors::Scalar     p_ex(dim);
    std::vector<SymmetricTensor<2, dim>> eps(qc.size());
    std::vector<double>                  div(qc.size()), p(qc.size());
    const double mu = spec.material.mu, lambda = spec.material.lambda;
    double       U  = 0.0;
    for (const auto &cell : dof_handler.active_cell_iterators())
      {
        fv.reinit(cell);
        fv[u_ex].get_function_symmetric_gradients(solution, eps);
        fv[u_ex].get_function_divergences(solution, div);
        if (mixed())
          fv[p_ex].get_function_values(solution, p);
        for (unsigned k = 0; k < qc.size(); ++k)
          {
            double e = 2.0 * mu * (eps[k] * eps[k]);
            e += mixed() ? p[k] * p[k] * spec.material.inv_lambda() :
                           lambda * div[k] * div[k];
            U += 0.5 * e * fv.JxW(k);
          }
      }
    return U;
  }

  template <int dim>
  std::pair<double, double>
  ElasticitySolver<dim>::nodal_errors(
    const VectorField<dim> &                         u_exact,
    const std::function<double(const Point<dim> &)> &p_exact) const
  {
    // Evaluate at every support point of every cell.
    const Quadrature<dim> q(fe->get_unit_support_points());
    FEValues<dim> fv(mapping, *fe, q, update_values | update_quadrature_points);
    std::vector<Vector<double>> v(q.size(), Vector<double>(fe->n_components()));
    double eu = 0.0, ep = 0.0;
    for (const auto &cell : dof_handler.active_cell_iterators())
      {
        fv.reinit(cell);
        fv.get_function_values(solution, v);
        for (unsigned k = 0; k < q.size(); ++k)
          {
            const Point<dim>     x  = fv.quadrature_point(k);
            const Tensor<1, dim> ue = u_exact(x);
            for (unsigned d = 0; d < dim; ++d)
              eu = std::max(eu, std::abs(v[k][d] - ue[d]));
            if (mixed() && p_exact)
              ep = std::max(ep, std::abs(v[k][dim] - p_exact(x)));
          }
      }
    return {eu, ep};
  }

  template <int dim>
  double
  ElasticitySolver<dim>::l2_error(const VectorField<dim> &u_exact) const
  {
    const QGauss<dim> qc(5);
    FEValues<dim>     fv(mapping, *fe, qc,
                     update_values | update_quadrature_points | update_JxW_values);
    const FEValuesExtractors::Vector u_ex(0);
    std::vector<Tensor<1, dim>>      u(qc.size());
    double                           e2 = 0.0;
    for (const auto &cell : dof_handler.active_cell_iterators())
      {
        fv.reinit(cell);
        fv[u_ex].get_function_values(solution, u);
        for (unsigned k = 0; k < qc.size(); ++k)
          e2 += (u[k] - u_exact(fv.quadrature_point(k))).norm_square() * fv.JxW(k);
      }
    return std::sqrt(e2);
  }

  // --------------------------------------------------------- geometries

  // Phantom box [0,0.04]x[0,0.02]x[0,0.02], n x n/2 x n/2 cells.
  // Boundary ids (colorize): x=0 ->0, x=0.04 ->1, y=0 ->2, y=0.02 ->3,
  // z=0 ->4, z=0.02 ->5.
  // half: only y <= 0.01, n x n/4 x n/2 cells (exactly the cells of the full
  // mesh with y <= 0.01), the symmetry plane y = 0.01 ->3.
  void
  make_box(Triangulation<3> &tria, const unsigned n, const bool half = false)
  {
    GridGenerator::subdivided_hyper_rectangle(tria,
                                              {n, half ? n / 4 : n / 2, n / 2},
                                              Point<3>(0, 0, 0),
                                              Point<3>(0.04, half ? 0.01 : 0.02, 0.02),
                                              true);
  }

  // Cook's membrane: the bilinear image of an n x n grid of the unit square
  // onto the quadrilateral (0,0), (48,44), (48,60), (0,44). Ids: x=0 (clamped)
  // ->0, x=48 (loaded) ->1, lower edge ->2, upper edge ->3.
  void
  make_cook(Triangulation<2> &tria, const unsigned n)
  {
    GridGenerator::subdivided_hyper_rectangle(
      tria, {n, n}, Point<2>(0, 0), Point<2>(1, 1), true);
    GridTools::transform(
      [](const Point<2> &s) {
        const double xi = s[0], eta = s[1];
        return Point<2>(48.0 * xi, 44.0 * xi + 44.0 * eta - 28.0 * xi * eta);
      },
      tria);
  }

  // ------------------------------------------------------------- tasks

  SolverKind
  pick_solver(const std::string &s, const types::global_dof_index n_dofs)
  {
    if (s == "direct")
      return SolverKind::direct;
    if (s == "iterative")
      return SolverKind::iterative;
    return n_dofs > 100000 ? SolverKind::iterative : SolverKind::direct;
  }

  std::string
  solve_json(const SolveInfo &s)
  {
    std::ostringstream o;
    o << "{\"method\": \"" << s.method << "\", \"iterations\": " << s.iterations
      << ", \"converged\": " << (s.converged ? "true" : "false")
      << ", \"relative_residual\": " << num(s.relative_residual)
      << ", \"seconds_setup\": " << num(s.seconds_setup)
      << ", \"seconds_solve\": " << num(s.seconds_solve) << "}";
    return o.str();
  }

  // The gravity-loaded box; half: the y <= 0.01 half with u_y = 0 on the
  // symmetry plane y = 0.01 (the same discrete solution as the full mesh,
  // whose cells are mirrored pairs; half the unknowns). Compliance and strain
  // energy are reported for the whole box (twice the half's).
  struct BoxResult
  {
    std::vector<std::pair<std::string, Point<3>>> points;
    std::vector<Tensor<1, 3>>                     u;
    double                                        compliance    = 0.0;
    double                                        strain_energy = 0.0;
    types::global_dof_index                       n_dofs        = 0;
    SolveInfo                                     solve;
  };

  BoxResult
  solve_box(const double       nu,
            const unsigned     n,
            const Formulation  form,
            const std::string &solver_name,
            const double       tol,
            const bool         half)
  {
    const double t_start = wall_seconds();
    const double E = 1.0e7, rho = 1000.0, g = 9.81;
    Triangulation<3> tria;
    make_box(tria, n, half);
    ProblemSpec<3> spec;
    spec.material      = Material::from_E_nu(E, nu);
    spec.dirichlet_ids = {1}; // x = 0.04
    if (half)
      spec.symmetry_ids[3] = 1; // y = 0.01: u_y = 0
    spec.body_force = [=](const Point<3> &) {
      return Tensor<1, 3>({0.0, 0.0, -rho * g});
    };
    ElasticitySolver<3> solver(tria, spec, form);
    solver.setup_and_assemble();
    const double t_asm = wall_seconds() - t_start;
    std::cerr << "box n=" << n << (half ? " (half)" : "") << " nu=" << nu
              << " dofs=" << solver.n_dofs() << " assembled in " << t_asm << " s"
              << std::endl;
    BoxResult res;
    res.n_dofs = solver.n_dofs();
    res.solve  = solver.solve(pick_solver(solver_name, solver.n_dofs()), tol);
    std::cerr << "  solved: " << res.solve.method << " it=" << res.solve.iterations
              << " res=" << res.solve.relative_residual << " ("
              << res.solve.seconds_setup << " + " << res.solve.seconds_solve << " s)"
              << std::endl;

    auto &pts = res.points;
    pts.emplace_back("tip", Point<3>(0.0, 0.01, 0.01));
    for (unsigned k = 1; k <= 7; ++k)
      pts.emplace_back("p" + std::to_string(k), Point<3>(0.0025 * k, 0.01, 0.01));
    for (unsigned j = 1; j <= 5; ++j)
      pts.emplace_back(std::string("p1") + char('A' + j - 1),
                       Point<3>(0.0025, 0.01, 0.01 + 0.0015 * j));
    pts.emplace_back("top_edge", Point<3>(0.0, 0.01, 0.02));
    for (const auto &pt : pts)
      res.u.push_back(solver.displacement_at(pt.second));

    const double factor = half ? 2.0 : 1.0;
    res.compliance      = factor * solver.external_work();
    res.strain_energy   = factor * solver.strain_energy();
    return res;
  }

  int
  run_box(const double       nu,
          const unsigned     n,
          const Formulation  form,
          const std::string &solver_name,
          const double       tol,
          const bool         half)
  {
    const double    t_start = wall_seconds();
    const BoxResult b       = solve_box(nu, n, form, solver_name, tol, half);
    const double    C = b.compliance, U = b.strain_energy;
    std::ostringstream o;
    o << "{\"benchmark\": \"phantom_box\", \"formulation\": \""
      << (form == Formulation::mixed ? "mixed_Q2Q1" : "displacement_Q2")
      << "\", \"nu\": " << num(nu) << ", \"mesh\": \"" << n << "x" << n / 2
      << "x" << n / 2 << "\", \"n\": " << n << ", \"half_symmetric\": "
      << (half ? "true" : "false") << ", \"n_dofs\": " << b.n_dofs
      << ", \"points\": {";
    for (unsigned i = 0; i < b.points.size(); ++i)
      o << (i ? ", " : "") << "\"" << b.points[i].first << "\": {\"x\": "
        << point_json(b.points[i].second) << ", \"u\": " << vec_json(b.u[i]) << "}";
    o << "}, \"compliance\": " << num(C) << ", \"strain_energy\": " << num(U)
      << ", \"energy_identity\": " << num((C - 2.0 * U) / C)
      << ", \"solver\": " << solve_json(b.solve)
      << ", \"seconds_total\": " << num(wall_seconds() - t_start) << "}";
    std::cout << o.str() << std::endl;
    return 0;
  }

  int
  run_cook(const double       nu,
           const double       E,
           const double       F,
           const unsigned     n,
           const bool         plane_stress,
           const Formulation  form,
           const std::string &solver_name,
           const double       tol)
  {
    const double     t_start = wall_seconds();
    Triangulation<2> tria;
    make_cook(tria, n);
    ProblemSpec<2> spec;
    spec.material      = Material::from_E_nu(E, nu, plane_stress);
    spec.dirichlet_ids = {0};
    const double t     = F / 16.0;
    spec.tractions[1]  = [=](const Point<2> &, const Tensor<1, 2> &) {
      return Tensor<1, 2>({0.0, t});
    };
    ElasticitySolver<2> solver(tria, spec, form);
    solver.setup_and_assemble();
    const SolveInfo si = solver.solve(pick_solver(solver_name, solver.n_dofs()), tol);
    const Point<2>  A(48.0, 60.0), B(48.0, 52.0);
    const double    C = solver.external_work();
    const double    U = solver.strain_energy();
    std::ostringstream o;
    o << "{\"benchmark\": \"cook_membrane\", \"formulation\": \""
      << (form == Formulation::mixed ? "mixed_Q2Q1" : "displacement_Q2")
      << "\", \"model\": \"" << (plane_stress ? "plane_stress" : "plane_strain")
      << "\", \"E\": " << num(E) << ", \"nu\": " << num(nu) << ", \"F\": " << num(F)
      << ", \"mesh\": \"" << n << "x" << n << "\", \"n\": " << n
      << ", \"n_dofs\": " << solver.n_dofs()
      << ", \"points\": {\"corner\": {\"x\": " << point_json(A)
      << ", \"u\": " << vec_json(solver.displacement_at(A)) << "}, \"mid\": {\"x\": "
      << point_json(B) << ", \"u\": " << vec_json(solver.displacement_at(B))
      << "}}, \"compliance\": " << num(C) << ", \"strain_energy\": " << num(U)
      << ", \"energy_identity\": " << num((C - 2.0 * U) / C)
      << ", \"solver\": " << solve_json(si)
      << ", \"seconds_total\": " << num(wall_seconds() - t_start) << "}";
    std::cout << o.str() << std::endl;
    return 0;
  }

  // ------------------------------------------------------- verification

  // A quadratic field u_i = a_i + B_ij x_j + 1/2 x.H_i.x with its exact
  // stress and body force; it lies in the Q2 space on affine cells, and its
  // pressure lambda div u (linear) lies in Q1, so both formulations must
  // reproduce it to round-off.
  template <int dim>
  struct QuadraticField
  {
    Tensor<1, dim>                       a;
    Tensor<2, dim>                       B;
    std::array<SymmetricTensor<2, dim>, dim> H;
    Material                             m;

    Tensor<1, dim>
    u(const Point<dim> &x) const
    {
      Tensor<1, dim> r = a + B * x;
      for (unsigned i = 0; i < dim; ++i)
        r[i] += 0.5 * (x * (H[i] * x));
      return r;
    }
    Tensor<2, dim>
    grad(const Point<dim> &x) const
    {
      Tensor<2, dim> G = B;
      for (unsigned i = 0; i < dim; ++i)
        for (unsigned j = 0; j < dim; ++j)
          for (unsigned k = 0; k < dim; ++k)
            G[i][j] += H[i][j][k] * x[k];
      return G;
    }
    double
    div(const Point<dim> &x) const
    {
      return trace(grad(x));
    }
    // pressure p = lambda div u (finite lambda only)
    double
    p(const Point<dim> &x) const
    {
      return m.lambda * div(x);
    }
    SymmetricTensor<2, dim>
    stress(const Point<dim> &x) const
    {
      const SymmetricTensor<2, dim> e = symmetrize(grad(x));
      return 2.0 * m.mu * e + m.lambda * trace(e) * unit_symmetric_tensor<dim>();
    }
    Tensor<1, dim>
    body_force() const
    {
      // f = -div sigma, sigma_ij = mu (u_i,j + u_j,i) + lambda div u delta_ij
      Tensor<1, dim> f;
      for (unsigned i = 0; i < dim; ++i)
        {
          double s = 0.0;
          for (unsigned j = 0; j < dim; ++j)
            s += m.mu * (H[i][j][j] + H[j][i][j]) + m.lambda * H[j][i][j];
          f[i] = -s;
        }
      return f;
    }
  };

  template <int dim>
  QuadraticField<dim>
  make_quadratic(const Material &m, const double scale_lin, const double scale_quad)
  {
    QuadraticField<dim> q;
    q.m = m;
    // Fixed, "generic" coefficients (no symmetry that could hide an error).
    const double c[] = {0.3, -0.7, 1.1, 0.45, -0.25, 0.9, -1.3, 0.6, 0.15,
                        -0.55, 0.8, -0.35, 1.05, -0.9, 0.2, 0.65, -0.4, 0.5};
    unsigned k = 0;
    for (unsigned i = 0; i < dim; ++i)
      {
        q.a[i] = scale_lin * 0.01 * c[k++ % 18];
        for (unsigned j = 0; j < dim; ++j)
          q.B[i][j] = scale_lin * c[k++ % 18];
        for (unsigned j = 0; j < dim; ++j)
          for (unsigned l = j; l < dim; ++l)
            q.H[i][j][l] = scale_quad * c[k++ % 18];
      }
    return q;
  }

  template <int dim>
  bool
  verify_exact(const std::string &       name,
               const Triangulation<dim> &tria,
               const std::set<types::boundary_id> &clamped,
               const std::set<types::boundary_id> &loaded,
               const QuadraticField<dim> &field,
               const Formulation          form,
               const SolverKind           kind,
               const double               tol_rel,
               std::ostream &             json)
  {
    ProblemSpec<dim> spec;
    spec.material        = field.m;
    spec.dirichlet_ids   = clamped;
    spec.dirichlet_value = [&](const Point<dim> &x) { return field.u(x); };
    const Tensor<1, dim> f = field.body_force();
    spec.body_force      = [=](const Point<dim> &) { return f; };
    for (const auto id : loaded)
      spec.tractions[id] = [&](const Point<dim> &x, const Tensor<1, dim> &n) {
        return Tensor<1, dim>(field.stress(x) * n);
      };
    ElasticitySolver<dim> s(tria, spec, form);
    s.setup_and_assemble();
    const SolveInfo si = s.solve(kind, 1e-14);
    const auto      err = s.nodal_errors(
      [&](const Point<dim> &x) { return field.u(x); },
      [&](const Point<dim> &x) { return field.p(x); });
    // scales for relative errors: max |u| and max |p| over the support points
    double umax = 0.0, pmax = 0.0;
    for (const auto &v : tria.get_vertices())
      {
        for (unsigned d = 0; d < dim; ++d)
          umax = std::max(umax, std::abs(field.u(v)[d]));
        pmax = std::max(pmax, std::abs(field.p(v)));
      }
    const double eu = err.first / umax;
    const double ep = form == Formulation::mixed ? err.second / pmax : 0.0;
    const bool   ok = eu < tol_rel && ep < tol_rel &&
                    si.relative_residual < 1e-8;
    std::cerr << (ok ? "PASS " : "FAIL ") << name << ": max nodal |u_h-u|/max|u| = "
              << eu << ", |p_h-p|/max|p| = " << ep << ", residual "
              << si.relative_residual << " (" << si.method << ", "
              << si.iterations << " it)" << std::endl;
    json << "{\"case\": \"" << name << "\", \"rel_nodal_error_u\": " << num(eu)
         << ", \"rel_nodal_error_p\": " << num(ep)
         << ", \"solver\": " << solve_json(si) << ", \"pass\": "
         << (ok ? "true" : "false") << "}";
    return ok;
  }

  // A smooth non-polynomial solution on the unit square (plane strain),
  // nearly divergence-free as nu -> 0.5 (u = u_df + (mu/lambda) w, div u_df = 0,
  // so p = lambda div u stays bounded): Taylor-Hood keeps its O(h^3) L2 rate
  // uniformly in nu; displacement-Q2 is reported alongside.
  bool
  verify_convergence(std::ostream &json)
  {
    bool ok = true;
    json << "\"smooth_convergence\": [";
    bool first = true;
    for (const double nu : {0.3, 0.4999})
      for (const Formulation form : {Formulation::mixed, Formulation::displacement})
        {
          const Material m     = Material::from_E_nu(1.0, nu);
          const double   kappa = m.mu * m.inv_lambda();
          const double   pi = M_PI, pi2 = pi * pi;
          auto u = [=](const Point<2> &x) {
            const double sx = std::sin(pi * x[0]), cx = std::cos(pi * x[0]);
            const double sy = std::sin(pi * x[1]), cy = std::cos(pi * x[1]);
            return Tensor<1, 2>(
              {sx * cy + kappa * (sx * cy + 0.1 * x[0] * x[1] * x[1]),
               -cx * sy + kappa * 0.5 * std::exp(x[0]) * std::sin(x[1])});
          };
          auto grad = [=](const Point<2> &x) {
            const double sx = std::sin(pi * x[0]), cx = std::cos(pi * x[0]);
            const double sy = std::sin(pi * x[1]), cy = std::cos(pi * x[1]);
            const double ex = std::exp(x[0]);
            Tensor<2, 2> G;
            G[0][0] = pi * cx * cy + kappa * (pi * cx * cy + 0.1 * x[1] * x[1]);
            G[0][1] = -pi * sx * sy + kappa * (-pi * sx * sy + 0.2 * x[0] * x[1]);
            G[1][0] = pi * sx * sy + kappa * 0.5 * ex * std::sin(x[1]);
            G[1][1] = -pi * cx * cy + kappa * 0.5 * ex * std::cos(x[1]);
            return G;
          };
          auto stress = [=](const Point<2> &x) {
            const SymmetricTensor<2, 2> e = symmetrize(grad(x));
            // lambda div u = lambda kappa div w = mu div w (exact, no 0*inf)
            const double ex = std::exp(x[0]);
            const double divw = pi * std::cos(pi * x[0]) * std::cos(pi * x[1]) +
                                0.1 * x[1] * x[1] + 0.5 * ex * std::cos(x[1]);
            const double p = std::isinf(m.lambda) ? 0.0 : m.mu * divw;
            return SymmetricTensor<2, 2>(2.0 * m.mu * e +
                                         p * unit_symmetric_tensor<2>());
          };
          auto body = [=](const Point<2> &x) {
            const double sx = std::sin(pi * x[0]), cx = std::cos(pi * x[0]);
            const double sy = std::sin(pi * x[1]), cy = std::cos(pi * x[1]);
            const double ex = std::exp(x[0]);
            // divergence-free part: Laplacians
            const double lap_df0 = -2.0 * pi2 * sx * cy;
            const double lap_df1 = 2.0 * pi2 * cx * sy;
            // w = (sin(pi x) cos(pi y) + 0.1 x y^2, 0.5 e^x sin y)
            const double w0_xx = -pi2 * sx * cy;
            const double w0_yy = -pi2 * sx * cy + 0.2 * x[0];
            const double w0_xy = -pi2 * cx * sy + 0.2 * x[1];
            const double w1_xx = 0.5 * ex * std::sin(x[1]);
            const double w1_yy = -0.5 * ex * std::sin(x[1]);
            const double w1_xy = 0.5 * ex * std::cos(x[1]);
            const double ddivw_x = w0_xx + w1_xy, ddivw_y = w0_xy + w1_yy;
            // div sigma_i = mu lap u_i + mu d_i div u + lambda d_i div u,
            // d_i div u = kappa d_i div w, lambda kappa = mu
            const double lk = std::isinf(m.lambda) ? 0.0 : m.mu;
            Tensor<1, 2> f;
            f[0] = -(m.mu * (lap_df0 + kappa * (w0_xx + w0_yy + ddivw_x)) +
                     lk * ddivw_x);
            f[1] = -(m.mu * (lap_df1 + kappa * (w1_xx + w1_yy + ddivw_y)) +
                     lk * ddivw_y);
            return f;
          };
          std::vector<double> errs;
          for (const unsigned n : {4u, 8u, 16u, 32u})
            {
              Triangulation<2> tria;
              GridGenerator::subdivided_hyper_rectangle(
                tria, {n, n}, Point<2>(0, 0), Point<2>(1, 1), true);
              ProblemSpec<2> spec;
              spec.material        = m;
              spec.dirichlet_ids   = {0};
              spec.dirichlet_value = u;
              spec.body_force      = body;
              for (const types::boundary_id id : {1, 2, 3})
                spec.tractions[id] = [=](const Point<2> &x, const Tensor<1, 2> &nn) {
                  return Tensor<1, 2>(stress(x) * nn);
                };
              ElasticitySolver<2> s(tria, spec, form);
              s.setup_and_assemble();
              s.solve(SolverKind::direct);
              errs.push_back(s.l2_error(u));
            }
          const double rate = std::log2(errs[2] / errs[3]);
          // Taylor-Hood: O(h^3) for every nu; displacement Q2 only reported
          const bool this_ok = form == Formulation::mixed ? (rate > 2.8) : true;
          ok = ok && this_ok;
          std::cerr << (this_ok ? "PASS " : "FAIL ") << "smooth 2D plane strain nu="
                    << nu << " "
                    << (form == Formulation::mixed ? "mixed" : "displacement")
                    << ": L2 errors";
          for (double e : errs)
            std::cerr << " " << e;
          std::cerr << ", rate " << rate << std::endl;
          json << (first ? "" : ", ") << "{\"nu\": " << num(nu)
               << ", \"formulation\": \""
               << (form == Formulation::mixed ? "mixed_Q2Q1" : "displacement_Q2")
               << "\", \"meshes\": [4, 8, 16, 32], \"l2_errors\": [" << num(errs[0])
               << ", " << num(errs[1]) << ", " << num(errs[2]) << ", "
               << num(errs[3]) << "], \"rate_16_32\": " << num(rate)
               << ", \"pass\": " << (this_ok ? "true" : "false") << "}";
          first = false;
        }
    json << "]";
    return ok;
  }

  int
  run_verify()
  {
    bool               ok = true;
    std::ostringstream json;
    json << "{\"verification\": {\"exact\": [";
    bool first = true;
    auto sep   = [&]() {
      if (!first)
        json << ", ";
      first = false;
    };

    // 3D: the phantom box geometry, clamped (exact Dirichlet values) at
    // x = 0.04, exact tractions sigma.n on the five other faces.
    for (const double nu : {0.3, 0.4999})
      for (const Formulation form : {Formulation::mixed, Formulation::displacement})
        for (const SolverKind kind : {SolverKind::direct, SolverKind::iterative})
          {
            Triangulation<3> tria;
            make_box(tria, 4);
            const Material m     = Material::from_E_nu(1.0e7, nu);
            const auto     field = make_quadratic<3>(m, 1e-4, 1e-2);
            std::ostringstream name;
            name << "box 4x2x2 quadratic nu=" << nu << " "
                 << (form == Formulation::mixed ? "mixed" : "displacement") << " "
                 << (kind == SolverKind::direct ? "direct" : "iterative");
            sep();
            // iterative: tolerance-limited, so a looser bound
            ok &= verify_exact<3>(name.str(), tria, {1}, {0, 2, 3, 4, 5}, field,
                                  form, kind,
                                  kind == SolverKind::direct ? 1e-9 : 1e-6, json);
          }

    // The same quadratic field on 8x4x4 cells (> 2000 displacement dofs, so
    // ML builds a real multigrid hierarchy instead of one coarse direct
    // solve): exercises the iterative path as used for the large box runs.
    for (const double nu : {0.3, 0.4999})
      for (const Formulation form : {Formulation::mixed, Formulation::displacement})
        {
          Triangulation<3> tria;
          make_box(tria, 8);
          const Material m     = Material::from_E_nu(1.0e7, nu);
          const auto     field = make_quadratic<3>(m, 1e-4, 1e-2);
          std::ostringstream name;
          name << "box 8x4x4 quadratic nu=" << nu << " "
               << (form == Formulation::mixed ? "mixed" : "displacement")
               << " iterative";
          sep();
          ok &= verify_exact<3>(name.str(), tria, {1}, {0, 2, 3, 4, 5}, field,
                                form, SolverKind::iterative, 1e-6, json);
        }

    // The y-symmetric half of the gravity box against the full box, same
    // cells: the discrete solutions coincide, so every reported value must
    // agree to the solvers' accuracy (direct and iterative half).
    for (const double nu : {0.3, 0.4999})
      for (const std::string kind : {"direct", "iterative"})
        {
          const BoxResult full =
            solve_box(nu, 8, Formulation::mixed, "direct", 1e-12, false);
          const BoxResult half =
            solve_box(nu, 8, Formulation::mixed, kind, 1e-12, true);
          double umax = 0.0, du = 0.0;
          for (unsigned i = 0; i < full.u.size(); ++i)
            {
              umax = std::max(umax, full.u[i].norm());
              du   = std::max(du, (full.u[i] - half.u[i]).norm());
            }
          const double eu = du / umax;
          const double ec =
            std::abs(full.compliance - half.compliance) / full.compliance;
          const bool this_ok = eu < 1e-9 && ec < 1e-9 &&
                               half.n_dofs < full.n_dofs;
          std::ostringstream name;
          name << "box 8x4x4 gravity half vs full nu=" << nu << " mixed " << kind;
          std::cerr << (this_ok ? "PASS " : "FAIL ") << name.str()
                    << ": max |u_half-u_full|/max|u| = " << eu
                    << ", compliance " << ec << " (dofs " << half.n_dofs << " vs "
                    << full.n_dofs << ")" << std::endl;
          sep();
          json << "{\"case\": \"" << name.str() << "\", \"rel_nodal_error_u\": "
               << num(eu) << ", \"rel_nodal_error_p\": 0, \"rel_compliance\": "
               << num(ec) << ", \"solver\": " << solve_json(half.solve)
               << ", \"pass\": " << (this_ok ? "true" : "false") << "}";
          ok &= this_ok;
        }

    // 3D uniaxial bar (the box, a linear field): pure tension sigma_xx = s,
    // u = (s/E x, -nu s/E y, -nu s/E z), clamped values at x = 0.04.
    for (const double nu : {0.3, 0.4999})
      {
        Triangulation<3> tria;
        make_box(tria, 8);
        const Material      m = Material::from_E_nu(1.0e7, nu);
        QuadraticField<3>   field;
        field.m       = m;
        const double s = 1.0e3;
        field.B[0][0] = s / m.E;
        field.B[1][1] = -nu * s / m.E;
        field.B[2][2] = -nu * s / m.E;
        std::ostringstream name;
        name << "box 8x4x4 uniaxial bar nu=" << nu << " mixed direct";
        sep();
        ok &= verify_exact<3>(name.str(), tria, {1}, {0, 2, 3, 4, 5}, field,
                              Formulation::mixed, SolverKind::direct, 1e-9, json);
      }

    // 2D: Cook's membrane mesh (non-affine quadrilaterals). Mapped Q2 holds
    // every linear field, so a linear (constant stress) field must come out
    // exactly, plane strain, clamped x = 0 with the exact values.
    for (const double nu : {1.0 / 3.0, 0.4999})
      for (const Formulation form : {Formulation::mixed, Formulation::displacement})
        {
          Triangulation<2> tria;
          make_cook(tria, 8);
          const Material m     = Material::from_E_nu(250.0, nu);
          auto           field = make_quadratic<2>(m, 1e-2, 0.0);
          std::ostringstream name;
          name << "cook 8x8 linear nu=" << nu << " "
               << (form == Formulation::mixed ? "mixed" : "displacement");
          sep();
          ok &= verify_exact<2>(name.str(), tria, {0}, {1, 2, 3}, field, form,
                                SolverKind::direct, 1e-9, json);
        }
    // 2D quadratic field on a rectangle (affine cells)
    for (const double nu : {0.3, 0.4999})
      {
        Triangulation<2> tria;
        GridGenerator::subdivided_hyper_rectangle(
          tria, {6, 3}, Point<2>(0, 0), Point<2>(48, 20), true);
        const Material m     = Material::from_E_nu(250.0, nu);
        auto           field = make_quadratic<2>(m, 1e-2, 1e-3);
        std::ostringstream name;
        name << "rectangle 6x3 quadratic nu=" << nu << " mixed";
        sep();
        ok &= verify_exact<2>(name.str(), tria, {0}, {1, 2, 3}, field,
                              Formulation::mixed, SolverKind::direct, 1e-9, json);
      }
    json << "], ";
    ok &= verify_convergence(json);
    json << ", \"all_pass\": " << (ok ? "true" : "false") << "}}";
    std::cout << json.str() << std::endl;
    std::cerr << (ok ? "verification: all passed" : "verification: FAILED")
              << std::endl;
    return ok ? 0 : 1;
  }

} // namespace ref

namespace
{
  void
  usage()
  {
    std::cerr
      << "usage:\n"
         "  locking_reference verify\n"
         "  locking_reference box  --nu NU --n N [--formulation mixed|displacement]\n"
         "                         [--solver auto|direct|iterative] [--tol T] [--half]\n"
         "  locking_reference cook --nu NU --n N [--E E] [--F F] [--plane-stress]\n"
         "                         [--formulation mixed|displacement]\n"
         "box: phantom box, N x N/2 x N/2 Q2 hexahedra (N even); --half: only\n"
         "the y <= 0.01 half with u_y = 0 on y = 0.01 (N divisible by 4), the same\n"
         "discrete solution with half the unknowns; cook: N x N.\n"
         "Each run prints one JSON object on stdout.\n";
  }
} // namespace

int
main(int argc, char **argv)
{
  try
    {
      Utilities::MPI::MPI_InitFinalize mpi(argc, argv, 1);
      if (argc < 2)
        {
          usage();
          return 2;
        }
      const std::string task = argv[1];
      double            nu = 0.3, E = -1.0, F = -1.0, tol = 1e-12;
      unsigned          n = 4;
      bool              plane_stress = false, half = false;
      std::string       formulation  = "mixed", solver = "auto";
      for (int i = 2; i < argc; ++i)
        {
          const std::string a    = argv[i];
          auto              next = [&]() -> std::string {
            if (i + 1 >= argc)
              throw std::runtime_error("missing value after " + a);
            return argv[++i];
          };
          if (a == "--nu")
            nu = std::stod(next());
          else if (a == "--n")
            n = std::stoul(next());
          else if (a == "--E")
            E = std::stod(next());
          else if (a == "--F")
            F = std::stod(next());
          else if (a == "--tol")
            tol = std::stod(next());
          else if (a == "--plane-stress")
            plane_stress = true;
          else if (a == "--half")
            half = true;
          else if (a == "--formulation")
            formulation = next();
          else if (a == "--solver")
            solver = next();
          else
            {
              usage();
              throw std::runtime_error("unknown argument " + a);
            }
        }
      if (formulation != "mixed" && formulation != "displacement")
        throw std::runtime_error("--formulation must be mixed or displacement");
      const ref::Formulation form = formulation == "mixed" ?
                                      ref::Formulation::mixed :
                                      ref::Formulation::displacement;
      if (task == "verify")
        return ref::run_verify();
      if (task == "box")
        {
          if (n < 2 || n % 2)
            throw std::runtime_error("--n must be even");
          if (half && n % 4)
            throw std::runtime_error("--half needs --n divisible by 4");
          return ref::run_box(nu, n, form, solver, tol, half);
        }
      if (task == "cook")
        return ref::run_cook(nu, E > 0 ? E : 250.0, F > 0 ? F : 100.0, n,
                             plane_stress, form, solver, tol);
      usage();
      return 2;
    }
  catch (const std::exception &e)
    {
      std::cerr << "error: " << e.what() << std::endl;
      return 1;
    }
}
