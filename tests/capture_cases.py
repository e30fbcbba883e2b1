"""Small captures for the io tests: the shared development data's folder, a tiny capture
manifest and frames to write, and a way to edit a written manifest."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import SHARED

from torchspec.io import Capture, Frame, LightSpec

DATA = SHARED
needs_data = pytest.mark.skipif(not DATA.is_dir(), reason=f"needs the shared development data {DATA}; absent here")

H, W = 4, 5


def direction(lx, ly):
    return (lx, ly, math.sqrt(1 - lx * lx - ly * ly))


def small_capture(root=".", light=None, count=3, channels=("R", "G", "B"), positions=None) -> Capture:
    """A ``W x H`` capture of ``count`` frames on a line of the l-plane (or at ``positions``)."""
    positions = positions or [(0.1 * k, -0.05 * k) for k in range(count)]
    frames = tuple(Frame(f"frames/{k:04d}.exr", direction(*l), 1.0 + k, 0.5 * (k + 1)) for k, l in enumerate(positions))
    return Capture(
        root=Path(root),
        width=W,
        height=H,
        channels=channels,
        view=(0.0, 0.0, 1.0),
        light=light or LightSpec("gaussian", domain="projected", sigma=0.05),
        frames=frames,
    )


def random_frames(count=3, channels=3, seed=0, low=0.0, high=2.0):
    """``(count, channels, H, W)`` float32 frames, uniform in ``[low, high)``."""
    rng = np.random.default_rng(seed)
    return torch.from_numpy(rng.uniform(low, high, (count, channels, H, W)).astype(np.float32))


def edit_manifest(root: Path, edit) -> None:
    """Apply ``edit`` to the JSON of ``root``'s ``capture.json`` and write it back."""
    path = root / "capture.json"
    manifest = json.loads(path.read_text())
    edit(manifest)
    path.write_text(json.dumps(manifest))


def write_painting(
    path: Path,
    *,
    size: int = 12,
    seed: int = 3,
    gilded: bool = False,
    dual: bool = False,
    grid: int = 5,
    extent: float = 0.6,
    radius: float = 1.0,
    photons: float | None = None,
    sensor_seed: int = 0,
) -> Path:
    """A simulated ``size x size`` painting (its gilded patch only with ``gilded``, a box of two-lobed
    gloss with ``dual``) under a
    ``grid x grid`` layout of a projected Gaussian light (sigma 0.08), with truth; shot noise of
    ``photons`` per unit when given, else the simulator's default sensor."""
    from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, simulate, write_simulation
    from torchspec.simulate.synth import DualConfig, GildedConfig, PaintingConfig, SensorConfig

    painting = PaintingConfig(
        width=size,
        height=size,
        seed=seed,
        gilded=GildedConfig() if gilded else None,
        dual=DualConfig() if dual else None,
    )
    sensor = {} if photons is None else {"sensor": SensorConfig(photons_per_unit=photons, seed=sensor_seed)}
    config = SimulationConfig(
        scene=SceneConfig(kind="painting", painting=painting),
        light=LightConfig(kernel="gaussian", domain="projected", sigma=0.08),
        layout=LayoutConfig(kind="grid", nx=grid, ny=grid, extent=extent, radius=radius),
        **sensor,
    )
    write_simulation(path, simulate(config))
    return path


def write_small_painting(path: Path) -> Path:
    """A simulated 12 x 12 painting (no gilding) under a 5 x 5 grid of a projected Gaussian light, with
    truth: 144 pixels, 25 frames; the fit, resume and Dask tests share it."""
    return write_painting(path)


def write_relight_painting(path: Path) -> Path:
    """A simulated 10 x 8 painting (3 strokes) under a 4 x 4 grid of lights within radius 0.6 (12
    frames, irradiance 1), with truth: the relighting tests' capture."""
    from torchspec.simulate import LayoutConfig, SceneConfig, SimulationConfig, simulate, write_simulation
    from torchspec.simulate.synth import PaintingConfig

    config = SimulationConfig(
        scene=SceneConfig(kind="painting", painting=PaintingConfig(width=10, height=8, strokes=3)),
        layout=LayoutConfig(kind="grid", nx=4, ny=4, extent=0.5, radius=0.6),
    )
    write_simulation(path, simulate(config))
    return path
