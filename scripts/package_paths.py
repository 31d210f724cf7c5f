"""Where the package's scripts find its files, from a source tree, a devel space or an
install space alike:
  share_dir()  config/, data/: $NEEDLE_SIM_SHARE_DIR, else the source tree this script is
               in, else the ROS package path (rospack: <prefix>/share/needle_sim);
  tool()       the needle_sim tool: $NEEDLE_SIM_TOOL, else beside this script (installed:
               <prefix>/lib/needle_sim/), else the source tree's devel space, else on PATH;
  results_dir(name)  ./results/<name> (the current folder: an install space is read-only).
"""
import os
import shutil

_HERE = os.path.dirname(os.path.abspath(__file__))
_SOURCE = os.path.dirname(_HERE)


def share_dir():
    env = os.environ.get("NEEDLE_SIM_SHARE_DIR")
    if env:
        return env
    if os.path.isdir(os.path.join(_SOURCE, "config", "scenes")):
        return _SOURCE
    try:
        import rospkg

        return rospkg.RosPack().get_path("needle_sim")
    except Exception:  # no ROS environment: the source tree is all there is
        return _SOURCE


def scene(name):
    return os.path.join(share_dir(), "config", "scenes", name)


def tool():
    env = os.environ.get("NEEDLE_SIM_TOOL")
    if env:
        return env
    for candidate in (os.path.join(_HERE, "needle_sim"), os.path.join(_SOURCE, "devel", "lib", "needle_sim", "needle_sim")):
        if os.path.isfile(candidate) and os.access(candidate, os.X_OK):
            return candidate
    return shutil.which("needle_sim") or os.path.join(_SOURCE, "devel", "lib", "needle_sim", "needle_sim")


def results_dir(name):
    return os.path.join(os.getcwd(), "results", name)
