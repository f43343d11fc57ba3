"""What the benchmark scripts share: the command line (--quick, --smoke, --out), anchors
that may be missing, Markdown tables (they run as scripts, so this folder is on their
import path)."""
from __future__ import annotations

import argparse
import contextlib
import importlib
import os
from pathlib import Path

RESULTS = Path(__file__).resolve().parent / "results"


def table(rows: list[dict], cols: list[str]) -> str:
    """A Markdown table of `rows` (dicts) with columns `cols`; floats to 4 significant
    digits, missing keys empty."""
    def fmt(v):
        if isinstance(v, float):
            return f"{v:.4g}"
        return str(v)

    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    lines += ["| " + " | ".join(fmt(r.get(c, "")) for c in cols) + " |" for r in rows]
    return "\n".join(lines)


def bench_args(doc: str | None, quick_help: str, smoke_help: str,
               parser: argparse.ArgumentParser | None = None) -> argparse.Namespace:
    """The command line of a benchmark: its docstring's first line, --quick, --smoke and
    --out, after any options of its own already on `parser`. ``args.mode`` is "full",
    "quick" or "smoke"; ``args.out`` the folder to write to, created.

    A smoke run goes through every code path on tiny inputs, so that a benchmark broken by
    a change in the package fails in the tests (which run it) rather than in the next
    `make bench`; its figures mean nothing, hence --out is required with it and may not be
    benchmarks/results, where the committed figures are."""
    if parser is None:
        parser = argparse.ArgumentParser(description=(doc or "").splitlines()[0])
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true", help=quick_help)
    mode.add_argument("--smoke", action="store_true",
                      help=f"every code path on tiny inputs, figures meaningless: {smoke_help}")
    parser.add_argument("--out", type=Path, metavar="DIR", help="where the results go "
                        "(default benchmarks/results; required with --smoke)")
    args = parser.parse_args()
    if args.smoke and (args.out is None or args.out.resolve() == RESULTS):
        parser.error("--smoke needs --out DIR other than benchmarks/results: its figures are "
                     "meaningless and must not replace the committed ones")
    args.mode = "smoke" if args.smoke else "quick" if args.quick else "full"
    args.out = (args.out or RESULTS).resolve()
    args.out.mkdir(parents=True, exist_ok=True)
    return args


def per_mode(args: argparse.Namespace, full, quick, smoke):
    """The size (files, seconds, repeats...) of a run in args.mode."""
    return {"full": full, "quick": quick, "smoke": smoke}[args.mode]


def installed(module: str, package: str) -> bool:
    """Whether an anchor imports; if not, a one-line note says it is skipped (the tests'
    smoke runs have requirements-dev.txt only). Called once per anchor and run."""
    try:
        importlib.import_module(module)
    except (ImportError, OSError) as exc:  # OSError: open3d's wheel without libusb-1.0
        print(f"({package} skipped, not installed: {str(exc).splitlines()[0]}; "
              "`make bench` installs it)", flush=True)
        return False
    return True


@contextlib.contextmanager
def quiet_stdout():
    """Anchors that print from C++ to file descriptor 1 (CSF's progress, Patchwork++'s
    greeting): keep the tables clean."""
    saved = os.dup(1)
    with open(os.devnull, "w") as null:
        os.dup2(null.fileno(), 1)
        try:
            yield
        finally:
            os.dup2(saved, 1)
            os.close(saved)
