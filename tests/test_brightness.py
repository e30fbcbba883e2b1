"""A frame much darker or brighter than its neighbours in light direction (torchspec.calibration.brightness),
as ``torchspec info`` reports it: flagged, named, with its ratio, as a warning."""

from __future__ import annotations

import math

import pytest
import torch

from torchspec.calibration.brightness import DARKER, MIN_ELEVATION_DEG, brightness_ratios, departures, ring_neighbours
from torchspec.cli import main
from torchspec.info import OK, WARNINGS, format_report, inspect_capture
from torchspec.io import Capture, Frame, LightSpec, write_capture
from torchspec.model.brdf import SVBRDF
from torchspec.model.lights import Kernel, Lights
from torchspec.model.rendering import render_image
from torchspec.view.check import model_maps

RINGS = (20.0, 40.0, 60.0)  # elevations of a dome's rings, degrees; 12 lights each, and one at the zenith
PER_RING = 12
DARK = 1 + PER_RING + 3  # the 40-degree ring's fourth light


def _dome() -> torch.Tensor:
    directions = [(0.0, 0.0, 1.0)]
    for ring, elevation in enumerate(RINGS):
        for j in range(PER_RING):
            azimuth, e = math.radians(360 / PER_RING * j + 10 * ring), math.radians(elevation)
            directions.append((math.cos(e) * math.cos(azimuth), math.cos(e) * math.sin(azimuth), math.sin(e)))
    return torch.tensor(directions, dtype=torch.float64)


