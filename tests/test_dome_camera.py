"""Cameras of the dome: the simulated camera is the simulator's renderer one frame at a time,
deterministic per frame; the folder camera takes one complete new file per frame."""

import threading
import time

import numpy as np
import pytest
import torch

from torchspec.dome.camera import (
    Camera,
    CameraError,
    CameraTimeout,
    FolderCamera,
    SimulatedCamera,
    SimulatedCameraConfig,
    command_trigger,
)
from torchspec.io import write_exr
from torchspec.model.lights import Kernel
from torchspec.simulate import LayoutConfig, LightConfig, SceneConfig, SimulationConfig, layout, simulate
from torchspec.simulate.synth import PaintingConfig, SensorConfig, painting

SCENE = SceneConfig(kind="painting", painting=PaintingConfig(width=10, height=8, seed=4, gilded=None))
GAUSSIAN = {"kernel": "gaussian", "domain": "projected", "sigma": 0.08}
NOISY = SensorConfig(exposure=2.0, photons_per_unit=500.0, read_noise=0.01, seed=9)


def test_simulated_frames_are_the_simulators():
    config = SimulationConfig(
        scene=SCENE, layout=LayoutConfig(kind="grid", nx=4, ny=4, extent=0.6, radius=0.8), irradiance=1.5
    )
    reference = simulate(config).frames.double()  # (K, C, H, W), rendered as one batch
    camera = SimulatedCamera(SCENE, GAUSSIAN, irradiance=1.5)
    assert isinstance(camera, Camera)
    assert camera.size == (8, 10) and camera.channels == ("R", "G", "B") and camera.exposure == 1.0
    frames = torch.stack([camera.capture(d, index=k) for k, d in enumerate(layout(config.layout))])
    error = ((frames - reference).abs() / reference.abs().max()).max()
    assert error < 1e-6, f"max relative difference to simulate() {error:.3g}"


def test_simulated_frames_are_deterministic_per_index():
    camera = SimulatedCamera(SCENE, GAUSSIAN, sensor=NOISY)
    direction = torch.tensor([0.3, -0.2, (1 - 0.13) ** 0.5], dtype=torch.float64)
    first = camera.capture(direction, index=3)
    again = SimulatedCamera(SCENE, GAUSSIAN, sensor=NOISY).capture(direction, index=3)  # another camera, later
    assert torch.equal(first, again)
    other = camera.capture(direction, index=4)
    assert not torch.equal(first, other), "another frame index must draw other noise"
    clean = SimulatedCamera(SCENE, GAUSSIAN, sensor=SensorConfig(exposure=2.0)).capture(direction, index=3)
    noise = (first - clean).std() / clean.mean()
    assert 1e-3 < noise < 0.2, f"relative noise {noise:.3g}"


def test_simulated_camera_follows_the_maps_dtype_and_checks_its_input():
    maps, _ = painting(SCENE.painting, dtype=torch.float32)
    camera = SimulatedCamera(maps, Kernel("point"), irradiance=(1.0, 0.5, 2.0))
    image = camera.capture(torch.tensor([0.0, 0.0, 1.0]), index=0)
    assert image.dtype == torch.float32 and image.shape == (3, 8, 10)
    with pytest.raises(ValueError, match="irradiance must be"):
        SimulatedCamera(maps, Kernel("point"), irradiance=(1.0, 2.0))
    with pytest.raises(ValueError, match="channels must name the scene's 3"):
        SimulatedCamera(maps, Kernel("point"), channels=("Y",))
    with pytest.raises(ValueError, match="unknown"):
        SimulatedCamera(maps, {"kernel": "unknown", "symmetric": True})


def test_camera_config_renders_the_true_light_of_an_unknown_one():
    config = SimulatedCameraConfig(scene=SCENE)
    with pytest.raises(ValueError, match="'unknown'.*true"):
        SimulatedCamera.from_config(config, None)
    truth = SimulatedCameraConfig(
        scene=SCENE, light=LightConfig(kernel="supergaussian", domain="angular", sigma=0.05, power=6.0)
    )
    camera = SimulatedCamera.from_config(truth, None)
    assert camera.kernel.kind == "supergaussian" and camera.kernel.power == 6.0


