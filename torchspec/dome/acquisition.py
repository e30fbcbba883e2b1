"""Acquisition with the light dome: for each planned light position, move the light, take the
frame, and add it to the capture, so that a stop at any moment leaves a valid capture of the
frames done, and ``resume`` continues it to the capture an uninterrupted run would have made.

A capture being acquired is a capture directory (``docs/capture-format.md``) plus ``acquire.json``,
the plan: the layout, the light, the camera's channels and exposure, the dome's identity and
every planned frame (file, direction, dome angles). Frame ``k`` goes to ``frames/kkkk.exr``
(written atomically), then ``capture.json`` is rewritten (atomically) listing frames ``0..k``:
the manifest lists exactly the frames on disk, always in the plan's order. A frame file written
but not yet listed (a stop between the two writes) is adopted when it reads completely, and
taken again otherwise; it is never listed twice. Readers ignore ``acquire.json``.

Layouts: :func:`torchspec.dome.plan.plan_directions`. Frames are taken in the layout's order
(rows from the top).
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from .._version import __version__
from ..atomic import read_json, write_json
from ..errors import TorchspecError
from ..io import Capture, ExrError, Frame, LightSpec, read_capture, read_exr, write_exr
from ..io._manifest import MANIFEST, parse_manifest, to_manifest
from ..outputs import TEMPORARY, OutputError, check_output, content
from ..progress import bar as progress_bar
from .camera import Camera, FolderCamera, SimulatedCamera, SimulatedCameraConfig, command_trigger
from .client import DomeDisconnected, DomeTimeout
from .plan import (
    KERNEL_FILE,
    AcquisitionError,
    LightSettings,
    as_tuple,
    dome_angles,
    dome_direction,
    load_light,
    parse_layout,
    plan_directions,
)

__all__ = [
    "PLAN",
    "AcquisitionError",
    "AcquisitionStopped",
    "AcquisitionInterrupted",
    "LightSettings",
    "load_light",
    "parse_layout",
    "plan_directions",
    "dome_angles",
    "open_camera",
    "acquire",
]

PLAN = "acquire.json"
"""The plan of an acquisition, beside its ``capture.json``."""
_PLAN_FORMAT = "torchspec.acquire"


class AcquisitionStopped(OSError):
    """An acquisition stopped by the dome, the camera or the disk. The frames done are saved as a
    valid capture and ``acquire(..., resume=True)`` continues it.

    Attributes:
        done, total: frames saved and planned.
        output: the capture folder.
        frame: the frame being taken when it stopped.
    """

    def __init__(self, message: str, *, done: int, total: int, output: Path, frame: int):
        super().__init__(message)
        self.done, self.total, self.output, self.frame = done, total, output, frame

    def __str__(self) -> str:
        return self.args[0]


class AcquisitionInterrupted(KeyboardInterrupt):
    """An acquisition stopped by Ctrl-C; the frames done are saved, as for :class:`AcquisitionStopped`."""

    def __init__(self, done: int, total: int, output: Path):
        super().__init__(f"the acquisition was interrupted after {done} of {total} frames; they are saved in {output}.")
        self.done, self.total, self.output = done, total, output


def _job(spec: str, radius: float, directions: Tensor, light: LightSettings, camera: Camera) -> dict:
    """The plan without the dome's identity: what a resumed acquisition must match."""
    channels = list(camera.channels)
    exposure = _exposure(light, camera)
    angles = dome_angles(directions)
    digits = max(4, len(str(directions.shape[0] - 1)))
    block = {"kernel": light.light.kernel}
    for key in ("domain", "sigma", "file", "extent", "symmetric"):
        if getattr(light.light, key) is not None:
            block[key] = getattr(light.light, key)
    if light.table is not None:
        block["table_sum"] = float(light.table.double().sum())  # a changed kernel image is another job
        block["table_shape"] = list(light.table.shape)
    job = {
        "format": _PLAN_FORMAT,
        "version": 1,
        "layout": str(spec),
        "radius": float(radius),
        "light": block,
        "intensity": float(light.intensity),
        "irradiance": list(light.irradiance_for(channels)),
        "exposure": exposure,
        "channels": channels,
        "view": [float(v) for v in getattr(camera, "view", (0.0, 0.0, 1.0))],
        "frames": [
            {"file": f"frames/{k:0{digits}d}.exr", "direction": d, "theta": a[0], "phi": a[1]}
            for k, (d, a) in enumerate(zip(directions.tolist(), angles.tolist(), strict=True))
        ],
    }
    return json.loads(json.dumps(job))  # as it reads back: lists, floats


