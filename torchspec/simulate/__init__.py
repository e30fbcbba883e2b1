"""Simulated captures: a procedural SVBRDF (:mod:`torchspec.simulate.synth`) rendered through
:func:`torchspec.model.rendering.render` under a light layout, recorded by the sensor model, and written
in the capture format with its ``truth/``.

A config (YAML, loaded strictly: an unknown key is an error) names the scene, the light, the
layout of the light centres, the channels and the sensor. ``torchspec simulate CONFIG -o DIR``
runs it; ``configs/sim_*.yaml`` hold the paper's 1D and 2D simulations and look-alikes of the
development captures.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from torch import Tensor

from ..config import ConfigError
from ..io import Capture, Frame, LightSpec, Maps, write_capture
from ..model.brdf import SVBRDF
from ..model.geometry import from_plane
from ..model.indirect import flat_maps
from ..model.lights import Kernel, Lights
from ..model.rendering import render_image
from ..model.visibility import kernel_visibility, sky_view
from . import relief as reliefs  # the module: torchspec.simulate.relief stays the module, not its function
from .relief import ReliefConfig
from .synth import MirrorConfig, PaintingConfig, SensorConfig, mirror, painting, sense

__all__ = [
    "SceneConfig",
    "LightConfig",
    "LayoutConfig",
    "SimulationConfig",
    "Simulation",
    "layout",
    "simulate",
    "write_simulation",
]

FORMAT_KERNELS = ("point", "gaussian", "tabulated")


@dataclass(frozen=True)
class SceneConfig:
    """``kind``: ``painting`` or ``mirror`` (a constant near-mirror, also the paper's single surface
    point: set its ``ks``, ``kd``, ``alpha`` and tilt). ``relief`` (none by default): a height field
    (:class:`~torchspec.simulate.relief.ReliefConfig`) whose normals replace the scene's and, with its
    ``shadows``, whose cast shadows darken the frames (the visibility of
    :func:`torchspec.model.visibility.kernel_visibility` multiplies the rendered values, diffuse and
    specular alike); its height goes to ``truth/height.exr``."""

    kind: str = "painting"
    painting: PaintingConfig = field(default_factory=PaintingConfig)
    mirror: MirrorConfig = field(default_factory=MirrorConfig)
    relief: ReliefConfig | None = None


@dataclass(frozen=True)
class LightConfig:
    """The light kernel: ``point``; ``gaussian`` (``domain`` projected or angular, ``sigma``);
    ``supergaussian`` (angular ``exp(-(g / sigma)^power)``, a disk-like light the capture format
    cannot name: the manifest then says ``unknown`` and ``truth/light.json`` keeps the truth)."""

    kernel: str = "gaussian"
    domain: str = "projected"
    sigma: float = 0.08
    power: float = 2.0


@dataclass(frozen=True)
class LayoutConfig:
    """Light centres. ``grid``: ``nx`` x ``ny`` points over ``[-extent, extent]^2`` of the l-plane,
    those beyond ``radius`` dropped; ``line``: ``n`` directions along the azimuth ``azimuth_deg``
    from ``theta_min_deg`` to ``theta_max_deg`` (signed: negative across the zenith);
    ``scattered``: ``n`` directions uniform in the l-plane disk of ``theta_max_deg``."""

    kind: str = "grid"
    nx: int = 12
    ny: int = 12
    extent: float = 0.8
    radius: float = 0.8
    n: int = 50
    azimuth_deg: float = 0.0
    theta_min_deg: float = -30.0
    theta_max_deg: float = 30.0
    seed: int = 0


@dataclass(frozen=True)
class SimulationConfig:
    name: str = "simulation"
    scene: SceneConfig = field(default_factory=SceneConfig)
    light: LightConfig = field(default_factory=LightConfig)
    layout: LayoutConfig = field(default_factory=LayoutConfig)
    channels: tuple[str, ...] = ("R", "G", "B")
    irradiance: float = 1.0
    sensor: SensorConfig = field(default_factory=SensorConfig)


@dataclass(frozen=True)
class Simulation:
    """A simulated capture before it is written: manifest, frames ``(K, C, H, W)`` float32 as
    recorded, the saturation mask, the truth and its region map, the light, and the relief's
    height ``(H, W)`` in pixels (``None`` without ``scene.relief``) and its true indirect share
    ``(H, W)`` (:mod:`torchspec.model.indirect`; ``None`` without ``scene.relief.indirect``)."""

    capture: Capture
    frames: Tensor
    saturated: Tensor
    truth: SVBRDF
    regions: Tensor
    light: dict
    height: Tensor | None = None
    indirect: Tensor | None = None


def layout(config: LayoutConfig) -> Tensor:
    """Unit light centres ``(K, 3)``, float64, in the order frames are numbered.

    Raises:
        ConfigError: ``kind`` is unknown, a count of its kind is below 1, or the layout gives no
            direction or reaches the horizon (the message names the key).
    """
    like = dict(dtype=torch.float64)
    counts = {"grid": ("nx", "ny"), "line": ("n",), "scattered": ("n",)}.get(config.kind, ())
    for key in counts:
        if getattr(config, key) < 1:
            raise ConfigError(f"layout.{key} must be >= 1 for a {config.kind} layout; got {getattr(config, key)}.")
    if config.kind == "grid":
        x = torch.linspace(-config.extent, config.extent, config.nx, **like)
        y = torch.linspace(config.extent, -config.extent, config.ny, **like)  # row by row from the top
        gy, gx = torch.meshgrid(y, x, indexing="ij")
        l = torch.stack([gx, gy], -1).reshape(-1, 2)
        l = l[(l * l).sum(-1) <= config.radius**2 + 1e-12]
    elif config.kind == "line":
        theta = torch.deg2rad(torch.linspace(config.theta_min_deg, config.theta_max_deg, config.n, **like))
        phi = math.radians(config.azimuth_deg)
        l = torch.stack([torch.sin(theta) * math.cos(phi), torch.sin(theta) * math.sin(phi)], -1)
    elif config.kind == "scattered":
        g = torch.Generator().manual_seed(config.seed)
        top = math.sin(math.radians(config.theta_max_deg))
        r = top * torch.sqrt(torch.rand(config.n, generator=g, **like))
        psi = 2 * math.pi * torch.rand(config.n, generator=g, **like)
        l = torch.stack([r * torch.cos(psi), r * torch.sin(psi)], -1)
    else:
        raise ConfigError(f"layout.kind must be 'grid', 'line' or 'scattered'; got {config.kind!r}.")
    if l.shape[0] == 0:
        raise ConfigError("layout gives no light direction; widen its radius or add points.")
    if bool(((l * l).sum(-1) >= 1.0).any()):
        raise ConfigError("layout reaches the horizon (|l| >= 1); lower its extent or theta.")
    return from_plane(l)


def _kernel(config: LightConfig) -> Kernel:
    if config.kernel == "point":
        return Kernel("point")
    return Kernel(config.kernel, config.domain, config.sigma, config.power)


def simulate(
    config: SimulationConfig, *, root: Path | str = ".", progress: bool = False, device: torch.device | str = "cpu"
) -> Simulation:
    """Render ``config``'s scene under its lights and record it (float64 inside, float32 out);
    ``progress`` shows a bar over the rows rendered (on stderr, when it is a terminal). The
    rendering runs on ``device``; the scene and the noise are drawn on the CPU from their seeds,
    so a config gives the same capture on every device (to rounding). The result is on the CPU."""
    dtype = torch.float64
    if config.scene.kind == "painting":
        truth, regions = painting(config.scene.painting, dtype=dtype, device=device)
    elif config.scene.kind == "mirror":
        truth, regions = mirror(config.scene.mirror, dtype=dtype, device=device)
    else:
        raise ConfigError(f"scene.kind must be 'painting' or 'mirror'; got {config.scene.kind!r}.")
    count = len(config.channels)
    if truth.diffuse.shape[-1] != count:
        raise ConfigError(f"channels: the list names {count} channels but the scene has {truth.diffuse.shape[-1]}.")
    truth = replace(truth, channels=tuple(config.channels))
    shape = None if config.scene.relief is None else reliefs.relief(config.scene.relief, *truth.shape, device=device)
    if shape is not None:
        truth = replace(truth, normal=shape.normal.to(truth.normal))
    centres = layout(config.layout).to(device)
    k = centres.shape[0]
    kernel = _kernel(config.light)
    irradiance = torch.full((k, 1), config.irradiance, dtype=dtype, device=centres.device)
    lights = Lights(centres, kernel, irradiance, torch.ones(k, dtype=dtype, device=centres.device))
    view = torch.tensor([0.0, 0.0, 1.0], dtype=dtype, device=centres.device)
    values = render_image(truth, lights, view, progress=progress, desc="simulate")  # (H, W, K, C)
    if shape is not None and config.scene.relief.shadows:
        softness = math.radians(config.scene.relief.softness_deg)
        values = values * kernel_visibility(shape.height, lights, 1.0, softness)[..., None]
    share = None
    if shape is not None and config.scene.relief.shadows and config.scene.relief.indirect > 0:
        share = config.scene.relief.indirect * (1.0 - sky_view(shape.height))  # (H, W)
        values = values + share[..., None, None] * render_image(flat_maps(truth), lights, view)
    recorded, saturated = sense(values.permute(2, 3, 0, 1), config.sensor)  # (K, C, H, W)
    light = {"kernel": config.light.kernel, "domain": config.light.domain, "sigma": config.light.sigma}
    if config.light.kernel == "supergaussian":
        light["power"] = config.light.power
    if config.light.kernel == "point":
        light = {"kernel": "point"}
    spec = LightSpec(**light) if config.light.kernel in FORMAT_KERNELS else LightSpec(kernel="unknown", symmetric=True)
    height, width = truth.shape
    frames = tuple(
        Frame(
            file=f"frames/{i:04d}.exr",
            direction=tuple(float(v) for v in centres[i]),
            irradiance=(config.irradiance,) * count,
            exposure=config.sensor.exposure,
        )
        for i in range(k)
    )
    capture = Capture(
        root=Path(root),
        width=width,
        height=height,
        channels=tuple(config.channels),
        view=(0.0, 0.0, 1.0),
        light=spec,
        frames=frames,
        extra={"generator": {"name": config.name, "torchspec": asdict(config)}},
    )
    recorded, saturated, regions = recorded.float().cpu(), saturated.cpu(), regions.cpu()
    height_map = None if shape is None else shape.height.float().cpu()
    indirect = None if share is None else share.float().cpu()
    return Simulation(
        capture, recorded, saturated, truth.to(torch.float32).to("cpu"), regions, light, height_map, indirect
    )


def write_simulation(path: Path | str, simulation: Simulation, *, overwrite: bool = False) -> Capture:
    """Write the capture, its ``truth/`` maps (with ``regions`` and the true ``light.json``); a
    folder that holds files is refused unless ``overwrite`` (:func:`torchspec.outputs.check_output`)."""
    from ..atomic import write_json

    path = Path(path)
    extra = {"regions": simulation.regions}
    meta = {"model": "ward", "source": "torchspec simulate"}
    if simulation.height is not None:
        extra["height"] = simulation.height
        meta["height"] = {"unit": "pixel", "pitch": 1.0}
    if simulation.indirect is not None:
        extra["indirect"] = simulation.indirect
    maps = Maps(simulation.truth, meta, extra)
    capture = Capture(**{**simulation.capture.__dict__, "root": path})
    written = write_capture(path, capture, simulation.frames, truth=maps, overwrite=overwrite)
    write_json(path / "truth" / "light.json", simulation.light)
    return written