# --- the folder camera ----------------------------------------------------------------------------


def _exr_bytes(tmp_path, value: float, size=(4, 5)) -> bytes:
    path = tmp_path / f"source-{value}.exr"
    write_exr(path, np.full((*size, 3), value, dtype=np.float32), ["R", "G", "B"])
    return path.read_bytes()


def _later(delay: float, action) -> threading.Thread:
    thread = threading.Thread(target=lambda: (time.sleep(delay), action()))
    thread.start()
    return thread


def test_folder_camera_takes_the_new_file_once_complete(tmp_path, monkeypatch):
    reads = []
    real = FolderCamera._read

    def spy(self, path, index):
        reads.append(path.name)
        return real(self, path, index)

    monkeypatch.setattr(FolderCamera, "_read", spy)
    watch = tmp_path / "watch"
    watch.mkdir()
    (watch / "old.exr").write_bytes(_exr_bytes(tmp_path, 9.0))  # there before: never a frame
    data = _exr_bytes(tmp_path, 0.25)
    target = watch / "IMG_0001.exr"

    def write_slowly():  # a camera program that writes in place, in two bursts
        with open(target, "wb") as out:
            out.write(data[: len(data) // 2])
            out.flush()
            time.sleep(0.3)
            out.write(data[len(data) // 2 :])

    shots = []
    camera = FolderCamera(watch, settle=0.1, timeout=5.0, trigger=lambda: shots.append(_later(0.05, write_slowly)))
    (watch / ".IMG_0002.exr.tmp.exr").write_bytes(b"partial")  # a hidden temporary: ignored
    image = camera.capture(torch.tensor([0.0, 0.0, 1.0]), index=7)
    shots[0].join()
    assert len(shots) == 1, f"the trigger fired {len(shots)} times"
    assert image.shape == (3, 4, 5) and torch.all(image == 0.25), f"read {image.unique().tolist()}"
    assert camera.size == (4, 5)
    assert len(reads) >= 2 and set(reads) == {"IMG_0001.exr"}, f"reads {reads}: the half file must be waited on"


def test_folder_camera_times_out_naming_folder_and_frame(tmp_path):
    camera = FolderCamera(tmp_path, timeout=0.2, settle=0.0)
    start = time.monotonic()
    with pytest.raises(CameraTimeout, match=rf"{tmp_path}.*0.2 s.*frame 12"):
        camera.capture(torch.tensor([0.0, 0.0, 1.0]), index=12)
    assert time.monotonic() - start < 1.0


def test_folder_camera_refuses_two_files_and_another_size(tmp_path):
    one, two = _exr_bytes(tmp_path, 1.0), _exr_bytes(tmp_path, 2.0, size=(3, 3))
    watch = tmp_path / "watch"
    watch.mkdir()

    def both():
        (watch / "a.exr").write_bytes(one)
        (watch / "b.exr").write_bytes(one)

    camera = FolderCamera(watch, settle=0.05, timeout=3.0, size=(4, 5), trigger=lambda: _later(0.0, both).join())
    with pytest.raises(CameraError, match=r"one new file per frame.*2 for frame 0.*a.exr"):
        camera.capture(torch.tensor([0.0, 0.0, 1.0]), index=0)
    camera.trigger = lambda: (watch / "c.exr").write_bytes(two)
    with pytest.raises(CameraError, match=r"frame 1 .*c.exr.*must be 4x5.*got 3x3"):
        camera.capture(torch.tensor([0.0, 0.0, 1.0]), index=1)


def test_command_trigger_reports_a_failing_command(tmp_path):
    command_trigger("true")()
    with pytest.raises(CameraError, match=r"exit status 3: no camera"):
        command_trigger(["sh", "-c", "echo no camera >&2; exit 3"])()
    with pytest.raises(CameraError, match="could not run"):
        command_trigger(str(tmp_path / "no-such-program"))()
