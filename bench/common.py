"""Shared helpers for benchmarks: argument parsing, tables, JSON, machine description."""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np


def parser(name: str, description: str) -> argparse.ArgumentParser:
    """The options every benchmark takes: --quick and --json PATH (and --seed)."""
    p = argparse.ArgumentParser(prog=f"python -m bench {name}", description=description)
    p.add_argument("--quick", action="store_true", help="small subset, same output shape")
    p.add_argument("--json", type=Path, default=None, help="write results here")
    p.add_argument("--seed", type=int, default=0)
    return p


def machine() -> dict[str, Any]:
    """What the numbers were measured on."""
    return {
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "date_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def table(headers: Sequence[str], rows: Sequence[Sequence[Any]], title: str | None = None) -> str:
    """A plain-text table; floats with 3 significant decimals."""

    def fmt(v: Any) -> str:
        if isinstance(v, float | np.floating):
            if not np.isfinite(v):
                return "-"
            return f"{v:.3f}" if abs(float(v)) < 1000 else f"{v:.0f}"
        return str(v)

    cells = [[fmt(v) for v in r] for r in rows]
    widths = [max(len(h), *(len(r[i]) for r in cells)) if cells else len(h) for i, h in enumerate(headers)]
    lines = []
    if title:
        lines.append(title)
    lines.append("  ".join(h.rjust(w) for h, w in zip(headers, widths)))
    lines.append("  ".join("-" * w for w in widths))
    lines.extend("  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells)
    return "\n".join(lines)


def _jsonable(o: Any) -> Any:
    if isinstance(o, dict):
        return {str(k): _jsonable(v) for k, v in o.items()}
    if isinstance(o, list | tuple):
        return [_jsonable(v) for v in o]
    if isinstance(o, np.ndarray):
        return _jsonable(o.tolist())
    if isinstance(o, np.floating | float):
        f = float(o)
        return f if np.isfinite(f) else None
    if isinstance(o, np.integer):
        return int(o)
    return o


def write_json(path: Path | None, results: dict[str, Any]) -> None:
    """Write ``results`` (plus the machine description) as JSON; NaN/inf become null."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    doc = {"machine": machine(), **results}
    path.write_text(json.dumps(_jsonable(doc), indent=2) + "\n")
    print(f"wrote {path}")
