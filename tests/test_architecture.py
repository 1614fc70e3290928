"""docs/architecture.md stays true: every top-level folder and every room of service/ has its
paragraph in the code map, service/ keeps at most eight rooms, and the import graph between
the rooms is acyclic and drawn in at most four layers (the layering itself is the
import-linter contracts of pyproject.toml, run by ``make test``)."""

from __future__ import annotations

import functools
import re
import subprocess
from pathlib import Path

import grimp
import pytest

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "architecture.md"
MAX_ROOMS = 8
MAX_LAYERS = 4


def top_level_folders() -> set[str]:
    """Folders at the repository's root that hold tracked files."""
    listed = subprocess.run(
        ["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True
    ).stdout.split("\n")
    return {path.split("/")[0] for path in listed if "/" in path}


def service_rooms() -> dict[str, str]:
    """Room name -> how the code map names it (``service/<room>/`` or ``service/<room>.py``)."""
    rooms = {}
    for entry in (ROOT / "service").iterdir():
        if entry.is_dir() and (entry / "__init__.py").is_file():
            rooms[entry.name] = f"service/{entry.name}/"
        elif entry.suffix == ".py" and entry.name != "__init__.py":
            rooms[entry.stem] = f"service/{entry.name}"
    return rooms


def code_map_headings() -> set[str]:
    text = ARCHITECTURE.read_text(encoding="utf-8")
    section = text.split("## Code map", 1)[1].split("\n## ", 1)[0]
    return set(re.findall(r"^### `([^`]+)`$", section, flags=re.MULTILINE))


def room_graph() -> dict[str, set[str]]:
    """Room -> the rooms its modules import (grimp: every import, lazy ones too)."""
    graph = grimp.build_graph("service")
    rooms = set(service_rooms())
    edges: dict[str, set[str]] = {room: set() for room in rooms}
    for module in graph.modules:
        parts = module.split(".")
        if len(parts) < 2 or parts[1] not in rooms:
            continue
        for imported in graph.find_modules_directly_imported_by(module):
            target = imported.split(".")
            if len(target) > 1 and target[1] in rooms and target[1] != parts[1]:
                edges[parts[1]].add(target[1])
    return edges


def layers_needed(edges: dict[str, set[str]]) -> int:
    """Nodes on the longest import path: the layers a drawing without an upward arrow
    needs. Raises on a cycle."""

    @functools.cache
    def depth(room: str, path: frozenset[str] = frozenset()) -> int:
        if room in path:
            raise AssertionError(f"import cycle through service.{room}")
        return 1 + max((depth(r, path | {room}) for r in edges[room]), default=0)

    return max(depth(room) for room in edges)


def test_code_map_names_every_top_level_folder_and_service_room() -> None:
    headings = code_map_headings()
    wanted = {f"{folder}/" for folder in top_level_folders()} | set(service_rooms().values())
    missing = sorted(wanted - headings)
    assert not missing, f"docs/architecture.md has no code-map paragraph for {missing}"


def test_service_root_holds_at_most_eight_rooms() -> None:
    rooms = sorted(service_rooms())
    assert len(rooms) <= MAX_ROOMS, f"service/ holds {len(rooms)} rooms: {rooms}"


def test_rooms_import_graph_is_acyclic_in_at_most_four_layers() -> None:
    edges = room_graph()
    assert layers_needed(edges) <= MAX_LAYERS, edges


def test_layer_count_sees_a_longer_chain() -> None:
    """The measure itself: a chain of five rooms needs five layers, a cycle is refused."""
    chain = {"a": {"b"}, "b": {"c"}, "c": {"d"}, "d": {"e"}, "e": set()}
    assert layers_needed(chain) == 5
    with pytest.raises(AssertionError, match="cycle"):
        layers_needed({"a": {"b"}, "b": {"a"}})
