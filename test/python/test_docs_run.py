"""The docs job (scripts/docs_run.py, issue #42) fails when a page's command fails or a quoted
figure is off its stated tolerance, and runs blocks as a reader would: one shell per page,
the directives applied. Small pages of its own in a temporary root; the real pages run in
.ci/run's docs phase."""
import os
import subprocess
import sys
import tempfile
import textwrap
import unittest

SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "scripts", "docs_run.py")


def run_page(text, *args):
    root = tempfile.mkdtemp(prefix="docs_run_test.")
    with open(os.path.join(root, "page.md"), "w") as f:
        f.write(textwrap.dedent(text))
    r = subprocess.run([sys.executable, SCRIPT, "--root", root, "--only", "page.md",
                        "--log", os.path.join(root, "log")] + list(args),
                       capture_output=True, text=True, timeout=120)
    return r, root


FIGURE_PAGE = """
    # A page

    ```bash
    N=1509
    mkdir -p results && echo "{\\"dofs\\": $N}" > results/s.json
    ```

    The largest mesh has {quoted}<!-- = J('results/s.json')['dofs'] ±3% --> DOFs.
    """


class Figures(unittest.TestCase):
    def test_a_figure_within_its_tolerance_passes(self):
        r, _ = run_page(FIGURE_PAGE.replace("{quoted}", "1,500"))
        self.assertEqual(r.returncode, 0, r.stdout + r.stderr)
        self.assertIn("| 1,500 | 1509 | ±3% | ok |", r.stdout)

    def test_a_stale_figure_fails(self):
        r, _ = run_page(FIGURE_PAGE.replace("{quoted}", "1,400"))
        self.assertEqual(r.returncode, 1)
        self.assertIn("the doc quotes 1,400, the run gives 1509", r.stderr)

    def test_a_figure_of_a_block_not_run_is_unchecked_and_the_full_run_checks_it(self):
        page = """
            <!-- docs: full a long study -->
            ```bash
            mkdir -p results && echo '{"x": 2}' > results/long.json
            ```

            It gives 2<!-- = J('results/long.json')['x'] ±0 -->.
            """
        r, root = run_page(page)
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn("unchecked", r.stdout)
        self.assertFalse(os.path.exists(os.path.join(root, "results", "long.json")))
        r, _ = run_page(page, "--full")
        self.assertEqual(r.returncode, 0, r.stderr)
        self.assertIn("| 2 | 2 | ±0 | ok |", r.stdout)

    def test_a_figure_comment_without_its_number_is_refused(self):
        r, _ = run_page("""
            ```bash
            true
            ```

            In about a quarter<!-- = 0.25 ×2 --> of a second.
            """)
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("page.md:6: a figure comment without a number", r.stdout + r.stderr)

    def test_printed_output_and_a_factor_tolerance(self):
        r, _ = run_page("""
            ```bash
            echo "computed in 0.25 s"
            ```

            About 0.5<!-- = num(OUT('computed in'), r'computed in ([\\d.]+) s') ×2 --> s, not
            0.1<!-- = num(OUT('computed in'), r'computed in ([\\d.]+) s') ×2 --> s.
            """)
        self.assertEqual(r.returncode, 1)
        self.assertIn("| 0.5 | 0.25 | within a factor 2 | ok |", r.stdout)
        self.assertIn("the doc quotes 0.1, the run gives 0.25", r.stderr)



    def test_a_bound_holds_the_run_under_it_and_takes_no_tolerance(self):
        r, _ = run_page("""
            ```bash
            echo "computed in 0.25 s"
            ```

            In less than 1<!-- = num(OUT('computed in'), r'computed in ([\\d.]+) s') ≥ --> s, not
            less than 0.2<!-- = num(OUT('computed in'), r'computed in ([\\d.]+) s') ≥ --> s.
            """)
        self.assertEqual(r.returncode, 1)
        self.assertIn("| 1 | 0.25 | at most the quoted figure | ok |", r.stdout)
        self.assertIn("the doc quotes 0.2, the run gives 0.25 (at most the quoted figure)", r.stderr)
        r, _ = run_page("""
            ```bash
            true
            ```

            Under 1<!-- = 0.5 ≥ 2 --> s.
            """)
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("page.md:6: ± and × take a tolerance, ≥ none", r.stdout + r.stderr)
class Blocks(unittest.TestCase):
    def test_a_failing_command_fails_the_page_and_stops_it(self):
        r, root = run_page("""
            ```bash
            true
            false
            touch after_false
            ```

            ```bash
            touch next_block
            ```
            """)
        self.assertEqual(r.returncode, 1)
        self.assertIn("page.md:2: exit 1", r.stderr)
        self.assertFalse(os.path.exists(os.path.join(root, "after_false")))
        self.assertFalse(os.path.exists(os.path.join(root, "next_block")))

    def test_blocks_share_a_shell_and_directives_apply(self):
        r, root = run_page("""
            ```bash
            T=value_from_the_first_block
            ```

            <!-- docs: short 'sleep 600' -> 'true' -->
            ```bash
            sleep 600; echo "$T" > carried
            cat > /dev/null   # reads stdin: must not swallow the session or hang
            ```

            <!-- docs: skip needs a display -->
            ```bash
            touch skipped
            ```
            """)
        self.assertEqual(r.returncode, 0, r.stderr)
        with open(os.path.join(root, "carried")) as f:
            self.assertEqual(f.read().strip(), "value_from_the_first_block")
        self.assertFalse(os.path.exists(os.path.join(root, "skipped")))
        self.assertIn("not run: needs a display", r.stdout)

    def test_a_skip_without_a_reason_and_a_replacement_that_does_not_match_are_refused(self):
        r, _ = run_page("""
            <!-- docs: skip -->
            ```bash
            true
            ```
            """)
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("needs a reason", r.stdout + r.stderr)
        r, _ = run_page("""
            <!-- docs: short 'absent' -> 'x' -->
            ```bash
            true
            ```
            """)
        self.assertNotEqual(r.returncode, 0)
        self.assertIn("is not in the block", r.stdout + r.stderr)


if __name__ == "__main__":
    unittest.main()
