"""Simulated captures the experiments share beyond what ``torchspec simulate`` writes: a procedural
painting rendered with either lobe (``ward``, the fit's model, or ``beckmann``, the development
captures' path tracer's), per-channel irradiance and a per-frame exposure, so a fit meets the
model error and the scale factors of a real capture; and the same maps under other lights (a pair
to fit one and predict the other)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import torch

from torchspec.io import Capture, Frame, LightSpec, Maps, write_capture
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render
from torchspec.simulate import LayoutConfig, LightConfig, layout
from torchspec.simulate.synth import PaintingConfig, SensorConfig, painting, sense

F64 = torch.float64


@dataclass(frozen=True)
class Scene:
    """The object: a procedural painting (:class:`torchspec.simulate.synth.PaintingConfig`) and the lobe its
    frames are rendered with (the truth's maps are written either way: under ``beckmann`` they are
    not the fit's model, as with the development captures)."""

    painting: PaintingConfig = field(default_factory=PaintingConfig)
    lobe: str = "ward"
    channels: tuple[str, ...] = ("R", "G", "B")


@dataclass(frozen=True)
class Lighting:
    """One capture of a :class:`Scene`: the light kernel, the layout of its centres, the sensor,
    ``irradiance`` per channel (one value: every channel) and each frame's exposure drawn
    log-uniformly from ``exposure`` (``lo, hi``) with ``seed`` (the sensor's ``exposure`` multiplies it)."""

    light: LightConfig = field(default_factory=LightConfig)
    layout: LayoutConfig = field(default_factory=LayoutConfig)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    irradiance: tuple[float, ...] = (1.0,)
    exposure: tuple[float, float] = (1.0, 1.0)
    seed: int = 0


def lights_of(lighting: Lighting, channels: int) -> Lights:
    """The :class:`~torchspec.model.lights.Lights` (float64) of ``lighting`` for ``channels`` channels."""
    centres = layout(lighting.layout)
    k = centres.shape[0]
    if len(lighting.irradiance) not in (1, channels):
        raise ValueError(f"irradiance: give 1 or {channels} values (one per channel); got {lighting.irradiance}.")
    irradiance = torch.tensor(lighting.irradiance, dtype=F64).expand(k, channels).clone()
    lo, hi = lighting.exposure
    if not 0 < lo <= hi:
        raise ValueError(f"exposure: (lo, hi) with 0 < lo <= hi; got {lighting.exposure}.")
    draw = torch.rand(k, generator=torch.Generator().manual_seed(lighting.seed), dtype=F64)
    exposure = torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * draw) * lighting.sensor.exposure
    kind = lighting.light.kernel
    kernel = Kernel("point") if kind == "point" else Kernel(kind, lighting.light.domain, lighting.light.sigma)
    return Lights(centres, kernel, irradiance, exposure)


def write_scene(path: Path, scene: Scene, lighting: Lighting) -> Path:
    """Render ``scene`` under ``lighting``, record it through the sensor (its ``exposure`` is in the
    frames' exposure, so the sensor itself is given 1) and write the capture with its ``truth/``
    (maps and ``regions``); returns ``path``."""
    truth, regions = painting(scene.painting, dtype=F64)
    truth = replace(truth, channels=tuple(scene.channels))
    count = len(scene.channels)
    lights = lights_of(lighting, count)
    view = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    values = render(truth, lights, view, lobe=scene.lobe)  # (H, W, K, C)
    sensor = SensorConfig(**{**lighting.sensor.__dict__, "exposure": 1.0})
    recorded, _ = sense(values.permute(2, 3, 0, 1), sensor)  # (K, C, H, W)
    kind = lighting.light.kernel
    spec = (
        LightSpec(kernel="point")
        if kind == "point"
        else LightSpec(kernel=kind, domain=lighting.light.domain, sigma=lighting.light.sigma)
    )
    frames = tuple(
        Frame(
            f"frames/{i:04d}.exr",
            tuple(float(v) for v in lights.directions[i]),
            tuple(float(v) for v in lights.irradiance[i]),
            float(lights.exposure[i]),
        )
        for i in range(lights.directions.shape[0])
    )
    height, width = truth.shape
    capture = Capture(
        root=path,
        width=width,
        height=height,
        channels=tuple(scene.channels),
        view=(0.0, 0.0, 1.0),
        light=spec,
        frames=frames,
    )
    maps = Maps(
        truth.to(torch.float32),
        {"model": "ward", "rendered_lobe": scene.lobe, "source": "experiments/_scenes.py"},
        {"regions": regions},
    )
    write_capture(path, capture, recorded.float(), truth=maps)
    return path


def warm_up(path: Path) -> None:
    """Fit (``auto``, the whole ladder) a tiny simulated painting written to ``path``: the
    process's one-off costs (first calls of each kernel, lazy imports) paid before fits are timed."""
    from torchspec.pipeline import fit

    scene = Scene(PaintingConfig(width=8, height=8, seed=1))
    lighting = Lighting(layout=LayoutConfig(kind="grid", nx=6, ny=6, extent=0.6, radius=0.8))
    fit(write_scene(path, scene, lighting))
