#pragma once
// Boundary conditions and loads of the tissue body on a mesh, from its parameters:
// prescribed displacements by region, the lumped (row-sum) mass, gravity and body force
// through it, and uniform tractions on the boundary faces in a region (consistent nodal
// forces of the bilinear face, 2x2 Gauss).
#include <string>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/tissue/tissue_parameters.hpp"

namespace needle_sim {

// Marks the prescribed DOFs (3n) and moves them in x by their condition's displacement;
// later conditions override earlier ones on shared nodes. Throws InputError (source, the
// condition's key within the tissue's parameters, "dirichlet[i].region") when a region
// selects no node.
std::vector<char> prescribeDirichlet(const HexMesh& mesh, const std::vector<DirichletCondition>& conditions,
                                     const std::string& source, VecX& x);
// Constant external nodal forces (3n): gravity and body force by nodal volume, tractions.
// Throws InputError (source, "tractions[i].region") when a traction's region holds no
// boundary face.
VecX tissueLoads(const HexMesh& mesh, const VecX& nodal_volume, const TissueParameters& p, const std::string& source);
// Adds the nodal forces of a uniform traction t on one boundary face to out (3n).
void addFaceTraction(const HexMesh& mesh, const BoundaryFace& face, const Vec3& t, VecX& out);

}  // namespace needle_sim
