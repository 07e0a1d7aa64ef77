"""Imports point one way (DESIGN.md): tools -> {drivers, perception, fusion} -> logs; inside
tools: cli -> {demo, fleet, bench} -> {jobs, daemon, emulators} -> config, and emulators -> sim; inside
fusion: slam -> localization -> {evaluation, odometry, matching} -> mapping -> optimization -> the
shared ground (fusion/geometry.py, fusion/observation_models.py, and fusion/compiled.py: how every kernel,
the shared ground's own included, is compiled and cached). Read from the source with ast, so a
new arrow back up fails here instead of becoming a circle later."""

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
    "fusion/optimization": {"logs", "fusion"},
    "fusion/mapping": {"logs", "fusion", "fusion/optimization"},
    "fusion/matching": {"logs", "fusion", "fusion/optimization", "fusion/mapping"},
    "fusion/odometry": {"logs", "fusion", "fusion/optimization"},
    "fusion/evaluation": {"logs", "fusion", "fusion/mapping"},
    "fusion/localization": {"logs", "fusion", "fusion/optimization", "fusion/mapping", "fusion/matching",
                            "fusion/odometry", "fusion/evaluation"},
    "fusion/slam": {"logs", "fusion", "fusion/optimization", "fusion/mapping", "fusion/matching", "fusion/odometry",
                    "fusion/evaluation", "fusion/localization"},
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


FUSION_ROOMS = {room.split("/")[1] for room in MAY_IMPORT if room.startswith("fusion/")}


def room_of_module(name: str) -> str | None:
    parts = name.split(".")
    if parts[0] != "trundle" or len(parts) < 2 or parts[1] not in ("logs", "drivers", "perception", "fusion", "tools"):
        return None  # not ours, or the root package itself (trundle.__version__)
    if parts[1] == "tools":
        return f"tools/{parts[2]}" if len(parts) > 2 else "tools"
    if parts[1] == "fusion" and len(parts) > 2 and parts[2] in FUSION_ROOMS:
        return f"fusion/{parts[2]}"
    return parts[1]


def room_of_file(path: Path) -> str:
    parts = path.relative_to(REPO).parts
    if parts[0] == "tools" or (parts[0] == "fusion" and len(parts) > 2):
        return f"{parts[0]}/{parts[1]}"
    return parts[0]


def may_import(room: str, target: str) -> bool:
    """Whether `room` may import `target`; outside fusion, fusion's rooms count as fusion."""
    if not room.startswith("fusion") and target.startswith("fusion/"):
        target = "fusion"
    return target in MAY_IMPORT[room]


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
            if target not in (None, room, "tools") and not may_import(room, target):
                wrong.append(f"{path.relative_to(REPO)} imports {name} ({room} -> {target})")
    assert not wrong, "\n".join(wrong)


def test_tools_has_only_rooms() -> None:
    loose = sorted(p.name for p in (REPO / "tools").iterdir() if p.is_file() and p.name != "__init__.py")
    assert not loose, f"files outside a room in tools/: {loose}"


def test_fusion_keeps_only_its_shared_ground_outside_rooms() -> None:
    loose = sorted(p.name for p in (REPO / "fusion").glob("*.py"))
    assert loose == ["__init__.py", "compiled.py", "geometry.py", "observation_models.py"], (
        f"files outside a room in fusion/: {loose}")
