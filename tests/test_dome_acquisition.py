"""Acquisition with the dome: the plan, a valid capture after a stop at any moment, a resume that
equals an uninterrupted run frame for frame; then end to end through the emulator's pty: a
fitted capture, each injected fault, and the command line killed with SIGKILL and resumed."""

import importlib
import json
import math
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch

from torchspec.cli import main
from torchspec.dome import DomeClient, DomeDisconnected, DomeEmulator, DomeFault, DomeTimeout
from torchspec.dome.acquisition import (
    PLAN,
    AcquisitionError,
    AcquisitionInterrupted,
    AcquisitionStopped,
    LightSettings,
    acquire,
    dome_angles,
    load_light,
    plan_directions,
)
from torchspec.dome.camera import CameraError, FolderCamera, SimulatedCamera
from torchspec.dome.protocol import DomeIdentity, DomeStatus
from torchspec.info import OK, UNUSABLE, inspect_capture
from torchspec.io import CaptureError, read_capture, write_exr
from torchspec.model.geometry import angle
from torchspec.pipeline import fit
from torchspec.simulate import LayoutConfig, SceneConfig, layout
from torchspec.simulate.synth import PaintingConfig, SensorConfig, painting

ACQ = importlib.import_module("torchspec.dome.acquisition")

GAUSSIAN = {"kernel": "gaussian", "domain": "projected", "sigma": 0.08}
POINT = {"kernel": "point"}  # cheap to render: the loop's logic does not depend on the kernel
LIGHT = LightSettings(POINT, intensity=0.7, irradiance=1.5)
SCENE = SceneConfig(kind="painting", painting=PaintingConfig(width=8, height=6, seed=2, gilded=None))
SENSOR = SensorConfig(exposure=2.0, photons_per_unit=400.0, read_noise=0.01, seed=3)
LAYOUT = "grid:5x5"  # 13 directions at radius 0.8
TOTAL = 13


def _camera() -> SimulatedCamera:
    return SimulatedCamera(SCENE, POINT, irradiance=1.5, sensor=SENSOR)


class FakeDome:
    """The client's methods over a dome that is wherever it was last sent; ``fail`` maps a method
    name to ``(call number, exception)``: that call raises instead."""

    def __init__(self, fail=None, identity=("FAKE", "2.1", 1), offset=0.0, lamp=True):
        self.fail = fail or {}
        self.identity = DomeIdentity(*identity)
        self.calls = []
        self.counts = {}
        self.theta = self.phi = 0.0
        self.lit = False
        self.offset, self.lamp = offset, lamp

    def _call(self, name, *args):
        number = self.counts.get(name, 0)
        self.counts[name] = number + 1
        if name in self.fail and self.fail[name][0] == number:
            raise self.fail[name][1]
        self.calls.append((name, *args))

    def identify(self):
        self._call("identify")
        return self.identity

    def home(self):
        self._call("home")
        self.theta = self.phi = 0.0

    def move(self, theta, phi):
        self._call("move", theta, phi)
        self.theta, self.phi = theta, phi

    def light(self, on, intensity=None):
        self._call("light", on, intensity)
        self.lit = on

    def status(self):
        self._call("status")
        return DomeStatus(self.theta + self.offset, self.phi, 0.0, False, self.lit and self.lamp, 0.7, None)

    def moves(self):
        return [call[1:] for call in self.calls if call[0] == "move"]


class Camera:
    """A camera that counts its frames and can fail at one index (or run an action there)."""

    def __init__(self, inner, fail_at=None, error=None, action=None):
        self.inner, self.fail_at, self.error, self.action = inner, fail_at, error, action
        self.channels, self.size, self.exposure = inner.channels, inner.size, inner.exposure
        self.taken = []

    def capture(self, direction, *, index):
        if index == self.fail_at:
            self.fail_at = None
            if self.action is not None:
                self.action()
            else:
                raise self.error
        self.taken.append(index)
        return self.inner.capture(direction, index=index)


