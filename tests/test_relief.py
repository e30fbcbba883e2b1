"""The synthetic relief (torchspec.simulate.relief) and simulate's scene.relief: exact normals, cast
shadows in the frames, truth/height.exr, the default simulation untouched."""

import pytest
import torch

from torchspec.config import ConfigError, from_mapping
from torchspec.io import read_svbrdf
from torchspec.model.height import normals_from_height
from torchspec.simulate import LayoutConfig, SceneConfig, SimulationConfig, simulate, write_simulation
from torchspec.simulate.relief import ReliefConfig, relief
from torchspec.simulate.synth import PaintingConfig


def _config(relief_config=None):
    return SimulationConfig(
        name="test",
        scene=SceneConfig(painting=PaintingConfig(width=20, height=16, strokes=3), relief=relief_config),
        layout=LayoutConfig(kind="grid", nx=3, ny=3, extent=0.9, radius=1.0),
    )


def test_relief_normals_are_its_height_gradient():
    r = relief(ReliefConfig(seed=1), 40, 48)
    # Central differences of the height agree with the exact normals away from the border.
    error = (normals_from_height(r.height) - r.normal)[2:-2, 2:-2].abs()
    assert float(error.mean()) < 0.01 and float(error.max()) < 0.1  # steep bumps: O(h^2) differences
    assert torch.equal(relief(ReliefConfig(seed=1), 40, 48).height, r.height)  # seeded


def test_relief_config_is_checked():
    with pytest.raises(ConfigError, match="bump_height"):
        from_mapping({"bump_height": [5.0, 1.0]}, ReliefConfig, "relief")


def test_shadows_darken_frames_and_height_is_written(tmp_path):
    shadowed = simulate(_config(ReliefConfig(seed=2)))
    lit = simulate(_config(ReliefConfig(seed=2, shadows=False)))
    assert torch.equal(shadowed.truth.normal, lit.truth.normal)
    ratio = shadowed.frames / lit.frames.clamp(min=1e-12)
    assert bool((ratio <= 1.0 + 1e-6).all()) and float((ratio < 0.5).float().mean()) > 0.01
    write_simulation(tmp_path / "cap", shadowed)
    truth = read_svbrdf(tmp_path / "cap" / "truth")
    assert torch.equal(truth.extra["height"], shadowed.height)
    assert truth.meta["height"] == {"unit": "pixel", "pitch": 1.0}


def test_no_relief_changes_nothing_and_unit_visibility_is_exact(monkeypatch):
    import torchspec.simulate as module

    plain = simulate(_config())
    assert plain.height is None
    # A relief whose shadows are all lit: visibility 1 exactly leaves the frames as without shadows.
    monkeypatch.setattr(
        module,
        "kernel_visibility",
        lambda height, lights, *a, **k: torch.ones_like(height)[..., None].expand(-1, -1, len(lights.directions)),
    )
    ones = simulate(_config(ReliefConfig(seed=2)))
    no_shadow = simulate(_config(ReliefConfig(seed=2, shadows=False)))
    assert torch.equal(ones.frames, no_shadow.frames)
