"""Run every benchmark and gather their Markdown tables into benchmarks/results/summary.md.

    python benchmarks/run_all.py [--quick | --smoke --out DIR] [--only NAME ...]

Each benchmark measures this package against anchors installed from PyPI in the same run
(requirements-bench.txt) and writes benchmarks/results/<name>.json. --quick, --smoke and
--out are passed on to every script; with --out the summary goes there too. With --only
(e.g. `--only ground flights`) just those run, and their sections of the existing
summary are replaced, each marked with the time it was rerun: the summary then says
which figures come from the full run and which from a later one.
"""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
import time
from pathlib import Path

from common import bench_args

HERE = Path(__file__).resolve().parent
NAMES = [script.stem[len("bench_"):] for script in sorted(HERE.glob("bench_*.py"))]
# A benchmark's section: "## ground (226 s)" (the scripts' own headings have no "(N s)").
SECTION = re.compile(r"^## (\w+) \(\d+ s[^)]*\)$", re.MULTILINE)


def run(name: str, passed: list[str]) -> tuple[str, bool, str]:
    """How long one benchmark took, whether it passed, and its output (or its error)."""
    print(f"== bench_{name}.py", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    res = subprocess.run([sys.executable, str(HERE / f"bench_{name}.py"), *passed],
                         capture_output=True, text=True, cwd=HERE.parent)
    took = f"{time.perf_counter() - t0:.0f} s"
    return took, res.returncode == 0, (res.stdout.strip() if res.returncode == 0 else
                                       "```\n" + res.stderr.strip()[-2000:] + "\n```")


def sections(text: str) -> tuple[str, dict[str, str]]:
    """A summary's header and its sections by benchmark name (each with its heading)."""
    marks = list(SECTION.finditer(text))
    head = text[:marks[0].start()] if marks else text
    body = {m.group(1): text[m.start():(marks[i + 1].start() if i + 1 < len(marks)
                                        else len(text))]
            for i, m in enumerate(marks)}
    return head, body


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", nargs="+", choices=NAMES, metavar="NAME",
                    help=f"rerun only these and splice them in: {', '.join(NAMES)}")
    args = bench_args(__doc__, "a short version of each", "each script's smoke run", ap)
    passed = ([f"--{args.mode}"] if args.mode != "full" else []) + ["--out", str(args.out)]
    when = time.strftime('%Y-%m-%d %H:%M')
    summary = args.out / "summary.md"
    if args.only and summary.is_file():
        head, body = sections(summary.read_text())
    else:
        head, body = f"# Benchmarks ({when}, {args.mode})\n\n", {}
    failed = []
    for name in args.only or NAMES:
        took, ok, text = run(name, passed)
        if not ok:
            failed.append(name)
        rerun = f"; rerun alone {when}" if args.only else ""
        body[name] = f"## {name} ({took}{rerun})\n\n{text}\n\n"
    text = head + "".join(body[name] for name in NAMES if name in body)
    summary.write_text(text.rstrip("\n") + "\n")
    print(text)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
