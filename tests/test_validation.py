"""Every bad input is refused or reported with the file, frame or key at fault; ``torchspec info``.

Bad inputs already covered by ``test_io_capture.py`` (truncated or missing frames, wrong size or
channels, NaN, manifest keys) are not repeated here; this file covers the rest, the error family,
:mod:`torchspec.info` and the ``info`` command, and random manifests (hypothesis)."""

from __future__ import annotations

import copy
import io
import json
import math
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from capture_cases import DATA, H, W, edit_manifest, needs_data, random_frames, small_capture
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import torchspec
from torchspec.cli import main
from torchspec.config import ConfigError
from torchspec.errors import TorchspecError
from torchspec.info import OK, UNUSABLE, WARNINGS, format_report, inspect_capture
from torchspec.io import (
    Capture,
    CaptureError,
    ExrError,
    LightSpec,
    SVBRDFError,
    read_capture,
    write_capture,
    write_exr,
)
from torchspec.start.photometric import sample_masks


def _capture(count=5, light=None, positions=None) -> Capture:
    """A capture of ``count`` frames on a line of the l-plane (or at ``positions``)."""
    return small_capture(".", light, count, positions=positions)


def _frames(count=5, seed=0):
    return random_frames(count, 3, seed, low=0.1)


@pytest.fixture
def written(tmp_path):
    """A small valid capture on disk (5 frames) and the frames written."""
    frames = _frames()
    return write_capture(tmp_path / "cap", _capture(), frames), frames


def _write_frame(capture: Capture, k: int, image: torch.Tensor) -> None:
    """Overwrite frame ``k`` with a ``(C, H, W)`` image."""
    write_exr(capture.root / capture.frames[k].file, image.permute(1, 2, 0), capture.channels)


# --- the error family --------------------------------------------------------------------------------


@pytest.mark.parametrize("error", [CaptureError, ExrError, SVBRDFError, ConfigError])
def test_every_input_error_is_a_torchspec_error_and_a_value_error(error):
    assert issubclass(error, TorchspecError) and issubclass(error, ValueError)
    assert torchspec.TorchspecError is TorchspecError and "TorchspecError" in torchspec.__all__


# --- frames --------------------------------------------------------------------------------------------


def test_unreadable_frame_names_index_and_file(written):
    capture, _ = written
    (capture.root / "frames" / "0003.exr").write_bytes(b"these bytes are not an OpenEXR image" * 4)
    capture.read_frames([0, 1, 2, 4])  # the others are fine
    with pytest.raises(CaptureError, match=r"frames\[3\] \(an EXR.*0003\.exr is a text file, not an EXR"):
        capture.read_frames()


def test_manifest_size_far_from_the_frames_allocates_nothing(written):
    capture, _ = written
    edit_manifest(capture.root, lambda manifest: manifest.update(width=10**6, height=10**6))
    with pytest.raises(CaptureError, match=r"frames\[0\] .*0000\.exr must be 1000000x1000000 .*got 4x5"):
        read_capture(capture.root).read_frames()  # 36 TB if allocated before the first frame is checked


def test_negative_pixels_are_refused_with_count_and_minimum(written):
    capture, frames = written
    image = frames[1].clone()
    image[1, 0, 0] = -0.5
    image[0, 2, 3] = -2.0
    image[2, 2, 3] = -1.0  # the same pixel: counted once
    _write_frame(capture, 1, image)
    with pytest.raises(
        CaptureError,
        match=r"frames\[1\] .*0001\.exr must be non-negative.*got 2 pixel\(s\) with a negative value \(of 20\), "
        r"the most negative -2\b",
    ):
        capture.read_frames()
    with pytest.warns(UserWarning, match=r"frames\[1\] .*0001\.exr: 2 pixel\(s\) with a negative value.*-2\b"):
        kept = capture.read_frames(nonfinite="keep")
    assert torch.equal(kept[1], image), "negative values must be kept as they are"


def test_read_no_frames_is_an_empty_stack(written):
    capture, _ = written
    assert capture.read_frames([]).shape == (0, 3, H, W)


# --- the manifest ----------------------------------------------------------------------------------


@pytest.mark.parametrize("offset", [0.0, 1e-12], ids=["identical", "within-1e-9"])
def test_duplicated_direction_names_both_frames(written, offset):
    capture, _ = written

    def edit(manifest):
        x, y, z = manifest["frames"][1]["direction"]
        manifest["frames"][3]["direction"] = [x + offset, y, z]

    edit_manifest(capture.root, edit)
    with pytest.raises(
        CaptureError, match=r"capture\.json: frames\[3\]\.direction must differ .* \(frames\[1\]\.direction\)"
    ):
        read_capture(capture.root)


