"""Runs the docs: every command block of the README, the tutorials and cli.md, in order, as a
reader would from the repository's root, and checks every figure the prose quotes against
what the run (or the benchmark script's tables in doc/benchmarks.md) gives, within the
tolerance the doc states. Exit 1 on a failing block or a figure out of its tolerance.

    docs_run.py [--full] [--only README.md ...] [--report FILE] [--clean] [--list]

A block is a fenced ```bash (or ```python) block; plain ``` blocks show output and are not
run. An HTML comment on the line before a block says how the docs job treats it:

    <!-- docs: skip REASON -->               not run (interactive, a display, a foreign tool);
                                             the reason is printed
    <!-- docs: full REASON -->               run with --full only (a long study)
    <!-- docs: short 'OLD' -> 'NEW'; ... --> run with these literal replacements unless --full
    <!-- docs: edit 'OLD' -> 'NEW'; ... -->  run with these replacements always (a GUI left out)
    <!-- docs: background TOPIC -->          run in the background (a node); the next block
                                             starts once TOPIC is advertised; stopped at the
                                             end of its page

Blocks of one page share one bash session (variables such as T= carry on). A figure is a
number followed at once by a comment stating where it comes from and how close it must be:

    1,509<!-- = J('results/phantom_insertion_adaptive/summary.json')['adaptivity']['tissue_dofs_max'] ±2% -->

The expression is Python with J(path) (a JSON file), CSV(path) (columns as lists), OUT(part)
(what the block of this page that contains `part` printed), nums(text, regex) and
num(text, regex) (the numbers the regex's group matches: all, or the last), median(list), mean(list), and
T(block, row, column) (a cell of a generated table of doc/benchmarks.md: row is the first
cells, a string or a tuple) and column(block, column) (a list). Tolerances: ±P% (relative), ±X (absolute), ×F (within a factor,
for wall times on a shared machine), ≥ (the quoted figure is a bound the run stays under: for
the wall time of work at idle priority, which takes what the rest of the machine leaves). A figure whose source a skipped or --full-only block
makes is reported unchecked in the short run and checked in the --full one. The report
(--report) lists every block with its wall time and every figure with quoted and found
values.
"""
import argparse
import csv
import json
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time

from .. import paths

ROOT = paths.source_dir()
PAGES = ["README.md", "doc/tutorials/00_library.md", "doc/tutorials/01_phantom_insertion.md",
         "doc/tutorials/02_dbs_brain_shift.md", "doc/tutorials/03_robot_node.md", "doc/tutorials/04_twin_experiment.md",
         "doc/cli.md"]
OUTPUTS = {}  # page -> [(block body, its output)] of the blocks run
FENCE = re.compile(r"^```(\w*)\s*$")
DIRECTIVE = re.compile(r"^<!--\s*docs:\s*(skip|full|short|edit|background)\b\s*(.*?)\s*-->\s*$")
NUMBER = r"[−-]?\d[\d,]*(?:\.\d+)?(?:e[−-]?\d+)?"
FIGURE = re.compile(r"(" + NUMBER + r")<!--\s*=\s*(.+?)\s+(±|×|≥)\s*([\d.eE+-]*)(%?)\s*-->", re.S)


class Block:
    def __init__(self, page, line, lang, body, kind, arg):
        self.page, self.line, self.lang, self.body, self.kind, self.arg = page, line, lang, body, kind, arg

    def where(self):
        return "%s:%d" % (self.page, self.line)


def blocks(page):
    lines = open(os.path.join(ROOT, page), encoding="utf-8").read().split("\n")
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        j = i + 1
        while not lines[j].startswith("```"):
            j += 1
        lang = m.group(1)
        if lang in ("bash", "python"):
            d = DIRECTIVE.match(lines[i - 1]) if i > 0 else None
            kind, arg = (d.group(1), d.group(2)) if d else ("run", "")
            if kind in ("skip", "full") and not arg:
                raise SystemExit("%s:%d: docs: %s needs a reason" % (page, i + 1, kind))
            out.append(Block(page, i + 1, lang, "\n".join(lines[i + 1:j]), kind, arg))
        i = j + 1
    return out


def replacements(arg, where):
    pairs = re.findall(r"'([^']*)'\s*->\s*'([^']*)'", arg)
    if not pairs or re.sub(r"'[^']*'\s*->\s*'[^']*'", "", arg).strip(" ;"):
        raise SystemExit("%s: docs: short/edit wants 'OLD' -> 'NEW'[; ...], got %r" % (where, arg))
    return pairs


