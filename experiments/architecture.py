"""The package's layout against the style guide (``docs/architecture.md``): the longest modules and
functions, every import of an underscore name across module boundaries outside its own subpackage,
every tensor the package makes without saying its device, and every import cycle of its modules.

Run ``python experiments/architecture.py`` (``--json`` for the numbers as JSON); it exits 1 when a module
is over ``MODULE_LINES`` lines, a function over ``FUNCTION_LINES``, an underscore name crosses a
boundary, a tensor is made without ``device=`` or a reason to be on the CPU
(:func:`deviceless_constructors`) or the package's modules import each other in a cycle, lazy and
type-only imports included (:func:`import_cycles`), so ``tests/test_architecture.py`` keeps the
layout as it is.
"""

from __future__ import annotations

import argparse
import ast
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "torchspec"
MODULE_LINES = 600
FUNCTION_LINES = 100
SCANNED = ("torchspec", "experiments")
CONSTRUCTORS = frozenset(
    "tensor as_tensor zeros ones empty full arange linspace logspace eye rand randn randint randperm".split()
)
"""``torch`` functions that make a tensor: in the package each names its ``device=`` (that of its
inputs), or its line (or the line above it) says why it is on the CPU on purpose (a comment naming
``CPU``), so that every command runs on CUDA as on the CPU."""


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _package_of(module: str, is_package: bool) -> str:
    return module if is_package else module.rpartition(".")[0]


def modules(root: Path = PACKAGE) -> list[tuple[str, int]]:
    """``(module, lines)`` of every module of the package, longest first."""
    rows = [(str(p.relative_to(ROOT)), len(p.read_text(encoding="utf-8").splitlines())) for p in root.rglob("*.py")]
    return sorted(rows, key=lambda row: -row[1])


def functions(root: Path = PACKAGE) -> list[tuple[str, int]]:
    """``(module:function, lines)`` of every function and method (nested ones included), longest first;
    a function's lines run from its ``def`` (or first decorator) to its last statement."""
    rows = []
    for path in root.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        stack = [(tree, "")]
        while stack:
            node, prefix = stack.pop()
            for child in ast.iter_child_nodes(node):
                if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                    name = f"{prefix}{child.name}"
                    if not isinstance(child, ast.ClassDef):
                        first = min([child.lineno] + [d.lineno for d in child.decorator_list])
                        rows.append((f"{path.relative_to(ROOT)}:{name}", child.end_lineno - first + 1))
                    stack.append((child, name + "."))
                else:
                    stack.append((child, prefix))
    return sorted(rows, key=lambda row: -row[1])


def _is_module(parts: list[str]) -> bool:
    path = ROOT.joinpath(*parts)
    return path.with_suffix(".py").is_file() or (path / "__init__.py").is_file()


def _source(node: ast.ImportFrom, package: str) -> str:
    """The absolute module a ``from ... import`` in ``package`` takes its names from."""
    source = node.module or ""
    if not node.level:
        return source
    anchor = package.split(".")
    anchor = anchor[: len(anchor) - (node.level - 1)]
    return ".".join(anchor + ([source] if source else []))


