"""The volumetric-locking benchmark (#37; doc/verification.md "Nearly incompressible tissue").

    locking_benchmark.py [--out results/locking_benchmark] [--tool T] [--reuse] [--write-doc]

Runs every hexahedron formulation (`tissue.element`) on two static problems over Poisson's
ratio and the mesh, and compares one displacement with a converged reference computed outside
the product (deal.II Taylor-Hood Q2-Q1, Richardson-extrapolated:
test/data/locking_reference.json, tools/reference/):

  locking_box                 the paper's phantom block under gravity (clamped at x = 4 cm):
                              the free end's sag, u_z at (0, 1, 1) cm, on 8x4x4, 16x8x8, 32x16x16
  cook_membrane_plane_strain  Cook's membrane in plane strain: the loaded corner's u_y on
                              8x8, 16x16, 32x32 (one element thick, u_z = 0)
  cantilever_hex8             the hex8 cantilever in bending: u_y / (P L^3 / 3 E I) on 10x1x1,
                              20x2x2, 40x4x4 (no converged reference: beam theory with shear
                              gives 1.008 at nu 0.3; bending shows what locking, or a too soft
                              element, does to the needle's tissue)

The error is (u_h - u_ref) / u_ref: negative when the element is stiffer than the continuum
(locking shows as an error near -1). Writes table.csv and table.md to --out; with --write-doc
the table goes into doc/verification.md between its '<!-- locking: table -->' markers, with
the date, the commit and this command.
"""
import json
import os

from .. import paths
from . import runs

FORMULATIONS = ["trilinear", "bbar", "incompatible_modes", "incompatible_modes_bbar"]
BOX_NU = [0.3, 0.4, 0.45, 0.49, 0.499, 0.4999]
BOX_MESHES = [(8, 4, 4), (16, 8, 8), (32, 16, 16)]
COOK_NU = [0.3, 0.4999]
COOK_MESHES = [(8, 8, 1), (16, 16, 1), (32, 32, 1)]
COOK_SCALE = 1e-4  # the scene's load is the reference's times this (keeps the model linear)
CANTILEVER_NU = [0.3, 0.499, 0.4999]
CANTILEVER_MESHES = [(10, 1, 1), (20, 2, 2), (40, 4, 4)]
CANTILEVER_SCALE = 4e-3  # P L^3 / 3 E I of cantilever_hex8.yaml


def reference(path=None):
    path = path or os.path.join(paths.share_dir(), "test", "data", "locking_reference.json")
    with open(path) as f:
        return json.load(f)


# Where each benchmark's reference is in locking_reference.json (tools/reference/make_reference.py).
REFERENCE_KEYS = {"phantom_box": ("phantom_box_mixed_Q2Q1", "tip_uz"),
                  "cook_membrane": ("cook_membrane_plane_strain_mixed_Q2Q1", "corner_uy")}


def reference_value(ref, benchmark, nu):
    """The extrapolated reference (and its error estimate) of a benchmark at nu."""
    name, quantity = REFERENCE_KEYS[benchmark]
    for key, case in ref["benchmarks"][name]["by_nu"].items():
        if abs(float(key) - nu) < 1e-12:
            q = case["quantities"][quantity]
            return q["extrapolated"], q["error_estimate"]
    raise KeyError(f"{benchmark}: no reference at nu = {nu}")


def cases():
    """(benchmark, scene, element, nu, mesh, probe, component, scale)"""
    for el in FORMULATIONS:
        for nu in BOX_NU:
            for m in BOX_MESHES:
                yield ("phantom_box", "locking_box.yaml", el, nu, m, "tip", "uz", 1.0)
        for nu in COOK_NU:
            for m in COOK_MESHES:
                yield ("cook_membrane", "cook_membrane_plane_strain.yaml", el, nu, m, "corner", "uy", COOK_SCALE)
        for nu in CANTILEVER_NU:
            for m in CANTILEVER_MESHES:
                yield ("cantilever", "cantilever_hex8.yaml", el, nu, m, "tip", "uy", CANTILEVER_SCALE)