def figures(page):
    text = open(os.path.join(ROOT, page), encoding="utf-8").read()
    marks = {m.start() for m in re.finditer(r"<!--\s*=", text)}
    parsed = {m.start(0) + len(m.group(1)) for m in FIGURE.finditer(text)}
    for pos in sorted(marks - parsed):
        raise SystemExit("%s:%d: a figure comment without a number right before it, or without a tolerance"
                         % (page, text.count("\n", 0, pos) + 1))
    for m in FIGURE.finditer(text):
        line = text.count("\n", 0, m.start()) + 1
        if text[text.rfind("\n", 0, m.start()) + 1:m.start()].count("`") % 2:
            continue  # inside an inline code span: the syntax shown, not a figure
        if (m.group(3) == "≥") != (m.group(4) == ""):
            raise SystemExit("%s:%d: ± and × take a tolerance, ≥ none" % (page, line))
        yield line, m.group(1), m.group(2), m.group(3), float(m.group(4) or "nan"), m.group(5) == "%"


def value(s):
    return float(s.replace("−", "-").replace(",", ""))  # 1,509 and −20 as printed


def _cell(s):
    s = s.strip().replace("−", "-").replace(",", "")
    s = re.sub(r"\s*(%|x|ms|s)$", "", s)
    try:
        return float(s)
    except ValueError:
        return s


def _rows(block, cache={}):
    """The rows (header first) of the generated table `block` of doc/benchmarks.md."""
    if block not in cache:
        text = open(os.path.join(ROOT, "doc", "benchmarks.md"), encoding="utf-8").read()
        m = re.search(r"<!-- %s: table -->(.*?)<!-- end %s -->" % (re.escape(block), re.escape(block)), text, re.S)
        if not m:
            raise KeyError("no table %s in doc/benchmarks.md" % block)
        cache[block] = [[c.strip() for c in l.strip().strip("|").split("|")] for l in m.group(1).split("\n")
                        if l.startswith("|") and not l.startswith("|---")]
    return cache[block]


def table(block, row, column):
    """A cell of a generated table of doc/benchmarks.md (benchmarks.py writes them)."""
    rows = _rows(block)
    head, key = rows[0], (row,) if isinstance(row, str) else tuple(row)
    for r in rows[1:]:
        if tuple(r[:len(key)]) == key:
            return _cell(r[head.index(column)])
    raise KeyError("table %s: no row %s" % (block, key))


def column(block, col):
    """A column of a generated table of doc/benchmarks.md, as a list."""
    rows = _rows(block)
    i = rows[0].index(col)
    return [_cell(r[i]) for r in rows[1:]]


def read_csv(path):
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    cols = {}
    for r in rows:
        for k, v in r.items():
            cols.setdefault(k, []).append(_cell(v) if v not in ("", None) else None)
    return cols


def _output(page, part):
    found = [text for body, text in OUTPUTS.get(page, []) if part in body]
    if len(found) != 1:
        raise KeyError("%d blocks run on %s contain %r" % (len(found), page, part))
    return found[0]


def _numbers(text, pattern):
    return [float(m.replace(",", "")) for m in re.findall(pattern, text)]