def private_imports(folders: tuple[str, ...] = SCANNED) -> list[str]:
    """Every import of an underscore name across a module boundary that the layout forbids:
    ``file:line imports module.name``.

    Inside ``torchspec``, an underscore *module* (``torchspec/_version.py``, ``io/_manifest.py``) is an
    explicit internal module whose public names any module may import; an underscore *name* of a
    module (a function, class or constant) may be imported only by the modules of the same
    subpackage (``fri/_single.py`` from ``fri/_hankel.py``), never across the top level. Outside the
    package (experiments, tests) no underscore module or name is imported at all."""
    found = []
    for folder in folders:
        for path in sorted((ROOT / folder).rglob("*.py")):
            module = _module_name(path)
            inside = module.split(".")[0] == "torchspec"
            package = _package_of(module, path.name == "__init__.py")
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                targets = []
                if isinstance(node, ast.ImportFrom):
                    base = _source(node, package)
                    targets = [(base, alias.name) for alias in node.names]
                elif isinstance(node, ast.Import):
                    targets = [(alias.name, "") for alias in node.names]
                for source, name in targets:
                    parts = [p for p in source.split(".") + ([name] if name else []) if p]
                    if not parts or parts[0] != "torchspec":
                        continue
                    for at, part in enumerate(parts):
                        if not part.startswith("_") or part.startswith("__"):
                            continue
                        owner = ".".join(parts[:at])  # the package or module that holds the private part
                        if inside and _is_module(parts[: at + 1]):
                            continue  # an explicit internal module
                        is_package = (ROOT.joinpath(*parts[:at]) / "__init__.py").is_file()
                        owner_package = owner if is_package else owner.rpartition(".")[0]
                        own = package == owner_package or package.startswith(owner_package + ".")
                        if inside and owner_package != "torchspec" and own:
                            continue  # a private name of the importer's own subpackage
                        found.append(f"{path.relative_to(ROOT)}:{node.lineno} imports {'.'.join(parts)}")
                        break
    return found


def deviceless_constructors(root: Path = PACKAGE) -> list[str]:
    """``path:line: code`` of each call ``torch.<constructor>(...)`` (:data:`CONSTRUCTORS`) in the
    package without a ``device=`` or ``generator=`` keyword (a seeded draw is made on its
    generator's device) and without a comment naming ``CPU`` on its lines or the line above
    (``new_*`` and ``*_like`` follow their tensor and are not listed)."""
    found = []
    for path in sorted(root.rglob("*.py")):
        lines = path.read_text().splitlines()
        for node in ast.walk(ast.parse("\n".join(lines))):
            if not (
                isinstance(node, ast.Call)
                and isinstance(node.func, ast.Attribute)
                and node.func.attr in CONSTRUCTORS
                and isinstance(node.func.value, ast.Name)
                and node.func.value.id == "torch"
            ):
                continue
            if any(keyword.arg in ("device", "generator", None) for keyword in node.keywords):
                continue  # device=, a generator's draw (on its device), or **options that carry either
            span = lines[max(node.lineno - 2, 0) : node.end_lineno]
            if any("#" in line and "CPU" in line.split("#", 1)[1] for line in span):
                continue
            found.append(f"{path.relative_to(root.parent)}:{node.lineno}: {lines[node.lineno - 1].strip()}")
    return found


