#pragma once
// A regular hexahedral grid laid over a closed surface without conforming to it (the
// finite-cell idea, doc/method.md): cells inside or cut by the surface are kept, each with
// its inside volume fraction; stiffness and mass are weighted by it (CorotationalHexModel).
// Cells with a tiny fraction keep `min_fraction` so that nodes which only touch a sliver of
// tissue are not left without stiffness (the usual finite-cell alpha; it adds a stiffness
// of min_fraction x E over a sliver, negligible against the tissue).
#include <memory>
#include <optional>
#include <vector>

#include "needle_sim/core/parameters.hpp"
#include "needle_sim/fem/hex_mesh.hpp"
#include "needle_sim/geometry/inside_test.hpp"

namespace needle_sim {

struct ImmersedGridSettings {
  std::optional<Vec3i> cells;      // cells over the bounding box, or
  std::optional<double> cell_size; // cubic cells of this size, grid centred on the box
  int refine = 0;                  // uniform refinements of that grid (2^refine per axis)
  double min_fraction = 1e-3;
  int samples = 8;                 // rays per cell and axis for the volume fractions

  // The value keys of an immersed tissue's `grid` (core/parameters.hpp); cells (a list of
  // three counts) is read by the scene loader.
  static const Parameters<ImmersedGridSettings>& parameters() {
    using S = ImmersedGridSettings;
    static const Parameters<S> p =
        Parameters<S>()
            .optionalReal("cell_size", [](S& s) -> std::optional<double>& { return s.cell_size; }, "m", Range::positive(),
                          "`surface` only, instead of `cells`: cubic cells, the grid centred on the surface's box")
            .integer("refine", [](S& s) -> int& { return s.refine; }, Range::closed(0, 6),
                     "`surface` only: uniform refinements of that grid (2^refine per axis)")
            .real("min_fraction", [](S& s) -> double& { return s.min_fraction; }, "", Range::openClosed(0, 1),
                  "`surface` only: floor of a cell's stiffness and mass fraction")
            .integer("samples", [](S& s) -> int& { return s.samples; }, Range::closed(1, 64),
                     "`surface` only: rays per cell and axis for the volume fractions");
    return p;
  }
};

class ImmersedGrid {
 public:
  // The grid over [lo, hi] the settings describe: cells per axis, origin, cell size.
  static void layout(const Vec3& lo, const Vec3& hi, const ImmersedGridSettings& s, Vec3i& dims, Vec3& origin, Vec3& h);

  // Throws std::invalid_argument when no cell is kept.
  ImmersedGrid(std::shared_ptr<const TriangleMesh> surface, const ImmersedGridSettings& s);

  // The kept cells as a mesh, with the (floored) fractions set on its elements.
  const HexMesh& mesh() const { return mesh_; }
  // Inside volume fraction of element e, not floored.
  double fraction(int e) const { return fraction_[e]; }
  // Sum of fraction x cell volume: the grid's approximation of the enclosed volume.
  double volume() const;
  Vec3i dims() const { return dims_; }  // the full grid over the box
  const Vec3& cellSize() const { return h_; }
  const InsideTest& insideTest() const { return inside_; }
  const ImmersedGridSettings& settings() const { return settings_; }
  // Fraction of an axis-aligned box (refined cells), with the grid's sampling.
  double boxFraction(const Vec3& lo, const Vec3& hi) const { return inside_.boxFraction(lo, hi, settings_.samples); }

 private:
  ImmersedGridSettings settings_;
  InsideTest inside_;
  Vec3i dims_;
  Vec3 lo_, h_;
  HexMesh mesh_;
  std::vector<double> fraction_;
};

}  // namespace needle_sim
