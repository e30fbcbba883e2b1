"""Cameras for the light dome: what takes a frame once the light is in place.

A camera is anything with :class:`Camera`'s attributes and ``capture(direction, *, index)``,
which returns the frame as a linear-radiance image ``(C, H, W)`` (what a capture's
``frames/*.exr`` hold, exposure included). Two are provided:

- :class:`SimulatedCamera` renders a known SVBRDF (maps, or a procedural scene of
  :mod:`torchspec.simulate.synth`) under the light at ``direction`` with :func:`torchspec.model.rendering.render`
  and records it with :func:`torchspec.simulate.synth.sense` - the simulator's renderer and sensor, one
  frame at a time. Its noise is seeded by the frame index, so a frame taken again (an
  acquisition resumed) is the same frame, bit for bit.
- :class:`FolderCamera` waits for a tethered camera's file: a frame is a new EXR that appears in
  a folder, taken once its size has stopped changing and it reads completely. An optional
  trigger (a callable, e.g. :func:`command_trigger` for a shutter command) fires first.

``capture`` takes the frame index beside the direction: the simulated camera derives its noise
from it, and every error names the frame.
"""

from __future__ import annotations

import shlex
import subprocess
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np
import torch
from torch import Tensor

from ..config import ConfigError
from ..errors import TorchspecError
from ..io import ExrError, LightSpec, read_exr
from ..model.brdf import SVBRDF
from ..model.lights import Kernel, Lights
from ..model.quadrature import Quadrature
from ..model.rendering import render
from ..simulate import LightConfig, SceneConfig
from ..simulate.synth import SensorConfig, mirror, painting, sense

__all__ = [
    "Camera",
    "CameraError",
    "CameraTimeout",
    "SimulatedCamera",
    "SimulatedCameraConfig",
    "FolderCamera",
    "command_trigger",
]


class CameraError(OSError):
    """A camera that failed to deliver a frame; the message names the camera (its folder or
    trigger) and the frame."""


class CameraTimeout(CameraError, TimeoutError):
    """No frame arrived in time."""


@runtime_checkable
class Camera(Protocol):
    """What the acquisition needs of a camera.

    Attributes:
        channels: the ``C`` channel names of every frame, in order.
        size: ``(H, W)``, or ``None`` while not known (a folder camera learns it from its first
            frame; the acquisition then holds every frame to the first one's size).
        exposure: the factor from radiance to recorded value, written in the manifest; ``None``
            when the camera does not know it (the light config then gives it, or 1).
    """

    channels: tuple[str, ...]
    size: tuple[int, int] | None
    exposure: float | None

    def capture(self, direction: Tensor, *, index: int) -> Tensor:
        """Take frame ``index`` under the light centred on ``direction`` ``(3,)``: a linear
        radiance image ``(C, H, W)``, raising :class:`CameraError` when no frame comes."""
        ...


# --- the simulated camera -----------------------------------------------------------------------


@dataclass(frozen=True)
class SimulatedCameraConfig:
    """A simulated camera in a config file (``torchspec acquire --camera sim:FILE``).

    Attributes:
        scene: the procedural object (:class:`torchspec.simulate.SceneConfig`).
        channels: the channel names; their count must be the scene's.
        sensor: exposure, noise (seeded by ``sensor.seed`` and the frame index) and clipping.
        light: the light's true shape, when it differs from what the acquisition records (a
            light described as ``unknown``, to be calibrated); ``None`` renders the recorded one.
    """

    scene: SceneConfig = field(default_factory=SceneConfig)
    channels: tuple[str, ...] = ("R", "G", "B")
    sensor: SensorConfig = field(default_factory=SensorConfig)
    light: LightConfig | None = None


