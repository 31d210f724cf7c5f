"""Where the package's programs find the rest of needle_sim, from a source checkout (its
devel space, or `pip install -e .`) or an install space alike:

  source_dir()       the source checkout this package sits in (<checkout>/src/needle_sim), or
                     None when it is installed;
  share_dir()        config/, data/: $NEEDLE_SIM_SHARE_DIR, else the source checkout, else the
                     install space's <prefix>/share/needle_sim (this package being
                     <prefix>/lib/python3/dist-packages/needle_sim), else the ROS package path
                     (rospack);
  scene(name)        a shipped scene, <share>/config/scenes/<name>;
  tool()             the needle_sim tool: $NEEDLE_SIM_TOOL, else the source checkout's devel
                     space (devel/lib/needle_sim/needle_sim) or plain-CMake build
                     (build/core/bin/needle_sim: scripts/core_build.sh; or
                     build/bin/needle_sim), else the install space's
                     <prefix>/lib/needle_sim/needle_sim, else `needle_sim` on PATH;
  results_dir(name)  ./results/<name> (the current folder: an install space is read-only).
"""
import os
import shutil

_PACKAGE = os.path.dirname(os.path.abspath(__file__))
# <prefix>/lib/python3/dist-packages/needle_sim (or .../lib/python3.X/site-packages/needle_sim)
_PREFIX = os.path.normpath(os.path.join(_PACKAGE, "..", "..", "..", ".."))


def _is_checkout(d):
    return os.path.isfile(os.path.join(d, "package.xml")) and os.path.isdir(os.path.join(d, "config", "scenes"))


def source_dir():
    d = os.path.dirname(os.path.dirname(_PACKAGE))  # <checkout>/src/needle_sim -> <checkout>
    return d if _is_checkout(d) else None


def share_dir():
    env = os.environ.get("NEEDLE_SIM_SHARE_DIR")
    if env:
        return env
    for d in (source_dir(), os.path.join(_PREFIX, "share", "needle_sim")):
        if d and os.path.isdir(os.path.join(d, "config", "scenes")):
            return d
    try:
        import rospkg

        return rospkg.RosPack().get_path("needle_sim")
    except Exception as e:  # no ROS environment either
        raise RuntimeError("needle_sim: cannot find the package's share folder (config/, data/): "
                           "set NEEDLE_SIM_SHARE_DIR") from e


def scene(name):
    return os.path.join(share_dir(), "config", "scenes", name)


def _executable(path):
    return os.path.isfile(path) and os.access(path, os.X_OK)


def tool():
    env = os.environ.get("NEEDLE_SIM_TOOL")
    if env:
        return env
    src = source_dir()
    candidates = [os.path.join(src, "devel", "lib", "needle_sim", "needle_sim"),
                  os.path.join(src, "build", "core", "bin", "needle_sim"),
                  os.path.join(src, "build", "bin", "needle_sim")] if src else []
    candidates.append(os.path.join(_PREFIX, "lib", "needle_sim", "needle_sim"))
    for c in candidates:
        if _executable(c):
            return c
    return shutil.which("needle_sim") or candidates[0]


def results_dir(name):
    return os.path.join(os.getcwd(), "results", name)