def test_close_but_distinct_directions_are_accepted(written):
    capture, _ = written

    def edit(manifest):
        x, y, z = manifest["frames"][1]["direction"]
        manifest["frames"][3]["direction"] = [x + 1e-6, y, z]

    edit_manifest(capture.root, edit)
    assert len(read_capture(capture.root).frames) == 5


def test_written_captures_are_checked_for_repeated_directions(tmp_path):
    capture = _capture()
    repeated = capture.frames[:4] + (replace(capture.frames[4], direction=capture.frames[2].direction),)
    with pytest.raises(CaptureError, match=r"frames\[4\]\.direction must differ .*\(frames\[2\]\.direction\)"):
        write_capture(tmp_path, replace(capture, frames=repeated), _frames())


def test_direction_below_the_horizon_in_the_camera(written):
    capture, _ = written
    edit_manifest(capture.root, lambda manifest: manifest["camera"].update(view=[0.0, 0.6, -0.8]))
    with pytest.raises(CaptureError, match=r"capture\.json: camera\.view must point above the surface \(z > 0\)"):
        read_capture(capture.root)


def test_not_unit_direction_renormalised_within_tolerance_only(written):
    capture, _ = written  # frames[0] is the one at (0, 0, 1)
    edit_manifest(capture.root, lambda manifest: manifest["frames"][0].update(direction=[0.0, 0.0, 1.0009]))
    with pytest.warns(UserWarning, match=r"frames\[0\]\.direction has norm 1\.0009"):
        assert read_capture(capture.root).frames[0].direction == (0.0, 0.0, 1.0)
    edit_manifest(capture.root, lambda manifest: manifest["frames"][0].update(direction=[0.0, 0.0, 1.0011]))
    with pytest.raises(CaptureError, match=r"frames\[0\]\.direction must be a unit vector .* of norm 1\.0011"):
        read_capture(capture.root)


MISSING_KEYS = {
    "camera.view": (lambda m: m["camera"].pop("view"), r"camera\.view must be given; got no such key"),
    "light.kernel": (lambda m: m["light"].pop("kernel"), r"light\.kernel must be one of .*; got null"),
    "frame-direction": (
        lambda m: m["frames"][2].pop("direction"),
        r"frames\[2\] must have the keys .*\['direction'\] missing",
    ),
    "several": (
        lambda m: (m.pop("camera"), m.pop("channels")),
        r"the manifest must have the keys .*\['channels', 'camera'\] missing",
    ),
    "format": (lambda m: m.pop("format"), r"format must be 'torchspec\.capture'; got null"),
    "version": (lambda m: m.pop("version"), r"version must be a supported version \(1\); got null"),
}


@pytest.mark.parametrize("edit, message", MISSING_KEYS.values(), ids=MISSING_KEYS.keys())
def test_missing_keys_are_named(written, edit, message):
    capture, _ = written
    edit_manifest(capture.root, edit)
    with pytest.raises(CaptureError, match=message) as info:
        read_capture(capture.root)
    assert str(capture.manifest) in str(info.value)


@pytest.mark.parametrize(
    "key, value, message",
    [
        ("version", "1", r"version must be a supported version \(1\); got \"1\""),
        ("version", True, r"version must be a supported version \(1\); got true"),
        ("format", "torchspec.svbrdf", r"format must be 'torchspec\.capture'; got \"torchspec\.svbrdf\""),
    ],
)
def test_unsupported_format_or_version_of_another_type(written, key, value, message):
    capture, _ = written
    edit_manifest(capture.root, lambda manifest: manifest.update({key: value}))
    with pytest.raises(CaptureError, match=message):
        read_capture(capture.root)


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda m: m["light"].update(kernel=["gaussian"]), r"light\.kernel must be one of .*; got \[\"gaussian\"\]"),
        (lambda m: m["frames"][0].update(exposure=10**400), r"frames\[0\]\.exposure must be a positive number"),
        (lambda m: m["frames"][0].update(file="frames/\0.exr"), r"frames\[0\]\.file must be a file name"),
        (lambda m: m["frames"][0].update(file="x" * 5000), r"frames\[0\]\.file must be a file the system can"),
    ],
    ids=["unhashable-kernel", "huge-int", "nul-in-name", "name-too-long"],
)
def test_values_that_crashed_the_reader(written, edit, message):
    capture, _ = written
    edit_manifest(capture.root, edit)
    with pytest.raises(CaptureError, match=message):
        read_capture(capture.root)


