"""How the measurement model's integrals are taken: the :class:`Quadrature` settings that
:func:`torchspec.model.rendering.render`, :func:`torchspec.model.jacobian.jacobian`,
:func:`torchspec.model.least_squares.normal_equations`, :func:`torchspec.model.least_squares.sandwich_terms`
and :meth:`torchspec.model.registry.Model.residuals` take as one object, the specular path's rule
(:func:`choose_path`), the rules of the diffuse clamp (:data:`CLAMPS`) and the Gauss rules
(:func:`legendre`, :func:`hermite`) the node rules are built from.

The Gauss rules live in :mod:`torchspec.model.gauss` (which :mod:`torchspec.model.lights` imports without
this module) and are re-exported here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

from ..errors import TorchspecError
from .gauss import gauss_rule, gauss_table, hermite, legendre  # re-exported: the Gauss rules

if TYPE_CHECKING:
    from .lights import Kernel, Lights

__all__ = [
    "Quadrature",
    "QUADRATURES",
    "PATHS",
    "FAST_ORDER",
    "REFERENCE_ORDER",
    "DIFFUSE_ORDER",
    "HORIZON_MARGIN",
    "BUDGET",
    "ClampRule",
    "CLAMPS",
    "choose_path",
    "check_quadrature",
    "gauss_table",
    "gauss_rule",
    "legendre",
    "hermite",
]

PATHS = ("auto", "point", "fast", "reference")
FAST_ORDER = 4  # Gauss-Hermite nodes per axis of the fast path
REFERENCE_ORDER = 16  # Gauss-Legendre radii of the reference path (twice as many angles)
DIFFUSE_ORDER = 12  # Gauss-Legendre nodes per piece of the clamped diffuse integral
HORIZON_MARGIN = 5.5  # kernel stds between its mean and the normal's horizon for the clamp to matter
BUDGET = 1 << 20  # pixel x frame x node elements per chunk of pixels


class ClampRule(NamedTuple):
    """How the diffuse clamp is integrated (:func:`torchspec.model.diffuse.diffuse_integral`): the
    pairs within ``margin`` kernel stds of the normal's horizon, with ``order`` Gauss-Legendre
    nodes per piece of ``lines`` lines (``None``: ``torchspec.model.diffuse.ACROSS`` per kernel width)."""

    margin: float
    order: int
    lines: int | None


CLAMPS = {
    # The renderer's: the kernel's mass left out under 1e-6, the integral to ~1e-7.
    "exact": ClampRule(HORIZON_MARGIN, DIFFUSE_ORDER, None),
    # A fit's: within 5e-4 of a pixel's largest value for normals tilted up to 70 deg
    # (tests/test_jacobian.py), far below a capture's noise.
    "fast": ClampRule(4.0, 8, 11),
}


@dataclass(frozen=True)
class Quadrature:
    """The quadrature of the measurement model's integrals.

    Attributes:
        path: the specular path: ``auto`` (the rule of :func:`choose_path`), ``point``, ``fast``
            or ``reference``.
        order: Gauss-Hermite nodes per axis of the fast rule (``FAST_ORDER`` when ``None``).
        reference_order: Gauss-Legendre radii of the reference rule (``REFERENCE_ORDER`` when
            ``None``; a tabulated kernel takes two per pixel of its table at least).
        clamp: the rule of the diffuse clamp (:data:`CLAMPS`): ``exact``, the renderer's, or
            ``fast``, a fit's.
        compile: fuse the integrations over nodes with ``torch.compile`` (the same values to
            float rounding, after a one-off compilation).

    Raises:
        TorchspecError: naming the attribute that is not one of its choices.

    Example:
        >>> Quadrature(order=3, reference_order=8, clamp="fast").orders(None)
        (3, 8)
        >>> Quadrature(clamp="rough")
        Traceback (most recent call last):
        ...
        torchspec.errors.TorchspecError: Quadrature.clamp must be one of ['exact', 'fast']; got 'rough'.
    """

    path: str = "auto"
    order: int | None = None
    reference_order: int | None = None
    clamp: str = "exact"
    compile: bool = False

    def __post_init__(self):
        if self.path not in PATHS:
            raise TorchspecError(f"Quadrature.path must be one of {PATHS}; got {self.path!r}.")
        for name in ("order", "reference_order"):
            value = getattr(self, name)
            if value is not None and (isinstance(value, bool) or not isinstance(value, int) or value < 1):
                raise TorchspecError(f"Quadrature.{name} must be an integer >= 1 or None; got {value!r}.")
        if self.clamp not in CLAMPS:
            raise TorchspecError(f"Quadrature.clamp must be one of {sorted(CLAMPS)}; got {self.clamp!r}.")
        if not isinstance(self.compile, bool):
            raise TorchspecError(f"Quadrature.compile must be True or False; got {self.compile!r}.")

    @property
    def default(self) -> bool:
        """The renderer's own orders and clamp (whatever the path and ``compile``)."""
        return self.order is None and self.reference_order is None and self.clamp == "exact"

    def orders(self, kernel: Kernel | None) -> tuple[int, int]:
        """``(fast, reference)``: Gauss-Hermite nodes per axis of the fast rule and Gauss-Legendre
        radii of the reference rule for ``kernel`` (a tabulated kernel's spline has a knot per
        pixel: two radii per pixel of its table at least)."""
        fast = self.order or FAST_ORDER
        reference = self.reference_order or REFERENCE_ORDER
        if kernel is not None and kernel.kind == "tabulated":
            reference = max(reference, 2 * max(kernel.table.shape))
        return fast, reference