def _in_type_checking(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            return True
    return False


def _in_function(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    while node in parents:
        node = parents[node]
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
            return True
    return False


def import_graph(root: Path = PACKAGE) -> dict[str, dict[str, list[str]]]:
    """``{module: {imported module: ["line kind", ...]}}`` of the package, from its source: every
    ``import`` and ``from ... import`` anywhere in a module, at the top level (``top``), inside a
    function (``lazy``) or under ``if TYPE_CHECKING:`` (``type``); relative imports resolved.

    A package is its ``__init__`` (module ``torchspec.io`` is ``torchspec/io/__init__.py``).
    ``import a.b`` imports ``a.b``; ``from a import b`` imports the submodule ``a.b`` when there is
    one, else ``a`` itself (its ``__init__`` when ``a`` is a package). The parent packages that
    Python initialises before any submodule are not edges: every module would otherwise depend on
    ``torchspec/__init__``, which imports the package's API, and all would be one cycle; a module
    that takes a name from its package's ``__init__`` (``from . import x`` where ``x`` is no
    submodule) does import it. Imports of other packages are left out."""
    top = root.name
    base = root.parent
    names = {}
    for path in sorted(root.rglob("*.py")):
        parts = list(path.relative_to(base).with_suffix("").parts)
        is_package = parts[-1] == "__init__"
        names[".".join(parts[:-1] if is_package else parts)] = (path, is_package)
    graph: dict[str, dict[str, list[str]]] = {module: {} for module in names}
    for module, (path, is_package) in names.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        package = module if is_package else module.rpartition(".")[0]
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                source = _source(node, package)
                targets = [f"{source}.{a.name}" if f"{source}.{a.name}" in names else source for a in node.names]
            else:
                continue
            kind = "type" if _in_type_checking(node, parents) else "lazy" if _in_function(node, parents) else "top"
            for target in targets:
                if target.split(".")[0] != top:
                    continue
                while target not in names:  # import a.b.name of a module a.b (not from ... import)
                    target = target.rpartition(".")[0]
                where = graph[module].setdefault(target, [])
                if target != module and f"{node.lineno} {kind}" not in where:
                    where.append(f"{node.lineno} {kind}")
        graph[module] = {target: where for target, where in graph[module].items() if where}
    return graph


def import_cycles(graph: dict[str, dict[str, list[str]]] | None = None) -> list[list[str]]:
    """The import cycles of the package (:func:`import_graph`, lazy and type-only imports included):
    each strongly connected component of more than one module, its modules sorted; the
    components sorted by their first module."""
    graph = import_graph() if graph is None else graph
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found = []
    for start in sorted(graph):  # Tarjan's algorithm, iterative
        if start in index:
            continue
        work = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = len(index)
        stack.append(start)
        on_stack.add(start)
        while work:
            node, successors = work[-1]
            for successor in successors:
                if successor not in index:
                    index[successor] = low[successor] = len(index)
                    stack.append(successor)
                    on_stack.add(successor)
                    work.append((successor, iter(sorted(graph[successor]))))
                    break
                if successor in on_stack:
                    low[node] = min(low[node], index[successor])
            else:
                work.pop()
                if work:
                    low[work[-1][0]] = min(low[work[-1][0]], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1:
                        found.append(sorted(component))
    return sorted(found)


def cycle_edges(cycle: list[str], graph: dict[str, dict[str, list[str]]] | None = None) -> list[str]:
    """``module -> module (line kind, ...)`` of every import inside one cycle of :func:`import_cycles`."""
    graph = import_graph() if graph is None else graph
    members = set(cycle)
    return [
        f"{module} -> {target} ({', '.join(where)})"
        for module in cycle
        for target, where in sorted(graph[module].items())
        if target in members
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the numbers as JSON")
    parser.add_argument("--most", type=int, default=5, help="how many of the longest to list (default: 5)")
    args = parser.parse_args(argv)
    mods, funcs, crossing, deviceless = modules(), functions(), private_imports(), deviceless_constructors()
    graph = import_graph()
    cycles = import_cycles(graph)
    over = [row for row in mods if row[1] > MODULE_LINES] + [row for row in funcs if row[1] > FUNCTION_LINES]
    if args.json:
        print(json.dumps({"modules": mods[: args.most], "functions": funcs[: args.most],
                          "private_imports": crossing, "over_limits": over,
                          "deviceless": deviceless,
                          "import_cycles": [cycle_edges(cycle, graph) for cycle in cycles]}, indent=1))
    else:
        print(f"longest modules (limit {MODULE_LINES} lines):")
        for name, lines in mods[: args.most]:
            print(f"  {lines:5d}  {name}")
        print(f"longest functions (limit {FUNCTION_LINES} lines):")
        for name, lines in funcs[: args.most]:
            print(f"  {lines:5d}  {name}")
        print(f"underscore names imported across modules: {len(crossing)}")
        for line in crossing:
            print(f"  {line}")
        print(f"tensors made without device= or a reason to be on the CPU: {len(deviceless)}")
        for line in deviceless[: args.most]:
            print(f"  {line}")
        edges = sum(len(targets) for targets in graph.values())
        print(f"import cycles ({len(graph)} modules, {edges} imports, lazy and type-only included): {len(cycles)}")
        for cycle in cycles:
            print(f"  {len(cycle)} modules:")
            for line in cycle_edges(cycle, graph):
                print(f"    {line}")
    return 1 if over or crossing or deviceless or cycles else 0


if __name__ == "__main__":
    sys.exit(main())
