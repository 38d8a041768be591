"""Text of a study's summary: numbers as the studies print them, Markdown tables, atomic writes."""
from __future__ import annotations

import math
from pathlib import Path
from typing import Any


def per_axis(n: Any, dim: int) -> str:
    """`n` per axis of a `dim`-D body as charts and summaries write it: "8²" in 2-D, "8³" in 3-D, "8" in 1-D."""
    return f"{n}" + {1: "", 2: "²", 3: "³"}.get(dim, f"^{dim}")


def fmt(x: Any, digits: int = 3) -> str:
    """A number to `digits` significant digits ("diverged" where it is not finite); anything else as text."""
    try:
        x = float(x)
    except (TypeError, ValueError):
        return str(x)
    if not math.isfinite(x):
        return "diverged"  # metrics of a rollout that left the finite range are NaN or inf
    return f"{x:.{digits}g}"


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str]]) -> str:
    """Rows as a Markdown table; columns are (key, header)."""
    head = "| " + " | ".join(h for _, h in columns) + " |\n|" + "---|" * len(columns) + "\n"
    return head + "".join("| " + " | ".join(fmt(r.get(k, "")) for k, _ in columns) + " |\n" for r in rows)


def write_text_atomic(path: Path, text: str) -> Path:
    """:func:`lnf.tempfiles.write_text_atomic`, imported when first used (importing lnf loads torch)."""
    from lnf.tempfiles import write_text_atomic as write

    return write(path, text)