def test_empty_capture(tmp_path, written):
    capture, _ = written
    with pytest.raises(
        CaptureError, match=r"capture\.json: frames must be a non-empty list of frame objects; got \[\]"
    ):
        write_capture(tmp_path / "empty", replace(capture, frames=()), torch.zeros(0, 3, H, W))
    assert not (tmp_path / "empty").exists()
    edit_manifest(capture.root, lambda manifest: manifest.update(frames=[]))
    report = inspect_capture(capture.root)
    assert report["verdict"] == UNUSABLE and "frames must be a non-empty list" in report["reason"]
    report = inspect_capture(tmp_path)  # a folder without a manifest
    assert report["verdict"] == UNUSABLE and f"{tmp_path / 'capture.json'} must exist" in report["reason"]


# --- torchspec.info ----------------------------------------------------------------------------------


def test_info_of_a_good_capture(written):
    capture, frames = written
    report = inspect_capture(capture.root)
    assert report["verdict"] == OK and report["reason"] is None and report["warnings"] == []
    assert (report["width"], report["height"], report["channels"], report["frames"]) == (W, H, ["R", "G", "B"], 5)
    assert report["light"] == {"kernel": "gaussian", "domain": "projected", "sigma": 0.05}
    assert report["kernel"] == "gaussian, projected domain, sigma 0.05 l units"
    assert report["layout"]["kind"] == "line" and report["layout"]["radius"] == pytest.approx(math.hypot(0.4, 0.2))
    assert report["exposure"] == [0.5, 2.5] and report["irradiance"] == [1.0, 5.0]
    assert report["values"] == [float(frames.min()), float(frames.max())]
    assert report["saturation"] is None
    assert report["counts"] == {"clipped": 0, "saturated": 0, "nonfinite": 0, "negative": 0}
    assert [row["index"] for row in report["per_frame"]] == list(range(5)) and report["frames_at_fault"] == []
    assert json.loads(json.dumps(report, allow_nan=False)) == report
    text = format_report(report)
    for line in ["verdict   ok", "size      5 x 4 (W x H), channels R, G, B", "frames    5, layout line"]:
        assert line in text, text


@pytest.mark.parametrize(
    "positions, layout",
    [
        ([(0.2 * i - 0.2, 0.2 * j - 0.2) for j in range(3) for i in range(3)], {"kind": "grid", "rows": 3}),
        ([(0.3, 0.1), (-0.2, 0.4), (0.05, -0.3), (-0.35, -0.1), (0.15, 0.25)], {"kind": "scattered"}),
    ],
    ids=["grid", "scattered"],
)
def test_info_light_layouts(tmp_path, positions, layout):
    count = len(positions)
    write_capture(tmp_path, _capture(positions=positions), _frames(count))
    report = inspect_capture(tmp_path)
    assert layout.items() <= report["layout"].items(), report["layout"]


def test_info_reads_one_frame_at_a_time_with_a_progress_bar_that_can_be_disabled(written, monkeypatch, capsys):
    capture, _ = written
    asked = []
    read = Capture.read_frames

    def recording(self, indices=None, **options):
        asked.append(list(indices))
        return read(self, indices, **options)

    monkeypatch.setattr(Capture, "read_frames", recording)
    inspect_capture(capture.root, progress=False)
    assert asked == [[k] for k in range(5)]
    assert capsys.readouterr().err == ""
    inspect_capture(capture.root, progress=True)  # stderr is not a terminal here: quiet all the same
    assert capsys.readouterr().err == ""
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    inspect_capture(capture.root, progress=True)
    assert "5/5" in terminal.getvalue()


class _Terminal(io.StringIO):
    """A stderr that says it is a terminal (progress bars show there only)."""

    def isatty(self) -> bool:
        return True


@needs_data
def test_info_of_painting_dev():
    report = inspect_capture(DATA / "painting-dev")
    assert report["verdict"] == OK, report["warnings"]
    assert (report["width"], report["height"], report["frames"]) == (48, 48, 88)
    assert report["layout"]["kind"] == "grid" and report["layout"]["radius"] < 0.8
    assert report["kernel"] == "gaussian, projected domain, sigma 0.08 l units"
    assert report["counts"] == {"clipped": 0, "saturated": 0, "nonfinite": 0, "negative": 0}


