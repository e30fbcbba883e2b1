"""The package's layout against the style guide (``docs/architecture.md``): the longest modules and
functions, every import of an underscore name across module boundaries outside its own subpackage,
and every tensor the package makes without saying its device.

Run ``python experiments/architecture.py`` (``--json`` for the numbers as JSON); it exits 1 when a module
is over ``MODULE_LINES`` lines, a function over ``FUNCTION_LINES``, an underscore name crosses a
boundary or a tensor is made without ``device=`` or a reason to be on the CPU
(:func:`deviceless_constructors`), so ``tests/test_architecture.py`` keeps the layout as it is.
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
                    base = node.module or ""
                    if node.level:
                        anchor = package.split(".")
                        anchor = anchor[: len(anchor) - (node.level - 1)]
                        base = ".".join(anchor + ([base] if base else []))
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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print the numbers as JSON")
    parser.add_argument("--most", type=int, default=5, help="how many of the longest to list (default: 5)")
    args = parser.parse_args(argv)
    mods, funcs, crossing, deviceless = modules(), functions(), private_imports(), deviceless_constructors()
    over = [row for row in mods if row[1] > MODULE_LINES] + [row for row in funcs if row[1] > FUNCTION_LINES]
    if args.json:
        print(json.dumps({"modules": mods[: args.most], "functions": funcs[: args.most],
                          "private_imports": crossing, "over_limits": over,
                          "deviceless": deviceless}, indent=1))
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
    return 1 if over or crossing or deviceless else 0


if __name__ == "__main__":
    sys.exit(main())
