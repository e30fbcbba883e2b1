"""torchspec: reflectance of nearly flat objects from a few HDR photographs under an extended
light, by finite-rate-of-innovation location of the specular peak and batched fitting."""

from . import (
    brdf,
    crb,
    fri,
    geometry,
    info,
    jacobian,
    layout,
    lights,
    lm,
    models,
    photometric,
    pipeline,
    relight,
    simulate,
    specular,
    synth,
)
from ._version import __version__
from .brdf import SVBRDF
from .errors import TorchspecError
from .io import read_capture, read_svbrdf, write_capture, write_svbrdf
from .pipeline import Fit, FitConfig, fit, write_fit
from .rendering import render

__all__ = [
    "Fit",
    "FitConfig",
    "SVBRDF",
    "TorchspecError",
    "__version__",
    "brdf",
    "crb",
    "fri",
    "geometry",
    "fit",
    "info",
    "jacobian",
    "layout",
    "lights",
    "lm",
    "models",
    "photometric",
    "pipeline",
    "relight",
    "simulate",
    "specular",
    "synth",
    "read_capture",
    "read_svbrdf",
    "render",
    "write_capture",
    "write_fit",
    "write_svbrdf",
]
