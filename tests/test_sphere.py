"""Light directions from a chrome sphere (torchspec.calibration.sphere, torchspec calibrate-sphere)."""

import json
import math

import numpy as np
import pytest
import torch
from conftest import DEVICES
from PIL import Image

from torchspec.calibration.sphere import Circle, circle_from_mask, find_sphere, sphere_directions
from torchspec.cli import main
from torchspec.errors import TorchspecError
from torchspec.io.images import read_photo
from torchspec.io.lp import read_light_file

CIRCLE = Circle(cx=40.3, cy=35.7, r=25.0)
LIGHTS = [
    (0.0, 0.0, 1.0),
    (0.5, 0.3, math.sqrt(1 - 0.34)),
    (-0.6, 0.2, math.sqrt(1 - 0.4)),
    (0.1, -0.7, math.sqrt(0.5)),
]


def _sphere_frames(lights, circle=CIRCLE, h=72, w=80):
    """A mirror sphere's highlight (a Gaussian spot of 1 px) where its normal halves light and view."""
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    frames = []
    for light in lights:
        half = np.add(light, (0, 0, 1))
        half /= np.linalg.norm(half)
        x, y = circle.cx + circle.r * half[0], circle.cy - circle.r * half[1]
        spot = np.exp(-((cols - x) ** 2 + (rows - y) ** 2) / 2)
        frames.append(np.repeat(spot[None], 3, 0))
    return torch.from_numpy(np.stack(frames))


def test_directions_from_highlights():
    result = sphere_directions(_sphere_frames(LIGHTS), CIRCLE)
    truth = torch.tensor(LIGHTS, dtype=torch.float64)
    angle = torch.rad2deg(torch.acos((result.directions * truth).sum(-1).clamp(-1, 1)))
    assert angle.max() < 0.6, angle  # a 25-pixel sphere, a highlight of 1 pixel: within its uncertainty
    assert (angle < result.uncertainty_deg).all(), (angle, result.uncertainty_deg)
    assert torch.allclose(result.directions.norm(dim=-1), torch.ones(4, dtype=torch.float64))
    assert (result.uncertainty_deg > 0).all() and (result.uncertainty_deg < 10).all()


def test_circle_from_mask():
    rows, cols = np.mgrid[0:72, 0:80]
    mask = ((cols - CIRCLE.cx) ** 2 + (rows - CIRCLE.cy) ** 2 <= CIRCLE.r**2).astype(np.float32)
    circle = circle_from_mask(mask)
    assert circle.cx == pytest.approx(CIRCLE.cx, abs=0.05) and circle.cy == pytest.approx(CIRCLE.cy, abs=0.05)
    assert circle.r == pytest.approx(CIRCLE.r, abs=0.1)


@pytest.mark.parametrize("device", [None, *DEVICES])
def test_command_line_writes_an_lp(tmp_path, device):
    frames = _sphere_frames(LIGHTS)
    for k, frame in enumerate(frames):
        Image.fromarray((frame.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(tmp_path / f"s.{k}.png")
    args = ["calibrate-sphere", str(tmp_path), "-o", str(tmp_path / "out" / "dome.lp")]
    on = [] if device is None else ["--device", device]
    assert main(args + ["--circle", str(CIRCLE.cx), str(CIRCLE.cy), str(CIRCLE.r), *on]) == 0
    lights = read_light_file(tmp_path / "out" / "dome.lp")
    assert [e.name for e in lights.entries] == [f"s.{k}.png" for k in range(4)]
    got = torch.tensor([e.direction for e in lights.entries], dtype=torch.float64)
    assert torch.rad2deg(torch.acos((got * torch.tensor(LIGHTS, dtype=torch.float64)).sum(-1).clamp(-1, 1))).max() < 1
    assert (tmp_path / "out" / "dome.json").is_file()


def _ball_scene(circle=CIRCLE, h=72, w=80, lights=LIGHTS, seed=0, noise=0.005):
    """A dark chrome ball on a background brighter above than below (only its upper rim contrasts),
    a bright rim on its left, its highlights, and sensor noise."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    distance = np.hypot(cols - circle.cx, rows - circle.cy)
    ball = np.clip(circle.r + 0.5 - distance, 0, 1)  # anti-aliased coverage
    background = 0.3 * np.clip(1 - rows / h * 1.5, 0, 1)
    rim = 0.3 * (distance > circle.r - 3) * (cols < circle.cx - 0.5 * circle.r)  # grazing reflections
    scene = background * (1 - ball) + ball * (0.02 + rim)
    frames = _sphere_frames(lights, circle, h, w).numpy() * ball + scene
    frames = frames + rng.normal(0, noise, frames.shape)
    return torch.from_numpy(frames.clip(0, 1))


def test_find_sphere_from_a_partial_outline():
    found = find_sphere(_ball_scene())
    assert math.hypot(found.cx - CIRCLE.cx, found.cy - CIRCLE.cy) < 0.5 and abs(found.r - CIRCLE.r) < 0.5, found
    result = sphere_directions(_ball_scene(), found)
    truth = torch.tensor(LIGHTS, dtype=torch.float64)
    assert torch.rad2deg(torch.acos((result.directions * truth).sum(-1).clamp(-1, 1))).max() < 2


def test_find_sphere_refuses_blank_frames():
    with pytest.raises(TorchspecError, match="--mask or --circle"):
        find_sphere(torch.zeros(3, 3, 40, 50, dtype=torch.float64))


def test_command_line_finds_the_sphere(tmp_path):
    for k, frame in enumerate(_ball_scene()):
        codes = (frame.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        Image.fromarray(codes).save(tmp_path / f"s.{k}.png")
    assert main(["calibrate-sphere", str(tmp_path), "-o", str(tmp_path / "dome.lp")]) == 0
    lights = read_light_file(tmp_path / "dome.lp")
    got = torch.tensor([e.direction for e in lights.entries], dtype=torch.float64)
    assert torch.rad2deg(torch.acos((got * torch.tensor(LIGHTS, dtype=torch.float64)).sum(-1).clamp(-1, 1))).max() < 2
    sidecar = json.loads((tmp_path / "dome.json").read_text())
    assert len(sidecar["lights"]) == 4 and all(light["uncertainty_deg"] > 0 for light in sidecar["lights"])


def test_chrome_sphere_found_like_its_mask(shared):
    """The shared chrome ball (a partial outline on a dark cloth): the outline found agrees with its
    mask's within 1.5 pixels, and the directions with lights.txt as well as the mask's do."""
    folder = shared("rti/chrome-sphere")
    frames = torch.stack(
        [torch.from_numpy(read_photo(folder / f"chrome.{k}.png").pixels).permute(2, 0, 1) for k in range(12)]
    )
    mask, found = circle_from_mask(folder / "chrome.mask.png"), find_sphere(frames)
    assert math.hypot(found.cx - mask.cx, found.cy - mask.cy) < 1.5 and abs(found.r - mask.r) < 1.5, (found, mask)
    truth = torch.tensor([e.direction for e in read_light_file(folder / "lights.txt").entries], dtype=torch.float64)
    angles = []
    for circle in (mask, found):
        directions = sphere_directions(frames, circle).directions
        angles.append(torch.rad2deg(torch.acos((directions * truth).sum(-1).clamp(-1, 1))).median())
    assert angles[1] < angles[0] + 0.5 and angles[0] < 2.5, angles
