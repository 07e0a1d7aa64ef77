"""Imports point one way (DESIGN.md): tools -> {drivers, perception, fusion} -> logs, and inside
tools: cli -> {demo, fleet, bench} -> {jobs, daemon, emulators} -> config, and emulators -> sim. Read from the source with ast,
so a new arrow back up fails here instead of becoming a circle later."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# room -> rooms it may import (besides itself); a room is a top-level folder or a folder in tools/
MAY_IMPORT = {
    "logs": set(),
    "drivers": {"logs"},
    "perception": {"logs"},
    "fusion": {"logs"},
    "tools/sim": {"logs", "drivers", "perception", "fusion"},
    "tools/emulators": {"logs", "drivers", "perception", "fusion", "tools/sim", "tools/config"},
    "tools/config": {"logs", "drivers", "perception", "fusion"},
    "tools/daemon": {"logs", "drivers", "perception", "fusion", "tools/config"},
    "tools/demo": {"logs", "drivers", "perception", "fusion", "tools/sim", "tools/emulators", "tools/daemon",
                   "tools/jobs", "tools/config"},
    "tools/jobs": {"logs", "drivers", "perception", "fusion", "tools/config"},
    "tools/fleet": {"logs", "drivers", "perception", "fusion", "tools/jobs", "tools/config"},
    "tools/bench": {"logs", "drivers", "perception", "fusion", "tools/sim", "tools/emulators", "tools/daemon",
                    "tools/jobs", "tools/config"},
    "tools/cli": {"logs", "drivers", "perception", "fusion", "tools/sim", "tools/emulators", "tools/daemon",
                  "tools/demo", "tools/jobs", "tools/fleet", "tools/config"},
}


def room_of_module(name: str) -> str | None:
    parts = name.split(".")
    if parts[0] != "trundle" or len(parts) < 2 or parts[1] not in ("logs", "drivers", "perception", "fusion", "tools"):
        return None  # not ours, or the root package itself (trundle.__version__)
    if parts[1] == "tools":
        return f"tools/{parts[2]}" if len(parts) > 2 else "tools"
    return parts[1]


def room_of_file(path: Path) -> str:
    parts = path.relative_to(REPO).parts
    return f"tools/{parts[1]}" if parts[0] == "tools" else parts[0]


def imported_modules(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def test_every_room_imports_only_downwards() -> None:
    wrong = []
    for path in sorted(REPO.glob("*/**/*.py")):
        top = path.relative_to(REPO).parts[0]
        if top not in ("logs", "drivers", "perception", "fusion", "tools") or path.parent == REPO / "tools":
            continue
        room = room_of_file(path)
        assert room in MAY_IMPORT, f"{path}: room {room} has no place in the layout (tests/test_layout.py)"
        for name in imported_modules(path):
            target = room_of_module(name)
            if target not in (None, room, "tools") and target not in MAY_IMPORT[room]:
                wrong.append(f"{path.relative_to(REPO)} imports {name} ({room} -> {target})")
    assert not wrong, "\n".join(wrong)


def test_tools_has_only_rooms() -> None:
    loose = sorted(p.name for p in (REPO / "tools").iterdir() if p.is_file() and p.name != "__init__.py")
    assert not loose, f"files outside a room in tools/: {loose}"
