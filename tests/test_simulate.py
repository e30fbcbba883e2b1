import math
from pathlib import Path

import pytest
import torch

from torchspec.config import ConfigError, load_config
from torchspec.io import read_capture, read_svbrdf
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render
from torchspec.simulate import (
    LayoutConfig,
    SceneConfig,
    SimulationConfig,
    layout,
    simulate,
    write_simulation,
)
from torchspec.simulate.synth import PaintingConfig

CONFIGS = Path(__file__).parents[1] / "configs"


def _small():
    return SimulationConfig(
        name="test",
        scene=SceneConfig(kind="painting", painting=PaintingConfig(width=12, height=10, strokes=4)),
        layout=LayoutConfig(kind="grid", nx=4, ny=4, extent=0.5, radius=0.6),
    )


def test_layouts():
    grid = layout(LayoutConfig(kind="grid", nx=12, ny=12, extent=0.8, radius=0.8))
    assert grid.shape == (88, 3)  # as painting-dev
    torch.testing.assert_close(grid.norm(dim=-1), torch.ones(88, dtype=torch.float64))
    line = layout(LayoutConfig(kind="line", n=5, azimuth_deg=90.0, theta_min_deg=-10.0, theta_max_deg=10.0))
    assert abs(line[0, 1].item() + math.sin(math.radians(10))) < 1e-12 and abs(line[2, 2].item() - 1) < 1e-12
    scattered = layout(LayoutConfig(kind="scattered", n=30, theta_max_deg=60.0))
    assert (scattered[:, 2] >= math.cos(math.radians(60)) - 1e-12).all()
    with pytest.raises(ValueError, match="reaches the horizon"):
        layout(LayoutConfig(kind="grid", nx=3, ny=3, extent=1.0, radius=2.0))
    with pytest.raises(ValueError, match="layout.kind must be"):
        layout(LayoutConfig(kind="spiral"))


def test_simulation_round_trip(tmp_path):
    result = simulate(_small())
    capture = write_simulation(tmp_path / "cap", result)
    back = read_capture(tmp_path / "cap")
    assert len(back.frames) == len(capture.frames) == 12 and (back.width, back.height) == (12, 10)
    frames = back.read_frames()
    torch.testing.assert_close(frames, result.frames)
    truth = read_svbrdf(tmp_path / "cap" / "truth")
    torch.testing.assert_close(truth.svbrdf.diffuse, result.truth.diffuse)
    assert "regions" in truth.extra
    # The frames are the truth rendered under the capture's lights (no noise in this config).
    lights = Lights(back.directions(), Kernel("gaussian", "projected", 0.08), back.irradiance(), back.exposure())
    again = render(truth.svbrdf.to(torch.float64), lights, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    torch.testing.assert_close(again.permute(2, 3, 0, 1).float(), frames, rtol=1e-5, atol=1e-6)


def test_unknown_light_is_written_as_unknown(unknown_light_capture):
    capture = read_capture(unknown_light_capture)
    assert capture.light.kernel == "unknown"
    assert (unknown_light_capture / "truth" / "light.json").exists()


@pytest.mark.parametrize(
    "path", ["sim_painting.yaml", "sim_mirror.yaml", "../experiments/configs/sim_paper_1d.yaml",
             "../experiments/configs/sim_paper_2d.yaml"]
)
def test_shipped_configs_load(path):
    config = load_config(CONFIGS / path, SimulationConfig)
    assert layout(config.layout).shape[0] > 0


def test_config_typo_is_an_error(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("scene: {kind: painting}\nlayuot: {kind: grid}\n")
    with pytest.raises(ConfigError, match=r"unknown key\(s\) \['layuot'\]"):
        load_config(path, SimulationConfig)