def _exposure(light: LightSettings, camera: Camera) -> float:
    own = getattr(camera, "exposure", None)
    if light.exposure is not None and own is not None and float(own) != float(light.exposure):
        raise AcquisitionError(
            f"exposure must be the camera's ({own:g}) when the light config gives one; got {light.exposure:g}. "
            "Drop exposure from the light config, or set the camera's."
        )
    chosen = light.exposure if light.exposure is not None else own
    return 1.0 if chosen is None else float(chosen)


# --- the output folder --------------------------------------------------------------------------


def _differences(saved: dict, job: dict) -> list[str]:
    out = []
    for key, value in job.items():
        if saved.get(key) == value:
            continue
        if key == "frames":
            out.append(f"frames (the planned directions or files: {len(saved.get(key) or [])} saved, {len(value)} now)")
        else:
            out.append(f"{key} ({_show(saved.get(key))} saved, {_show(value)} now)")
    return out


def _show(value) -> str:
    text = json.dumps(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _open_output(output: Path, job: dict, resume: bool, overwrite: bool) -> dict | None:
    """Check the output folder; the saved plan when resuming one (``None`` to start afresh)."""
    try:  # a file in the way, a folder that does not accept files; the content is checked below
        check_output(output, overwrite=True)
    except OutputError as error:
        raise AcquisitionError(str(error)) from None
    # Temporary files of atomic writes that a kill left (``.NAME.*.part*``) are not content.
    entries = content(output)
    plan = output / PLAN
    if not resume:
        if entries and not overwrite:
            raise AcquisitionError(
                f"the output {output} must be empty or absent to start an acquisition; got {len(entries)} "
                f"entr{'y' if len(entries) == 1 else 'ies'} ({', '.join(entries[:5])}{', ...' * (len(entries) > 5)})."
                + (" Add --resume to continue the acquisition there," if PLAN in entries else "")
                + " Add --overwrite to start afresh there, or choose another folder."
            )
        return None
    if not plan.is_file():
        if entries:
            raise AcquisitionError(
                f"the output {output} holds no {PLAN}, so it is not an acquisition to resume; got "
                f"{', '.join(entries[:5])}. Choose another folder."
            )
        return None
    saved = read_json(plan, AcquisitionError, "")
    if not isinstance(saved, dict) or saved.get("format") != _PLAN_FORMAT or saved.get("version") != 1:
        raise AcquisitionError(
            f"{plan} must be a plan of torchspec acquire (format {_PLAN_FORMAT!r}, version 1); got another file."
        )
    differ = _differences(saved, job)
    if differ:
        raise AcquisitionError(
            f"{plan} records another acquisition: its {'; '.join(differ)}. Resuming would mix two jobs: run the "
            "same command as before (layout, radius, light config, camera), or acquire into another folder."
        )
    return saved


def _remove_temporaries(output: Path) -> None:
    """Remove the temporary files of atomic writes that a killed process left (``.NAME.*.part*``)."""
    for folder in (output, output / "frames"):
        if folder.is_dir():
            for path in folder.iterdir():
                if TEMPORARY.match(path.name) and path.is_file():
                    path.unlink(missing_ok=True)


def _frames_done(output: Path, job: dict) -> tuple[int, tuple[int, int] | None]:
    """Frames the manifest lists (a prefix of the plan, checked) and the capture's ``(H, W)``."""
    if not (output / MANIFEST).is_file():
        return 0, None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        capture = read_capture(output)
    planned = job["frames"]
    if list(capture.channels) != job["channels"]:
        raise AcquisitionError(
            f"{capture.manifest}: channels must be the plan's {job['channels']}; got {list(capture.channels)}."
        )
    for k, frame in enumerate(capture.frames):
        if k >= len(planned) or frame.file != planned[k]["file"] or list(frame.direction) != planned[k]["direction"]:
            want = planned[k]["file"] if k < len(planned) else "nothing (the plan has fewer frames)"
            raise AcquisitionError(
                f"{capture.manifest}: frames[{k}] must be the planned frame {want}; got {frame.file} at "
                f"{list(frame.direction)}. The capture no longer follows {PLAN}: acquire into another folder."
            )
    return len(capture.frames), (capture.height, capture.width)


def _write_manifest(output: Path, job: dict, frames: list[Frame], size: tuple[int, int], generator: dict) -> None:
    """Rewrite ``capture.json`` atomically, validated as :func:`~torchspec.io.read_capture` does."""
    block = {key: value for key, value in job["light"].items() if not key.startswith("table_")}
    capture = Capture(
        root=output,
        width=size[1],
        height=size[0],
        channels=tuple(job["channels"]),
        view=tuple(job["view"]),
        light=LightSpec(**block),
        frames=tuple(frames),
        extra={"generator": generator},
    )
    path = output / MANIFEST
    data = to_manifest(capture, path)
    parse_manifest(data, path, [], extra_known=True)
    write_json(path, data)


def _frame(job: dict, k: int) -> Frame:
    planned = job["frames"][k]
    return Frame(planned["file"], tuple(planned["direction"]), tuple(job["irradiance"]), job["exposure"])


def _checked(image, k: int, job: dict, size: tuple[int, int] | None) -> Tensor:
    """The camera's frame ``k`` as ``(C, H, W)`` float32, checked against the capture."""
    image = torch.as_tensor(image)  # checked where the camera made it; moved to the CPU below, to be written
    count = len(job["channels"])
    if image.dim() != 3 or image.shape[0] != count or (size is not None and tuple(image.shape[1:]) != size):
        want = f"({count}, {size[0]}, {size[1]})" if size is not None else f"({count}, H, W)"
        raise AcquisitionError(
            f"frame {k} from the camera must have shape {want} (channels {job['channels']}, the capture's size); "
            f"got {tuple(image.shape)}."
        )
    bad = int((~torch.isfinite(image)).any(0).sum())
    if bad:
        raise AcquisitionError(f"frame {k} from the camera must be finite; got {bad} pixel(s) with NaN or Inf.")
    return image.detach().to(device="cpu", dtype=torch.float32)


def _adoptable(output: Path, job: dict, k: int, size: tuple[int, int] | None) -> Tensor | None:
    """Frame ``k``'s file when it was written but not listed (a stop between the two writes) and
    reads completely; ``None`` when it must be taken (again)."""
    file = output / job["frames"][k]["file"]
    if not file.is_file():
        return None
    try:
        return _checked(torch.from_numpy(read_exr(file, job["channels"])).permute(2, 0, 1), k, job, size)
    except (ExrError, AcquisitionError):
        return None


# --- the loop -----------------------------------------------------------------------------------


def acquire(
    client,
    camera: Camera,
    output: str | Path,
    *,
    light: LightSettings,
    layout: str = "grid:12x12",
    radius: float = 0.8,
    resume: bool = False,
    progress: bool = True,
    tolerance: float | None = 1e-3,
    overwrite: bool = False,
) -> Capture:
    """Acquire a capture: home the dome, switch the light on, and for each planned direction move
    the light there, take the frame and save it.

    Args:
        client: an open :class:`~torchspec.dome.DomeClient` (or any object with its
            ``identify``, ``home``, ``move``, ``light`` and ``status`` methods).
        camera: a :class:`~torchspec.dome.camera.Camera`.
        output: the capture folder; it must be empty or absent unless ``resume``.
        light: the light (recorded kernel, intensity, irradiance, exposure).
        layout, radius: the light positions (:func:`plan_directions`).
        resume: continue the acquisition in ``output`` from its first missing frame; it must be
            the same job (plan, light, channels, exposure, dome model and firmware). With
            nothing in ``output``, start.
        progress: show a tqdm bar (on stderr).
        tolerance: after each move, ``client.status()`` must place the light within this angle
            (radians) of the planned direction, at rest, with the light on and no fault;
            ``None`` skips the check (one exchange less per frame).
        overwrite: start afresh in an ``output`` that holds files (an earlier capture's manifest
            and plan are removed first; frame files are replaced as they are taken).

    Returns:
        The capture, as :func:`~torchspec.io.read_capture` reads it.

    Raises:
        AcquisitionError: before anything moves: a bad layout or light, an output folder that
            is not empty (without ``resume``) or that holds another job.
        AcquisitionStopped: the dome, the camera or the disk failed; the message names the
            frame, the step and the cause, and says how many frames are saved.
        AcquisitionInterrupted: Ctrl-C; the frames done are saved.

    Example:
        >>> with DomeClient("/dev/ttyUSB0") as dome:  # doctest: +SKIP
        ...     acquire(dome, camera, "capture", light=load_light("light.yaml"), layout="grid:12x12")
    """
    output = Path(output)
    directions = plan_directions(layout, radius)
    job = _job(layout, radius, directions, light, camera)
    saved = _open_output(output, job, resume, overwrite)
    done, size = _resume_state(output, job, saved, camera)
    total = len(job["frames"])
    generator = {
        "name": "torchspec acquire",
        "torchspec": __version__,
        "layout": job["layout"],
        "radius": job["radius"],
        "intensity": job["intensity"],
        "planned": total,
    }
    bar = progress_bar(total, initial=done, desc="acquire", unit="frame", enabled=progress, leave=False)
    run = _Run(output, job, [_frame(job, k) for k in range(done)], done, size, generator, bar)
    try:
        _identify(client, run, saved, light)
        _adopt(run)
        _take_frames(client, camera, directions, run, tolerance)
    except KeyboardInterrupt as error:
        _switch_off(client, None)
        raise AcquisitionInterrupted(len(run.frames), total, output) from error
    except (OSError, TorchspecError) as error:
        if isinstance(error, AcquisitionError) and run.step == "identify":
            raise  # refused before anything moved
        raise _stopped(client, run, error) from error
    finally:
        bar.close()
    note = _switch_off(client, None)
    if note:
        warnings.warn(note.strip(), stacklevel=2)
    return read_capture(output)


@dataclass
class _Run:
    """An acquisition in progress: the step being taken at frame ``k``, the frames the manifest
    lists, and the frames' ``(H, W)`` once known."""

    output: Path
    job: dict
    frames: list[Frame]
    k: int
    size: tuple[int, int] | None
    generator: dict
    bar: Any
    step: str = "identify"

    @property
    def total(self) -> int:
        return len(self.job["frames"])

    def list_frame(self) -> None:
        """Rewrite the manifest with frame ``k`` (on disk) listed, and count it."""
        frame = _frame(self.job, self.k)
        _write_manifest(self.output, self.job, [*self.frames, frame], self.size, self.generator)
        self.frames.append(frame)  # counted once listed
        self.k += 1
        self.bar.update()


def _resume_state(output: Path, job: dict, saved: dict | None, camera: Camera) -> tuple[int, tuple[int, int] | None]:
    """The frames already done and the frames' ``(H, W)`` (``None`` while unknown), after removing
    the temporary files of a resumed acquisition and checking the camera's size against them."""
    if saved is not None:
        _remove_temporaries(output)
    done, size = _frames_done(output, job) if saved is not None else (0, None)
    if camera.size is not None:
        if size is not None and tuple(camera.size) != size:
            raise AcquisitionError(
                f"the camera's frames must be {size[0]}x{size[1]} (height x width) like the {done} saved in "
                f"{output}; got a {camera.size[0]}x{camera.size[1]} camera. Resume with the same camera settings."
            )
        size = tuple(camera.size)
    return done, size


def _identify(client, run: _Run, saved: dict | None, light: LightSettings) -> None:
    """Check the dome against a resumed plan, then write the plan (with the dome's identity) and
    the light's table."""
    identity = client.identify()
    dome = {"model": identity.model, "firmware": identity.firmware, "protocol": identity.protocol}
    if saved is not None and saved.get("dome") != dome:
        raise AcquisitionError(
            f"{run.output / PLAN} was acquired with the dome {saved.get('dome')}; got {dome}. Resume with the same "
            "dome (model and firmware), or acquire into another folder."
        )
    run.generator["dome"] = dome
    if saved is None:
        run.output.mkdir(parents=True, exist_ok=True)
        (run.output / MANIFEST).unlink(missing_ok=True)  # an overwritten capture's: it lists other frames
        write_json(run.output / PLAN, {**run.job, "dome": dome})
    if light.table is not None and not (run.output / KERNEL_FILE).is_file():
        write_exr(run.output / KERNEL_FILE, light.table, ["Y"])


def _adopt(run: _Run) -> None:
    """List frame ``k`` when its file was written but not listed and reads completely."""
    adopted = _adoptable(run.output, run.job, run.k, run.size) if run.k < run.total else None
    if adopted is not None:
        run.size = tuple(adopted.shape[1:])
        run.list_frame()


def _take_frames(client, camera: Camera, directions: Tensor, run: _Run, tolerance: float | None) -> None:
    """Home the dome, switch the light on and take the frames from ``k`` on, each listed once written."""
    job = run.job
    if run.k < run.total:
        run.step = "home"
        client.home()
        run.step = "light on"
        client.light(True, job["intensity"])
    while run.k < run.total:
        k = run.k
        planned = job["frames"][k]
        run.step = f"move to theta={math.degrees(planned['theta']):.4f}, phi={math.degrees(planned['phi']):.4f} deg"
        client.move(planned["theta"], planned["phi"])
        if tolerance is not None:
            run.step = "status after the move"
            _check_position(client, k, planned, tolerance)
        run.step = "capture"
        image = _checked(camera.capture(directions[k], index=k), k, job, run.size)
        run.size = tuple(image.shape[1:])
        run.step = f"write {planned['file']}"
        write_exr(run.output / planned["file"], image.permute(1, 2, 0), job["channels"])
        run.list_frame()


def _stopped(client, run: _Run, error: BaseException) -> AcquisitionStopped:
    """The :class:`AcquisitionStopped` for ``error`` at the run's step, after switching the light off
    when it may be on."""
    note = _switch_off(client, error) if run.step not in ("identify", "home") else ""
    k, total = run.k, run.total
    where = run.job["frames"][k]["file"] if k < total else "the end"
    saved_note = (
        f"{len(run.frames)} of {total} frames are saved in {run.output} (a valid capture)"
        if run.frames
        else f"no frame is saved yet in {run.output}"
    )
    return AcquisitionStopped(
        f"the acquisition stopped at frame {k} ({where}) of {total}, at {run.step}: {type(error).__name__}: "
        f"{str(error).rstrip('.')}. "
        f"{saved_note}.{note}",
        done=len(run.frames),
        total=total,
        output=run.output,
        frame=k,
    )


def _check_position(client, k: int, planned: dict, tolerance: float) -> None:
    status = client.status()
    want = dome_direction(planned["theta"], planned["phi"])
    got = dome_direction(status.theta, status.phi)
    cosine = max(-1.0, min(1.0, sum(a * b for a, b in zip(want, got, strict=True))))
    off = math.acos(cosine)
    problems = []
    if status.fault:
        problems.append(f"fault {status.fault!r}")
    if status.moving:
        problems.append("still moving")
    if off > tolerance:
        problems.append(
            f"at theta={math.degrees(status.theta):.4f}, phi={math.degrees(status.phi):.4f} deg "
            f"({math.degrees(off):.3g} deg away)"
        )
    if not status.light:
        problems.append("the light off")
    if problems:
        raise _PositionError(
            f"the dome must be at rest at frame {k}'s position (theta={math.degrees(planned['theta']):.4f}, "
            f"phi={math.degrees(planned['phi']):.4f} deg, within {math.degrees(tolerance):.3g} deg) with the light "
            "on; its status says: "
            f"{', '.join(problems)}"
        )


class _PositionError(OSError):
    """The dome's status after a move disagrees with the plan."""


def _switch_off(client, error: BaseException | None) -> str:
    """Switch the light off, best effort; a note for the message when it could not be."""
    if isinstance(error, (DomeTimeout, DomeDisconnected)):
        return " The light may still be on: switch it off at the dome."
    try:
        client.light(False)
    except (OSError, TorchspecError) as failure:
        return f" The light could not be switched off ({failure}): switch it off at the dome."
    return ""


# --- the command line's camera --------------------------------------------------------------------


def open_camera(
    spec: str,
    light: LightSettings,
    *,
    channels: Sequence[str] = ("R", "G", "B"),
    pattern: str = "*.exr",
    timeout: float = 60.0,
    trigger: str | None = None,
) -> Camera:
    """The camera of ``torchspec acquire --camera``: ``sim:CONFIG`` (a
    :class:`~torchspec.dome.camera.SimulatedCameraConfig` YAML, rendering ``light``) or
    ``folder:DIR`` (a :class:`~torchspec.dome.camera.FolderCamera` on ``DIR`` with the
    ``channels``, ``pattern``, ``timeout`` and shell ``trigger`` command)."""
    from ..config import load_config

    kind, _, where = spec.partition(":")
    if kind == "sim" and where:
        config = load_config(where, SimulatedCameraConfig)
        return SimulatedCamera.from_config(config, light.kernel(), irradiance=as_tuple(light.irradiance))
    if kind == "folder" and where:
        fire = command_trigger(trigger) if trigger else None
        return FolderCamera(where, channels=channels, pattern=pattern, timeout=timeout, trigger=fire)
    raise AcquisitionError(f"camera must be 'sim:CONFIG' or 'folder:DIR'; got {spec!r}.")
