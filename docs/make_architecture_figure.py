"""The house drawn from its imports: docs/architecture.png and the import cycles, read from the source with `ast`.

    python docs/make_architecture_figure.py   # writes docs/architecture.png; prints the cycles and deferred imports
    python docs/make_architecture_figure.py --walk lanevil_train.tasks.detector.evaluate   # one module's walk

Every `import lanevil_train...` / `from lanevil_train... import` counts, at module level or inside a function (a
deferred import is still a dependency; the script lists them). Modules are grouped by folder (lanevil_train/models/
clrnet/head.py -> models); the figure draws the folders in layers, each above what it imports, with an arrow per
folder dependency. Exit status 1 when modules import each other in a circle.
"""

from __future__ import annotations

import ast
import sys
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1] / "lanevil_train"


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports_of(path: Path, modules: set[str]) -> tuple[set[str], set[str]]:
    """(every lanevil_train module `path` imports, those imported inside a function)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found, deferred = set(), set()
    functions = [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]
    inside = {id(n) for f in functions for n in ast.walk(f)}
    for node in ast.walk(tree):
        names = []
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            # `from pkg import sub` depends on the module pkg.sub; `from pkg import name` on pkg
            names = [f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in modules else node.module
                     for alias in node.names]
        for name in names:
            while name and name not in modules:
                name = name.rpartition(".")[0]
            if name.startswith("lanevil_train") and name != module_name(path):
                found.add(name)
                if id(node) in inside:
                    deferred.add(name)
    return found, deferred


def graph() -> tuple[dict[str, set[str]], dict[str, set[str]]]:
    paths = {module_name(p): p for p in ROOT.rglob("*.py")}
    edges, deferred = {}, {}
    for name, path in paths.items():
        edges[name], deferred[name] = imports_of(path, set(paths))
        edges[name].discard("lanevil_train")  # the package's own __init__ holds only its version
    return edges, deferred


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on_stack, out, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    sys.setrecursionlimit(10000)
    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def folder(module: str) -> str:
    """The folder a module is in (models/clrnet/head.py -> models/); a top-level module stands for itself."""
    parts = module.split(".")
    if len(parts) > 2 or (len(parts) == 2 and (ROOT / parts[1]).is_dir()):
        return parts[1] + "/"
    return parts[-1] + ".py"


def draw(edges: dict[str, set[str]], out: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    folders = defaultdict(set)
    for a, targets in edges.items():
        if a == "lanevil_train":
            continue  # the package's __init__
        for b in targets:
            if folder(a) != folder(b):
                folders[folder(a)].add(folder(b))
        folders.setdefault(folder(a), set())
    layer: dict[str, int] = {}

    def depth(f: str, seen: tuple = ()) -> int:
        if f in layer:
            return layer[f]
        below = [depth(g, seen + (f,)) for g in folders[f] if g not in seen]
        layer[f] = 1 + max(below, default=-1)
        return layer[f]

    for f in folders:
        depth(f)
    rows = defaultdict(list)
    for f, d in layer.items():
        rows[d].append(f)
    position = {}
    for d, names in rows.items():
        for i, name in enumerate(sorted(names)):
            position[name] = ((i + 1) / (len(names) + 1), d)
    fig, ax = plt.subplots(figsize=(16, 1.3 * (max(rows) + 1) + 1))
    for a, targets in folders.items():
        for b in targets:
            (x0, y0), (x1, y1) = position[a], position[b]
            ax.annotate("", xy=(x1, y1 + 0.12), xytext=(x0, y0 - 0.12),
                        arrowprops=dict(arrowstyle="->", color="#8899aa", alpha=0.45, lw=0.7, shrinkA=0, shrinkB=0))
    for name, (x, y) in position.items():
        folder_node = name.endswith("/")
        ax.text(x, y, name, ha="center", va="center", fontsize=10 if folder_node else 8.5,
                bbox=dict(boxstyle="round,pad=0.4", fc="#eef4fb" if folder_node else "#f6f6f0",
                          ec="#4a7ab0" if folder_node else "#999988"))
    ax.set_xlim(0, 1)
    ax.set_ylim(-0.6, max(rows) + 0.6)
    ax.axis("off")
    ax.set_title("lanevil_train: each folder (blue) and top-level module above what it imports (arrows: imports)")
    fig.tight_layout()
    fig.savefig(out, dpi=110)


def walk(edges: dict[str, set[str]], start: str) -> tuple[set[str], int]:
    """The modules reached by following the imports from `start` (the rooms) and how many imports lead back to a
    module still being walked (climbs back: each closes a circle)."""
    reached, stack, climbs = set(), [], 0

    def visit(module: str) -> None:
        nonlocal climbs
        reached.add(module)
        stack.append(module)
        for target in sorted(edges.get(module, ())):
            if target in stack:
                climbs += 1
            elif target not in reached:
                visit(target)
        stack.pop()

    visit(start)
    return reached, climbs


def main() -> int:
    edges, deferred = graph()
    if sys.argv[1:2] == ["--walk"]:
        reached, climbs = walk(edges, sys.argv[2])
        tasks = sorted(m.removeprefix("lanevil_train.tasks.") for m in reached if m.startswith("lanevil_train.tasks."))
        print(f"{sys.argv[2]}: {len(reached)} modules reached, {climbs} climbs back, task modules: {', '.join(tasks)}")
        return 0
    found = cycles(edges)
    draw(edges, Path(__file__).with_name("architecture.png"))
    late = sorted((a, b) for a, targets in deferred.items() for b in targets)
    print(f"{len(edges)} modules, {sum(map(len, edges.values()))} imports, {len(late)} of them inside functions")
    for a, b in late:
        print(f"  deferred: {a} -> {b}")
    for component in found:
        print(f"circle of {len(component)}: {', '.join(component)}")
    if not found:
        print("no import circle")
    return 1 if found else 0


if __name__ == "__main__":
    raise SystemExit(main())