def test_info_of_a_saturated_capture_agrees_with_the_fit_masks(tmp_path):
    frames = _frames()
    frames[1, :, 0, :] = 5.0  # a clipped plateau: 15 values ...
    frames[1, 0, 1, 0] = 5.0  # ... and one more, at the stack's maximum
    frames[3, :, 2:, 1:4] = 3.0  # 18 values at a lower level: a frame's own top, not the sensor's
    write_capture(tmp_path, _capture(), frames)
    report = inspect_capture(tmp_path)
    # every pixel keeps 4 of its 5 frames, all a fit needs: a note, and the verdict stays ok
    assert report["verdict"] == OK and report["reason"] is None and report["warnings"] == []
    assert report["saturation"] == 5.0
    expected = sample_masks(frames).saturated.sum((1, 2)).tolist()  # as the fit masks them
    # row 0 and pixel (1, 0) clip; grown by a pixel: rows 0 and 1, and pixels (2, 0), (2, 1)
    assert [row["saturated"] for row in report["per_frame"]] == expected == [0, 12, 0, 0, 0]
    assert [row["clipped"] for row in report["per_frame"]] == [0, 6, 0, 0, 0]  # pixels: row 0 (5) and (1, 0)
    assert report["frames_at_fault"] == [1]
    assert report["kept"] == {"fewest": 4, "need": 4, "short": 0}
    assert any("saturated pixel(s)" in note and "frames 1," in note for note in report["notes"])
    assert "frames[1] frames/0001.exr: 6 clipped, 12 saturated (grown by a pixel)" in format_report(report)
    assert "every pixel keeps at least 4 of the 5 frames" in format_report(report)
    # a known clipping level instead of the detection
    given_level = inspect_capture(tmp_path, saturation=3.0)
    assert [row["saturated"] for row in given_level["per_frame"]] == sample_masks(frames, saturation=3.0).saturated.sum(
        (1, 2)
    ).tolist()


def test_info_warns_where_saturation_leaves_a_pixel_short_of_frames(tmp_path):
    """Saturated samples lower the verdict only where the pixels that hold them keep fewer frames
    than a fit needs; the counts agree with a brute-force count over the fit's masks."""
    frames = _frames(count=6, seed=1)
    frames[0:4, :, 1, 1] = 5.0  # one pixel clipped in 4 of 6 frames (grown to its neighbours)
    frames[5, :, 0, 0] = 5.0
    frames[5, :, 3, 2:] = 5.0  # 16 samples at the level in all: a clipped sensor's plateau
    write_capture(tmp_path, _capture(6), frames)
    report = inspect_capture(tmp_path)
    assert report["verdict"] == WARNINGS and report["notes"] == []
    kept = 6 - sample_masks(frames).saturated.sum(0)  # brute force: frames kept at each pixel
    assert report["kept"] == {"fewest": int(kept.min()), "need": 4, "short": int((kept < 4).sum())}
    assert report["kept"]["fewest"] < 4 and report["kept"]["short"] > 1
    assert any(
        f"leaves {report['kept']['short']} pixel(s) fewer than 4 of the 6 frames" in w for w in report["warnings"]
    )


def test_info_counts_nan_and_negative_pixels(written):
    capture, frames = written
    image = frames[2].clone()
    image[0, 0, 0] = float("nan")
    image[1, 1, 1] = -0.25
    _write_frame(capture, 2, image)
    report = inspect_capture(capture.root)
    assert report["verdict"] == WARNINGS
    assert report["counts"] == {"clipped": 0, "saturated": 0, "nonfinite": 1, "negative": 1}
    assert report["frames_at_fault"] == [2] and report["per_frame"][2]["min"] == -0.25
    notes = " | ".join(report["warnings"])
    assert "1 pixel(s) with NaN or Inf in 1 frame(s) (frames 2)" in notes
    assert "1 pixel(s) with a negative value in 1 frame(s) (frames 2, the most negative -0.25)" in notes


