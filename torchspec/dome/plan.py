"""What an acquisition takes: the light (the config of ``torchspec acquire --light``) and the
layout of light positions, as directions and dome angles.

Layouts (:func:`plan_directions`): ``grid:NXxNY``, the grid of
:func:`torchspec.simulate.layout` over ``[-radius, radius]^2`` of the l-plane with the points
beyond ``radius`` dropped (``grid:12x12`` at radius 0.8 gives the 88 frames of
``configs/sim_painting.yaml``), and ``line:N``, ``N`` directions along the ``x`` axis across the
zenith with ``|l| <= radius``.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..config import read_yaml
from ..errors import TorchspecError
from ..io import ExrError, LightSpec, read_exr
from ..io._manifest import Where, parse_light
from ..model.lights import Kernel
from ..simulate import LayoutConfig, layout

__all__ = ["AcquisitionError", "LightSettings", "load_light", "parse_layout", "plan_directions", "dome_angles"]

_LIGHT_KEYS = ("light", "intensity", "irradiance", "exposure", "calibration")
"""The light config's keys; ``calibration`` (the statistics ``torchspec calibrate`` writes beside
its ``light``) is a record, not read, so calibrate's kernel.json is a light config as it is."""
KERNEL_FILE = "kernel.exr"
"""A tabulated light's table, copied into the capture folder under this name."""


class AcquisitionError(TorchspecError):
    """An acquisition refused before it moves anything: a bad layout or light config, an output
    folder that is not empty (without resume), or one that holds another job."""


# --- the light ----------------------------------------------------------------------------------


@dataclass(frozen=True)
class LightSettings:
    """The dome's light for an acquisition (the light config of ``torchspec acquire --light``).

    Attributes:
        light: the capture format's light block: the kernel recorded in the manifest
            (``unknown`` for a light not yet calibrated).
        intensity: the dome's light setting, in ``[0, 1]``.
        irradiance: the irradiance at that setting: a number or one per channel (the manifest's).
        exposure: the camera's exposure factor when the camera does not know it (a tethered
            camera); a camera that knows it must agree. ``None``: the camera's, or 1.
        table: ``(Hk, Wk)`` image of a tabulated kernel (written to the capture's ``kernel.exr``).
    """

    light: LightSpec
    intensity: float = 1.0
    irradiance: float | tuple[float, ...] = 1.0
    exposure: float | None = None
    table: Tensor | None = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if isinstance(self.light, Mapping):
            object.__setattr__(self, "light", _light_block(dict(self.light), Path("light")))
        if not isinstance(self.light, LightSpec):
            raise AcquisitionError(f"light must be a LightSpec or a light block; got {type(self.light).__name__}.")
        if isinstance(self.irradiance, (list, tuple)) and all(_number(v) for v in self.irradiance):
            object.__setattr__(self, "irradiance", tuple(float(v) for v in self.irradiance))
        checks = [
            (_number(self.intensity) and 0 <= self.intensity <= 1, "intensity must be in [0, 1]", self.intensity),
            (
                all(_number(v) and v > 0 for v in as_tuple(self.irradiance)) and as_tuple(self.irradiance),
                "irradiance must be a positive number or one per channel",
                self.irradiance,
            ),
            (
                self.exposure is None or (_number(self.exposure) and self.exposure > 0),
                "exposure must be a positive number or absent",
                self.exposure,
            ),
            (
                self.light.kernel != "tabulated" or self.table is not None,
                "a tabulated light needs its kernel image (table)",
                None,
            ),
        ]
        for ok, what, got in checks:
            if not ok:
                raise AcquisitionError(f"{what}; got {got!r}.")
        if self.table is not None:
            # CPU on purpose: the kernel image as read from its file (a tensor given stays where it is)
            object.__setattr__(self, "table", torch.as_tensor(self.table))
        self.kernel()  # the kernel must be one the renderer accepts

    def kernel(self) -> Kernel | None:
        """The :class:`~torchspec.model.lights.Kernel` of :attr:`light`; ``None`` for ``unknown``."""
        if self.light.kernel == "unknown":
            return None
        try:
            return Kernel.from_spec(self.light, self.table)
        except ValueError as error:
            raise AcquisitionError(f"light must describe a valid kernel; got {self.light}: {error}") from error

    def irradiance_for(self, channels: Sequence[str]) -> tuple[float, ...]:
        """One irradiance per channel."""
        values = as_tuple(self.irradiance)
        if len(values) == 1:
            return values * len(channels)
        if len(values) != len(channels):
            raise AcquisitionError(
                f"irradiance must be one number or one per channel {list(channels)}; got {list(values)}. "
                "Give as many values as the camera has channels."
            )
        return values


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)


def as_tuple(value) -> tuple:
    """A list or tuple as a tuple; any other value as a 1-tuple (one irradiance for every channel)."""
    return tuple(value) if isinstance(value, (list, tuple)) else (value,)


def _light_block(block, source: Path) -> LightSpec:
    """The format's light block validated as the manifest reader does; unknown keys are errors."""
    notes: list[str] = []
    spec = parse_light(Where(source), block, notes)
    if notes:
        raise AcquisitionError(notes[0].replace("are ignored", "are not light keys") + " Remove them.")
    return spec


