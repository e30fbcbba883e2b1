"""The package's layout keeps the limits of ``docs/architecture.md``, measured by
``experiments/architecture.py``: module and function lengths, underscore names that stay inside
their subpackage, no import cycle (lazy and type-only imports included) and no function of a
package hiding a module of the same name."""

import importlib
import importlib.util
import inspect
import pkgutil
from pathlib import Path

import torchspec

ROOT = Path(__file__).resolve().parents[1]


def _architecture():
    """``experiments/architecture.py`` imported by its path (experiments/ is not a package)."""
    spec = importlib.util.spec_from_file_location("architecture", ROOT / "experiments" / "architecture.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


ARCHITECTURE = _architecture()


def test_no_module_is_over_the_limit():
    over = [(name, lines) for name, lines in ARCHITECTURE.modules() if lines > ARCHITECTURE.MODULE_LINES]
    assert not over, f"modules over {ARCHITECTURE.MODULE_LINES} lines: {over}"


def test_no_function_is_over_the_limit():
    over = [(name, lines) for name, lines in ARCHITECTURE.functions() if lines > ARCHITECTURE.FUNCTION_LINES]
    assert not over, f"functions over {ARCHITECTURE.FUNCTION_LINES} lines: {over}"


def test_no_underscore_name_crosses_a_module_boundary():
    crossing = ARCHITECTURE.private_imports()
    assert not crossing, "underscore names imported across modules:\n" + "\n".join(crossing)


def test_every_tensor_the_package_makes_says_its_device():
    deviceless = ARCHITECTURE.deviceless_constructors()
    assert not deviceless, (
        "tensors made without device= (that of the inputs) or a comment on the line saying why they are on the CPU:\n"
        + "\n".join(deviceless)
    )


def test_the_device_check_finds_a_constructor_without_device(tmp_path):
    package = tmp_path / "torchspec"
    package.mkdir()
    (package / "m.py").write_text(
        "import torch\n"
        "a = torch.zeros(3)\n"
        "b = torch.zeros(3, device=a.device)\n"
        "c = torch.tensor([1.0])  # on the CPU: a table the caller moves\n"
        "# the CPU on purpose: read from a file\n"
        "d = torch.arange(\n    4\n)\n"
        "e = torch.ones_like(a)\n"
        "f = torch.eye(\n    2,\n)\n"
        "g = torch.rand(2, generator=torch.Generator())\n"
    )
    found = ARCHITECTURE.deviceless_constructors(package)
    assert [line.split(":")[:2] for line in found] == [["torchspec/m.py", "2"], ["torchspec/m.py", "10"]]


def test_no_modules_import_each_other_in_a_cycle():
    """Issue 38: no import cycle, lazy (inside a function) and type-only (``if TYPE_CHECKING:``)
    imports included: a cycle held apart by a lazy import is a cycle of the design all the same."""
    graph = ARCHITECTURE.import_graph()
    assert len(graph) > 100 and "torchspec.pipeline.tile" in graph["torchspec.pipeline.in_process"]
    cycles = ARCHITECTURE.import_cycles(graph)
    assert len(cycles) == 0, "import cycles:\n" + "\n".join(
        line for cycle in cycles for line in ARCHITECTURE.cycle_edges(cycle, graph)
    )


def test_the_cycle_finder_counts_lazy_type_only_and_package_imports(tmp_path):
    package = tmp_path / "torchspec"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("from . import a, sub\n")
    (package / "a.py").write_text("def f():\n    from .sub import b  # lazy: a submodule\n")
    (package / "sub" / "__init__.py").write_text("from .b import B\n")
    (package / "sub" / "b.py").write_text(
        "from typing import TYPE_CHECKING\nimport torch\nif TYPE_CHECKING:\n    from ..c import C\nB = 1\n"
    )
    (package / "c.py").write_text("import torchspec.a\nfrom torchspec.sub import B  # the package's __init__\n")
    (package / "d.py").write_text("from . import c\n")
    graph = ARCHITECTURE.import_graph(package)
    assert graph == {
        "torchspec": {"torchspec.a": ["1 top"], "torchspec.sub": ["1 top"]},
        "torchspec.a": {"torchspec.sub.b": ["2 lazy"]},
        "torchspec.c": {"torchspec.a": ["1 top"], "torchspec.sub": ["2 top"]},
        "torchspec.d": {"torchspec.c": ["1 top"]},
        "torchspec.sub": {"torchspec.sub.b": ["1 top"]},
        "torchspec.sub.b": {"torchspec.c": ["4 type"]},
    }
    assert ARCHITECTURE.import_cycles(graph) == [["torchspec.a", "torchspec.c", "torchspec.sub", "torchspec.sub.b"]]


def test_the_layout_script_passes():
    assert ARCHITECTURE.main(["--most", "0"]) == 0


def test_no_function_of_a_package_hides_a_module_of_that_package():
    hidden = []
    packages = [torchspec] + [
        importlib.import_module(info.name)
        for info in pkgutil.walk_packages(torchspec.__path__, "torchspec.")
        if info.ispkg
    ]
    for package in packages:
        submodules = {info.name for info in pkgutil.iter_modules(package.__path__)}
        for name in submodules:
            value = package.__dict__.get(name)
            if value is not None and not inspect.ismodule(value):
                hidden.append(f"{package.__name__}.{name} is a {type(value).__name__}, hiding the module")
    assert not hidden, "\n".join(hidden)


def test_every_module_the_readme_and_the_architecture_name_imports():
    """``torchspec.X.Y`` in README.md and docs/*.md: each is a module (``import`` works and gives a
    module, not a function that hides it) or a public name of one."""
    import re

    text = (ROOT / "README.md").read_text() + "".join(p.read_text() for p in sorted((ROOT / "docs").glob("*.md")))
    # Not names: the formats' strings ("torchspec.capture") and file names (dask's torchspec.yaml).
    named = sorted(set(re.findall(r"(?<![\"/])\btorchspec(?:\.[A-Za-z_][A-Za-z0-9_]*)+(?![\w.]*\")", text)))
    named = [name for name in named if not name.endswith((".yaml", ".json"))]
    assert len(named) > 10, named
    unresolved = []
    for dotted in named:
        parts = dotted.split(".")
        for cut in range(len(parts), 0, -1):  # the longest importable prefix, then attributes
            try:
                value = importlib.import_module(".".join(parts[:cut]))
            except ImportError:
                continue
            try:
                for attribute in parts[cut:]:
                    value = getattr(value, attribute)
            except AttributeError:
                unresolved.append(dotted)
            break
        else:
            unresolved.append(dotted)
    assert not unresolved, f"named in the docs but not found: {unresolved}"
