"""--downsample N and --crop X,Y,W,H of torchspec import and torchspec fit: box averages of the
full frames, clipping kept, near lights moved, the scale recorded (torchspec.io.scale)."""

import json
import math
import re

import numpy as np
import pytest
import torch
from capture_cases import write_painting
from PIL import Image

from torchspec.cli import main
from torchspec.io import Capture, Frame, LightSpec, read_capture, read_svbrdf, write_capture
from torchspec.io.rti import import_rti
from torchspec.io.scale import Scale, ScaledCapture, ScaleError, reduce_image, scaled
from torchspec.model.near_lights import image_points, near_light
from torchspec.pipeline import FitConfig, MasksConfig, fit, write_fit
from torchspec.pipeline.plan import setup
from torchspec.relight import render_capture
from torchspec.start.photometric import sample_masks


def _box(frames: torch.Tensor, n: int) -> torch.Tensor:
    """``(K, C, H, W)`` -> the means of its ``n x n`` boxes, computed here another way (float64)."""
    k, c, h, w = frames.shape
    return frames.double()[:, :, : h // n * n, : w // n * n].reshape(k, c, h // n, n, w // n, n).mean((3, 5))


def test_reduce_image_is_the_box_mean_and_keeps_clipping():
    image = np.arange(5 * 7 * 2, dtype=np.float32).reshape(5, 7, 2) / 100
    image[1, 1, 0] = 1.0  # a clipped sample in channel 0 of box (0, 0)
    image[2, 5, 1] = np.nan
    out = reduce_image(image, 2, level=1.0)
    assert out.shape == (2, 3, 2) and out.dtype == np.float32
    expected = _box(torch.from_numpy(image).permute(2, 0, 1)[None], 2)[0].permute(1, 2, 0).numpy()
    assert out[0, 0, 0] == 1.0 and out[0, 0, 1] == np.float32(expected[0, 0, 1])  # clipped channel only
    assert np.isnan(out[1, 2, 1]) and not np.isnan(out[1, 2, 0])
    keep = np.ones((2, 3, 2), dtype=bool)
    keep[0, 0, 0] = keep[1, 2, 1] = False
    assert np.allclose(out[keep], expected[keep], rtol=1e-6)
    assert np.allclose(reduce_image(image, 2)[0, 0, 0], expected[0, 0, 0])  # no level: the mean
    assert np.array_equal(reduce_image(image, 1), image, equal_nan=True)


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda: Scale(0), "--downsample N must be >= 1"),
        (lambda: Scale(1.5), "--downsample N must be a whole number"),
        (lambda: Scale.parse(2, "1,2,3"), "--crop must be X,Y,W,H"),
        (lambda: Scale.parse(2, "1,2,a,4"), "--crop must be X,Y,W,H"),
        (lambda: Scale(1, (-1, 0, 4, 4)), "X, Y >= 0"),
        (lambda: Scale(1, (0, 0, 0, 4)), "W, H >= 1"),
        (lambda: Scale(1, (300, 0, 20, 10)).region(310, 200, "img.jpg"), r"--crop 300,0,20,10 .* img.jpg.* 310x200"),
        (lambda: Scale(8, (0, 0, 20, 5)).region(310, 200), "--downsample 8 is larger than --crop 0,0,20,5"),
        (lambda: Scale(400).region(310, 200), "--downsample 400 is larger than the image"),
    ],
)
def test_bad_scales_name_the_option_and_the_image_size(make, message):
    with pytest.raises(ScaleError, match=message):
        make()


def test_scale_record_and_region():
    scale = Scale.parse(3, "10, 20, 100, 50")
    assert scale.region(200, 100) == (10, 20, 99, 48) and scale.size(200, 100) == (33, 16)
    assert scale.record(200, 100) == {"downsample": 3, "crop": [10, 20, 99, 48], "full_size": [200, 100]}
    assert Scale.from_record(scale.record(200, 100)) == Scale(3, (10, 20, 99, 48))
    assert Scale().identity and not Scale(2).identity and Scale(2).region(7, 5) == (0, 0, 6, 4)


