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
target: the moved needles are turned and translated rigidly, as one tool, so that the scene's
aim goes to `target` and its axis to the entry's direction. The scene's aim is where its
first moved needle's tip ends: base + (length + largest `advance` of its motion) x direction
(for the DBS scenes, the left STN's planned position, where cannula and electrode tips end).
The motions (advances along the axis) are kept, so the needles start as far from the target
as in the scene: entries farther from the target than that start inside the brain and are
refused by the tool (key needle.base.position) before the study runs. `set` adds any other
overrides (applied after the computed ones).
"""
import math
import os

import numpy as np
import yaml

from .distributions import UsageError, format_value

_UNITS = {"m": 1.0, "mm": 1e-3}


def _merge(base, over):
    """scene_format.md `extends`: maps merged key by key, lists and scalars replaced."""
    if isinstance(base, dict) and isinstance(over, dict):
        out = dict(base)
        for k, v in over.items():
            out[k] = _merge(base[k], v) if k in base else v
        return out
    return over


def read_scene(path):
    """The scene file as a dict, its `extends` chain applied (the C++ loader validates it)."""
    try:
        with open(path) as f:
            doc = yaml.safe_load(f) or {}
    except (OSError, yaml.YAMLError) as e:
        raise UsageError(f"scene {path}: {e}")
    parent = doc.pop("extends", None)
    if parent:
        doc = _merge(read_scene(os.path.join(os.path.dirname(path), parent)), doc)
    return doc


def scene_needles(scene):
    """[(name, --set prefix, needle dict)] in scene order."""
    if "needles" in scene:
        return [(n.get("name", "needle"), f"needles.{i}", n) for i, n in enumerate(scene["needles"])]
    if "needle" in scene:
        return [(scene["needle"].get("name", "needle"), "needle", scene["needle"])]
    return []


def _vec(x, what, scale=1.0):
    try:
        v = np.array([float(c) for c in x], dtype=float) * scale
    except (TypeError, ValueError):
        v = None
    if v is None or v.shape != (3,) or not np.all(np.isfinite(v)):
        raise UsageError(f"{what}: expected three numbers, got {x!r}")
    return v


def _rotation(a, b):
    """The smallest rotation taking unit vector a onto unit vector b (Rodrigues)."""
    v, c = np.cross(a, b), float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: half a turn about any axis normal to a
        n = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
        n /= np.linalg.norm(n)
        return 2.0 * np.outer(n, n) - np.eye(3)
    k = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def scene_aim(needle, where):
    """Where the needle's tip ends: base + (length + largest advance) x direction."""
    base = needle.get("base", {})
    p, d = _vec(base.get("position"), f"{where}.base.position"), _vec(base.get("direction"), f"{where}.base.direction")
    advance = 0.0
    for key in needle.get("motion", []) or []:
        if "position" in key:
            raise UsageError(f"{where}.motion: trajectory entries move needles driven by 'advance' keyframes; "
                             "this needle has full-pose keyframes")
        advance = max(advance, float(key.get("advance", 0.0)))
    return p + (float(needle["length"]) + advance) * d


def _fmt_vec(v):
    return "[" + ",".join(format_value(c) for c in v) + "]"


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


def load(path, scene):
    """The trajectories of `path` for the scene (a dict from read_scene)."""
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

    needles = scene_needles(scene)
    wanted = defaults.get("needles", [n[0] for n in needles])
    names = [n[0] for n in needles]
    for w in wanted:
        if w not in names:
            raise UsageError(f"--trajectories {path}: needles: the scene has no needle '{w}' (it has {', '.join(names) or 'none'})")
    moved = [n for n in needles if n[0] in wanted]
    default_target = _vec(defaults["target"], f"{path}: target", scale) if "target" in defaults else None

    out, seen = [], set()
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
        sets, info = [], {}
        if "entry" in e:
            if not moved:
                raise UsageError(f"{where}: the scene has no needle to aim")
            entry = _vec(e["entry"], f"{where}: entry", scale)
            target = _vec(e["target"], f"{where}: target", scale) if "target" in e else default_target
            ref_name, ref_prefix, ref = moved[0]
            aim = scene_aim(ref, ref_prefix)
            if target is None:
                target = aim
            axis = target - entry
            if np.linalg.norm(axis) < 1e-9:
                raise UsageError(f"{where}: entry and target coincide")
            d_new = axis / np.linalg.norm(axis)
            d_old = _vec(ref["base"]["direction"], f"{ref_prefix}.base.direction")
            rot = _rotation(d_old / np.linalg.norm(d_old), d_new)
            for _, prefix, nd in moved:
                p = target + rot @ (_vec(nd["base"]["position"], f"{prefix}.base.position") - aim)
                d = rot @ _vec(nd["base"]["direction"], f"{prefix}.base.direction")
                # Not renormalised: the tool takes the direction as given (unit to 1e-6), so the
                # turned tool is the scene's, rigidly, and its tips end exactly on the target.
                sets += [f"{prefix}.base.position={_fmt_vec(p)}", f"{prefix}.base.direction={_fmt_vec(d)}"]
            info = {"entry": entry.tolist(), "target": target.tolist(),
                    "entry_target_distance": float(np.linalg.norm(axis)),
                    "start_target_distance": float(np.linalg.norm(aim - _vec(ref["base"]["position"], "base") ) - float(ref["length"])),
                    "angle_to_scene_deg": math.degrees(math.acos(max(-1.0, min(1.0, float(np.dot(d_old / np.linalg.norm(d_old), d_new))))))}
        extra = e.get("set", {}) or {}
        if not isinstance(extra, dict):
            raise UsageError(f"{where}: set: expected a map key: value")
        sets += [f"{k}={_yaml_value(v)}" for k, v in extra.items()]
        out.append(Trajectory(name, sets, info))
    return out