def _capture(folder, gain: dict[int, float] | None = None, directions: torch.Tensor | None = None, model="diffuse"):
    """A 16 x 16 surface of ``model`` (a relief: normals tilted up to 12 degrees) under the dome's 37 point lights,
    each frame at its own exposure and irradiance (rendered so), frame ``k`` then times ``gain[k]``:
    a flash that fired weakly or strongly."""
    directions = _dome() if directions is None else directions
    count = len(directions)
    exposure = torch.linspace(0.5, 2.0, count, dtype=torch.float64)
    irradiance = torch.linspace(3.0, 1.0, count, dtype=torch.float64)[:, None].expand(count, 3)
    svbrdf = model_maps(model, 16, 16, seed=3).svbrdf.to(torch.float64)
    normal = svbrdf.normal + torch.tensor([0.0, 0.0, 2.0], dtype=torch.float64)  # tilts of a relief: up to 12 degrees
    svbrdf = SVBRDF(normal / normal.norm(dim=-1, keepdim=True), svbrdf.diffuse, svbrdf.specular, svbrdf.roughness)
    lights = Lights(directions, Kernel("point"), irradiance, exposure)
    values = render_image(svbrdf, lights, torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    values = values.permute(2, 3, 0, 1).clone()  # (K, C, H, W)
    for k, factor in (gain or {}).items():
        values[k] *= factor
    frames = [
        Frame(f"f{k:02d}.exr", tuple(directions[k].tolist()), tuple(irradiance[k].tolist()), float(exposure[k]))
        for k in range(count)
    ]
    capture = Capture(folder, 16, 16, ("R", "G", "B"), (0.0, 0.0, 1.0), LightSpec("point"), frames)
    return write_capture(folder, capture, values.float())


def _ratios(report) -> list[float | None]:
    return [row["brightness"]["ratio"] if row["brightness"] else None for row in report["per_frame"]]


def test_neighbours_are_the_ring_first():
    neighbours, judged = ring_neighbours(_dome())
    assert bool(judged.all())
    # the 40-degree ring's light 4 (index 12): its two ring neighbours first, then the two nearest
    # of the rings above and below (a degree of elevation counts three along the ring)
    assert sorted(neighbours[DARK, :2].tolist()) == [DARK - 1, DARK + 1]
    low = torch.tensor([[math.cos(math.radians(5)), 0.0, math.sin(math.radians(5))]], dtype=torch.float64)
    neighbours, judged = ring_neighbours(torch.cat([_dome(), low]))
    assert not bool(judged[-1]) and neighbours[-1].tolist() == [-1] * 4  # 5 degrees: not judged
    assert 37 not in neighbours[:37].flatten().tolist()  # nor anyone's neighbour
    assert not bool(ring_neighbours(_dome()[:4])[1].any())  # 4 frames: none judged


@pytest.mark.parametrize(("model", "spread"), [("diffuse", 0.01), ("ward-iso", 0.5)])
def test_a_frame_40_percent_darker_than_its_ring_is_flagged_by_info(tmp_path, model, spread):
    """Matte, the frames' ratios are 1 within 1 %; glossy, the highlight makes the zenith's frame 1.45
    times its neighbours (on the 60-degree ring), the others 1 within 2 %: none flagged; then the
    darkened frame is, and only it."""
    clean = inspect_capture(_capture(tmp_path / "clean", model=model).root)
    assert clean["verdict"] == OK and clean["warnings"] == [] and clean["brightness"]["flagged"] == []
    ratios = _ratios(clean)
    print(f"unmodified dome, {model}: ratios {min(ratios):.3f} .. {max(ratios):.3f}")
    assert all(abs(ratio - 1) < spread for ratio in ratios), ratios  # exposure and irradiance taken out

    dark = inspect_capture(_capture(tmp_path / "dark", {DARK: 0.6}, model=model).root)
    assert dark["verdict"] == WARNINGS and dark["reason"] is None  # usable: a warning
    assert dark["brightness"]["flagged"] == [DARK]
    # the frame's pixels are 0.6 times what they were; its neighbours' are unchanged
    assert _ratios(dark)[DARK] == pytest.approx(0.6 * ratios[DARK], rel=1e-6)
    (warning,) = dark["warnings"]
    neighbours = ", ".join(map(str, dark["per_frame"][DARK]["brightness"]["neighbours"]))
    darker = f"{100 * (1 - 0.6 * ratios[DARK]):.0f} % darker"
    assert darker == "40 % darker" or model != "diffuse"
    assert warning.startswith(
        f"frames[{DARK}] f{DARK}.exr is {darker} than its neighbours in light direction (frames {neighbours}): "
        f"{0.6 * ratios[DARK]:.2f} times their brightness"
    ), warning
    assert "leave it out (torchspec fit --frames)" in warning
    assert f"departing: frames {DARK}" in format_report(dark)


def test_a_frame_three_times_as_bright_is_flagged_and_a_third_darker_is_not(tmp_path):
    report = inspect_capture(_capture(tmp_path / "c", {3: 3.0, 20: 0.75}).root)
    assert report["brightness"]["flagged"] == [3]
    ratio = _ratios(report)[3]
    assert ratio == pytest.approx(3.0, rel=0.03)
    assert f"frames[3] f03.exr is {ratio:.2f} times as bright as its neighbours" in report["warnings"][0]
    assert 0.7 < _ratios(report)[20] < 0.8 and 0.75 > DARKER  # 25 % darker: within the capture's own spread


def test_neighbours_that_disagree_judge_no_one():
    """About a mirror's highlight the frames differ a hundredfold: none is flagged."""
    directions = _dome()
    values = directions[:, 2:].expand(-1, 64).clone()  # a matte surface facing the camera: cos(theta)
    values[DARK] *= 0.5  # a dark frame among agreeing neighbours: flagged
    assert departures(brightness_ratios(values, directions)) == [DARK]
    neighbours, _ = ring_neighbours(directions)
    values[neighbours[DARK, :2]] = torch.tensor([[30.0], [0.02]], dtype=torch.float64)  # its neighbours disagree
    ratios = brightness_ratios(values, directions)
    assert float(ratios["spread"][DARK]) > 1.25 and DARK not in departures(ratios)


def test_info_says_why_frames_are_not_compared(tmp_path, capsys):
    low = torch.tensor(
        [[math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)]
         for e, a in ((math.radians(5), 0.3 * j) for j in range(6))],
        dtype=torch.float64,
    )  # fmt: skip
    capture = _capture(tmp_path / "low", directions=low)
    report = inspect_capture(capture.root)
    assert report["brightness"]["judged"] == 0 and all(row["brightness"] is None for row in report["per_frame"])
    assert main(["info", str(capture.root), "--quiet"]) == 0
    assert (
        "bright    frames not compared with their neighbours in light direction: fewer than 5 frames "
        f"{MIN_ELEVATION_DEG:g} deg or more above the horizon"
    ) in capsys.readouterr().out
