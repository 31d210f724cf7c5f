"""Brain shift against Poisson's ratio (#37; doc/verification.md "Nearly incompressible tissue").

    brain_shift_poisson.py [--out results/brain_shift_poisson] [--tool T] [--write-doc]

(--reuse is accepted and ignored: every pre-step is run again, about a minute in all.)

The brain-shift pre-step of dbs_coarse.yaml (gravity scaled until the left STN has moved
`brain_shift.target_shift`, 6.5 mm, the skull holding the brain) for Poisson's ratio from 0.45
to 0.4999, on the paper's trilinear hexahedron and on the default locking-free one, at the
scene's stiffness. For each: the load scale the shift needed, the largest displacement, the
skull's contacts and force, the Newton iterations; or the pre-step's refusal. Answers whether
the brains the ensemble study refused at nu >= 0.4836 could not shift (an incompressible
brain in a closed skull) or were locked by the element. Writes table.csv and table.md to
--out; with --write-doc the table goes into doc/verification.md between its
'<!-- brain_shift_nu: table -->' markers, with the date, the commit and this command.
"""
import json
import os
import re
import subprocess

from . import runs

ELEMENTS = ["trilinear", "incompatible_modes_bbar"]
NU = [0.45, 0.47, 0.48, 0.485, 0.49, 0.495, 0.4977, 0.499, 0.4999]
SCENE = "dbs_coarse.yaml"


def run(tool, out):
    rows = []
    for el in ELEMENTS:
        for nu in NU:
            d = os.path.join(out, runs.slug(f"{el}_nu{nu}"))
            cmd = [tool, "run", os.path.join(runs.SCENES, SCENE), "--out", d, "--quiet",
                   "--set", f"tissue.element={el}", "--set", f"tissue.material.poisson={nu}",
                   "--set", "time.duration=0.01"]
            print("+", " ".join(cmd), flush=True)
            rc = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode
            with open(os.path.join(d, "summary.json")) as f:
                s = json.load(f)
            row = {"element": el, "nu": nu, "status": s.get("status", "ok" if rc == 0 else f"exit {rc}"),
                   "load_scale": "", "max_displacement_mm": "", "skull_contacts": "", "skull_force_N": "",
                   "newton_iterations": "", "message": s.get("message", "")}
            if rc == 0:
                b = s["brain_shift"]
                row.update(load_scale=b["load_scale"], max_displacement_mm=1e3 * b["max_displacement"],
                           skull_contacts=b["skull_contacts"], skull_force_N=b["skull_force"],
                           newton_iterations=b["newton_iterations"])
            rows.append(row)
    return rows


def markdown(rows):
    out = ["| ν | " + " | ".join(f"`{e}`: load scale, largest displacement, skull contacts / force" for e in ELEMENTS) + " |",
           "|---|" + "---|" * len(ELEMENTS)]
    for nu in NU:
        cells = []
        for el in ELEMENTS:
            r = next(r for r in rows if r["element"] == el and r["nu"] == nu)
            if r["load_scale"] == "":
                m = re.match(r".*?target_shift [0-9.e+-]+ m \((.*)\) \(brain-shift pre-step\)$", r["message"])
                reason = m.group(1) if m else (r["message"] or r["status"])
                cells.append(f"**refused**: {reason}")
            else:
                cells.append("%.2f g, %.1f mm, %d / %.1f N" % (r["load_scale"], r["max_displacement_mm"],
                                                               r["skull_contacts"], r["skull_force_N"]))
        out.append("| %g | %s |" % (nu, " | ".join(cells)))
    return "\n".join(out) + "\n"


def main():
    a = runs.parse_args(__doc__, "brain_shift_poisson",
                        lambda ap: ap.add_argument("--write-doc", action="store_true",
                                                   help="write the table into doc/verification.md"))
    rows = run(a.tool, a.out)
    runs.publish_table(a.out, rows, markdown(rows), a.write_doc, "verification.md", "brain_shift_nu",
                       "python3 scripts/brain_shift_poisson.py --write-doc")
    return 0
