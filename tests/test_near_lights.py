"""Near lights (torchspec.model.near_lights, the manifest's frame positions, the fit in blocks): geometry
against hand-computed cases, the block order as a permutation, and a fit of a Lambertian capture
lit by a dome of near lights against the same fit that takes the lights as distant."""

from __future__ import annotations

import math
import re
from dataclasses import replace

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from torchspec.io import Capture, Frame, LightSpec, read_capture, write_capture
from torchspec.io.capture import CaptureError
from torchspec.model.geometry import angle
from torchspec.model.near_lights import block_order, image_points, near_light
from torchspec.model.rendering import TILE_PIXELS
from torchspec.pipeline import FitConfig, QuadratureConfig, TermConfig, fit
from torchspec.pipeline.tiling import BLOCK_ANGLE, LEAST_BLOCK, near_block, tiling_of

D = torch.float64
DIFFUSE = FitConfig(model="diffuse", quadrature=QuadratureConfig(compile=False))
"""The fits of this file: diffuse, uncompiled (small captures)."""


def test_image_points_follow_the_format():
    points = image_points(2, 4)
    assert torch.allclose(points[0], torch.tensor([-0.375, 0.125, 0.0], dtype=D))  # row 0, column 0: top left
    assert torch.allclose(points[7], torch.tensor([0.375, -0.125, 0.0], dtype=D))


def test_near_light_by_hand():
    directions, falloff = near_light(
        torch.tensor([[0.0, 0.0, 2.0]], dtype=D), torch.tensor([[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]], dtype=D)
    )
    assert torch.allclose(directions[0, 0], torch.tensor([0.0, 0.0, 1.0], dtype=D))
    assert torch.allclose(directions[1, 0], torch.tensor([-1.0, 0.0, 1.0], dtype=D) / math.sqrt(2))
    assert torch.allclose(falloff[:, 0], torch.tensor([1.0, 0.5], dtype=D))  # |p|^2 / |p - x|^2 = 4 / 8


@given(st.integers(1, 23), st.integers(1, 23), st.integers(1, 9))
@settings(max_examples=60, deadline=None)
def test_block_order_is_a_permutation_of_compact_blocks(height, width, block):
    order = block_order(height, width, block)
    assert torch.equal(torch.sort(order).values, torch.arange(height * width))
    positions = torch.ones(4, 3, dtype=D)
    tiling = tiling_of(height, width, block * block, positions)
    assert tiling.ranges[-1][1] == height * width
    side = near_block(height, width, TILE_PIXELS, positions)  # render's blocks, whatever the fit's tile
    for first, stop in tiling.ranges:  # each tile spans at most a block's rows and columns
        rows, cols = tiling.order[first:stop] // width, tiling.order[first:stop] % width
        assert int(rows.max() - rows.min()) < max(side, 8) and int(cols.max() - cols.min()) < max(side, 8)


@given(st.floats(1.2, 40.0), st.integers(8, 96), st.integers(8, 96), st.sampled_from([64, 256, 1024, 4096, 1 << 16]))
@settings(max_examples=40, deadline=None)
def test_a_fit_takes_the_blocks_its_render_takes(radius, height, width, tile):
    """Under near lights a fit of any tile size is cut into the blocks torchspec render lights
    (torchspec.relight.render_near: TILE_PIXELS), so each pixel is rendered under the lights its
    maps and residual term were fitted under."""
    positions = radius * torch.tensor([[0.6, 0.0, 0.8], [0.0, -0.6, 0.8], [0.0, 0.0, 1.0]], dtype=D)
    fitted, rendered = tiling_of(height, width, tile, positions), tiling_of(height, width, TILE_PIXELS, positions)
    assert fitted.ranges == rendered.ranges and torch.equal(fitted.order, rendered.order)