QUADRATURES = {
    # The renderer's: the fast and reference rules' own orders, the exact clamp.
    "render": Quadrature(),
    # A fit's: 3 x 3 Gauss-Hermite nodes for the lobe, 8 reference radii, the fast clamp.
    "fit": Quadrature(order=3, reference_order=8, clamp="fast"),
}
"""Named settings (``torchspec.fit``'s ``quadrature``); :func:`dataclasses.replace` sets the
path and ``compile``."""


def choose_path(lights: Lights, path: str = "auto") -> str:
    """The specular path of the frames.

    ``auto``: ``point`` for a point light; ``fast`` for a Gaussian kernel (either domain), whose
    pixel-frame pairs fall back to ``reference`` where the product of kernel and lobe reaches
    the horizon (a Gaussian rule cannot follow the cut): returned as ``auto``; ``reference`` for
    super-Gaussian and tabulated kernels, whose shape a Gaussian rule cannot follow.
    A forced path must fit the kernel: ``point`` only for point lights, ``fast`` (then used for
    every pair) only for Gaussian kernels.

    Raises:
        TorchspecError: an unknown path, a path that does not fit the kernel, or an ``unknown``
            kernel.
    """
    if path not in PATHS:
        raise TorchspecError(f"path must be one of {PATHS}; got {path!r}.")
    kernel = lights.kernel
    if kernel.kind == "unknown":
        raise TorchspecError(
            "the light kernel is 'unknown': rendering needs its shape. Calibrate it into a tabulated "
            "kernel, or describe a known light (e.g. torchspec render --light-model FILE)."
        )
    if kernel.kind == "point":
        if path not in ("auto", "point"):
            raise TorchspecError(f"path {path!r} does not apply to a point light; use 'auto' or 'point'.")
        return "point"
    if path == "point":
        raise TorchspecError(f"path 'point' needs a point light; this one is {kernel.kind!r}.")
    if path == "fast" and kernel.kind != "gaussian":
        raise TorchspecError(f"path 'fast' needs a Gaussian kernel; this one is {kernel.kind!r}.")
    if path != "auto":
        return path
    return "auto" if kernel.kind == "gaussian" else "reference"


def check_quadrature(quadrature) -> None:
    """Raise a :class:`~torchspec.errors.TorchspecError` unless the argument ``quadrature`` is a
    :class:`Quadrature` (not, e.g., a dict of its fields)."""
    if not isinstance(quadrature, Quadrature):
        raise TorchspecError(
            f"quadrature must be a torchspec.model.quadrature.Quadrature; got {type(quadrature).__name__}."
        )
