"""Run every benchmark and gather their Markdown tables into benchmarks/results/summary.md.

    python benchmarks/run_all.py [--quick | --smoke --out DIR]

Each benchmark measures this package against anchors installed from PyPI in the same run
(requirements-bench.txt) and writes benchmarks/results/<name>.json. --quick, --smoke and
--out are passed on to every script; with --out the summary goes there too.
"""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

from common import bench_args

HERE = Path(__file__).resolve().parent


def main() -> int:
    args = bench_args(__doc__, "a short version of each", "each script's smoke run")
    passed = ([f"--{args.mode}"] if args.mode != "full" else []) + ["--out", str(args.out)]
    when = time.strftime('%Y-%m-%d %H:%M')
    parts = [f"# Benchmarks ({when}, {args.mode})", ""]
    failed = []
    for script in sorted(HERE.glob("bench_*.py")):
        print(f"== {script.name}", file=sys.stderr, flush=True)
        t0 = time.perf_counter()
        res = subprocess.run([sys.executable, str(script), *passed], capture_output=True,
                             text=True, cwd=HERE.parent)
        parts += [f"## {script.stem[6:]} ({time.perf_counter() - t0:.0f} s)", ""]
        if res.returncode != 0:
            failed.append(script.name)
            parts += ["```", res.stderr.strip()[-2000:], "```", ""]
        else:
            parts += [res.stdout.strip(), ""]
    text = "\n".join(parts)
    (args.out / "summary.md").write_text(text)
    print(text)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
