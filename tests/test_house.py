"""The house's one rule (docs/design.md): imports flow one way between the package's rooms (its
top-level modules and subpackages), read from the code's own import statements, lazy ones too."""

from __future__ import annotations

import ast
import collections
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "pi0_armfix"


def _room(module: str) -> str | None:
    """`pi0_armfix.<room>...` -> `<room>`."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 and parts[0] == "pi0_armfix" else None


def room_imports(package: Path = PACKAGE) -> dict[str, set[str]]:
    """`{room: rooms it imports}` over every import statement of every module."""
    edges: dict[str, set[str]] = collections.defaultdict(set)
    for path in package.rglob("*.py"):
        source = _room(".".join(path.relative_to(package.parent).with_suffix("").parts))
        if source in (None, "__init__"):
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module]
                if node.module == "pi0_armfix":  # from pi0_armfix import <room>
                    names += [f"pi0_armfix.{alias.name}" for alias in node.names]
            else:
                continue
            edges[source] |= {r for r in map(_room, names) if r not in (None, source)}
    return edges


def find_cycle(edges: dict[str, set[str]]) -> list[str] | None:
    """A cycle of rooms (`[a, b, ..., a]`), or None where the imports form no circle."""
    state: dict[str, int] = {}  # 1 on the path, 2 done

    def visit(room: str, path: list[str]) -> list[str] | None:
        state[room] = 1
        for target in sorted(edges.get(room, ())):
            if state.get(target) == 1:
                return path[path.index(target):] + [target]
            if target not in state:
                found = visit(target, path + [target])
                if found:
                    return found
        state[room] = 2
        return None

    for room in sorted(edges):
        if room not in state:
            found = visit(room, [room])
            if found:
                return found
    return None


def test_the_rooms_import_one_way():
    edges = room_imports()
    assert "training" in edges and "evaluation" in edges  # the walk found the rooms
    cycle = find_cycle(edges)
    assert cycle is None, f"imports run in a circle: {' -> '.join(cycle)}"


def test_the_evaluator_and_the_training_machinery_stay_apart():
    edges = room_imports()
    assert "training" not in edges["evaluation"]
    assert "policies" not in edges["training"] and "evaluation" not in edges["training"]


def test_a_circle_of_imports_is_found(tmp_path):
    package = tmp_path / "pi0_armfix"
    for room, imported in (("a", "b"), ("b", "c"), ("c", "a")):
        (package / room).mkdir(parents=True)
        (package / room / "m.py").write_text(
            f"def f():\n    from pi0_armfix.{imported} import m\n")
    assert find_cycle(room_imports(package)) == ["a", "b", "c", "a"]
