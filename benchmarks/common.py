"""What the benchmark scripts share: the --quick option and Markdown tables (they run as
scripts, so this folder is on their import path)."""
from __future__ import annotations

import argparse
import contextlib
import os


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


def quick_args(doc: str | None, quick_help: str) -> argparse.Namespace:
    """The command line of a benchmark: its docstring's first line, and --quick."""
    parser = argparse.ArgumentParser(description=(doc or "").splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    return parser.parse_args()


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