@given(st.floats(1.2, 40.0), st.integers(8, 48), st.integers(8, 48), st.integers(0, 2**31 - 1))
@settings(max_examples=40, deadline=None)
def test_blocks_hold_each_light_within_the_block_angle(radius, height, width, seed):
    """Brute force over every pixel: under near lights each block's pixels see every light within
    BLOCK_ANGLE (x sqrt 2, the block's half diagonal against its half side) of the direction at the
    block's centre, unless the block is LEAST_BLOCK wide; a farther dome takes larger blocks."""
    generator = torch.Generator().manual_seed(seed)
    up = torch.rand(12, generator=generator, dtype=D) * 1.3 + 0.2  # elevations 11-86 degrees
    around = torch.rand(12, generator=generator, dtype=D) * 2 * math.pi
    positions = radius * torch.stack([up.cos() * around.cos(), up.cos() * around.sin(), up.sin()], 1)
    tiling = tiling_of(height, width, 4096, positions)
    worst = 0.0
    for first, stop in tiling.ranges if near_block(height, width, 4096, positions) > LEAST_BLOCK else []:
        points = tiling.points[tiling.order[first:stop]]
        at_centre, _ = near_light(positions, points.mean(0, keepdim=True))
        at_pixels, _ = near_light(positions, points)
        cos = (at_pixels * at_centre).sum(-1).clamp(max=1.0)
        worst = max(worst, float(torch.acos(cos).max()))
    assert worst <= math.sqrt(2) * BLOCK_ANGLE * 1.01
    sizes = [stop - first for first, stop in tiling.ranges]
    farther = tiling_of(height, width, 4096, 4 * positions)
    assert max(stop - first for first, stop in farther.ranges) >= max(sizes)


def _dome(radius: float) -> torch.Tensor:
    out = []
    for elevation in (25.0, 45.0, 65.0):
        for a in range(8):
            e, phi = math.radians(elevation), 2 * math.pi * (a + elevation / 90) / 8
            out.append([math.cos(e) * math.cos(phi), math.cos(e) * math.sin(phi), math.sin(e)])
    out.append([0.0, 0.0, 1.0])
    return torch.tensor(out, dtype=D) * radius


def _lambertian_near_capture(root, radius: float, size: int = 32) -> tuple[Capture, torch.Tensor]:
    """A Lambertian relief lit by point lights at ``radius`` image widths: rendered per pixel."""
    torch.manual_seed(0)
    positions = _dome(radius)
    points = image_points(size, size)
    y, x = points[:, 1], points[:, 0]
    normal = torch.stack([0.3 * torch.sin(9 * x), 0.25 * torch.cos(7 * y), torch.ones_like(x)], -1)
    normal = normal / normal.norm(dim=-1, keepdim=True)
    albedo = 0.5 + 0.3 * torch.rand(points.shape[0], 1, dtype=D)
    directions, falloff = near_light(positions, points)
    value = albedo / math.pi * (directions * normal[:, None]).sum(-1).clamp(min=0) * falloff  # (N, K)
    frames = value.T.reshape(-1, 1, size, size)
    unit = positions / positions.norm(dim=-1, keepdim=True)
    capture = Capture(
        root=root,
        width=size,
        height=size,
        channels=("Y",),
        view=(0.0, 0.0, 1.0),
        light=LightSpec(kernel="point"),
        frames=tuple(
            Frame(f"f{k:02d}.exr", tuple(unit[k].tolist()), (1.0,), 1.0, position=tuple(positions[k].tolist()))
            for k in range(len(positions))
        ),
    )
    return write_capture(root, capture, frames.float()), normal.reshape(size, size, 3)


def test_a_fit_under_near_lights_recovers_the_normals_that_distant_lights_bend(tmp_path):
    capture, truth = _lambertian_near_capture(tmp_path / "near", radius=3.0)
    assert read_capture(capture.root).positions() is not None
    near = fit(capture, config=DIFFUSE)
    distant_capture = write_capture(
        tmp_path / "distant",
        Capture(
            **{
                **capture.__dict__,
                "root": tmp_path / "distant",
                "frames": tuple(Frame(f.file, f.direction, f.irradiance, f.exposure) for f in capture.frames),
            }
        ),
        capture.read_frames(),
    )
    distant = fit(distant_capture, config=DIFFUSE)
    error_near = torch.rad2deg(angle(near.svbrdf.normal.double(), truth)).median()
    error_distant = torch.rad2deg(angle(distant.svbrdf.normal.double(), truth)).median()
    # Within a block (4 pixels of 32: tiling's LEAST_BLOCK) the lights' directions vary by up to
    # +-1.2 degrees about the block's centre, at which the block is fitted: the normals err by about as
    # much; taken as distant, by the lights' direction's whole variation over the image (+-10 degrees).
    assert float(error_near) < 2.0 and float(error_distant) > 5 * float(error_near)


def test_positions_must_be_given_for_every_frame_or_none(tmp_path):
    capture, _ = _lambertian_near_capture(tmp_path / "near", radius=3.0, size=8)
    import json

    data = json.loads(capture.manifest.read_text())
    del data["frames"][3]["position"]
    capture.manifest.write_text(json.dumps(data))
    with pytest.raises(CaptureError, match=r"frames\[3\]\.position"):
        read_capture(capture.root)
    data["frames"][3]["position"] = [0.1, 0.2, -1.0]
    capture.manifest.write_text(json.dumps(data))
    with pytest.raises(CaptureError, match=r"frames\[3\]\.position.*z > 0"):
        read_capture(capture.root)