def mesh_name(m):
    return "x".join(str(c) for c in m)


def run(tool, out, reuse):
    todo = []
    for bench, scene, el, nu, m, probe, comp, scale in cases():
        name = f"{bench}_{el}_nu{nu}_{mesh_name(m)}"
        extra = ["--set", f"tissue.element={el}", "--set", f"tissue.material.poisson={nu}",
                 "--set", "tissue.grid.cells=[%d,%d,%d]" % m]
        todo.append((name, scene, extra))
    return runs.run_all(tool, runs.SCENES, out, todo, reuse)


def table(results, ref):
    rows = []
    for bench, scene, el, nu, m, probe, comp, scale in cases():
        name = f"{bench}_{el}_nu{nu}_{mesh_name(m)}"
        summary, _, series = results[name]
        u = float(series[-1][f"{probe}_{comp}"]) / scale
        if bench not in REFERENCE_KEYS:
            rows.append({"benchmark": bench, "element": el, "nu": nu, "mesh": mesh_name(m),
                         "dofs": int(series[-1]["dofs"]), "u": u, "u_ref": "", "u_ref_error": "", "error": ""})
            continue
        u_ref, u_ref_err = reference_value(ref, bench, nu)
        rows.append({"benchmark": bench, "element": el, "nu": nu, "mesh": mesh_name(m), "dofs": int(series[-1]["dofs"]),
                     "u": u, "u_ref": u_ref, "u_ref_error": u_ref_err, "error": (u - u_ref) / u_ref})
    return rows


def by_case(rows, bench):
    """(nu, mesh, {element: row}) for each case of a benchmark, in run order."""
    sel = [r for r in rows if r["benchmark"] == bench]
    keys = list(dict.fromkeys((r["nu"], r["mesh"]) for r in sel))
    return [(nu, mesh, {r["element"]: r for r in sel if (r["nu"], r["mesh"]) == (nu, mesh)}) for nu, mesh in keys]


def markdown(rows):
    """One table per benchmark: a row per (nu, mesh), a column per formulation."""
    columns = " | ".join(f"`{f}`" for f in FORMULATIONS)
    out = []
    for bench, title in (("phantom_box", "Phantom block under gravity, the free end's sag u_z(0, 1, 1 cm)"),
                         ("cook_membrane", "Cook's membrane, plane strain, the corner's u_y")):
        out.append(f"**{title}**: error against the reference (− stiffer)\n")
        out.append(f"| ν | mesh | reference | {columns} |")
        out.append("|---|---|---|" + "---|" * len(FORMULATIONS))
        for nu, mesh, by in by_case(rows, bench):
            r = by[FORMULATIONS[0]]
            cells = " | ".join("%+.1f %%" % (100 * by[f]["error"]) for f in FORMULATIONS)
            out.append("| %g | %s | %.4g (± %.1g) | %s |" % (nu, mesh, r["u_ref"], r["u_ref_error"], cells))
        out.append("")
    out.append("**The hex8 cantilever in bending** (`cantilever_hex8.yaml`), the tip's u_y / (P L³ / 3 E I): "
               "no converged reference (beam theory with shear: 1.008 at ν 0.3)\n")
    out.append(f"| ν | mesh | {columns} |")
    out.append("|---|---|" + "---|" * len(FORMULATIONS))
    for nu, mesh, by in by_case(rows, "cantilever"):
        out.append("| %g | %s | %s |" % (nu, mesh, " | ".join("%.3f" % by[f]["u"] for f in FORMULATIONS)))
    out.append("")
    return "\n".join(out)


def main():
    def extra(ap):
        ap.add_argument("--reference", default=None, help="test/data/locking_reference.json")
        ap.add_argument("--write-doc", action="store_true", help="write the table into doc/verification.md")

    a = runs.parse_args(__doc__, "locking_benchmark", extra)
    rows = table(run(a.tool, a.out, a.reuse), reference(a.reference))
    runs.publish_table(a.out, rows, markdown(rows), a.write_doc, "verification.md", "locking",
                       "python3 scripts/locking_benchmark.py --write-doc")
    return 0
