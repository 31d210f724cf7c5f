"""Checks the relative links of the package's Markdown: every linked file exists and every
#anchor names a heading of its file (GitHub's slugs). Exit 1 with the broken links listed.

    doc_links.py [--root CHECKOUT]      # CTest doc_links; the root defaults to this checkout
"""
import argparse
import os
import re
import sys

from .. import paths

ROOT = paths.source_dir() or paths.share_dir()
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def slug(heading):
    s = heading.strip().lower()
    s = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", s)
    s = re.sub(r"[^\w\- ]", "", s)
    return s.replace(" ", "-")


def anchors(path, cache={}):
    if path not in cache:
        found, counts, fence = set(), {}, False
        for line in open(path, encoding="utf-8"):
            if line.lstrip().startswith("```"):
                fence = not fence
            if fence:
                continue
            m = re.match(r"#{1,6}\s+(.*?)\s*#*\s*$", line)
            if m:
                base = slug(m.group(1))
                n = counts.get(base, 0)
                counts[base] = n + 1
                found.add(base if n == 0 else "%s-%d" % (base, n))
            for a in re.findall(r'<a\s+(?:name|id)="([^"]+)"', line):
                found.add(a)
        cache[path] = found
    return cache[path]


def markdown_files():
    for top in ["README.md", "CHANGELOG.md", "doc", "data", "config"]:
        p = os.path.join(ROOT, top)
        if os.path.isfile(p):
            yield p
        for d, _, files in os.walk(p):
            for f in files:
                if f.endswith(".md"):
                    yield os.path.join(d, f)


def main():
    global ROOT
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--root", default=ROOT)
    ROOT = ap.parse_args().root
    broken = []
    for md in markdown_files():
        fence = False
        for no, line in enumerate(open(md, encoding="utf-8"), 1):
            if line.lstrip().startswith("```"):
                fence = not fence
            if fence:
                continue
            for target in LINK.findall(line):
                if re.match(r"[a-z]+:", target):
                    continue  # http:, https:, mailto:
                path, _, anchor = target.partition("#")
                dest = os.path.normpath(os.path.join(os.path.dirname(md), path)) if path else md
                where = "%s:%d: %s" % (os.path.relpath(md, ROOT), no, target)
                if not os.path.exists(dest):
                    broken.append(where + " (no such file)")
                elif anchor and dest.endswith(".md") and anchor not in anchors(dest):
                    broken.append(where + " (no such heading)")
    for b in broken:
        print(b)
    print("%d broken links" % len(broken))
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main())
