"""Shared by the study scripts: run a list of scenes with the needle_sim tool (or reuse runs
whose summary.json says ok) and load their summaries and time series."""
import argparse
import csv
import datetime
import json
import os
import re
import subprocess
import sys

from .. import paths

SCENES = os.path.join(paths.share_dir(), "config", "scenes")


def parse_args(doc, name, extra=None):
    """--out (results/<name>), --tool, --reuse and what `extra(parser)` adds; checks the tool and
    makes the output folder."""
    ap = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default=paths.results_dir(name))
    ap.add_argument("--tool", default=paths.tool())
    ap.add_argument("--reuse", action="store_true", help="keep runs whose summary.json says ok")
    if extra:
        extra(ap)
    args = ap.parse_args()
    if not os.access(args.tool, os.X_OK):
        sys.exit(f"{name}: no needle_sim tool at {args.tool} (build first: bash scripts/test.sh)")
    os.makedirs(args.out, exist_ok=True)
    return args


def slug(name):
    return "".join(c if c.isalnum() else "_" for c in name).strip("_")


def run_all(tool, scenes_dir, out, runs, reuse):
    """runs: (name, scene file, extra arguments). Returns {name: (summary, run_dir, rows)}."""
    results = {}
    for name, scene, extra in runs:
        d = os.path.join(out, slug(name))
        summary_path = os.path.join(d, "summary.json")
        ok = False
        if reuse and os.path.exists(summary_path):
            with open(summary_path) as f:
                ok = json.load(f).get("status") == "ok"
        if not ok:
            cmd = [tool, "run", os.path.join(scenes_dir, scene), "--out", d, "--quiet"] + list(extra)
            print("+", " ".join(cmd), flush=True)
            subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        with open(summary_path) as f:
            summary = json.load(f)
        with open(os.path.join(d, "timeseries.csv"), newline="") as f:
            rows = list(csv.DictReader(f))
        results[name] = (summary, d, rows)
    return results


def write_csv(path, table):
    """table: a list of dicts with the same keys (the columns, in order)."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(table[0].keys()))
        w.writeheader()
        w.writerows(table)


def write_doc_block(doc, marker, md, command, commit=None):
    """Replaces what is between '<!-- MARKER: table -->' and '<!-- end MARKER -->' in doc/DOC with
    a line naming the date, the commit (`commit`, else the checkout's now) and `command`, then
    `md`: figures in the docs are written by the study that measured them, never by hand."""
    path = os.path.join(paths.share_dir(), "doc", doc)
    text = open(path, encoding="utf-8").read()
    block = re.compile(r"(<!-- %s: table -->\n)(.*?)(<!-- end %s -->)" % (re.escape(marker), re.escape(marker)), re.S)
    if not block.search(text):
        sys.exit(f"{path}: no '<!-- {marker}: table -->' ... '<!-- end {marker} -->' block")
    commit = commit or subprocess.run(["git", "describe", "--always", "--dirty"], cwd=paths.share_dir(),
                                      stdout=subprocess.PIPE, text=True).stdout.strip()
    head = f"Made on {datetime.date.today().isoformat()} at {commit} by `{command}`.\n\n"
    text = block.sub(lambda m: m.group(1) + head + md + m.group(3), text)
    with open(path, "w", encoding="utf-8") as f:
        f.write(text)


def publish_table(out, rows, md, write_doc, doc, marker, command):
    """A study's table: table.csv and table.md in `out`, printed, and with `write_doc` into the
    doc's block (write_doc_block)."""
    write_csv(os.path.join(out, "table.csv"), rows)
    with open(os.path.join(out, "table.md"), "w") as f:
        f.write(md)
    print(md)
    if write_doc:
        write_doc_block(doc, marker, md, command)
