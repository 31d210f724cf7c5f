#!/usr/bin/python3
"""Architecture checks (CTest `layers`), on the include directives of the sources:
  - the core's modules (folders under include/needle_sim and src/core) form no cycle;
  - the core includes nothing of ROS;
  - the ROS layer (src/ros) includes no fem/, adapt/, solver/ or tissue/ header: it talks to
    the simulation through sim/ (observables, snapshots), command/ and scene/ only;
  - the command-line tool (src/tools) includes nothing of ROS but in its bag input and output
    (bag_input.*, bag_output.*: built only when rosbag, or ROS, is there), so that it builds
    with the core alone (NEEDLE_SIM_ROS=OFF).
Prints the module graph; exits 1 with the offending includes otherwise."""
import os
import re
import sys
from collections import defaultdict

ROOT = os.path.abspath(os.path.join(os.path.dirname(__file__), "..", ".."))
INCLUDE = re.compile(r'^\s*#\s*include\s*[<"]([^">]+)[">]')


def includes(path):
    with open(path, encoding="utf-8") as f:
        for line in f:
            m = INCLUDE.match(line)
            if m:
                yield m.group(1)


def core_files():
    for base in ("include/needle_sim", "src/core"):
        for dirpath, _, names in os.walk(os.path.join(ROOT, base)):
            for n in names:
                if n.endswith((".hpp", ".cpp")):
                    p = os.path.join(dirpath, n)
                    rel = os.path.relpath(p, os.path.join(ROOT, base))
                    module = rel.split(os.sep)[0]
                    if module != "ros":
                        yield p, module


def main():
    problems = []
    graph = defaultdict(set)
    for path, module in core_files():
        for inc in includes(path):
            if inc.startswith("ros/") or inc.startswith("needle_sim/ros/") or inc in ("ros/ros.h",):
                problems.append("%s: the core includes ROS (%s)" % (os.path.relpath(path, ROOT), inc))
            if inc.startswith("needle_sim/"):
                dep = inc.split("/")[1]
                if dep != module:
                    graph[module].add(dep)
    # cycles (depth-first search on the module graph)
    state, stack = {}, []

    def visit(m):
        state[m] = 1
        stack.append(m)
        for d in sorted(graph.get(m, ())):
            if state.get(d) == 1:
                problems.append("include cycle: " + " -> ".join(stack[stack.index(d):] + [d]))
            elif d not in state:
                visit(d)
        stack.pop()
        state[m] = 2

    for m in sorted(graph):
        if m not in state:
            visit(m)
    ros_dir = os.path.join(ROOT, "src", "ros")
    for n in sorted(os.listdir(ros_dir)):
        for inc in includes(os.path.join(ros_dir, n)):
            if re.match(r"needle_sim/(fem|adapt|solver|tissue)/", inc):
                problems.append("src/ros/%s includes %s: physics in the ROS layer" % (n, inc))
    tools_dir = os.path.join(ROOT, "src", "tools")
    ros_headers = re.compile(r"(ros|rosbag|geometry_msgs|nav_msgs|std_msgs|sensor_msgs|tf2\w*|needle_sim/ros)/|\.\./ros/")
    for n in sorted(os.listdir(tools_dir)):
        if n.startswith(("bag_input.", "bag_output.")):
            continue
        for inc in includes(os.path.join(tools_dir, n)):
            if ros_headers.match(inc):
                problems.append("src/tools/%s includes %s: the tool must build without ROS" % (n, inc))
    for m in sorted(graph):
        print("%-9s -> %s" % (m, ", ".join(sorted(graph[m]))))
    if problems:
        print("\n".join(problems), file=sys.stderr)
        return 1
    print("no cycle; no ROS in the core; no physics headers in src/ros; no ROS in src/tools but its bag I/O")
    return 0


if __name__ == "__main__":
    sys.exit(main())
