"""Markdown tables for the benchmark scripts (they run as scripts, so this folder is on
their import path)."""
from __future__ import annotations


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
