"""doc/scene_format.md's key tables, generated from the declarations (core/parameters.hpp).

    scene_keys_doc.py [--tool PATH] [--doc doc/scene_format.md]            # rewrite the tables
    scene_keys_doc.py --check [--tool PATH] [--doc doc/scene_format.md]    # exit 1 when stale

Each table sits between '<!-- keys: SECTION -->' and '<!-- end keys -->' and is what
`needle_sim keys --markdown SECTION` prints. CTest runs --check (scene_format_doc): a changed
declaration fails it until the page is regenerated.
"""
import argparse
import os
import re
import subprocess
import sys

from .. import paths

BLOCK = re.compile(r"(<!-- keys: ([a-z_.]+) -->\n)(.*?)(<!-- end keys -->)", re.S)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tool", default=paths.tool())
    ap.add_argument("--doc", default=os.path.join(paths.share_dir(), "doc", "scene_format.md"))
    ap.add_argument("--check", action="store_true")
    a = ap.parse_args()
    text = open(a.doc, encoding="utf-8").read()
    stale = []

    def table(m):
        section = m.group(2)
        new = subprocess.run([a.tool, "keys", "--markdown", section], check=True, stdout=subprocess.PIPE,
                             text=True).stdout
        if not new.strip():
            sys.exit("scene_keys_doc: no section '%s' in `needle_sim keys`" % section)
        if new != m.group(3):
            stale.append(section)
        return m.group(1) + new + m.group(4)

    out, n = BLOCK.subn(table, text)
    if n == 0:
        sys.exit("scene_keys_doc: no '<!-- keys: ... -->' block in " + a.doc)
    if a.check:
        if stale:
            print("%s: the key tables of %s are not those the declarations give; run scripts/scene_keys_doc.py"
                  % (a.doc, ", ".join(stale)))
            return 1
        print("%s: %d key tables current" % (a.doc, n))
        return 0
    if out != text:
        open(a.doc, "w", encoding="utf-8").write(out)
    print("%s: %d key tables written (%s changed)" % (a.doc, n, ", ".join(stale) or "none"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
