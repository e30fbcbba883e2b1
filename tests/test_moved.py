"""The modules moved into stage packages stay importable by their old names for one release, with a
DeprecationWarning naming the new place (torchspec.moved)."""

import importlib
import pickle
import subprocess
import sys

import pytest

import torchspec
from torchspec.moved import MOVED, new_name


@pytest.mark.parametrize("old", sorted(MOVED))
def test_an_old_module_name_gives_the_new_module_with_a_warning(old):
    new = importlib.import_module(f"torchspec.{MOVED[old]}")
    sys.modules.pop(f"torchspec.{old}", None)
    vars(torchspec).pop(old.split(".")[0], None)
    with pytest.warns(DeprecationWarning, match=rf"torchspec\.{old} has moved to torchspec\.{MOVED[old]}"):
        module = importlib.import_module(f"torchspec.{old}")
    assert module is new
    assert module.__name__ == f"torchspec.{MOVED[old]}"  # the real module, its spec untouched
    assert module.__spec__.name == f"torchspec.{MOVED[old]}"


@pytest.mark.parametrize("old", sorted(name for name in MOVED if "." not in name))
def test_an_old_attribute_of_the_package_warns(old):
    vars(torchspec).pop(old, None)  # an earlier import of the old name set it, as the import system does
    with pytest.warns(DeprecationWarning, match="has moved"):
        module = getattr(torchspec, old)
    assert module is importlib.import_module(f"torchspec.{MOVED[old]}")


def test_submodules_of_a_moved_package_and_unknown_names():
    assert new_name("fri.pulses") == "start.fri.pulses"
    assert new_name("pipeline") is None and new_name("pipeline.tile") is None
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        torchspec.nothing  # noqa: B018


def test_an_object_pickled_under_an_old_name_loads():
    """A checkpoint written before the move names its classes' old modules."""
    from torchspec.model.lights import Kernel

    sys.modules.pop("torchspec.lights", None)
    data = pickle.dumps(Kernel("gaussian", sigma=0.1), protocol=0)
    data = data.replace(b"torchspec.model.lights", b"torchspec.lights")
    assert b"torchspec.lights" in data
    with pytest.warns(DeprecationWarning):
        assert pickle.loads(data) == Kernel("gaussian", sigma=0.1)


def test_a_fresh_interpreter_imports_an_old_name():
    code = (
        "import warnings; warnings.simplefilter('error');\n"
        "try:\n    import torchspec.lights\nexcept DeprecationWarning as e:\n    print('warned', e)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert "warned torchspec.lights has moved to torchspec.model.lights" in out
