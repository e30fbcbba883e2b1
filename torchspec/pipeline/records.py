"""The records the stages of a tile's fit hand on and the whole image's assembly, the checkpoint and
the cluster driver share: a tile's result (:class:`TileResult`) and every pixel's fit without a
lobe (:class:`PlainFit`). Here, below every module that makes or reads them, so that the
checkpoint (which saves tiles) imports no stage that fits one; :mod:`~torchspec.pipeline.tile` and
:mod:`~torchspec.pipeline.smoothing` re-export them. Also what every driver starts from
(:class:`Setup`) and the warning of a fit (:class:`FitWarning`), which the planning
(:mod:`~torchspec.pipeline.plan`, which re-exports them) and the light calibration
(:mod:`~torchspec.pipeline.calibration`) share without importing each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields, replace

import torch
from torch import Tensor

from ..io import Capture
from ..model.brdf import SVBRDF
from ..model.lights import Lights
from ..model.residual_term import ResidualTerm, TermDomain
from ..start.photometric import Masks
from .checks import Checks
from .settings import FitConfig

__all__ = ["FitWarning", "PlainFit", "Setup", "StackRun", "TileResult"]


class FitWarning(UserWarning):
    """Something a fit ran through but its user should know: lights that miss where the peaks lie,
    many pixels stopped at the solver's iteration limit (also listed in ``stats["warnings"]``)."""


@dataclass(frozen=True)
class Setup:
    """What every driver of a fit starts from.

    Attributes:
        config: the settings; capture: the capture (its manifest read); picked: the frames fitted.
        lights: the picked frames' lights (``K``), on the settings' device and dtype.
        view: ``(3,)`` the view direction, alike.
        positions: ``(K, 3)`` the picked frames' near-light positions (``Frame.position``; object
            units, :mod:`torchspec.model.near_lights`), alike; ``None`` for distant lights.
        gains: ``(K, C)`` the gains :func:`~torchspec.pipeline.calibration.calibrated` found (in
            ``lights``' irradiance), else ``None``.
        domain: the encoding the residual term is fitted in: the capture's estimated camera response
            where its import estimated one (``source.transfer: response``), else sRGB
            (:class:`torchspec.model.residual_term.TermDomain`).
    """

    config: FitConfig
    capture: Capture
    picked: list[int]
    lights: Lights
    view: Tensor
    positions: Tensor | None = None
    gains: Tensor | None = None
    domain: TermDomain = field(default_factory=TermDomain)


@dataclass(frozen=True)
class StackRun:
    """A fit's frames read, masked and their lights calibrated: what remains is to fit the tiles
    (:func:`torchspec.pipeline.in_process.fit_stack`), once or (cast shadows,
    :mod:`~torchspec.pipeline.shadows`) several times on subsets of the frames.

    Attributes:
        job: the :class:`Setup`, its lights calibrated; stack: ``(K, C, H, W)`` the frames;
        masks: their :class:`~torchspec.start.photometric.Masks`; calibration: the light calibration's
        record (``None``: none); seconds: per stage so far; started: ``time.perf_counter`` when
        the fit began.
    """

    job: Setup
    stack: Tensor
    masks: Masks
    calibration: dict | None
    seconds: dict
    started: float

    def frames(self, index: list[int]) -> StackRun:
        """The run on its frames ``index`` only (positions in its own frames)."""
        at = torch.tensor(index, dtype=torch.long, device=self.stack.device)
        job, lights = self.job, self.job.lights
        picked = Lights(lights.directions[at], lights.kernel, lights.irradiance[at], lights.exposure[at])
        job = replace(
            job,
            picked=[job.picked[i] for i in index],
            lights=picked,
            positions=None if job.positions is None else job.positions[at],
            gains=None if job.gains is None else job.gains[at],
        )
        return replace(self, job=job, stack=self.stack[at], masks=self.masks.map(lambda mask: mask[at]))


@dataclass(frozen=True)
class PlainFit:
    """Every pixel's fit without a lobe, leading dims ``(n,)`` (a tile) or ``(H, W)`` (an image):
    ``normal (*, 3)``, ``diffuse (*, C)``, ``criterion`` (``inf`` where a pixel has none), the
    solver's ``status`` and ``iterations``, ``residual``, ``quality``, ``flags`` and the
    deviations ``std_normal``, ``std_diffuse (*, C)``, as in :class:`~torchspec.pipeline.result.Fit`."""

    normal: Tensor
    diffuse: Tensor
    criterion: Tensor
    status: Tensor
    iterations: Tensor
    residual: Tensor
    quality: Tensor
    flags: Tensor
    std_normal: Tensor
    std_diffuse: Tensor


@dataclass(frozen=True)
class TileResult:
    """The fit of one tile of ``n`` pixels, the fields of :class:`~torchspec.pipeline.result.Fit`
    with leading dim ``(n,)``, and what the image's assembly needs besides.

    Attributes:
        svbrdf, flags, residual, quality, status, iterations, lobe, model, criterion, std: as
            :class:`~torchspec.pipeline.result.Fit`'s.
        checks: the peak checks behind two flags.
        tried: pixels fitted per model.
        noise: ``(2,)`` the sensor's ``(a, b)`` (zeros when not estimated).
        times: seconds per stage.
        plain: every pixel's fit without a lobe (``FitConfig.ladder.smooth`` only; else ``None``).
        masked: the count of masked samples per kind of :data:`~torchspec.pipeline.tile.MASK_KINDS`
            (:func:`~torchspec.pipeline.tile.fit_tile`).
        term: the residual term (``FitConfig.term.order``; else ``None``).
    """

    svbrdf: SVBRDF
    flags: Tensor
    checks: Checks
    residual: Tensor
    quality: Tensor
    status: Tensor
    iterations: Tensor
    lobe: Tensor
    model: Tensor
    criterion: Tensor
    std: dict[str, Tensor]
    tried: dict[str, int]
    noise: Tensor
    times: dict[str, float]
    plain: PlainFit | None = None
    masked: dict[str, int] | None = None
    term: ResidualTerm | None = None

    def to(self, device: torch.device | str) -> TileResult:
        """Every tensor moved to ``device``."""
        return _moved(self, device)


def _moved(value, device):
    """``value`` with every tensor in it moved to ``device``: a tensor or :class:`~torchspec.model.brdf.SVBRDF`,
    a dict of them, or a record of this module, :class:`~torchspec.pipeline.checks.Checks` or
    :class:`~torchspec.model.residual_term.ResidualTerm` field by field; anything else as it is."""
    if isinstance(value, (Tensor, SVBRDF)):
        return value.to(device=device)
    if isinstance(value, dict):
        return {name: _moved(item, device) for name, item in value.items()}
    if isinstance(value, (TileResult, Checks, PlainFit, ResidualTerm)):
        return replace(value, **{f.name: _moved(getattr(value, f.name), device) for f in fields(value)})
    return value