class SimulatedCamera:
    """A camera looking straight down at a known SVBRDF lit by the dome's light.

    Each frame is :func:`torchspec.model.rendering.render` of the scene under one light centred on the
    requested direction (the kernel, irradiance and view given here), recorded by
    :func:`torchspec.simulate.synth.sense` with a generator seeded by ``(sensor.seed, index)``: frames
    are deterministic per index, and independent of the order they are taken in.

    Args:
        scene: maps with leading dims ``(H, W)`` (their dtype and device are the rendering's),
            or a :class:`~torchspec.simulate.SceneConfig` built in float64 as
            :func:`torchspec.simulate.simulate` builds it.
        light: the light's shape: a :class:`~torchspec.model.lights.Kernel`, or a format light block
            (a mapping or :class:`~torchspec.io.LightSpec`) read by :meth:`Kernel.from_spec`.
        irradiance: a number or ``C`` numbers, as the manifest will record them.
        sensor: exposure, shot and read noise, saturation and the noise seed.
        channels: the ``C`` channel names (by default the maps' names).
        view: the direction towards the camera.
        path: the quadrature of :func:`torchspec.model.rendering.render`.

    Example:
        >>> camera = SimulatedCamera(SceneConfig(), {"kernel": "gaussian", "domain": "projected", "sigma": 0.08})
        >>> camera.capture(torch.tensor([0.0, 0.0, 1.0]), index=0).shape  # doctest: +SKIP
        torch.Size([3, 48, 48])
    """

    def __init__(
        self,
        scene: SVBRDF | SceneConfig,
        light: Kernel | LightSpec | Mapping,
        *,
        irradiance: float | Sequence[float] = 1.0,
        sensor: SensorConfig | None = None,
        channels: Sequence[str] | None = None,
        view: Sequence[float] = (0.0, 0.0, 1.0),
        path: str = "auto",
    ):
        svbrdf = _scene(scene) if isinstance(scene, SceneConfig) else scene
        if not isinstance(svbrdf, SVBRDF) or svbrdf.normal.dim() != 3:
            raise TorchspecError(f"scene must be (H, W) maps or a SceneConfig; got {type(scene).__name__}.")
        count = svbrdf.diffuse.shape[-1]
        names = tuple(channels) if channels is not None else svbrdf.channels
        if names is None or len(names) != count:
            raise TorchspecError(f"channels must name the scene's {count} channel(s); got {names!r}.")
        kernel = light if isinstance(light, Kernel) else Kernel.from_spec(light)
        if kernel.kind == "unknown":
            raise TorchspecError("light must be a known kernel to render frames; got 'unknown'. Give the true shape.")
        like = dict(dtype=svbrdf.diffuse.dtype, device=svbrdf.diffuse.device)
        values = [float(irradiance)] if isinstance(irradiance, (int, float)) else [float(v) for v in irradiance]
        if len(values) not in (1, count) or not all(v > 0 for v in values):
            raise TorchspecError(
                f"irradiance must be a positive number or {count} positive numbers; got {irradiance!r}."
            )
        self.svbrdf = svbrdf
        self.kernel = kernel
        self.irradiance = torch.tensor(values, **like)[None]  # (1, 1) or (1, C)
        self.sensor = sensor if sensor is not None else SensorConfig()
        self.view = torch.tensor(tuple(view), **like)
        self.path = path
        self.channels = names
        self.size = (svbrdf.normal.shape[0], svbrdf.normal.shape[1])
        self.exposure = self.sensor.exposure

    @classmethod
    def from_config(
        cls, config: SimulatedCameraConfig, kernel: Kernel | None, *, irradiance: float | Sequence[float] = 1.0
    ) -> SimulatedCamera:
        """The camera of a :class:`SimulatedCameraConfig`. ``kernel`` is the acquisition's light
        (``None`` when it is recorded as ``unknown``), rendered unless the config gives the true one."""
        if config.light is not None:
            truth = config.light
            if truth.kernel == "point":
                kernel = Kernel("point")
            else:
                kernel = Kernel(truth.kernel, truth.domain, truth.sigma, truth.power)
        if kernel is None:
            raise ConfigError(
                "the acquisition's light is 'unknown', so a simulated camera cannot render it; give the true "
                "shape as 'light' in the camera config."
            )
        return cls(config.scene, kernel, irradiance=irradiance, sensor=config.sensor, channels=config.channels)

    def capture(self, direction: Tensor, *, index: int) -> Tensor:
        """Frame ``index`` under the light centred on ``direction`` ``(3,)``: ``(C, H, W)`` in the
        maps' dtype and on their device."""
        like = self.svbrdf.diffuse
        centre = torch.as_tensor(direction, device=like.device).to(dtype=like.dtype).reshape(1, 3)
        ones = torch.ones(1, dtype=like.dtype, device=like.device)
        lights = Lights(centre, self.kernel, self.irradiance, ones)
        values = render(self.svbrdf, lights, self.view, quadrature=Quadrature(path=self.path))  # (H, W, 1, C)
        noise = _generator(self.sensor.seed, index)
        recorded, _ = sense(values[:, :, 0].permute(2, 0, 1), self.sensor, generator=noise)
        return recorded


def _scene(config: SceneConfig) -> SVBRDF:
    """The truth of :func:`torchspec.simulate.simulate`'s scene, float64."""
    if config.kind == "painting":
        svbrdf, _ = painting(config.painting, dtype=torch.float64)
    elif config.kind == "mirror":
        svbrdf, _ = mirror(config.mirror, dtype=torch.float64)
    else:
        raise ConfigError(f"scene.kind must be 'painting' or 'mirror'; got {config.kind!r}.")
    return svbrdf


