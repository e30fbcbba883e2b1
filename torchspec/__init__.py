"""torchspec: reflectance of nearly flat objects from a few HDR photographs under an extended
light, by finite-rate-of-innovation location of the specular peak and batched fitting."""

import importlib

# isort: off
from . import moved, threads  # first: OMP_WAIT_POLICY is read as torch loads its OpenMP runtime

threads.quiet_waits()
# isort: on

from . import (  # noqa: E402
    calibration,
    info,
    lm,
    model,
    pipeline,
    relight,
    simulate,
    start,
)
from ._version import __version__  # noqa: E402
from .errors import TorchspecError  # noqa: E402
from .io import read_capture, read_svbrdf, write_capture, write_svbrdf  # noqa: E402
from .model.brdf import SVBRDF  # noqa: E402
from .model.rendering import render  # noqa: E402
from .pipeline import Fit, FitConfig, fit, write_fit  # noqa: E402

__all__ = [
    "Fit",
    "FitConfig",
    "SVBRDF",
    "TorchspecError",
    "__version__",
    "calibration",
    "fit",
    "info",
    "lm",
    "model",
    "pipeline",
    "relight",
    "simulate",
    "start",
    "read_capture",
    "read_svbrdf",
    "render",
    "write_capture",
    "write_fit",
    "write_svbrdf",
]

moved.install()  # the modules' old names (torchspec.lights, ...) for one release, with a warning


def __getattr__(name: str):
    """``torchspec.<old module name>`` (``torchspec.lights``, ...): the module at its new place, with a
    DeprecationWarning (:mod:`torchspec.moved`)."""
    new = moved.new_name(name)
    if new is None or "." in name:
        raise AttributeError(f"module 'torchspec' has no attribute {name!r}")
    moved.warn(name, new)
    return importlib.import_module(f"torchspec.{new}")

