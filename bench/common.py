"""Shared helpers for benchmarks: argument parsing, tables, JSON, machine description."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import time
from collections.abc import Sequence
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
from threadpoolctl import threadpool_info


def parser(name: str, description: str) -> argparse.ArgumentParser:
    """The options every benchmark takes: --quick and --json PATH (and --seed)."""
    p = argparse.ArgumentParser(prog=f"python -m bench {name}", description=description)
    p.add_argument("--quick", action="store_true", help="small subset, same output shape")
    p.add_argument("--json", type=Path, default=None, help="write results here")
    p.add_argument("--seed", type=int, default=0)
    return p


_NUMERIC_PACKAGES = ("numpy", "scipy", "opencv-python-headless", "gtsam", "evo")


def _cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or platform.machine()


def machine() -> dict[str, Any]:
    """What the numbers were measured on. The flights' figures are chaotic in the last bits of floating
    point: another CPU (its SIMD kernels in numpy, OpenBLAS, OpenCV) or another build of these libraries
    moves a scene's APE by a few per cent (README), so the JSON says which ones made them."""

    def version(name: str) -> str | None:
        try:
            return metadata.version(name)
        except metadata.PackageNotFoundError:
            return None

    return {
        "cpu_count": os.cpu_count(),
        "processor": platform.processor() or platform.machine(),
        "cpu_model": _cpu_model(),
        "numpy_simd_found": np.show_config(mode="dicts").get("SIMD Extensions", {}).get("found"),
        "blas": sorted(
            {f"{i['internal_api']} {i.get('version')} {i.get('architecture')}" for i in threadpool_info()}
        ),
        "python": platform.python_version(),
        "numpy": np.__version__,
        "packages": {n: version(n) for n in _NUMERIC_PACKAGES},
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