def _generator(seed: int, index: int) -> torch.Generator:
    """A CPU generator for frame ``index``: SeedSequence mixes the pair into unrelated streams
    (``seed + index`` would make frame 1 of seed 0 frame 0 of seed 1)."""
    state = np.random.SeedSequence([int(seed), int(index)]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator().manual_seed(int(state) & 0x7FFF_FFFF_FFFF_FFFF)


# --- the folder camera --------------------------------------------------------------------------


def command_trigger(command: str | Sequence[str], *, timeout: float = 30.0) -> Callable[[], None]:
    """A trigger that runs ``command`` (a shell-like string, split with :func:`shlex.split`, or a
    list) and raises :class:`CameraError` when it fails, e.g. ``gphoto2 --trigger-capture``."""
    argv = shlex.split(command) if isinstance(command, str) else list(command)
    if not argv:
        raise TorchspecError("command must name a program; got an empty command.")

    def trigger() -> None:
        try:
            done = subprocess.run(argv, capture_output=True, text=True, timeout=timeout, check=False)
        except (OSError, subprocess.TimeoutExpired) as error:
            raise CameraError(f"the trigger command {shlex.join(argv)!r} could not run: {error}.") from error
        if done.returncode != 0:
            detail = (done.stderr or done.stdout).strip().splitlines()
            raise CameraError(
                f"the trigger command {shlex.join(argv)!r} must succeed; got exit status {done.returncode}"
                + (f": {detail[-1]}" if detail else "")
                + ". Check the camera's connection."
            )

    return trigger


class FolderCamera:
    """A tethered camera that saves each frame as a file in ``folder``.

    ``capture`` notes the files already there, fires the trigger, and waits for one new file
    matching ``pattern`` (names starting with ``.``, the temporary names of atomic writers, are
    never taken); the file is taken once its size has been the same, and non-zero, for
    ``settle`` seconds and it reads as an EXR with the channels. The file is left in the folder.

    Args:
        folder: the folder the camera software saves into.
        channels: the ``C`` channels to read from each file.
        pattern: a glob of the frame files.
        timeout: seconds to wait for a frame after the trigger.
        settle: seconds a file's size must stay the same before it is read.
        trigger: called with no argument to fire the shutter (e.g. :func:`command_trigger`);
            ``None`` when the camera fires by itself.
        exposure: the camera's exposure factor, if known.
        size: the expected ``(H, W)``, if known.
        poll: seconds between looks at the folder.

    Raises:
        CameraTimeout: (from ``capture``) no complete new file within ``timeout``; the message
            names the folder, the pattern and the frame.
        CameraError: two new files for one frame, or a frame of another size.
    """

    def __init__(
        self,
        folder: str | Path,
        *,
        channels: Sequence[str] = ("R", "G", "B"),
        pattern: str = "*.exr",
        timeout: float = 60.0,
        settle: float = 0.2,
        trigger: Callable[[], object] | None = None,
        exposure: float | None = None,
        size: tuple[int, int] | None = None,
        poll: float = 0.02,
    ):
        self.folder = Path(folder)
        if not self.folder.is_dir():
            raise TorchspecError(f"folder must be an existing folder to watch; got {self.folder}. Create it first.")
        if not (timeout > 0 and settle >= 0 and poll > 0):
            raise TorchspecError(f"timeout and poll must be > 0 and settle >= 0; got {timeout}, {poll}, {settle}.")
        self.channels = (channels,) if isinstance(channels, str) else tuple(channels)
        self.pattern = pattern
        self.timeout = timeout
        self.settle = settle
        self.trigger = trigger
        self.exposure = exposure
        self.size = size
        self.poll = poll

    def _files(self) -> dict[Path, int]:
        sizes = {}
        for path in self.folder.glob(self.pattern):
            if path.name.startswith("."):
                continue
            try:
                sizes[path] = path.stat().st_size
            except FileNotFoundError:  # renamed or removed between the listing and the look
                continue
        return sizes

    def capture(self, direction: Tensor, *, index: int) -> Tensor:
        """Frame ``index``: the next new complete file, as ``(C, H, W)`` float32."""
        before = set(self._files())
        if self.trigger is not None:
            self.trigger()
        deadline = time.monotonic() + self.timeout
        stable: dict[Path, tuple[int, float]] = {}  # size, and since when
        problem = ""
        while True:
            now = time.monotonic()
            new = {path: size for path, size in self._files().items() if path not in before}
            for path, size in new.items():
                if stable.get(path, (None,))[0] != size:
                    stable[path] = (size, now)
            ready = sorted(path for path, size in new.items() if size > 0 and now - stable[path][1] >= self.settle)
            if len(ready) > 1:
                raise CameraError(
                    f"one new file per frame must appear in {self.folder}; got {len(ready)} for frame {index}: "
                    f"{[path.name for path in ready]}. Set the camera to save one {self.pattern!r} file per shot."
                )
            if ready:
                try:
                    return self._read(ready[0], index)
                except ExrError as error:  # still being written by a writer that does not rename
                    problem = f" ({ready[0].name} stays unreadable: {error})"
                    stable[ready[0]] = (new[ready[0]], now)
            if now >= deadline:
                raise CameraTimeout(
                    f"a new complete {self.pattern!r} file must appear in {self.folder} within {self.timeout:g} s "
                    f"for frame {index}; got none{problem}. Check that the camera is tethered, fires, and saves "
                    "into that folder."
                )
            time.sleep(self.poll)

    def _read(self, path: Path, index: int) -> Tensor:
        image = torch.from_numpy(read_exr(path, self.channels)).permute(2, 0, 1)
        if self.size is not None and tuple(image.shape[1:]) != tuple(self.size):
            raise CameraError(
                f"frame {index} ({path}) must be {self.size[0]}x{self.size[1]} (height x width, as the frames "
                f"before); got {image.shape[1]}x{image.shape[2]}. Keep the camera's resolution fixed."
            )
        self.size = (image.shape[1], image.shape[2])
        return image
