from __future__ import annotations

import json
import warnings
from dataclasses import replace

import numpy as np
import pytest
import torch
from capture_cases import DATA, H, W, edit_manifest, needs_data, random_frames, small_capture

import torchspec.io.capture as capture_module
from torchspec.io import (
    Capture,
    CaptureError,
    LightSpec,
    read_capture,
    read_exr,
    read_svbrdf,
    write_capture,
    write_exr,
)
from torchspec.model.brdf import SVBRDF


def _capture(root=".", light=None, count=3, channels=("R", "G", "B")) -> Capture:
    return small_capture(root, light, count, channels)


def _frames(count=3, channels=3, seed=0):
    return random_frames(count, channels, seed)


@pytest.fixture
def written(tmp_path):
    """A small capture on disk and the frames written."""
    frames = _frames()
    return write_capture(tmp_path / "cap", _capture(), frames), frames


# --- round trips -----------------------------------------------------------------------------------


def test_round_trip(written):
    capture, frames = written
    back = read_capture(capture.root)
    assert back == capture
    assert back.frames[1].irradiance == (2.0, 2.0, 2.0)
    assert back.light == LightSpec("gaussian", domain="projected", sigma=0.05)
    assert torch.equal(back.read_frames(), frames)
    assert torch.equal(back.read_frames([2, 0]), frames[[2, 0]])
    assert torch.equal(back.read_frames([-1]), frames[[2]])
    read = back.read_frames(dtype=torch.float64)
    assert read.dtype == torch.float64 and read.shape == (3, 3, H, W)
    directions = back.directions()
    assert directions.dtype == torch.float64 and directions.shape == (3, 3)
    assert torch.allclose(directions.norm(dim=-1), torch.ones(3, dtype=torch.float64))
    assert torch.equal(back.irradiance(), torch.tensor([[1.0] * 3, [2.0] * 3, [3.0] * 3], dtype=torch.float64))
    assert torch.equal(back.exposure(), torch.tensor([0.5, 1.0, 1.5], dtype=torch.float64))


def test_round_trip_of_per_channel_irradiance_extra_keys_kernel_and_truth(tmp_path):
    light = LightSpec("tabulated", file="light/kernel.exr", extent=0.2)
    capture = _capture(light=light, count=2, channels=("Y",))
    frames = (replace(capture.frames[0], irradiance=(3.0,)), capture.frames[1])
    capture = replace(capture, frames=frames, extra={"generator": {"tool": "test", "seed": 3}, "notes": "x"})
    kernel = torch.rand(9, 9) + 0.1
    truth = SVBRDF(
        normal=torch.tensor([0.0, 0.0, 1.0]).expand(H, W, 3),
        diffuse=torch.rand(H, W, 1),
        specular=torch.zeros(H, W, 1),
        roughness=torch.zeros(H, W, 2),
        channels=("Y",),
    )
    written = write_capture(tmp_path, capture, _frames(2, 1).numpy(), kernel=kernel, truth=truth)
    assert written.root == tmp_path
    with pytest.warns(UserWarning, match=r"unknown top-level key\(s\) \['notes'\]"):  # "generator" is known
        back = read_capture(tmp_path / "capture.json")
    assert back == written and back.extra == {"generator": {"tool": "test", "seed": 3}, "notes": "x"}
    assert back.frames[0].irradiance == (3.0,)
    assert torch.equal(back.read_kernel(), kernel)
    assert read_svbrdf(tmp_path / "truth").svbrdf.channels == ("Y",)
    # written again from the capture read, the tabulated kernel is copied along
    again = write_capture(tmp_path / "copy", back, back.read_frames())
    assert torch.equal(again.read_kernel(), kernel)


def test_per_channel_irradiance_is_kept(tmp_path):
    capture = _capture()
    capture = replace(capture, frames=(replace(capture.frames[0], irradiance=(1.0, 2.0, 4.0)),) + capture.frames[1:])
    write_capture(tmp_path, capture, _frames())
    assert json.loads((tmp_path / "capture.json").read_text())["frames"][0]["irradiance"] == [1.0, 2.0, 4.0]
    assert read_capture(tmp_path).frames[0].irradiance == (1.0, 2.0, 4.0)


# --- manifest errors -------------------------------------------------------------------------------


def _set(path, value):
    def edit(manifest):
        *parents, last = path
        target = manifest
        for key in parents:
            target = target[key]
        if value is _DELETE:
            del target[last]
        else:
            target[last] = value

    return edit


_DELETE = object()

