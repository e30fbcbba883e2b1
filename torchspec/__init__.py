"""torchspec: reflectance of nearly flat objects from a few HDR photographs under an extended
light, by finite-rate-of-innovation location of the specular peak and batched fitting."""

from . import crb, fri
from ._version import __version__

__all__ = ["__version__", "crb", "fri"]