def _run(output, dome=None, camera=None, **kwargs):
    options = {"light": LIGHT, "layout": LAYOUT, "progress": False, **kwargs}
    return acquire(dome or FakeDome(), camera or _camera(), output, **options)


def _assert_same(path, reference, *, manifest=True):
    """``path`` holds the capture at ``reference``: the same frames (torch.equal) and manifest."""
    a, b = read_capture(path), read_capture(reference)
    assert a.frames == b.frames, "the frames' files, directions, irradiance or exposure differ"
    if manifest:
        assert json.loads(a.manifest.read_text()) == json.loads(b.manifest.read_text())
    for k in range(len(b.frames)):
        assert torch.equal(a.read_frames([k]), b.read_frames([k])), f"frame {k} differs"


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted acquisition with the fake dome: (capture folder, the dome)."""
    dome = FakeDome()
    path = tmp_path_factory.mktemp("reference") / "capture"
    _run(path, dome)
    return path, dome


# --- the plan -------------------------------------------------------------------------------------


def test_the_grid_is_the_simulators():
    planned = plan_directions("grid:12x12", 0.8)
    assert torch.equal(planned, layout(LayoutConfig()))  # configs/sim_painting.yaml's 88 centres
    assert planned.shape == (88, 3)
    assert float(planned[:, :2].norm(dim=-1).max()) <= 0.8 + 1e-12
    line = plan_directions("line:5", 0.5)
    assert torch.all(line[:, 1] == 0) and abs(float(line[2, 2]) - 1) < 1e-15, "line:N runs along x across the zenith"
    assert abs(float(line[:, 0].abs().max()) - 0.5) < 1e-12 and torch.all(torch.diff(line[:, 0]) > 0)


def test_dome_angles_give_back_the_directions():
    planned = plan_directions("grid:12x12", 0.8)
    angles = dome_angles(planned)
    theta, phi = angles.unbind(-1)
    assert float(theta.min()) >= 0 and float(theta.max()) <= math.asin(0.8) + 1e-12
    assert float(phi.min()) >= 0 and float(phi.max()) < 2 * math.pi
    back = torch.stack([theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos()], -1)
    error = (back - planned).abs().max()
    assert error < 1e-15, f"max error {error:.3g}"
    zenith = dome_angles(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64))
    assert zenith.tolist() == [[0.0, 0.0]]


@pytest.mark.parametrize(
    "spec, radius, message",
    [
        ("grid:0x4", 0.8, "grid:NXxNY"),
        ("spiral:12", 0.8, "grid:NXxNY.*line:N"),
        ("line:1", 0.8, "line:N"),
        ("grid:4x4", 1.2, r"radius must be in \(0, 1\)"),
        ("grid:1x1", 0.8, "no light direction"),  # its one point, a corner, is outside the disc
    ],
)
def test_bad_layouts_are_refused(spec, radius, message):
    with pytest.raises(AcquisitionError, match=message):
        plan_directions(spec, radius)


# --- a whole run, and the light config --------------------------------------------------------------


def test_an_acquisition_drives_the_dome_and_writes_the_capture(reference):
    path, dome = reference
    angles = dome_angles(plan_directions(LAYOUT, 0.8)).tolist()
    assert dome.calls[:3] == [("identify",), ("home",), ("light", True, 0.7)]
    assert dome.calls[-1] == ("light", False, None)
    assert dome.moves() == [tuple(a) for a in angles]
    assert sum(call[0] == "status" for call in dome.calls) == TOTAL  # one position check per frame
    capture = read_capture(path)
    assert torch.equal(capture.directions(), plan_directions(LAYOUT, 0.8))
    assert torch.all(capture.irradiance() == 1.5) and torch.all(capture.exposure() == 2.0)
    assert capture.extra["generator"]["dome"] == {"model": "FAKE", "firmware": "2.1", "protocol": 1}
    assert capture.extra["generator"]["planned"] == TOTAL
    camera = _camera()
    for k in (0, 7, 12):
        direct = camera.capture(capture.directions()[k], index=k).float()
        assert torch.equal(capture.read_frames([k])[0], direct), f"frame {k} is not the camera's"
    report = inspect_capture(path)
    assert report["verdict"] == OK, report["reason"] or report["warnings"]
    plan = json.loads((path / PLAN).read_text())
    assert plan["layout"] == LAYOUT and len(plan["frames"]) == TOTAL and plan["dome"]["model"] == "FAKE"
    assert sorted(p.name for p in path.iterdir()) == ["acquire.json", "capture.json", "frames"]


def test_the_light_config(tmp_path):
    yaml_file = tmp_path / "light.yaml"
    yaml_file.write_text(
        "light: {kernel: gaussian, domain: angular, sigma: 0.05}\nintensity: 0.5\nirradiance: [1, 2, 3]\n"
    )
    settings = load_light(yaml_file)
    assert settings.light.kernel == "gaussian" and settings.light.domain == "angular" and settings.intensity == 0.5
    assert settings.irradiance_for(["R", "G", "B"]) == (1.0, 2.0, 3.0)
    with pytest.raises(AcquisitionError, match=r"one per channel \['Y'\]"):
        settings.irradiance_for(["Y"])
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({"kernel": "point"}))  # a bare light block, as `torchspec render --light` takes
    assert load_light(bare).light.kernel == "point"
    cases = {
        "light: {kernel: point}\ncolour: red\n": r"unknown key\(s\) \['colour'\]",
        "light: {kernel: gaussian, domain: projected, sigma: -1}\n": r"light.sigma must be a positive number",
        "light: {kernel: gaussian, domain: projected, sigma: 0.1, radius: 2}\n": r"\['radius'\] in light",
        "light: {kernel: point}\nintensity: 1.5\n": r"intensity must be in \[0, 1\]",
        "light: {kernel: point}\nirradiance: [1, red]\n": r"irradiance must be a positive number or one per channel",
        "intensity: 1\n": "must be a mapping with a 'light' block",
    }
    for text, message in cases.items():
        yaml_file.write_text(text)
        with pytest.raises((AcquisitionError, CaptureError), match=message) as error:
            load_light(yaml_file)
        assert str(yaml_file) in str(error.value)


def test_a_tabulated_light_is_copied_into_the_capture(tmp_path):
    table = np.outer(np.hanning(9), np.hanning(9)).astype(np.float32) + 1e-3
    write_exr(tmp_path / "measured.exr", table, ["Y"])
    (tmp_path / "light.yaml").write_text("light: {kernel: tabulated, file: measured.exr, extent: 0.2}\n")
    light = load_light(tmp_path / "light.yaml")
    capture = _run(tmp_path / "capture", light=light, layout="grid:3x3")
    assert capture.light.file == "kernel.exr"
    assert torch.equal(capture.read_kernel(), torch.from_numpy(table))


def test_exposure_comes_from_the_camera_or_the_light_config_never_both(tmp_path):
    with pytest.raises(AcquisitionError, match=r"exposure must be the camera's \(2\)"):
        _run(tmp_path / "a", light=LightSettings(POINT, exposure=3.0))
    camera = Camera(_camera())
    camera.exposure = None  # a tethered camera that does not know it
    capture = _run(tmp_path / "b", camera=camera, light=LightSettings(POINT, exposure=3.0), layout="grid:3x3")
    assert torch.all(capture.exposure() == 3.0)


def test_a_tethered_camera_in_the_loop(tmp_path):
    watch = tmp_path / "watch"
    watch.mkdir()
    shots = []

    def trigger():  # the camera program saves each shot under its own counter
        shots.append(len(shots) + 1)
        write_exr(watch / f"IMG_{shots[-1]:04d}.exr", np.full((6, 8, 3), shots[-1], np.float32), ["R", "G", "B"])

    camera = FolderCamera(watch, settle=0.0, timeout=5.0, trigger=trigger)
    capture = _run(tmp_path / "capture", camera=camera, light=LightSettings(POINT, exposure=0.5), layout="grid:3x3")
    means = [float(frame.mean()) for frame in capture.read_frames()]
    assert means == [1, 2, 3, 4, 5], f"frame values {means}: one shot per frame, in order"
    assert (capture.height, capture.width) == (6, 8) and torch.all(capture.exposure() == 0.5)


# --- stops and resumes ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "k, dome, camera_error",
    [
        (0, {"move": (0, DomeFault("motor", code="MOTOR"))}, None),
        (4, {"move": (4, DomeTimeout("no reply"))}, None),
        (6, None, CameraError("no file")),
        (9, {"status": (9, DomeDisconnected("gone"))}, None),
    ],
    ids=["fault-at-0", "timeout-at-4", "camera-at-6", "disconnect-at-9"],
)
def test_a_stop_leaves_the_frames_done_and_resume_completes_them(reference, tmp_path, k, dome, camera_error):
    path = tmp_path / "capture"
    failing = FakeDome(fail=dome)
    camera = Camera(_camera(), fail_at=k if camera_error else None, error=camera_error)
    with pytest.raises(AcquisitionStopped) as stop:
        _run(path, failing, camera)
    message = str(stop.value)
    assert f"stopped at frame {k} (frames/{k:04d}.exr) of {TOTAL}, at " in message, message
    assert (stop.value.done, stop.value.total, stop.value.frame) == (k, TOTAL, k)
    if k:
        assert f"{k} of {TOTAL} frames are saved in {path} (a valid capture)" in message, message
        saved = read_capture(path)
        assert len(saved.frames) == k
        assert inspect_capture(path)["verdict"] != UNUSABLE  # valid; info may warn that a lobe needs more frames
        for j in range(k):
            assert torch.equal(saved.read_frames([j]), read_capture(reference[0]).read_frames([j]))
    else:
        assert "no frame is saved yet" in message and not (path / "capture.json").exists()
    if isinstance(stop.value.__cause__, (DomeTimeout, DomeDisconnected)):
        assert "may still be on" in message  # a dome that does not answer is not sent more commands
    else:
        assert failing.calls[-1] == ("light", False, None), "the light must be switched off after a stop"

    again = FakeDome()
    _run(path, again, resume=True)
    assert again.moves() == reference[1].moves()[k:], "resume must start at the first missing frame"
    _assert_same(path, reference[0])


def test_ctrl_c_between_frame_and_manifest_adopts_the_frame(reference, tmp_path, monkeypatch):
    path, k = tmp_path / "capture", 5
    real, calls = ACQ._write_manifest, []

    def write_manifest(*args):  # Ctrl-C lands after frame k's file is written, before its listing
        calls.append(1)
        if len(calls) == k + 1:
            raise KeyboardInterrupt
        real(*args)

    monkeypatch.setattr(ACQ, "_write_manifest", write_manifest)
    dome = FakeDome()
    with pytest.raises(AcquisitionInterrupted) as stop:
        _run(path, dome)
    monkeypatch.undo()
    assert (stop.value.done, stop.value.total) == (k, TOTAL)
    assert dome.calls[-1] == ("light", False, None)
    assert len(read_capture(path).frames) == k and (path / f"frames/{k:04d}.exr").is_file()
    camera, again = Camera(_camera()), FakeDome()
    _run(path, again, camera, resume=True)
    assert camera.taken == list(range(k + 1, TOTAL)), "the written frame must be adopted, not taken again"
    _assert_same(path, reference[0])


def test_a_damaged_frame_left_by_a_kill_is_taken_again(reference, tmp_path):
    path, k = tmp_path / "capture", 3
    with pytest.raises(AcquisitionStopped):
        _run(path, FakeDome(fail={"move": (k, DomeTimeout("no reply"))}))
    orphan = path / f"frames/{k:04d}.exr"
    orphan.write_bytes(read_capture(path).root.joinpath("frames/0000.exr").read_bytes()[:100])  # cut short
    (path / ".capture.json.x1.part.json").write_text("{")  # what atomic writes leave when killed
    (path / f"frames/.{k:04d}.exr.x2.part.exr").write_bytes(b"half")
    camera = Camera(_camera())
    _run(path, FakeDome(), camera, resume=True)
    assert camera.taken == list(range(k, TOTAL))
    assert not list(path.glob(".*part*")) and not list(path.glob("frames/.*part*")), "leftovers must be removed"
    _assert_same(path, reference[0])


def test_outputs_that_are_not_this_job_are_refused(reference, tmp_path):
    path = tmp_path / "capture"
    with pytest.raises(AcquisitionStopped):
        _run(path, FakeDome(fail={"move": (2, DomeTimeout("no reply"))}))
    with pytest.raises(AcquisitionError, match=r"must be empty or absent.*--resume"):
        _run(path)
    refusals = [
        ({"layout": "grid:6x6"}, r"another acquisition: its layout \(\"grid:5x5\" saved, \"grid:6x6\" now\)"),
        ({"light": LightSettings(POINT, intensity=0.5, irradiance=1.5)}, r"its intensity \(0.7 saved, 0.5 now\)"),
        ({"light": LightSettings(GAUSSIAN, intensity=0.7, irradiance=1.5)}, "its light"),
        ({"radius": 0.7}, "its radius.*frames"),
    ]
    for change, message in refusals:
        with pytest.raises(AcquisitionError, match=message):
            _run(path, resume=True, **change)
    with pytest.raises(AcquisitionError, match=r"acquired with the dome .*FAKE.*OTHER"):
        _run(path, FakeDome(identity=("OTHER", "2.1", 1)), resume=True)
    small = Camera(_camera())
    small.size = (4, 4)
    with pytest.raises(AcquisitionError, match=r"must be 6x8 \(height x width\) like the 2 saved.*got a 4x4 camera"):
        _run(path, camera=small, resume=True)
    assert len(read_capture(path).frames) == 2, "a refused resume must leave the capture as it was"
    leftover = tmp_path / "leftover"  # killed while writing its plan: the temporary file is not content
    leftover.mkdir()
    (leftover / ".acquire.json.k3x.part.json").write_text("{")
    assert len(_run(leftover, layout="grid:3x3").frames) == 5
    stranger = tmp_path / "stranger"
    stranger.mkdir()
    (stranger / "notes.txt").write_text("mine")
    for resume in (False, True):
        with pytest.raises(AcquisitionError, match=r"notes.txt"):
            _run(stranger, resume=resume)
    done = FakeDome()  # resuming a finished acquisition does nothing
    _run(reference[0], done, resume=True)
    assert done.moves() == []


def test_the_dome_must_be_where_it_was_sent(tmp_path):
    with pytest.raises(AcquisitionStopped, match=r"frame 0 .*at status after the move.*deg away") as stop:
        _run(tmp_path / "a", FakeDome(offset=0.01))
    message = str(stop.value)  # one unit in one message: degrees, as the protocol
    assert " rad" not in message and "within 0.0573 deg" in message and "phi=90.0000 deg" in message, message
    with pytest.raises(AcquisitionStopped, match=r"the light off"):
        _run(tmp_path / "b", FakeDome(lamp=False))
    capture = _run(tmp_path / "c", FakeDome(offset=0.01), tolerance=None, layout="grid:3x3")
    assert len(capture.frames) == 5


def test_a_wrong_frame_from_the_camera_stops_the_run(tmp_path):
    camera = Camera(_camera())
    camera.capture = lambda direction, *, index: torch.zeros(3, 5, 5) if index == 2 else torch.ones(3, 6, 8)
    with pytest.raises(AcquisitionStopped, match=r"frame 2 .*shape \(3, 6, 8\).*got \(3, 5, 5\)"):
        _run(tmp_path / "capture", camera=camera)
    assert len(read_capture(tmp_path / "capture").frames) == 2


# --- end to end through the emulator's pty --------------------------------------------------------------

FAST = 200.0  # rad/s: motions of a few ms


def test_end_to_end_a_fit_recovers_the_painting(tmp_path):
    scene = SceneConfig(kind="painting", painting=PaintingConfig(width=16, height=16, seed=5, gilded=None))
    camera = SimulatedCamera(scene, GAUSSIAN)
    with DomeEmulator(speed=FAST) as emulator, DomeClient(emulator.port, timeout=1.0) as client:
        capture = acquire(
            client, camera, tmp_path / "capture", light=LightSettings(GAUSSIAN), layout="grid:8x8", progress=False
        )
        assert emulator.executed["MOVE"] == len(capture.frames) == 32
        assert not emulator.status().light
    result = fit(tmp_path / "capture", progress=False)
    truth, regions = painting(scene.painting, dtype=torch.float64)
    s, t = result.svbrdf.flatten(), truth.flatten()
    lobe = regions.reshape(-1) == 1
    normal = torch.rad2deg(angle(s.normal.double(), t.normal))
    kd = ((s.diffuse.double() - t.diffuse) / t.diffuse).abs()
    ks = ((s.specular.double().mean(-1) - t.specular.mean(-1)) / t.specular.mean(-1)).abs()[lobe]
    alpha = ((s.roughness[:, 0].double() - t.roughness[:, 0]) / t.roughness[:, 0]).abs()[lobe]
    # The tolerances of tests/test_fit.py's simulated painting.
    assert normal.median() < 0.05 and normal.max() < 1.0, (
        f"normal error median {normal.median():.3g}, max {normal.max():.3g} deg"
    )
    assert kd.median() < 2e-3, f"median k_d error {kd.median():.3g}"
    assert ks.median() < 0.02, f"median k_s error {ks.median():.3g}"
    assert alpha.median() < 0.02, f"median alpha error {alpha.median():.3g}"


@pytest.mark.parametrize("fault", ["drop", "garble", "stall", "disconnect", "motor"])
def test_end_to_end_each_fault_recovers_or_stops_cleanly(reference, tmp_path, fault):
    path, k = tmp_path / "capture", 4
    emulator = DomeEmulator(speed=FAST).start()
    try:
        command = "MOVE" if fault in ("motor", "drop", "garble") else None
        camera = Camera(_camera(), fail_at=k - 1, action=lambda: emulator.inject(fault, command=command, seconds=0.7))
        with DomeClient(emulator.port, timeout=0.15, retries=2, backoff=0.01) as client:
            if fault in ("drop", "garble"):  # recovered by a resend: the run completes
                _run(path, client, camera)
                assert emulator.executed["MOVE"] == TOTAL, "a resent MOVE must not be acted on twice"
                _assert_same(path, reference[0], manifest=False)
                return
            with pytest.raises(AcquisitionStopped) as stop:
                _run(path, client, camera)
        cause = {"stall": DomeTimeout, "disconnect": DomeDisconnected, "motor": DomeFault}[fault]
        message = str(stop.value)
        assert isinstance(stop.value.__cause__, cause), message
        assert f"stopped at frame {k} (frames/{k:04d}.exr) of {TOTAL}, at move to theta=" in message, message
        assert emulator.port in message, message
        assert f"{k} of {TOTAL} frames are saved" in message, message
        assert len(read_capture(path).frames) == k and inspect_capture(path)["verdict"] != UNUSABLE
        if fault == "motor":
            assert not emulator.status().light, "the light must be switched off after a motor fault"
        if fault == "disconnect":  # the device is gone: a new one (the same model) on another port
            emulator.stop()
            emulator = DomeEmulator(speed=FAST).start()
        time.sleep(0.7 if fault == "stall" else 0.0)  # the stalled device wakes up
        with DomeClient(emulator.port, timeout=0.5) as client:
            _run(path, client, resume=True)
    finally:
        emulator.stop()
    _assert_same(path, reference[0], manifest=False)


# --- the command line ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def cli_files(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cli")
    (folder / "light.yaml").write_text(
        "light: {kernel: gaussian, domain: projected, sigma: 0.08}\nintensity: 0.7\nirradiance: 1.5\n"
    )
    (folder / "camera.yaml").write_text(
        "scene: {kind: painting, painting: {width: 8, height: 6, seed: 2, gilded: null}}\n"
        "sensor: {exposure: 2.0, photons_per_unit: 400.0, read_noise: 0.01, seed: 3}\n"
    )
    return folder


def _argv(port, files, output, *extra):
    return [
        "acquire",
        "--port",
        port,
        "--layout",
        "grid:6x6",
        "--light",
        str(files / "light.yaml"),
        "--camera",
        f"sim:{files / 'camera.yaml'}",
        "-o",
        str(output),
        "--quiet",
        *extra,
    ]


def test_cli_reports_a_stop_and_resumes(cli_files, tmp_path, capsys, monkeypatch):
    output = tmp_path / "capture"
    with DomeEmulator(speed=FAST) as emulator:
        emulator.inject("motor", command="MOVE")
        argv = _argv(emulator.port, cli_files, output)
        monkeypatch.setattr(sys, "argv", ["torchspec", *argv])
        assert main(argv) == 1
        err = capsys.readouterr().err
        assert "DomeFault" in err and "no frame is saved yet" in err and f"torchspec {' '.join(argv)} --resume" in err
        assert main(argv) == 2 and "must be empty or absent" in capsys.readouterr().err
        assert main([*argv, "--resume"]) == 0, capsys.readouterr().err
    assert "wrote" in capsys.readouterr().out
    capture = read_capture(output)
    assert len(capture.frames) == 16 and torch.all(capture.exposure() == 2.0)  # the camera config's


def test_cli_with_a_tethered_camera(tmp_path):
    watch, source = tmp_path / "watch", tmp_path / "shot.exr"
    watch.mkdir()
    write_exr(source, np.full((4, 5, 3), 0.25, np.float32), ["R", "G", "B"])
    (tmp_path / "light.json").write_text(json.dumps({"light": POINT, "exposure": 0.5}))
    shutter = f"sh -c 'cp {source} {watch}/IMG_$(date +%s%N).exr'"  # a camera program writing in place
    with DomeEmulator(speed=FAST) as emulator:
        argv = ["acquire", "--port", emulator.port, "--layout", "grid:3x3", "--light", str(tmp_path / "light.json"),
                "--camera", f"folder:{watch}", "--trigger", shutter, "--frame-timeout", "10", "-o",
                str(tmp_path / "capture"), "--quiet"]  # fmt: skip
        assert main(argv) == 0
    capture = read_capture(tmp_path / "capture")
    assert len(capture.frames) == 5 and len(list(watch.glob("IMG_*.exr"))) == 5
    assert torch.all(capture.read_frames() == 0.25) and torch.all(capture.exposure() == 0.5)


def test_cli_killed_mid_way_and_resumed_equals_an_uninterrupted_run(cli_files, tmp_path):
    reference, output = tmp_path / "reference", tmp_path / "capture"
    with DomeEmulator(speed=FAST) as emulator:
        assert main(_argv(emulator.port, cli_files, reference)) == 0
    with DomeEmulator(speed=4.0) as emulator:  # motions of ~0.05-0.8 s: the child is caught mid-way
        env = {**os.environ, "OMP_NUM_THREADS": "1"}
        command = [sys.executable, "-m", "torchspec", *_argv(emulator.port, cli_files, output)]
        child = subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 120
        while _listed(output) < 4:
            assert child.poll() is None, f"the acquisition ended before it was killed: {child.communicate()}"
            assert time.monotonic() < deadline, "no frame within 2 minutes"
            time.sleep(0.005)
        child.send_signal(signal.SIGKILL)
        child.communicate(timeout=60)
    assert child.returncode == -signal.SIGKILL
    done = _listed(output)
    assert 4 <= done < 16, f"killed after {done} frames"
    report = inspect_capture(output)
    assert report["verdict"] != UNUSABLE and report["frames"] == done, report["reason"] or report["warnings"]
    with DomeEmulator(speed=FAST) as emulator:  # the dome power-cycled: homed again by the resume
        assert main(_argv(emulator.port, cli_files, output, "--resume")) == 0
    _assert_same(output, reference)


def _listed(output: Path) -> int:
    try:
        return len(json.loads((output / "capture.json").read_text())["frames"])
    except (OSError, ValueError):
        return 0