def check_figure(page, quoted, expr, op, tol, rel):
    env = {"OUT": lambda part: _output(page, part), "nums": _numbers,
           "num": lambda text, pattern: _numbers(text, pattern)[-1], "median": lambda v: sorted(v)[len(v) // 2],
           "mean": lambda v: sum(v) / len(v),
           "J": lambda p: json.load(open(p)), "CSV": read_csv, "T": table, "column": column, "abs": abs, "max": max,
           "min": min, "round": round, "len": len, "sum": sum}
    found = float(eval(expr, env))  # the docs' own expressions, from this checkout
    q = value(quoted)
    if op == "≥":
        ok = found <= q
        stated = "at most the quoted figure"
    elif op == "×":
        ok = found != 0 and q != 0 and max(q / found, found / q) <= tol and (q > 0) == (found > 0)
        stated = "within a factor %g" % tol
    else:
        lim = tol * abs(found) / 100 if rel else tol
        ok = abs(q - found) <= lim + 1e-12
        stated = "±%g%s" % (tol, "%" if rel else "")
    return ok, found, stated


def wait_for_topic(topic, timeout, env):
    t0 = time.time()
    while time.time() - t0 < timeout:
        r = subprocess.run(["rostopic", "list"], capture_output=True, text=True, env=env)
        if r.returncode == 0 and topic in r.stdout.split():
            return True
        time.sleep(1)
    return False


def stop(background):
    """Stops the background terminals: SIGINT (roslaunch's Ctrl-C), then SIGKILL."""
    for pid in background:
        for sig, wait in ((signal.SIGINT, 15), (signal.SIGKILL, 2)):
            try:
                os.killpg(pid, sig)
            except ProcessLookupError:
                break
            t0 = time.time()
            while time.time() - t0 < wait:
                try:
                    os.killpg(pid, 0)
                except ProcessLookupError:
                    break
                time.sleep(0.2)
    background.clear()


def run_page(page, full, log, report):
    """The page's blocks in one bash session; returns the failures."""
    failures = []
    # A reader's fresh terminal: none of the ROS or devel environment this program runs in (a
    # block that needs it must source devel/setup.bash, as the docs tell the reader to).
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("ROS_", "ROSLISP", "PYTHONPATH", "CMAKE_PREFIX_PATH", "LD_LIBRARY_PATH",
                                "PKG_CONFIG_PATH", "CATKIN"))}
    env["PATH"] = "/usr/bin:" + env.get("PATH", "")
    for k in ("ROS_HOME", "ROS_MASTER_URI"):
        if k in os.environ:
            env[k] = os.environ[k]
    shell = subprocess.Popen(["bash", "--noprofile", "--norc"], stdin=subprocess.PIPE, stdout=log, stderr=log,
                             cwd=ROOT, env=env, text=True, start_new_session=True)
    status_dir = tempfile.mkdtemp(prefix="needle_sim_docs_run.")
    background = []
    try:
        for n, b in enumerate(blocks(page)):
            if b.kind == "skip" or (b.kind == "full" and not full):
                why = b.arg if b.kind == "skip" else "--full only: " + b.arg
                report.append("| %s | %s | not run: %s |" % (b.where(), "-", why))
                print("docs_run: %s not run (%s)" % (b.where(), why), file=sys.stderr)
                continue
            body = b.body
            if b.kind == "edit" or (b.kind == "short" and not full):
                for old, new in replacements(b.arg, b.where()):
                    if old not in body:
                        raise SystemExit("%s: docs: short: %r is not in the block" % (b.where(), old))
                    body = body.replace(old, new)
            src = os.path.join(status_dir, "block%d.%s" % (n, "py" if b.lang == "python" else "sh"))
            with open(src, "w") as f:
                f.write(body + "\n")
            done = os.path.join(status_dir, "block%d.rc" % n)
            if os.path.exists(done):
                os.remove(done)
            t0 = time.time()
            print("docs_run: %s (%s) ..." % (b.where(), b.kind), file=sys.stderr, flush=True)
            log.write("\n===== %s (%s) =====\n" % (b.where(), b.kind))
            log.flush()
            if b.kind == "background":
                # A terminal of its own (its own process group); a later one replaces it, as
                # the reader's Ctrl-C in that terminal before the next launch.
                stop(background)
                shell.stdin.write("setsid bash --norc -c 'source %s' < /dev/null > %s.log 2>&1 &\necho $! > %s\n"
                                  % (src, src, done))
                shell.stdin.flush()
                while not os.path.exists(done) or not open(done).read().strip():
                    time.sleep(0.1)
                background.append(int(open(done).read()))
                topic = b.arg.split()[0] if b.arg else ""
                if not topic or not wait_for_topic(topic, 180, os.environ):
                    failures.append("%s: %s never advertised (log %s.log)" % (b.where(), topic, src))
                    break
                report.append("| %s | %.1f | started; %s advertised |" % (b.where(), time.time() - t0, topic))
                continue
            out = src + ".out"
            run = ("/usr/bin/python3 %s < /dev/null > %s 2>&1" % (src, out) if b.lang == "python"
                   else "source %s < /dev/null > %s 2>&1" % (src, out))
            # set -e inside the sourced block (a failing command fails the block), off again for
            # the session; the block's status is written where this process waits for it.
            shell.stdin.write("( set -eo pipefail; %s ) ; echo $? > %s.tmp && mv %s.tmp %s\n" % (run, done, done, done)
                              if b.lang == "python" else
                              "set -eo pipefail; %s; rc=$?; set +e +o pipefail; echo $rc > %s.tmp; mv %s.tmp %s\n"
                              % (run, done, done, done))
            shell.stdin.flush()
            while not os.path.exists(done):
                if shell.poll() is not None:
                    break
                time.sleep(0.2)
            rc = int(open(done).read()) if os.path.exists(done) else shell.returncode
            text = open(out, errors="replace").read() if os.path.exists(out) else ""
            log.write(text)
            log.flush()
            OUTPUTS.setdefault(page, []).append((b.body, text))
            dt = time.time() - t0
            report.append("| %s | %.1f | %s |" % (b.where(), dt, "ok" if rc == 0 else "FAILED (exit %s)" % rc))
            print("docs_run: %s %s in %.1f s" % (b.where(), "ok" if rc == 0 else "FAILED", dt), file=sys.stderr)
            if rc != 0:
                failures.append("%s: exit %s (log above)" % (b.where(), rc))
                break
    finally:
        if shell.poll() is None:
            shell.stdin.close()
            try:
                shell.wait(30)
            except subprocess.TimeoutExpired:
                pass
        stop(background)
        for f in sorted(os.listdir(status_dir)):
            if f.endswith(".log"):  # the background terminals' output
                log.write("\n===== %s: background terminal %s =====\n" % (page, f))
                log.write(open(os.path.join(status_dir, f), errors="replace").read())
        shutil.rmtree(status_dir, ignore_errors=True)
        if shell.poll() is None:
            try:
                os.killpg(shell.pid, signal.SIGINT)
                time.sleep(3)
                os.killpg(shell.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    return failures


def main():
    global ROOT
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--full", action="store_true", help="run the long blocks as written too")
    ap.add_argument("--only", nargs="+", help="these pages (paths from the root)")
    ap.add_argument("--report", help="write the blocks' and figures' table (Markdown) here")
    ap.add_argument("--log", default="docs_run.log", help="the blocks' output (default: ./docs_run.log)")
    ap.add_argument("--clean", action="store_true", help="remove results/ first (the docs write there)")
    ap.add_argument("--figures-only", action="store_true", help="check the figures against what is there")
    ap.add_argument("--list", action="store_true", help="list the blocks and figures, run nothing")
    ap.add_argument("--root", default=ROOT)
    a = ap.parse_args()
    ROOT = a.root
    pages = a.only or PAGES
    if a.list:
        for p in pages:
            for b in blocks(p):
                print("%-45s %-10s %s" % (b.where(), b.kind, b.arg))
            for line, q, expr, op, tol, rel in figures(p):
                print("%s:%d figure %s = %s %s%g%s" % (p, line, q, expr, op, tol, "%" if rel else ""))
        return 0
    if not a.figures_only:
        if os.path.isdir(os.path.join(ROOT, "results")):
            if not a.clean:
                raise SystemExit("docs_run: results/ exists and the docs write there; move it away or --clean")
            shutil.rmtree(os.path.join(ROOT, "results"))
    report = ["| block | wall s | result |", "|---|---|---|"]
    failures = []
    t_start = time.time()
    if not a.figures_only:
        with open(os.path.abspath(a.log), "w") as log:
            for p in pages:
                f = run_page(p, a.full, log, report)
                failures += f
                if f:
                    break
    saved = os.path.abspath(a.log) + ".outputs.json"  # for --figures-only
    if a.figures_only:
        if os.path.exists(saved):
            OUTPUTS.update(json.load(open(saved)))
    else:
        with open(saved, "w") as f:
            json.dump(OUTPUTS, f)
    figs = ["", "| figure | quoted | found | tolerance | result |", "|---|---|---|---|---|"]
    unchecked = 0
    if not failures:
        cwd = os.getcwd()
        os.chdir(ROOT)
        for p in pages:
            for line, q, expr, op, tol, rel in figures(p):
                where = "%s:%d" % (p, line)
                try:
                    ok, found, stated = check_figure(p, q, expr, op, tol, rel)
                except (OSError, KeyError) as e:
                    if a.full:
                        failures.append("%s: figure %s: %s" % (where, q, e))
                        figs.append("| %s | %s | - | - | FAILED: %s |" % (where, q, e))
                    else:
                        unchecked += 1
                        figs.append("| %s | %s | - | - | unchecked (what it reads was not made in this run): %s |" % (where, q, e))
                    continue
                except Exception as e:  # noqa: BLE001 -- a figure whose expression fails is a failure
                    failures.append("%s: figure %s: %s: %s" % (where, q, type(e).__name__, e))
                    figs.append("| %s | %s | - | - | FAILED: %s |" % (where, q, e))
                    continue
                figs.append("| %s | %s | %.6g | %s | %s |" % (where, q, found, stated, "ok" if ok else "FAILED"))
                if not ok:
                    failures.append("%s: the doc quotes %s, the run gives %.6g (%s)" % (where, q, found, stated))
        os.chdir(cwd)
    text = "\n".join(report + figs) + "\n"
    if a.report:
        with open(a.report, "w") as f:
            f.write(text)
    print(text)
    print("docs_run: %d pages, %.0f s, %d figures unchecked (--full checks them), %d failures" % (
        len(pages), time.time() - t_start, unchecked, len(failures)))
    for f in failures:
        print("docs_run: FAILED %s" % f, file=sys.stderr)
    return 1 if failures else 0