def _capture(root, frames, positions=None, irradiance=1.0):
    k, c, h, w = frames.shape
    directions = [(0.3 * math.cos(a), 0.3 * math.sin(a), math.sqrt(1 - 0.09)) for a in np.linspace(0, 6, k)]
    made = tuple(
        Frame(f"frames/{j:04d}.exr", d, irradiance, 1.0, None if positions is None else tuple(positions[j]))
        for j, d in enumerate(directions)
    )
    channels = ("R", "G", "B")[:c]
    capture = Capture(root, w, h, channels, (0.0, 0.0, 1.0), LightSpec("point"), made)
    return write_capture(root, capture, frames)


def test_a_scaled_capture_reads_the_box_average_of_its_crop(tmp_path):
    generator = torch.Generator().manual_seed(0)
    frames = torch.rand(3, 3, 9, 11, generator=generator)
    capture = _capture(tmp_path / "c", frames)
    small = scaled(capture, Scale(2, (1, 2, 9, 7)), level=None)  # the region 1,2,8,6: 4 x 3 pixels
    assert isinstance(small, ScaledCapture) and (small.width, small.height) == (4, 3)
    expected = _box(frames[:, :, 2:8, 1:9], 2)
    assert torch.allclose(small.read_frames(dtype=torch.float64), expected, rtol=1e-6)
    assert torch.allclose(small.read_frames([2], rows=(1, 3), dtype=torch.float64), expected[2:, :, 1:3], rtol=1e-6)
    assert scaled(capture, Scale()) is capture
    assert small.record() == {"downsample": 2, "crop": [1, 2, 8, 6], "full_size": [11, 9], "photographs": None}


def test_near_lights_are_seen_from_the_reduced_pixels_as_before(tmp_path):
    """After a crop, each reduced pixel sees every light from the direction, and with the
    irradiance, that the full image's pixels it averages saw at their centre."""
    frames = torch.rand(3, 1, 12, 16, generator=torch.Generator().manual_seed(1))
    positions = [(0.4, -0.3, 1.5), (-0.6, 0.2, 1.2), (0.0, 0.9, 2.0)]
    capture = _capture(tmp_path / "c", frames, positions, irradiance=2.0)
    small = scaled(capture, Scale(2, (3, 1, 10, 8)))  # 5 x 4 pixels
    moved, seen = small.positions(), image_points(4, 5)
    rows, cols = torch.arange(4, dtype=torch.float64), torch.arange(5, dtype=torch.float64)
    x = (3 + (cols + 0.5) * 2) / 16 - 0.5
    y = (12 / 2 - (1 + (rows + 0.5) * 2)) / 16
    yy, xx = torch.meshgrid(y, x, indexing="ij")
    before = torch.stack([xx, yy, torch.zeros_like(xx)], -1).reshape(-1, 3)
    d_new, f_new = near_light(moved, seen)
    d_old, f_old = near_light(capture.positions(), before)
    assert torch.allclose(d_new, d_old, atol=1e-12)
    assert torch.allclose(f_new * small.irradiance()[:, 0], f_old * capture.irradiance()[:, 0], atol=1e-12)
    centre = near_light(capture.positions(), before.mean(0, keepdim=True))[0][0]
    assert torch.allclose(small.directions(), centre, atol=1e-12)  # each frame's direction: from the new centre


def _clipped_capture(root):
    """8 x 8, 5 frames, values below 0.9 but 1.0 (the clipping level, 18 samples) in frame 0's
    pixel (1, 1) and pixel (6, 3) of every frame."""
    frames = 0.9 * torch.rand(5, 3, 8, 8, generator=torch.Generator().manual_seed(2))
    frames[0, :, 1, 1] = 1.0
    frames[:, :, 6, 3] = 1.0
    return _capture(root, frames), frames