MANIFEST_ERRORS = {
    "format": (_set(["format"], "other"), r"capture\.json: format must be 'torchspec\.capture'"),
    "version": (_set(["version"], 2), r"capture\.json: version must be a supported version \(1\); got 2"),
    "version-float": (_set(["version"], 1.0), r"version must be a supported version"),
    "missing-width": (
        _set(["width"], _DELETE),
        r"capture\.json: the manifest must have the keys .*\['width'\] missing",
    ),
    "width-zero": (_set(["width"], 0), r"width must be a positive integer; got 0"),
    "height-float": (_set(["height"], 4.0), r"height must be a positive integer; got 4\.0"),
    "channels-empty": (_set(["channels"], []), r"channels must be a non-empty list of distinct channel names"),
    "channels-repeated": (_set(["channels"], ["R", "R", "B"]), r"channels must be .*distinct"),
    "camera-model": (_set(["camera", "model"], "perspective"), r"camera\.model must be \"orthographic\""),
    "camera-view": (_set(["camera", "view"], [0, 0, 2]), r"camera\.view must be a unit vector"),
    "light-kernel": (_set(["light", "kernel"], "laser"), r"light\.kernel must be one of \['point'"),
    "light-sigma-missing": (_set(["light", "sigma"], _DELETE), r"light\.sigma must be given for kernel 'gaussian'"),
    "light-sigma": (_set(["light", "sigma"], -0.1), r"light\.sigma must be a positive number; got -0\.1"),
    "light-domain": (_set(["light", "domain"], "solid"), r"light\.domain must be one of \['projected', 'angular'\]"),
    "light-extent": (
        _set(["light"], {"kernel": "tabulated", "file": "k.exr", "extent": 0}),
        r"light\.extent must be a positive number",
    ),
    "light-symmetric": (
        _set(["light"], {"kernel": "unknown", "symmetric": False}),
        r"light\.symmetric must be true",
    ),
    "frames-empty": (_set(["frames"], []), r"frames must be a non-empty list"),
    "frame-key": (_set(["frames", 1, "exposure"], _DELETE), r"frames\[1\] must have the keys .*\['exposure'\] missing"),
    "direction-length": (_set(["frames", 1, "direction"], [0, 1]), r"frames\[1\]\.direction must be a list of 3"),
    "direction-nan": (_set(["frames", 1, "direction"], [0, float("nan"), 1]), r"frames\[1\]\.direction must be"),
    "direction-norm": (_set(["frames", 2, "direction"], [0, 0, 0.9]), r"frames\[2\]\.direction must be a unit vector"),
    "direction-below": (
        _set(["frames", 2, "direction"], [0.6, 0, -0.8]),
        r"frames\[2\]\.direction must point above the surface \(z > 0\)",
    ),
    "direction-horizon": (_set(["frames", 0, "direction"], [1, 0, 0]), r"frames\[0\]\.direction must point above"),
    "irradiance": (_set(["frames", 1, "irradiance"], -1), r"frames\[1\]\.irradiance must be a positive number"),
    "irradiance-bool": (_set(["frames", 1, "irradiance"], True), r"frames\[1\]\.irradiance must be a positive number"),
    "irradiance-count": (
        _set(["frames", 1, "irradiance"], [1, 2]),
        r"frames\[1\]\.irradiance must be a number or one number per channel \(3\)",
    ),
    "irradiance-channel": (
        _set(["frames", 1, "irradiance"], [1, -2, 1]),
        r"frames\[1\]\.irradiance\[1\] must be a positive number",
    ),
    "exposure": (_set(["frames", 0, "exposure"], 0), r"frames\[0\]\.exposure must be a positive number; got 0"),
    "file-type": (_set(["frames", 0, "file"], 7), r"frames\[0\]\.file must be a file name"),
    "file-absolute": (_set(["frames", 0, "file"], "/tmp/x.exr"), r"frames\[0\]\.file must be a path relative"),
    "file-twice": (
        _set(["frames", 2, "file"], "./frames/0000.exr"),
        r"frames\[2\]\.file must differ from every other frame's file \(frames\[0\]\.file\)",
    ),
    "frame-missing": (_set(["frames", 1, "file"], "frames/gone.exr"), r"frames\[1\]\.file must exist.*gone\.exr"),
}


@pytest.mark.parametrize("edit, message", MANIFEST_ERRORS.values(), ids=MANIFEST_ERRORS.keys())
def test_manifest_errors_name_file_and_key(written, edit, message):
    capture, _ = written
    edit_manifest(capture.root, edit)
    with pytest.raises(CaptureError, match=message) as info:
        read_capture(capture.root)
    assert str(capture.manifest) in str(info.value)


def test_missing_manifest(tmp_path):
    with pytest.raises(CaptureError, match=r"capture\.json must exist; got no such file"):
        read_capture(tmp_path)


def test_manifest_not_json(tmp_path):
    (tmp_path / "capture.json").write_text('{"format": "torchspec.capture",\n "version": 1,,}')
    with pytest.raises(CaptureError, match=r"capture\.json must be valid JSON; got .* at line 2 column 15"):
        read_capture(tmp_path)