@pytest.mark.parametrize(
    "edit, note",
    [
        (
            lambda m: m["frames"][3].update(direction=[1.0005 * v for v in m["frames"][3]["direction"]]),
            "frames[3].direction has norm 1.0005",
        ),
        (lambda m: m.update(comment="x"), "unknown top-level key(s) ['comment']"),
        (lambda m: m["light"].update(colour="white"), "unknown key(s) ['colour'] in light"),
    ],
    ids=["renormalised", "unknown-top-level-key", "unknown-light-key"],
)
def test_info_warns_about_what_it_fixes_or_ignores(written, edit, note):
    capture, _ = written
    edit_manifest(capture.root, edit)
    report = inspect_capture(capture.root)
    assert report["verdict"] == WARNINGS and any(note in warning for warning in report["warnings"]), report


def _missing_frame(root: Path):
    (root / "frames" / "0002.exr").unlink()


def _unreadable_frame(root: Path):
    (root / "frames" / "0004.exr").write_bytes(b"garbage")


def _wrong_channels(root: Path):
    write_exr(root / "frames" / "0001.exr", np.zeros((H, W, 1)), ["Y"])


BROKEN = {
    "missing-exr": (_missing_frame, r"frames[2].file must exist; got 'frames/0002.exr'"),
    "unreadable-exr": (_unreadable_frame, "1 of 5 frame(s) cannot be read (frames 4); the first: "),
    "wrong-channels": (_wrong_channels, "0001.exr must have channel(s) ['R', 'G', 'B']; it has ['Y']"),
    "version": (lambda root: edit_manifest(root, lambda m: m.update(version=2)), "version must be a supported"),
    "frame-twice": (
        lambda root: edit_manifest(root, lambda m: m["frames"][4].update(file="frames/0000.exr")),
        "frames[0] and frames[4] list the same file",
    ),
    "too-few-frames": (
        lambda root: edit_manifest(root, lambda m: m.update(frames=m["frames"][:3])),
        "3 frame(s): a fit needs at least 4",
    ),
}


@pytest.mark.parametrize("break_it, reason", BROKEN.values(), ids=BROKEN.keys())
def test_info_of_a_broken_capture_is_unusable_with_the_reason(written, break_it, reason):
    capture, _ = written
    break_it(capture.root)
    report = inspect_capture(capture.root)
    assert report["verdict"] == UNUSABLE and reason in report["reason"], report["reason"]
    assert json.dumps(report, allow_nan=False)
    assert "verdict   unusable" in format_report(report)


def test_info_of_a_tabulated_kernel(tmp_path):
    capture = _capture(light=LightSpec("tabulated", file="kernel.exr", extent=0.1))
    write_capture(tmp_path, capture, _frames(), kernel=np.ones((3, 7)))
    assert inspect_capture(tmp_path)["kernel"] == "tabulated, kernel.exr, extent 0.1 l units, a 7x3 image"
    write_exr(tmp_path / "kernel.exr", np.full((3, 7), np.nan), ["Y"])
    report = inspect_capture(tmp_path)
    assert report["verdict"] == UNUSABLE and "light.file" in report["reason"] and "NaN" in report["reason"]


def test_info_of_an_unknown_kernel(unknown_light_capture):
    report = inspect_capture(unknown_light_capture)
    assert report["verdict"] == WARNINGS and "light.kernel is 'unknown'" in report["warnings"][0]


# --- the info command ------------------------------------------------------------------------------