def load_light(path: str | Path) -> LightSettings:
    """Read a light config (YAML or JSON).

    The file holds ``light`` (the capture format's light block, e.g. ``{kernel: gaussian,
    domain: projected, sigma: 0.08}``) and optionally ``intensity``, ``irradiance`` and
    ``exposure`` (:class:`LightSettings`); a bare light block is read as ``light``. A tabulated
    light's ``file`` is relative to the config.

    Raises:
        AcquisitionError, CaptureError: the file is unreadable, a key is unknown or missing, or
            a value is out of its domain; the message names the file and the key.

    Example:
        >>> import pathlib, tempfile
        >>> path = pathlib.Path(tempfile.mkdtemp()) / "light.yaml"
        >>> _ = path.write_text("light: {kernel: gaussian, domain: projected, sigma: 0.08}")
        >>> settings = load_light(path)
        >>> settings.light.kernel, settings.intensity
        ('gaussian', 1.0)
    """
    path = Path(path)
    data = read_yaml(path, what="the light config", error=AcquisitionError)
    if isinstance(data, dict) and "kernel" in data and "light" not in data:
        data = {"light": data}
    if not isinstance(data, dict) or "light" not in data:
        raise AcquisitionError(
            f"the light config {path} must be a mapping with a 'light' block; got {type(data).__name__}"
            f"{' without light' if isinstance(data, dict) else ''}. E.g. light: {{kernel: point}}."
        )
    unknown = sorted(set(data) - set(_LIGHT_KEYS))
    if unknown:
        raise AcquisitionError(
            f"the light config {path} has unknown key(s) {unknown}; known keys are {list(_LIGHT_KEYS)}."
        )
    spec = _light_block(data["light"], path)
    table = None
    if spec.kernel == "tabulated":
        file = path.parent / spec.file
        try:
            table = torch.from_numpy(read_exr(file, ["Y"])[:, :, 0])
        except ExrError as error:
            raise AcquisitionError(f"{path}: light.file must be a readable kernel image; got: {error}") from error
        spec = LightSpec(kernel="tabulated", file=KERNEL_FILE, extent=spec.extent)
    values = {key: data[key] for key in ("intensity", "irradiance", "exposure") if key in data}
    try:
        return LightSettings(spec, table=table, **values)
    except AcquisitionError as error:
        raise AcquisitionError(f"the light config {path}: {error}") from None


# --- the plan -----------------------------------------------------------------------------------


def parse_layout(spec: str, radius: float) -> LayoutConfig:
    """The :class:`~torchspec.simulate.LayoutConfig` of ``grid:NXxNY`` or ``line:N`` at ``radius``.

    Raises:
        AcquisitionError: an unknown spec, or ``radius`` outside ``(0, 1)``.
    """
    if not (_number(radius) and 0 < radius < 1):
        raise AcquisitionError(
            f"radius must be in (0, 1) (the largest |l| of a light; 1 is the horizon); got {radius!r}."
        )
    grid = re.fullmatch(r"grid:(\d+)x(\d+)", str(spec))
    line = re.fullmatch(r"line:(\d+)", str(spec))
    if grid and min(int(grid[1]), int(grid[2])) >= 1:
        return LayoutConfig(kind="grid", nx=int(grid[1]), ny=int(grid[2]), extent=radius, radius=radius)
    if line and int(line[1]) >= 2:
        top = math.degrees(math.asin(radius))
        return LayoutConfig(kind="line", n=int(line[1]), theta_min_deg=-top, theta_max_deg=top, azimuth_deg=0.0)
    raise AcquisitionError(
        f"layout must be 'grid:NXxNY' (NX, NY >= 1, e.g. grid:12x12) or 'line:N' (N >= 2); got {spec!r}."
    )


def plan_directions(spec: str, radius: float) -> Tensor:
    """The planned light centres ``(K, 3)``, float64, in the order the frames are taken.

    Example:
        >>> plan_directions("grid:12x12", 0.8).shape
        torch.Size([88, 3])
    """
    try:
        return layout(parse_layout(spec, radius))
    except AcquisitionError:
        raise
    except ValueError as error:
        raise AcquisitionError(f"layout {spec!r} at radius {radius:g}: {error}") from None


def dome_angles(directions: Tensor) -> Tensor:
    """Dome angles ``(*, 2)``: ``theta`` from the zenith and ``phi``, the azimuth from ``+x``
    towards ``+y`` in ``[0, 2 pi)``, of unit directions ``(*, 3)``; the inverse of
    ``l = (sin t cos p, sin t sin p, cos t)``. At the zenith ``phi`` is 0."""
    x, y, z = directions.unbind(-1)
    theta = torch.atan2(torch.hypot(x, y), z)
    phi = torch.remainder(torch.atan2(y, x), 2 * math.pi)
    phi = torch.where(phi >= 2 * math.pi, torch.zeros_like(phi), phi)  # remainder can round up to 2 pi
    return torch.stack([theta, phi], -1)


def dome_direction(theta: float, phi: float) -> tuple[float, float, float]:
    """The unit direction of the dome angles ``theta`` (from the zenith) and ``phi`` (from ``+x``),
    radians: the inverse of :func:`dome_angles`."""
    return (math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta))