def test_first_missing_frame_is_named(written):
    capture, _ = written
    (capture.root / "frames" / "0002.exr").unlink()
    (capture.root / "frames" / "0001.exr").unlink()
    with pytest.raises(CaptureError, match=r"frames\[1\]\.file must exist; got 'frames/0001\.exr'"):
        read_capture(capture.root)


def test_near_unit_direction_is_renormalised_with_a_warning(written):
    capture, _ = written
    # frames[0] is the one at (0, 0, 1): another frame there would repeat its light direction
    edit_manifest(capture.root, _set(["frames", 0, "direction"], [0.0, 0.0, 1.0005]))
    with pytest.warns(UserWarning, match=r"frames\[0\]\.direction has norm 1\.0005.*renormalised"):
        back = read_capture(capture.root)
    assert back.frames[0].direction == (0.0, 0.0, 1.0)


def test_unknown_keys_warn(written):
    capture, _ = written

    def edit(manifest):
        manifest["notes"] = "hi"
        manifest["frames"][2]["gain"] = 2
        manifest["light"]["radius"] = 1
        manifest["camera"]["fov"] = 3

    edit_manifest(capture.root, edit)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        back = read_capture(capture.root)
    messages = " | ".join(str(w.message) for w in caught)
    for expected in ["['notes'] are kept", r"['gain'] in frames[2]", "['radius'] in light", "['fov'] in camera"]:
        assert expected in messages, messages
    assert back.extra == {"notes": "hi"}


# --- frames ----------------------------------------------------------------------------------------


def test_frame_of_the_wrong_size(written):
    capture, _ = written
    write_exr(capture.root / "frames" / "0001.exr", np.zeros((H, W + 1, 3)), ["R", "G", "B"])
    capture.read_frames([0])  # the others are fine
    with pytest.raises(CaptureError, match=r"frames\[1\] .*0001\.exr must be 4x5 \(height x width.*got 4x6"):
        capture.read_frames()


def test_frame_with_nan_and_inf_pixels(written):
    capture, frames = written
    image = frames[2].permute(1, 2, 0).clone()
    image[0, 0, 1] = float("nan")
    image[1, 2] = float("inf")
    write_exr(capture.root / "frames" / "0002.exr", image, ["R", "G", "B"])
    with pytest.raises(CaptureError, match=r"frames\[2\] .*0002\.exr must be finite; got 2 pixel\(s\) with NaN or Inf"):
        capture.read_frames()


def test_frame_without_a_channel(written):
    capture, _ = written
    write_exr(capture.root / "frames" / "0000.exr", np.zeros((H, W, 2)), ["R", "G"])
    with pytest.raises(
        CaptureError,
        match=r"frames\[0\] \(an EXR.*0000\.exr must have channel\(s\) \['B'\]; it has \['R', 'G'\]",
    ):
        capture.read_frames()