def _lambertian_with_gains(
    root, gains: torch.Tensor, scramble: float = 0.0, radius: float = 1e4
) -> tuple[Capture, torch.Tensor]:
    """A Lambertian relief whose frames' intensities are ``gains``, lit by lights at ``radius``
    (distant by default) and written as directions only (the manifest lists its irradiance as
    unknown and writes 1); ``scramble``: a random factor per sample that no reflectance explains."""
    capture, normal = _lambertian_near_capture(root / "near", radius=radius, size=24)
    frames = capture.read_frames(dtype=D) * gains[:, None, None, None]
    if scramble:
        generator = torch.Generator().manual_seed(1)
        frames = frames * (1 + scramble * torch.rand(frames.shape, generator=generator, dtype=D))
    flat = Capture(
        **{
            **capture.__dict__,
            "root": root / "gains",
            "frames": tuple(Frame(f.file, f.direction, f.irradiance, f.exposure) for f in capture.frames),
            "extra": {"unknown": ["irradiance"]},
        }
    )
    return write_capture(root / "gains", flat, frames.float()), normal


def test_unknown_irradiance_is_calibrated_from_the_photographs(tmp_path):
    gains = 1 + 0.3 * (2 * torch.rand(25, generator=torch.Generator().manual_seed(2), dtype=D) - 1)
    capture, truth = _lambertian_with_gains(tmp_path, gains)
    assert read_capture(capture.root).unknown == ("irradiance",)
    calibrated = fit(capture, config=DIFFUSE)
    nominal = fit(capture, config=replace(DIFFUSE, calibrate="none"))
    record = calibrated.stats["lights"]
    assert record["calibrated"] == ["irradiance"] and nominal.stats["lights"] is None
    assert record["judged_pixels"] == capture.width * capture.height and record["explained_share"] > 0.8
    found = torch.tensor(record["gains"], dtype=D)[:, 0]
    expected = gains / gains.log().mean().exp()  # the estimate's gauge: geometric mean 1
    assert float(((found - expected) / expected).abs().max()) < 0.01  # noise-free: the clamp's edge only
    error = torch.rad2deg(angle(calibrated.svbrdf.normal.double(), truth)).median()
    assert float(error) < 0.5 < float(torch.rad2deg(angle(nominal.svbrdf.normal.double(), truth)).median())


def test_lights_the_photographs_do_not_determine_are_kept_with_a_warning(tmp_path):
    from torchspec.pipeline import FitWarning

    capture, _ = _lambertian_with_gains(tmp_path, torch.ones(25, dtype=D), scramble=0.8)
    with pytest.warns(FitWarning, match="not calibrated from the photographs") as caught:
        result = fit(capture, config=DIFFUSE)
    assert result.stats["lights"]["calibrated"] == []
    # The warning keeps its figures and says what they mean and what the user can do.
    message = str(next(w.message for w in caught if "not calibrated" in str(w.message)))
    assert re.search(r"explains \d+ % of the pixels with a median relative misfit of [\d.]+ % per frame", message)
    assert "calibrating needs at least 80 % and at most 5 %" in message and "gloss, shadows or relief" in message
    assert "Nothing needs doing if every frame was lit alike" in message and "pass --calibrate gains" in message
    assert message == result.stats["lights"]["refused"]


def test_auto_keeps_a_dome_radius_the_photographs_show_where_it_refuses_their_gains(tmp_path):
    """A dome at 3 widths written as directions, with a scramble no reflectance explains: the gains
    are refused (the misfit is above CALIBRATION_RMS) but the dome's radius, one number that the
    change of the lights' directions across the image shows, is kept with the irradiance as written;
    the normals then err far less than under the lights as written."""
    from torchspec.pipeline import FitWarning

    capture, truth = _lambertian_with_gains(tmp_path, torch.ones(25, dtype=D), scramble=0.3, radius=3.0)
    with pytest.warns(FitWarning, match="taken at the dome radius 3"):
        auto = fit(capture, config=DIFFUSE)
    record = auto.stats["lights"]
    assert record["calibrated"] == ["radius"] and record["radius"] == 3.0 and "refused" in record
    written = fit(capture, config=replace(DIFFUSE, calibrate="none"))
    error = torch.rad2deg(angle(auto.svbrdf.normal.double(), truth)).median()
    assert 3 * float(error) < float(torch.rad2deg(angle(written.svbrdf.normal.double(), truth)).median())


