"""What the needle_sim tool's scene loader made of a scene, for the Python to read instead of
re-implementing it: `needle_sim check SCENE --json` (doc/cli.md), the scene's YAML tree after
`extends` and --set, its needles with their --set prefixes and planned final tips (the
deepest keyframe's tip: needle/trajectory_replan.hpp), its targets and probes; with --aim,
the --set overrides that move needles rigidly, as one tool, onto a line entry -> target."""
import json
import subprocess


class CheckError(Exception):
    """The tool refused the scene or the request (exit 2: its message), or could not run."""


def check(tool, scene, sets=(), aims=(), aim_needles=None):
    """The tool's JSON for `scene` with the --set overrides `sets`; aims: [(entry, target)],
    points in metres, each answered in the JSON's "aims" (moving aim_needles, default all)."""
    cmd = [tool, "check", scene, "--json"] + [x for s in sets for x in ("--set", s)]
    for entry, target in aims:
        cmd += ["--aim"] + [repr(float(v)) for v in list(entry) + list(target)]
    if aim_needles:
        cmd += ["--aim-needles", ",".join(aim_needles)]
    try:
        p = subprocess.run(cmd, capture_output=True, text=True)
    except OSError as e:
        raise CheckError(f"cannot run the needle_sim tool {tool}: {e.strerror}")
    if p.returncode != 0:
        message = p.stderr.strip().splitlines()[-1] if p.stderr.strip() else f"exit status {p.returncode}"
        raise CheckError(message.replace("needle_sim: invalid input: ", ""))
    return json.loads(p.stdout)