def test_a_box_holding_a_clipped_sample_is_clipped(tmp_path):
    """The fit's saturation level, found at full size (no level recorded), masks every box holding
    a clipped sample in some channel: the max-pool of the full frames' clipped samples."""
    capture, frames = _clipped_capture(tmp_path / "c")
    job = setup(capture.root, FitConfig(model="diffuse", masks=MasksConfig(downsample=2, grow=0)), None)
    assert job.config.masks.saturation == 1.0 and job.capture.level == 1.0
    reduced = job.capture.read_frames()
    masks = sample_masks(reduced, saturation=job.config.masks.saturation, grow=0)
    clipped = (frames >= 1.0).any(1).float()
    expected = torch.nn.functional.max_pool2d(clipped[:, None], 2)[:, 0] > 0
    assert torch.equal(masks.saturated, expected) and int(expected.sum()) == 6  # frame 0: 2 boxes; others 1
    kept = ~expected[:, None].expand_as(reduced)
    assert torch.allclose(reduced[kept].double(), _box(frames, 2)[kept])
    assert torch.all(reduced[~kept] == 1.0)  # every channel of a clipped box here: its largest value, 1


def test_a_fit_at_a_downsample_is_the_fit_of_the_reduced_frames(tmp_path):
    """fit --downsample 2 --crop ... reads the frames reduced and fits them as it fits a capture
    written with those frames; svbrdf.json records the scale, and render --capture compares the
    maps with the capture read at it."""
    painting = write_painting(tmp_path / "p", size=16, seed=5, grid=5, extent=0.8, radius=0.8)
    config = FitConfig(masks=MasksConfig(downsample=2, crop=(2, 1, 13, 12)))
    result = fit(painting, config=config)
    full = read_capture(painting)
    small = scaled(full, Scale(2, (2, 1, 13, 12)))
    copy = Capture(tmp_path / "small", small.width, small.height, full.channels, full.view, full.light, full.frames)
    write_capture(copy.root, copy, small.read_frames())
    direct = fit(copy.root)
    assert result.svbrdf.shape == (6, 6)
    for name in ("normal", "diffuse", "specular", "roughness"):
        assert torch.equal(getattr(result.svbrdf, name), getattr(direct.svbrdf, name)), name
    assert torch.equal(result.model, direct.model)
    record = {"downsample": 2, "crop": [2, 1, 12, 12], "full_size": [16, 16], "photographs": None}
    assert result.stats["scale"] == record
    masks = result.stats["settings"]["masks"]
    assert masks["downsample"] == 2 and masks["crop"] == (2, 1, 13, 12)
    write_fit(tmp_path / "maps", result)
    meta = read_svbrdf(tmp_path / "maps").meta
    assert meta["fit"]["scale"]["crop"] == [2, 1, 12, 12]
    report = render_capture(tmp_path / "maps", painting, tmp_path / "relit")
    assert report["predicted"].shape == (len(full.frames), 3, 6, 6) and report["psnr_db"] > 30
    relit = read_capture(tmp_path / "relit")
    assert (relit.width, relit.height) == (6, 6) and torch.equal(relit.read_frames(), report["predicted"])
    other = write_painting(tmp_path / "q", size=12, seed=5, grid=5)
    with pytest.raises(Exception, match="fitted from a 16x16 capture at --downsample 2"):
        render_capture(tmp_path / "maps", other, None)
    from torchspec.view import open_site

    site = open_site(tmp_path / "maps", painting, cache=False)  # the page's photographs at the maps' scale
    try:
        assert (site.capture.width, site.capture.height) == (6, 6)
        assert torch.equal(site.capture.read_frames(), small.read_frames())
    finally:
        site.close()