def test_cli_info(written, capsys):
    capture, _ = written
    assert main(["info", str(capture.root), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "verdict   ok" in out and "5, layout line" in out
    assert main(["info", str(capture.root), "--json", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out) == inspect_capture(capture.root)


def test_cli_info_exit_codes_of_warnings_and_broken_captures(written, capsys):
    capture, _ = written
    edit_manifest(capture.root, lambda manifest: manifest.update(comment="x"))
    assert main(["info", str(capture.root), "--quiet"]) == 0
    assert "usable with warnings" in capsys.readouterr().out
    _missing_frame(capture.root)
    assert main(["info", str(capture.root), "--json", "--quiet"]) == 2
    report = json.loads(capsys.readouterr().out)
    assert report["verdict"] == UNUSABLE and "frames[2].file must exist" in report["reason"]
    assert main(["info", str(capture.root / "nowhere"), "--quiet"]) == 2
    assert "the capture folder " + str(capture.root / "nowhere") + " does not exist" in capsys.readouterr().out


# --- random manifests --------------------------------------------------------------------------------

_NAMES = [
    "frames/0000.exr",
    "frames/0003.exr",
    "./frames/0001.exr",
    "kernel.exr",
    "capture.json",
    "frames",
    ".",
    "../cap/frames/0002.exr",
    "format",
    "version",
    "file",
    "direction",
    "irradiance",
    "exposure",
    "kernel",
    "domain",
    "sigma",
    "extent",
    "symmetric",
    "view",
    "model",
    "gaussian",
    "tabulated",
    "unknown",
    "point",
    "projected",
    "angular",
    "orthographic",
    "torchspec.capture",
    "R",
    "Y",
]
_NUMBERS = st.one_of(
    st.sampled_from([0, 1, 2, 0.05, -1, 1e-300, 1e300, 10**400, -(10**400), 2**63, 10**6, math.nan, math.inf]),
    st.integers(-3, 5),
    st.floats(-1.5, 1.5),
    st.floats(allow_nan=True, allow_infinity=True),
)
_SCALARS = st.one_of(_NUMBERS, _NUMBERS, st.none(), st.booleans(), st.text(max_size=6), st.sampled_from(_NAMES))
_KEYS = st.sampled_from(_NAMES) | st.text(max_size=4)
_VALUES = st.one_of(
    _SCALARS,
    st.lists(_SCALARS, max_size=4),
    st.dictionaries(_KEYS, _SCALARS, max_size=3),
    st.recursive(_SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(_KEYS, inner), max_leaves=8),
)


def _paths(value, prefix=()):
    """Every path of keys and indices into a JSON value."""
    yield prefix
    children = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, child in children:
        yield from _paths(child, prefix + (key,))


def _mutate(data, manifest):
    """One random change: drop, replace, add or repeat a part, or plant a typical mistake."""
    kind = data.draw(st.sampled_from(["drop", "replace", "replace", "add", "repeat", "same-light", "tabulated"]))
    frames = manifest.get("frames")
    if kind == "same-light" and isinstance(frames, list) and len(frames) >= 2:
        i, j = data.draw(st.lists(st.integers(0, len(frames) - 1), min_size=2, max_size=2, unique=True))
        if isinstance(frames[i], dict) and isinstance(frames[j], dict):
            frames[j]["direction"] = copy.deepcopy(frames[i].get("direction"))
        return
    if kind == "tabulated":
        extent = data.draw(st.floats(0.01, 1.0) | _SCALARS)
        manifest["light"] = {"kernel": "tabulated", "file": data.draw(st.sampled_from(_NAMES)), "extent": extent}
        return
    # Mostly deep in the frames and the light, where most of the validation is.
    section = data.draw(st.sampled_from(["frames", "frames", "frames", "light", "light", "camera", ""]))
    root = (section,) if section in manifest else ()
    inside = manifest[section] if root else manifest
    paths = [root + sub for sub in _paths(inside) if sub or kind == "add"]
    path = data.draw(st.sampled_from(paths)) if paths else root
    if not path:
        if kind == "add":
            manifest[data.draw(_KEYS)] = data.draw(_VALUES)
        return
    *parents, last = path
    target = manifest
    for key in parents:
        target = target[key]
    if kind == "drop":
        del target[last]
    elif kind == "replace":
        target[last] = data.draw(_VALUES)
    elif kind == "repeat" and isinstance(target, list):
        target.insert(last, copy.deepcopy(target[last]))
    elif kind == "add" and isinstance(target[last], dict):
        target[last][data.draw(_KEYS)] = data.draw(_VALUES)
    elif kind == "add" and isinstance(target[last], list):
        target[last].append(data.draw(_VALUES))


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory):
    """A valid capture of 4 frames (and a spare kernel image) whose manifest the test rewrites."""
    root = tmp_path_factory.mktemp("fuzz") / "cap"
    write_capture(root, _capture(count=4), _frames(4))
    write_exr(root / "kernel.exr", np.ones((3, 3)), ["Y"])
    return root, json.loads((root / "capture.json").read_text())


@settings(max_examples=200, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_random_manifests_raise_only_torchspec_errors(fuzzed, data):
    root, valid = fuzzed
    manifest = copy.deepcopy(valid)
    for _ in range(data.draw(st.integers(1, 3))):
        _mutate(data, manifest)
    (root / "capture.json").write_text(json.dumps(manifest))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            capture = read_capture(root)
            capture.read_frames()
            capture.read_frames([0], nonfinite="keep")
            capture.directions(), capture.irradiance(), capture.exposure()
            if capture.light.kernel == "tabulated":
                capture.read_kernel()
        except TorchspecError:
            pass
        report = inspect_capture(root)  # never raises
    assert report["verdict"] in (OK, WARNINGS, UNUSABLE)
    json.dumps(report, allow_nan=False)
