"""`--trajectories FILE`: base trajectories, each a set of `--set` overrides, crossed with the
material samples.

The file (YAML) is a list of entries, or a map with defaults and the list under
`trajectories:`:

    units: mm                       # of every position in this file: mm or m (default m)
    target: [-11.1, -12.9, -7.7]    # default aim of the entries (default: the scene's own aim)
    needles: [cannula, electrode]   # the needles moved (default: all the scene's needles)
    trajectories:
      - {name: planned, entry: [-31.9, 23.3, 68.9]}
      - {name: lateral, entry: [-36.0, 20.0, 62.0], target: [-11.1, -12.9, -7.7]}
      - {name: by_hand, set: {needles.0.base.direction: [0, 0, -1]}}

An entry with `entry` (and optionally `target`) aims the scene's insertion along entry ->
target: the moved needles are turned and translated rigidly, as one tool, so that the
planned final tip of the first moved needle (in scene order) goes to `target` and its axis to
the entry's direction. The needle_sim tool computes this (`needle_sim check --aim`,
doc/cli.md), with the scene as its loader reads it (`extends` and the study's --set applied)
and the rule of the C++ re-planning: a needle's planned final tip is its deepest keyframe's
tip (needle/trajectory_replan.hpp; for the DBS scenes, the left STN's planned position, where
cannula and electrode tips end). Without a target, the scene's own: that planned tip. The
motions are kept, so the needles start as far from the target as in the scene: entries
farther from the target than that start inside the brain and are refused by the tool (key
needle.base.position) before the study runs. `set` adds any other overrides (applied after
the computed ones).
"""
import yaml

from ..scene_check import CheckError, check
from .distributions import UsageError, format_value

_UNITS = {"m": 1.0, "mm": 1e-3}


def _vec(x, what, scale=1.0):
    try:
        v = [float(c) * scale for c in x]
    except (TypeError, ValueError):
        v = None
    if v is None or len(v) != 3 or not all(abs(c) < float("inf") for c in v):
        raise UsageError(f"{what}: expected three numbers, got {x!r}")
    return v


def _yaml_value(v):
    """An override value from the file, as --set text (YAML flow style)."""
    if isinstance(v, (list, tuple)):
        return "[" + ",".join(_yaml_value(c) for c in v) + "]"
    if isinstance(v, float):
        return format_value(v)
    if isinstance(v, (dict,)):
        return yaml.safe_dump(v, default_flow_style=True, width=1 << 20).strip()
    return str(v).lower() if isinstance(v, bool) else str(v)


class Trajectory:
    def __init__(self, name, sets, info):
        self.name, self.sets, self.info = name, sets, info

    def to_json(self):
        return {"name": self.name, "set": self.sets, **self.info}


def _scene_check(tool, scene_file, sets, **aims):
    try:
        return check(tool, scene_file, sets, **aims)
    except CheckError as e:
        raise UsageError(f"scene {scene_file}: {e}")


def load(path, tool, scene_file, sets=()):
    """The trajectories of `path` for the scene file with the study's --set overrides, their
    poses computed by the needle_sim tool `tool`."""
    try:
        with open(path) as f:
            doc = yaml.safe_load(f)
    except OSError as e:
        raise UsageError(f"--trajectories {path}: {e.strerror}")
    except yaml.YAMLError as e:
        raise UsageError(f"--trajectories {path}: not valid YAML: {e}")
    defaults = {}
    if isinstance(doc, dict):
        defaults = {k: v for k, v in doc.items() if k != "trajectories"}
        unknown = set(defaults) - {"units", "target", "needles"}
        if unknown:
            raise UsageError(f"--trajectories {path}: unknown key '{sorted(unknown)[0]}' (known: units, target, needles, trajectories)")
        doc = doc.get("trajectories")
    if not isinstance(doc, list) or not doc:
        raise UsageError(f"--trajectories {path}: no trajectories (expected a non-empty list)")
    unit = defaults.get("units", "m")
    if unit not in _UNITS:
        raise UsageError(f"--trajectories {path}: units '{unit}': one of m, mm")
    scale = _UNITS[unit]
    wanted = defaults.get("needles")
    if wanted is not None:
        if not isinstance(wanted, list) or not wanted:
            raise UsageError(f"--trajectories {path}: needles: expected a non-empty list of needle names")
        wanted = [str(w) for w in wanted]
    default_target = _vec(defaults["target"], f"{path}: target", scale) if "target" in defaults else None

    entries, seen = [], set()
    for i, e in enumerate(doc):
        where = f"--trajectories {path}: entry {i}"
        if not isinstance(e, dict):
            raise UsageError(f"{where}: expected a map (name, entry, target, set)")
        unknown = set(e) - {"name", "entry", "target", "set"}
        if unknown:
            raise UsageError(f"{where}: unknown key '{sorted(unknown)[0]}' (known: name, entry, target, set)")
        name = str(e.get("name", f"t{i}"))
        if not name.replace("_", "").replace("-", "").isalnum():
            raise UsageError(f"{where}: name '{name}': letters, digits, '_' and '-' only")
        if name in seen:
            raise UsageError(f"{where}: name '{name}' is used twice")
        seen.add(name)
        if "entry" not in e and "set" not in e:
            raise UsageError(f"{where}: give 'entry' (and optionally 'target') or 'set'")
        extra = e.get("set", {}) or {}
        if not isinstance(extra, dict):
            raise UsageError(f"{where}: set: expected a map key: value")
        entry = _vec(e["entry"], f"{where}: entry", scale) if "entry" in e else None
        target = _vec(e["target"], f"{where}: target", scale) if "target" in e else default_target
        entries.append((name, entry, target, [f"{k}={_yaml_value(v)}" for k, v in extra.items()]))

    # The tool answers every aim at once; an entry without a target aims at the scene's own
    # (the reference needle's planned final tip), which a first call reads.
    aimed = [x for x in entries if x[1] is not None]
    if any(x[2] is None for x in aimed):
        scene = _scene_check(tool, scene_file, sets)
        names = [n["name"] for n in scene["needles"]]
        for w in wanted or []:
            if w not in names:
                raise UsageError(f"--trajectories {path}: needles: the scene has no needle '{w}' "
                                 f"(it has {', '.join(names) or 'none'})")
        moved = [n for n in scene["needles"] if wanted is None or n["name"] in wanted]
        if not moved:
            raise UsageError(f"--trajectories {path}: the scene has no needle to aim (it has {', '.join(names) or 'none'})")
        own = moved[0]["planned_tip"]
        aimed = [(n, entry, own if target is None else target, s) for n, entry, target, s in aimed]
    aims = {}
    if aimed:
        answer = _scene_check(tool, scene_file, sets, aims=[(x[1], x[2]) for x in aimed], aim_needles=wanted)
        aims = {x[0]: a for x, a in zip(aimed, answer["aims"])}

    out = []
    for name, entry, target, extra in entries:
        sets_, info = [], {}
        if name in aims:
            a = aims[name]
            sets_ = list(a["set"])
            info = {"entry": a["entry"], "target": a["target"], "entry_target_distance": a["entry_target_distance"],
                    "start_target_distance": a["start_target_distance"], "angle_to_scene_deg": a["angle_deg"]}
        out.append(Trajectory(name, sets_ + extra, info))
    return out
