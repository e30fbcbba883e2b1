"""The modules that moved into stage packages, importable by their old names for one release.

``import torchspec.lights`` (or ``from torchspec.lights import Lights``, or ``torchspec.lights``
after ``import torchspec``) still gives the module, now :mod:`torchspec.model.lights`, with a
:class:`DeprecationWarning` naming the new place. Objects pickled under an old name (a checkpoint
written before the move) load through the same aliases. :data:`MOVED` is the whole list; the
aliases go in the release after next.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

__all__ = ["MOVED", "install", "new_name"]

MOVED = {
    "_kernel_table": "calibration._kernel_table",
    "brdf": "model.brdf",
    "brightness": "calibration.brightness",
    "calibrate": "calibration.kernel",
    "crb": "model.crb",
    "diffuse": "model.diffuse",
    "flags": "pipeline.flags",
    "forward_terms": "model.forward_terms",
    "fri": "start.fri",
    "fusion": "model.fusion",
    "gauss": "model.gauss",
    "geometry": "model.geometry",
    "height": "model.height",
    "jacobian": "model.jacobian",
    "layout": "model.layout",
    "least_squares": "model.least_squares",
    "lightcal": "calibration.lights",
    "lights": "model.lights",
    "lobe": "model.lobe",
    "lobes": "model.lobes",
    "models": "model.registry",
    "near_lights": "model.near_lights",
    "nodes": "model.nodes",
    "noise": "model.noise",
    "params": "model.params",
    "photometric": "start.photometric",
    "quadrature": "model.quadrature",
    "relief": "simulate.relief",
    "relight_lights": "relight.lights",
    "rendering": "model.rendering",
    "residual_term": "model.residual_term",
    "response": "calibration.response",
    "response_judge": "calibration.response_judge",
    "specular": "start.specular",
    "sphere": "calibration.sphere",
    "synth": "simulate.synth",
    "visibility": "model.visibility",
}
"""Old module name -> new one, both below ``torchspec.`` (a package's submodules move with it)."""


def new_name(old: str) -> str | None:
    """The new name of the module ``old`` (below ``torchspec.``), or ``None`` where it did not move.

    Example:
        >>> new_name("fri.pulses"), new_name("pipeline")
        ('start.fri.pulses', None)
    """
    for moved in sorted(MOVED, key=len, reverse=True):
        if old == moved or old.startswith(moved + "."):
            return MOVED[moved] + old[len(moved) :]
    return None


def warn(old: str, new: str, stacklevel: int = 3) -> None:
    warnings.warn(
        f"torchspec.{old} has moved to torchspec.{new}; import it from there (the old name goes in a "
        "later release).",
        DeprecationWarning,
        stacklevel=stacklevel,
    )


class _Aliases(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Finds ``torchspec.<old>`` and gives the module at its new name (the same module object)."""

    def __init__(self):
        self.real: dict[str, object] = {}  # alias name -> the module's own spec, between create and exec

    def find_spec(self, fullname, path=None, target=None):
        if not fullname.startswith("torchspec."):
            return None
        new = new_name(fullname[len("torchspec.") :])
        if new is None:  # not a moved name (a new name never is one: no moved name is a prefix of it)
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        old = spec.name[len("torchspec.") :]
        new = new_name(old)
        warn(old, new, stacklevel=6)
        module = importlib.import_module(f"torchspec.{new}")
        self.real[spec.name] = module.__spec__  # importlib sets the alias's spec on it: put the real one back
        return module

    def exec_module(self, module):
        module.__spec__ = self.real.pop(module.__spec__.name)  # by the alias's name: imports may interleave


def install() -> None:
    """Put the old names' finder on :data:`sys.meta_path` (once)."""
    if not any(isinstance(finder, _Aliases) for finder in sys.meta_path):
        sys.meta_path.insert(0, _Aliases())  # before an editable install's finder, which may know old files