def test_fit_command_line_scale_and_its_errors(tmp_path, capsys):
    capture, _ = _clipped_capture(tmp_path / "c")
    args = ["fit", str(capture.root), "--model", "diffuse", "--quiet"]
    assert main([*args, "-o", str(tmp_path / "m"), "--downsample", "2", "--crop", "0,2,8,6"]) == 0
    assert "pixels (of 8x8 at --downsample 2, the region 0,2,8,6) from 5 frames" in capsys.readouterr().out
    assert read_svbrdf(tmp_path / "m").svbrdf.shape == (3, 4)
    for extra, message in [
        (["--downsample", "0"], "--downsample N must be >= 1"),
        (["--crop", "4,4,8,2"], r"--crop 4,4,8,2 reaches outside the frames of .*capture.json, which is 8x8"),
        (["--crop", "4x4"], "--crop must be X,Y,W,H"),
    ]:
        assert main([*args, "-o", str(tmp_path / "x"), *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and re.search(message, err), err


def _photographs(folder, count=5, w=6, h=4):
    """``count`` 8-bit PNG photographs ``w x h`` (a 255 at pixel (0, 0): clipped) and their .lp."""
    folder.mkdir(parents=True)
    lines = [str(count)]
    for k in range(count):
        codes = np.random.default_rng(k).integers(0, 255, size=(h, w, 3), dtype=np.uint8)
        codes[0, 0] = 255
        Image.fromarray(codes).save(folder / f"img{k:02d}.png")
        a = 2 * math.pi * k / count
        lines.append(f"img{k:02d}.png {0.5 * math.cos(a)} {0.5 * math.sin(a)} {math.sqrt(0.75)}")
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")
    return folder / "dirs.lp"


@pytest.mark.parametrize("transfer", ["srgb", None])
def test_import_averages_linear_values_and_keeps_clipping(tmp_path, transfer):
    """import --downsample 2 (sRGB, or the camera response estimated from the codes at full size):
    each frame is the box average of the full import's linear frame; the box holding the clipped
    pixel reads 1 (the clipping level); source.scale records the scale."""
    lp = _photographs(tmp_path / "rti", count=7, w=8, h=6)  # enough to estimate a response
    import_rti(lp, tmp_path / "full", transfer=transfer)
    imported = import_rti(lp, tmp_path / "small", transfer=transfer, scale=Scale(2))
    whole = read_capture(tmp_path / "full")
    full = whole.read_frames(dtype=torch.float64)
    small = imported.capture.read_frames(dtype=torch.float64)
    assert small.shape == (7, 3, 3, 4)
    assert torch.allclose(small[..., 1:], _box(full, 2)[..., 1:], rtol=1e-5)
    assert torch.allclose(small[:, :, 1:, 0], _box(full, 2)[:, :, 1:, 0], rtol=1e-5)
    assert torch.all(small[:, :, 0, 0] == 1.0) and float(_box(full, 2)[:, :, 0, 0].max()) < 1.0
    source = imported.capture.extra["source"]
    assert source["scale"] == {"downsample": 2, "crop": [0, 0, 8, 6], "full_size": [8, 6]}
    assert source["saturated_pixels"] == [1] * 7 and whole.extra["source"]["scale"] is None
    assert source["transfer"] == whole.extra["source"]["transfer"] == ("srgb" if transfer else "response")
    assert source["response"] == whole.extra["source"]["response"]  # estimated from the same codes


def test_import_command_line_crop_and_its_errors(tmp_path, capsys):
    lp = _photographs(tmp_path / "rti")
    out = tmp_path / "out"
    assert main(["import", str(lp), "-o", str(out), "--transfer", "srgb", "--crop", "2,1,4,3", "--downsample", "2",
                 "--quiet"]) == 0  # fmt: skip
    assert "5 frames of 2x1 RGB (of 6x4 at --downsample 2, the region 2,1,4,2)" in capsys.readouterr().out
    capture = read_capture(out)
    assert (capture.width, capture.height) == (2, 1)
    import_rti(lp, tmp_path / "full", transfer="srgb")
    full = read_capture(tmp_path / "full").read_frames(dtype=torch.float64)
    assert torch.allclose(capture.read_frames(dtype=torch.float64), _box(full[:, :, 1:3, 2:6], 2), rtol=1e-5)
    assert json.loads(capture.manifest.read_text())["source"]["scale"]["crop"] == [2, 1, 4, 2]
    for extra, message in [
        (["--crop", "3,0,4,4"], r"--crop 3,0,4,4 reaches outside the photographs \(img00.png\), which is 6x4"),
        (["--downsample", "-1"], "--downsample N must be >= 1"),
        (["--downsample", "5"], "--downsample 5 is larger than the photographs"),
    ]:
        assert main(["import", str(lp), "-o", str(tmp_path / "x"), "--quiet", *extra]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and re.search(message, err), err
        assert not (tmp_path / "x").exists()
