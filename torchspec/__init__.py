"""torchspec: reflectance of nearly flat objects from a few HDR photographs under an extended
light, by finite-rate-of-innovation location of the specular peak and batched fitting."""

# isort: off
from . import threads  # first: OMP_WAIT_POLICY is read as torch loads its OpenMP runtime

threads.quiet_waits()
# isort: on

from . import (  # noqa: E402
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
from ._version import __version__  # noqa: E402
from .brdf import SVBRDF  # noqa: E402
from .errors import TorchspecError  # noqa: E402
from .io import read_capture, read_svbrdf, write_capture, write_svbrdf  # noqa: E402
from .pipeline import Fit, FitConfig, fit, write_fit  # noqa: E402
from .rendering import render  # noqa: E402

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
