"""STYLE.md rule 1: the math modules import no I/O (no Zenoh, MAVLink, sockets, serial, files' codecs),
and the daemon never imports the GPL-3 evo."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MATH_FILES = [
    p
    for pkg in ("georef", "vo", "lba", "ekf", "estimators")
    for p in sorted((ROOT / "companion" / pkg).rglob("*.py"))
] + [
    ROOT / "companion/geometry.py",
    ROOT / "companion/types.py",
    ROOT / "companion/metrics.py",
    ROOT / "companion/undistort.py",
]
FORBIDDEN_IN_MATH = (
    "zenoh",
    "pymavlink",
    "serial",
    "socket",
    "rosbags",
    "companion.io",
    "requests",
    "evo",
    "mavsdk",
)


def imported_modules(path: Path) -> set[str]:
    tree = ast.parse(path.read_text(), str(path))
    names: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return names


@pytest.mark.parametrize("path", MATH_FILES, ids=lambda p: str(p.relative_to(ROOT)))
def test_math_modules_import_no_io(path: Path) -> None:
    bad = sorted(
        m for m in imported_modules(path) for f in FORBIDDEN_IN_MATH if m == f or m.startswith(f + ".")
    )
    assert not bad, f"{path.relative_to(ROOT)} imports I/O: {bad}"


def test_daemon_never_imports_evo() -> None:
    for path in sorted((ROOT / "companion").rglob("*.py")):
        mods = imported_modules(path)
        assert not any(m == "evo" or m.startswith("evo.") for m in mods), f"{path} imports GPL-3 evo"
