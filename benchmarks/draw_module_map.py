"""The module map of docs/architecture.md: bh8_gym's modules and packages and agents/' verbs as
rooms on floors, imports as arrows, read from the code's import statements (nothing is run).

A room is a module of bh8_gym/, a package of bh8_gym/ (its folder), a package of agents/ (one
verb) or a module left directly in agents/. A room stands one floor above the highest room it
imports, so every arrow runs down; an arrow that a longer way down already implies is not drawn.
It prints the floors and exits 1 if rooms import each other in a circle (then no floor exists).

Run: python benchmarks/draw_module_map.py [--out docs/images/architecture.png] [--root CHECKOUT]
(--root draws another checkout, e.g. the "before" map from a `git worktree add` of an older commit.)
"""
from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def room_of(path: Path, root: Path = ROOT) -> str | None:
    """The room a source file belongs to (None: a package's face of the whole tree)."""
    parts = path.relative_to(root).with_suffix("").parts
    if parts[0] == "agents":
        parts = ("bh8_gym", "agents", *parts[1:])
    if len(parts) == 2:
        return None if parts[1] == "__init__" else parts[1]
    if parts[1] == "agents":
        return None if parts[2] == "__init__" else ("agents/" + parts[2] + ("" if len(parts) == 3 else "/"))
    return parts[1] + "/"


def module_name(path: Path, root: Path = ROOT) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    if parts[0] == "agents":
        parts = ("bh8_gym", "agents", *parts[1:])
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def read_rooms(root: Path = ROOT) -> tuple[dict[str, int], dict[str, set[str]]]:
    """Lines per room, and the rooms each room imports."""
    files = sorted([*root.glob("bh8_gym/**/*.py"), *root.glob("agents/**/*.py")])
    modules = {module_name(path, root): path for path in files}
    lines: dict[str, int] = {}
    imports: dict[str, set[str]] = {}
    for path in files:
        room = room_of(path, root)
        if room is None:
            continue
        source = path.read_text()
        lines[room] = lines.get(room, 0) + source.count("\n")
        used = imports.setdefault(room, set())
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
                names = [node.module, *(f"{node.module}.{alias.name}" for alias in node.names)]
            else:
                continue
            for name in names:
                target = room_of(modules[name], root) if name in modules else None
                if target is not None and target != room:
                    used.add(target)
    return lines, imports


def floors_of(imports: dict[str, set[str]]) -> dict[str, int]:
    """Floor 1 imports no room; every other room stands one above the highest it imports.
    SystemExit(1) naming them if rooms import each other in a circle."""
    floors: dict[str, int] = {}
    visiting: list[str] = []

    def floor(room: str) -> int:
        if room in visiting:
            raise SystemExit("rooms importing each other in a circle: "
                             + " -> ".join(visiting[visiting.index(room):] + [room]))
        if room not in floors:
            visiting.append(room)
            floors[room] = 1 + max((floor(used) for used in imports[room]), default=0)
            visiting.pop()
        return floors[room]

    for room in imports:
        floor(room)
    return floors


def drawn_arrows(imports: dict[str, set[str]]) -> list[tuple[str, str]]:
    """The imports no longer way down implies (the transitive reduction)."""
    def reach(room: str, seen: set[str]) -> set[str]:
        for used in imports[room]:
            if used not in seen:
                seen.add(used)
                reach(used, seen)
        return seen

    arrows = []
    for room, used in imports.items():
        implied = set().union(*(reach(other, set()) for other in used))
        arrows += [(room, target) for target in sorted(used - implied)]
    return arrows


def draw(lines: dict[str, int], floors: dict[str, int], arrows: list[tuple[str, str]], imports: int,
         out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import FancyBboxPatch

    top = max(floors.values())
    rows = {floor: sorted((room for room in floors if floors[room] == floor), key=lambda r: (-lines[r], r))
            for floor in range(1, top + 1)}
    width = 2.0 * max(len(row) for row in rows.values())  # a slot of 2 per room of the widest floor
    figure, axes = plt.subplots(figsize=(1.1 * width, 1.0 * top + 0.8), dpi=100)
    place = {}
    for floor, row in rows.items():
        for index, room in enumerate(row):
            place[room] = ((index + 0.5) * width / len(row), floor)
    for room, target in arrows:
        (x0, y0), (x1, y1) = place[room], place[target]
        axes.annotate("", xy=(x1, y1 + 0.22), xytext=(x0, y0 - 0.22),
                      arrowprops={"arrowstyle": "-|>", "color": "#8a94a6", "lw": 0.7, "shrinkA": 0, "shrinkB": 0})
    for room, (x, y) in place.items():
        agents = room.startswith("agents/")
        axes.add_patch(FancyBboxPatch((x - 0.9, y - 0.22), 1.8, 0.44, boxstyle="round,pad=0.02",
                                      facecolor="#f6dfe6" if agents else "#e3ebf6", edgecolor="#52607a", lw=0.8))
        axes.text(x, y + 0.05, room, ha="center", va="center", fontsize=9, weight="bold")
        axes.text(x, y - 0.12, f"{lines[room]:,} lines", ha="center", va="center", fontsize=7, color="#52607a")
    axes.set_xlim(-0.1, width + 0.1)
    axes.set_ylim(0.5, top + 0.5)
    axes.set_yticks(range(1, top + 1), [f"floor {floor}" for floor in range(1, top + 1)], fontsize=8)
    axes.set_xticks([])
    for side in ("top", "right", "bottom", "left"):
        axes.spines[side].set_visible(False)
    axes.set_title(f"{len(place)} rooms on {top} floors, {imports} imports "
                   f"between rooms ({len(arrows)} drawn: the rest a longer way implies); every arrow runs down",
                   fontsize=10)
    figure.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(out)
    plt.close(figure)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=None, help="PNG to draw (default: print the floors only)")
    parser.add_argument("--root", type=Path, default=ROOT, help="the checkout to read (default: this one)")
    args = parser.parse_args(argv)
    lines, imports = read_rooms(args.root.resolve())
    floors = floors_of(imports)
    for floor in range(max(floors.values()), 0, -1):
        rooms = sorted(room for room in floors if floors[room] == floor)
        print(f"floor {floor}: " + ", ".join(f"{room} {lines[room]}" for room in rooms))
    arrows = drawn_arrows(imports)
    count = sum(len(used) for used in imports.values())
    print(f"{len(floors)} rooms on {max(floors.values())} floors, {count} imports between rooms, no circle")
    if args.out is not None:
        draw(lines, floors, arrows, count, args.out)
        print(f"drew {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