def test_truncated_frame(written):
    capture, _ = written
    file = capture.root / "frames" / "0001.exr"
    file.write_bytes(file.read_bytes()[: file.stat().st_size // 2])
    with pytest.raises(CaptureError, match=r"frames\[1\] \(an EXR.*0001\.exr.*truncated"):
        capture.read_frames()


def test_frame_index_out_of_range(written):
    capture, _ = written
    with pytest.raises(CaptureError, match=r"frame index must be in \[0, 3\).*got 3"):
        capture.read_frames([3])


def test_read_kernel_needs_a_tabulated_light(written):
    capture, _ = written
    with pytest.raises(CaptureError, match=r"light\.kernel must be 'tabulated' to read a kernel image; got 'gaussian'"):
        capture.read_kernel()


def test_bad_kernel_file(tmp_path):
    capture = _capture(light=LightSpec("tabulated", file="kernel.exr", extent=0.1))
    write_capture(tmp_path, capture, _frames(), kernel=np.ones((3, 3)))
    write_exr(tmp_path / "kernel.exr", np.ones((3, 3)), ["R"])
    with pytest.raises(CaptureError, match=r"light\.file must be a readable EXR with channel 'Y'.*kernel\.exr"):
        read_capture(tmp_path).read_kernel()


# --- write errors ----------------------------------------------------------------------------------


def test_write_validates_like_read(tmp_path):
    capture = _capture()
    bad = replace(capture, frames=(replace(capture.frames[0], direction=(0.0, 0.0, -1.0)),) + capture.frames[1:])
    with pytest.raises(CaptureError, match=r"capture\.json: frames\[0\]\.direction must point above the surface"):
        write_capture(tmp_path, bad, _frames())
    assert not any(tmp_path.iterdir()), "nothing may be written for an invalid manifest"


def test_write_checks_the_frames_shape(tmp_path):
    with pytest.raises(CaptureError, match=r"must have shape \(K, C, H, W\) = \(3, 3, 4, 5\).*got \(3, 3, 5, 4\)"):
        write_capture(tmp_path, _capture(), _frames().transpose(2, 3))


def test_write_refuses_nan_frames(tmp_path):
    frames = _frames()
    frames[1, 0, 0, 0] = float("nan")
    with pytest.raises(CaptureError, match=r"frames\[1\] for .* must be finite; got 1 pixel"):
        write_capture(tmp_path, _capture(), frames)


def test_write_kernel_only_for_a_tabulated_light(tmp_path):
    with pytest.raises(CaptureError, match=r"kernel for .* must be None unless light\.kernel is 'tabulated'"):
        write_capture(tmp_path, _capture(), _frames(), kernel=np.ones((3, 3)))
    with pytest.raises(CaptureError, match=r"kernel for .* must be given for a tabulated light"):
        write_capture(tmp_path, _capture(light=LightSpec("tabulated", file="k.exr", extent=0.1)), _frames())


def test_write_checks_the_truth(tmp_path):
    truth = SVBRDF(torch.zeros(2, 2, 3), torch.zeros(2, 2, 3), torch.zeros(2, 2, 3), torch.zeros(2, 2, 2))
    with pytest.raises(CaptureError, match=r"truth for .* must have leading dims \(H, W\) = \(4, 5\)"):
        write_capture(tmp_path, _capture(), _frames(), truth=truth)


def test_manifest_is_written_last(written, monkeypatch):
    capture, frames = written
    calls = []

    def failing_write(path, image, channels):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt  # interrupted half way through the frames

    monkeypatch.setattr(capture_module, "write_exr", failing_write)
    with pytest.raises(KeyboardInterrupt):
        write_capture(capture.root, capture, frames + 1, overwrite=True)
    assert not capture.manifest.exists(), "a manifest over a half-written set of frames"
    assert not list(capture.root.rglob(".*.part*"))


# --- the shared development captures ---------------------------------------------------------------


@pytest.fixture(scope="module")
def painting():
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # "generator", the renderer's notes, is a known optional key
        return read_capture(DATA / "painting-dev")


@needs_data
def test_painting_dev(painting):
    assert (len(painting.frames), painting.height, painting.width, painting.channels) == (88, 48, 48, ("R", "G", "B"))
    assert painting.light == LightSpec("gaussian", domain="projected", sigma=0.08)
    assert painting.view == (0.0, 0.0, 1.0)
    assert "generator" in painting.extra
    frames = painting.read_frames()
    assert frames.shape == (88, 3, 48, 48) and frames.dtype == torch.float32
    assert torch.isfinite(frames).all() and (frames >= 0).all() and frames.amax() > 0
    assert torch.equal(
        frames[5], torch.from_numpy(read_exr(DATA / "painting-dev" / "frames" / "0005.exr")).permute(2, 0, 1)
    )


@needs_data
def test_painting_dev_truth(painting):
    maps = read_svbrdf(painting.root / "truth")
    svbrdf = maps.svbrdf
    assert tuple(svbrdf.shape) == (48, 48) and svbrdf.channels == painting.channels
    assert svbrdf.normal.shape == (48, 48, 3) and svbrdf.roughness.shape == (48, 48, 2)
    assert set(maps.extra) == {"regions"} and maps.extra["regions"].shape == (48, 48)
    assert set(maps.extra["regions"].unique().tolist()) == {0.0, 1.0, 2.0}
    matte = (svbrdf.specular == 0).all(-1)
    assert matte.any() and (svbrdf.roughness[matte] == 0).all()
    assert maps.meta["model"] == "ward"


@needs_data
@pytest.mark.parametrize(
    "name, count, light",
    [
        ("painting-dev-relight", 24, LightSpec("point")),
        ("mirror-dev-1d", 80, LightSpec("unknown", symmetric=True)),
        ("mirror-dev-1d-point", 80, LightSpec("point")),
    ],
)
def test_other_shared_captures(name, count, light):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        capture = read_capture(DATA / name)
    assert len(capture.frames) == count and capture.light == light
    assert capture.read_frames([0, count - 1]).shape == (2, 3, capture.height, capture.width)
    assert read_svbrdf(capture.root / "truth").svbrdf.shape == (capture.height, capture.width)


@needs_data
def test_shared_capture_rewritten_reads_back_the_same(tmp_path, painting):
    subset = replace(painting, frames=painting.frames[:4])
    written = write_capture(tmp_path, subset, painting.read_frames(range(4)))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        back = read_capture(tmp_path)
    assert back == written == replace(subset, root=tmp_path)
    assert torch.equal(back.read_frames(), painting.read_frames(range(4)))