def test_auto_keeps_no_dome_radius_that_only_refitted_gains_show(tmp_path):
    """The same dome with frame intensities spread as a real dome's (log-normal, sigma 0.8): with the
    gains refitted a dome radius shows, but under the irradiance as written none does;
    where auto refuses the gains it takes the lights as written, distant, not at that radius."""
    from torchspec.calibration.lights import calibrate_lights
    from torchspec.pipeline import FitWarning

    gains = (0.8 * torch.randn(25, generator=torch.Generator().manual_seed(4), dtype=D)).exp()
    capture, _ = _lambertian_with_gains(tmp_path, gains, scramble=0.3, radius=3.0)
    frames = read_capture(capture.root).read_frames(dtype=D)
    found = calibrate_lights(frames, read_capture(capture.root).directions(), dome=True)
    assert found.radius is not None and found.radius_as_written is None
    with pytest.warns(FitWarning, match="taken as written"):
        auto = fit(capture, config=DIFFUSE)
    assert auto.stats["lights"]["calibrated"] == [] and auto.stats["lights"].get("radius") is None


def test_a_cluster_fit_refuses_lights_it_cannot_handle(tmp_path):
    """Near lights and lights to calibrate are fitted in one process: a cluster fit says so
    before any work (the client is not touched)."""
    from torchspec.errors import TorchspecError
    from torchspec.pipeline import fit_on_cluster

    near, _ = _lambertian_near_capture(tmp_path / "dome", radius=3.0, size=8)
    with pytest.raises(TorchspecError, match="near-light positions.*one process"):
        fit_on_cluster(near, None, checkpoint=tmp_path / "tiles")
    unknown, _ = _lambertian_with_gains(tmp_path, torch.ones(25, dtype=D))
    with pytest.raises(TorchspecError, match="calibrated from the photographs.*--calibrate none"):
        fit_on_cluster(unknown, None, checkpoint=tmp_path / "tiles")


def test_render_of_a_near_light_capture_follows_each_block_lights(tmp_path):
    """``torchspec render`` of the true maps of a near-light capture predicts its frames block by
    block under the lights seen from each block's centre (torchspec.relight.render_near): within
    what a block's spread of directions leaves, far closer than the lights taken as distant."""
    from torchspec.io import write_svbrdf
    from torchspec.model.brdf import SVBRDF
    from torchspec.relight import render_capture, render_near

    capture, normal = _lambertian_near_capture(tmp_path / "near", radius=3.0, size=32)
    frames = capture.read_frames(dtype=D)
    albedo = frames.new_zeros(32, 32, 1)
    # the albedo back from the zenith frame (last): value = albedo / pi * cos * falloff
    zenith = torch.tensor([0.0, 0.0, 3.0], dtype=D)
    directions, falloff = near_light(zenith[None], image_points(32, 32))
    cos = (directions[:, 0] * normal.reshape(-1, 3)).sum(-1)
    albedo[..., 0] = (frames[-1, 0].reshape(-1) * math.pi / (cos * falloff[:, 0])).reshape(32, 32)
    zeros = torch.zeros(32, 32, 1, dtype=D)
    maps = SVBRDF(normal, albedo, zeros, torch.zeros(32, 32, 2, dtype=D), channels=("Y",))
    write_svbrdf(tmp_path / "maps", maps.to(torch.float32))
    near = render_capture(tmp_path / "maps", capture.root, None, dtype=D)
    lights = capture.lights(dtype=D)
    distant = render_near(maps, lights, lights.directions * 1e6, torch.tensor([0.0, 0.0, 1.0], dtype=D))
    distant_psnr = -10 * math.log10(
        float((distant.permute(2, 3, 0, 1) - frames).pow(2).mean()) / float(frames.max()) ** 2
    )
    assert near["psnr_db"] > 35 and near["psnr_db"] > distant_psnr + 10  # measured: 39.9 dB, 21.7 distant


def test_a_near_light_fit_carries_its_residual_term_across_blocks(tmp_path):
    """The residual term of each block joins into one image-wide term (its weight too)."""
    capture, _ = _lambertian_near_capture(tmp_path / "near", radius=3.0, size=16)
    result = fit(capture, config=replace(DIFFUSE, term=TermConfig(order=2)))
    assert result.term.coefficients.shape == (16, 16, 4, 1) and result.term.weight.shape == (16, 16)
    assert bool(((result.term.weight >= 0) & (result.term.weight <= 1)).all())
