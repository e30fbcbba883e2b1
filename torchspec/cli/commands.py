"""The ``torchspec`` subcommands: each a function ``(parser, args) -> exit status``, in :data:`COMMANDS`."""

from __future__ import annotations

import argparse
import shlex
import shutil
import sys
from dataclasses import replace
from pathlib import Path

from ..errors import TorchspecError
from ..outputs import check_apart, check_output
from ..pipeline.checkpoint import CHECKPOINT, refuse_unfinished
from .parser import OVERWRITE

__all__ = ["COMMANDS", "INTERRUPTED", "device_option"]

INTERRUPTED = 130
"""The exit status of a command stopped by Ctrl-C: 128 + SIGINT, what a shell reports for it."""


def device_option(parser: argparse.ArgumentParser, args: argparse.Namespace):
    """``args.device`` checked before any work: the ``torch.device``, or ``None`` when not given."""
    if args.device is None:
        return None
    from ..pipeline.plan import device_of

    try:
        return device_of(args.device)
    except TorchspecError as error:
        parser.error(f"--device: {error}")



def _again(args: argparse.Namespace, *extra: str) -> str:
    """The command line as typed (``args.argv``, set by :func:`torchspec.cli.main`) without
    ``--resume``, ``extra`` added: what runs it again."""
    return " ".join(["torchspec", *(shlex.quote(a) for a in args.argv if a != "--resume"), *extra])


def _rerun(args: argparse.Namespace) -> str:
    """The command line that continues the interrupted command ``args``: the same, with ``--resume``."""
    return _again(args, "--resume")


def _check_output(args: argparse.Namespace, path: Path | None = None, **rule) -> Path:
    """``args.output`` (or ``path``) checked before any work (:func:`torchspec.outputs.check_output`)."""
    return check_output(args.output if path is None else path, overwrite=args.overwrite, flag=OVERWRITE, **rule)

def _calibrate_sphere(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import torch

    from ..calibration.sphere import Circle, circle_from_mask, find_sphere, sphere_directions, write_lp
    from ..io.images import read_photo
    from ..io.rti import photographs

    images = photographs(args.folder)
    if len(images) < 1:
        raise TorchspecError(f"{args.folder} must hold the sphere's photographs; got none.")
    device = device_option(parser, args) or "cpu"
    frames = torch.stack([torch.from_numpy(read_photo(path).pixels).permute(2, 0, 1) for path in images]).to(device)
    if args.circle:
        circle = Circle(*args.circle)
    else:
        circle = circle_from_mask(args.mask) if args.mask else find_sphere(frames)
    result = sphere_directions(frames, circle)
    write_lp(args.output, [path.name for path in images], result)
    found = "" if args.circle or args.mask else "found "
    print(f"wrote {args.output}: {len(images)} lights from a sphere {found}at ({circle.cx:.1f}, {circle.cy:.1f}), "
          f"radius {circle.r:.1f} px; uncertainty {float(result.uncertainty_deg.median()):.2f} deg (median), "
          f"{float(result.uncertainty_deg.max()):.2f} deg (largest)")
    return 0


def _import(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import warnings

    from ..calibration.response import describe_response
    from ..io.rti import import_rti
    from ..io.scale import Scale
    from ..pipeline.verdict import scale_words

    scale = Scale.parse(args.downsample, args.crop)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the notes are printed below, once each
        result = import_rti(args.source, args.output, transfer=args.transfer, overwrite=args.overwrite,
                            progress=not args.quiet, scale=scale)
    for note in result.notes:
        print(f"torchspec import: note: {note}", file=sys.stderr)
    estimated = result.transfer.name == "response"
    transfer = describe_response(result.response.to_json()) if estimated else result.transfer
    capture = result.capture
    print(f"wrote {args.output}: {len(capture.frames)} frames of {capture.width}x{capture.height} "
          f"{''.join(capture.channels)}{scale_words(capture.extra['source'].get('scale'))} from "
          f"{result.light_file.path} (images matched by {result.matched}; "
          f"transfer {transfer}; {sum(result.saturated)} clipped pixels); check it with: torchspec info "
          f"{shlex.quote(str(args.output))}")
    return 0


def _demo(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if not 8 <= args.size <= 4096:
        parser.error(f"--size must be in 8..4096; got {args.size}")
    from .. import demo

    device = device_option(parser, args)
    _check_output(args, args.output or demo.DEFAULT_OUTPUT)
    demo.run(args.output, size=args.size, progress=not args.quiet, overwrite=args.overwrite,
             device=str(device or "auto"))
    return 0


def _simulate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..simulate import SimulationConfig, simulate, write_simulation

    config = load_config(args.config, SimulationConfig)
    device = device_option(parser, args)
    _check_output(args)
    simulation = simulate(config, root=args.output, progress=not args.quiet, device=device or "cpu")
    result = write_simulation(args.output, simulation, overwrite=args.overwrite)
    print(f"wrote {args.output}: {len(result.frames)} frames of {result.width}x{result.height} "
          f"{''.join(result.channels)}, with truth/")
    return 0


def _fit_on_cluster(args: argparse.Namespace, config, checkpoint: Path):
    """``torchspec fit --scheduler/--workers``: the same fit, its tiles on a Dask cluster."""
    from ..pipeline import ClusterError, connect, fit_on_cluster

    try:
        with connect(args.scheduler, workers=args.workers) as client:
            return fit_on_cluster(args.capture, client, checkpoint=checkpoint, config=config, frames=args.frames,
                                  progress=not args.quiet, resume=args.resume)
    except ClusterError as error:  # printed by main like an unreadable file: the message names the address or tile
        raise OSError(str(error)) from error


def _fit(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from ..config import load_config
    from ..pipeline import FitConfig, fit, write_fit
    from ..pipeline.verdict import summary_lines

    config = load_config(args.config, FitConfig) if args.config is not None else FitConfig()
    if args.model is not None:
        config = replace(config, model=args.model)
    if args.calibrate is not None:
        config = replace(config, calibrate=args.calibrate)
    if args.shadows is not None:
        config = replace(config, shadows=args.shadows)
    if args.residual_term is not None:
        term = args.residual_term
        config = replace(config, term=replace(config.term, order=term if term == "auto" else int(term)))
    if args.device is not None:
        config = replace(config, compute=replace(config.compute, device=str(device_option(parser, args))))
    if args.downsample is not None or args.crop is not None:
        from ..io.scale import Scale

        given = Scale.parse(config.masks.downsample if args.downsample is None else args.downsample, args.crop)
        crop = given.crop if args.crop else config.masks.crop
        config = replace(config, masks=replace(config.masks, downsample=given.downsample, crop=crop))
    if args.threads is not None:
        if args.threads != "auto" and not args.threads.isdigit():
            parser.error(f"--threads must be 'auto' or a number; got {args.threads!r}")
        threads = args.threads if args.threads == "auto" else int(args.threads)
        config = replace(config, compute=replace(config.compute, threads=threads))
    checkpoint = args.output / CHECKPOINT
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers must be >= 1; got {args.workers}")
    check_apart(args.output, args.capture, "the capture")
    _check_output(args, job=CHECKPOINT)  # its own checkpoint: --resume decides
    if args.overwrite and not args.resume:
        shutil.rmtree(checkpoint, ignore_errors=True)  # an unfinished fit there: dropped, as asked
    refuse_unfinished(checkpoint, args.resume)  # before any work (reading, calibrating, a cluster's start)
    try:
        if args.scheduler is None and args.workers is None:
            result = fit(
                args.capture,
                config=config,
                frames=args.frames,
                progress=not args.quiet,
                checkpoint=checkpoint,
                resume=args.resume,
            )
        else:
            result = _fit_on_cluster(args, config, checkpoint)
        write_fit(args.output, result, overwrite=True)  # checked above, before the fit
    except KeyboardInterrupt as stop:  # Ctrl-C at any point: reading, calibrating, a tile, writing
        return _fit_interrupted(args, stop, checkpoint)
    shutil.rmtree(checkpoint, ignore_errors=True)  # the maps are written: the tiles are no longer needed
    previews = None
    if not args.no_previews:
        from ..io import read_capture
        from ..io.scale import capture_at
        from ..report import write_fit_previews

        seen = capture_at(read_capture(args.capture), result.stats.get("scale"))  # as the fit read it
        previews = write_fit_previews(args.output / "previews", result, seen)
    for line in summary_lines(result.stats, str(args.output), capture=str(args.capture), previews=previews):
        print(line)
    return 0


def _fit_interrupted(args: argparse.Namespace, stop: KeyboardInterrupt, checkpoint: Path) -> int:
    """Say, in one line, what an interrupted fit saved and the command that continues it (or runs it
    again, when no tile was saved: the checkpoint, which holds no work, is removed); exit 130."""
    from ..pipeline import FitInterrupted

    saved = len(list(checkpoint.glob("tile-*.pt"))) if checkpoint.is_dir() else 0
    if saved:
        total = f" of {stop.total}" if isinstance(stop, FitInterrupted) else ""
        print(f"torchspec fit: interrupted: {saved}{total} tiles are saved in {checkpoint}; continue with: "
              f"{_rerun(args)}", file=sys.stderr)
    else:
        shutil.rmtree(checkpoint, ignore_errors=True)  # no tile: nothing to continue, the same command starts over
        print(f"torchspec fit: interrupted before any tile was saved: nothing is written. Run it again with: "
              f"{_again(args)}", file=sys.stderr)
    return INTERRUPTED


def _render(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from ..relight import render_capture

    device = device_option(parser, args)
    _check_output(args)
    if args.light or args.lights:
        return _render_lights(args, device)
    if args.capture is None:
        raise TorchspecError("render needs --capture CAPTURE (its frames predicted) or new lights: --light X,Y,Z "
                             "(repeatable) or --lights FILE.lp")
    if args.format != "auto" or args.irradiance is not None or args.srgb:
        raise TorchspecError("--format, --srgb and --irradiance are for new lights (--light, --lights); a capture's "
                             "frames are written as a capture (EXR frames and capture.json)")
    report = render_capture(args.svbrdf, args.capture, args.output, light=args.light_model, path=args.path,
                            overwrite=args.overwrite, progress=not args.quiet, term=not args.no_term,
                            device=str(device or "auto"))
    print(f"wrote {report['frames']} frames to {args.output}")
    if report.get("psnr_db") is not None:
        print(f"  against the capture's frames: PSNR {report['psnr_db']:.2f} dB (peak = the capture's maximum), "
              f"relative RMS error {100 * report['relative_rms']:.2f} %")
    return 0


def _render_lights(args: argparse.Namespace, device) -> int:
    """``torchspec render MAPS --light X,Y,Z`` / ``--lights FILE``: :func:`torchspec.relight.lights.render_lights`."""
    from ..relight.lights import LIGHTS_JSON, LIGHTS_LP, parse_light, read_new_lights, render_lights

    lights = [parse_light(text) for text in args.light or []]
    if args.lights is not None:
        found, notes = read_new_lights(args.lights)
        lights += found
        for note in notes:
            print(f"torchspec render: note: {note}", file=sys.stderr)
    report = render_lights(args.svbrdf, args.output, lights, capture=args.capture, light_model=args.light_model,
                           irradiance=args.irradiance, fmt=args.format, srgb=args.srgb, term=not args.no_term,
                           path=args.path,
                           overwrite=args.overwrite, progress=not args.quiet, device=str(device or "auto"))
    files = report["files"]
    shown = ", ".join(files[:3]) + (f", ... {files[-1]}" if len(files) > 3 else "")
    print(f"wrote {len(files)} image(s) to {args.output}: {shown}; their lights in {LIGHTS_JSON} and {LIGHTS_LP}")
    print(f"  {report['format'].upper()}: {report['encoding']}")
    values = ", ".join(f"{v:.4g}" for v in report["irradiance"])
    print(f"  irradiance {values}: {report['irradiance_chosen']} (--irradiance to change)")
    clipped = [(file, count) for file, count in zip(files, report["clipped"], strict=True) if count]
    if clipped and report["format"] == "png":
        print(f"  {len(clipped)} image(s) hold pixels above 1, shown as white (e.g. {clipped[0][0]}: {clipped[0][1]} "
              "pixels); lower --irradiance to keep them, or --format exr")
    return 0


def _export(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from ..export import export

    _check_output(args)
    written = export(args.svbrdf, args.output, to=args.to, light=args.light, irradiance=args.irradiance,
                     overwrite=args.overwrite, capture=args.capture, progress=args.to == "web" and not args.quiet)
    print(f"wrote {written} ({args.to}; mappings and their limits: docs/export.md)")
    if args.to == "rti":
        import json

        record = json.loads(written.read_text())
        encoded = "the photographs' camera response" if record["encoding"]["transfer"] == "response" else "sRGB"
        print(f"  lit by irradiance {record['irradiance']:.4g} ({record['irradiance_from']}); encoded as {encoded}")
    if args.to == "mitsuba" and args.light is None:
        print("  lit by a directional light at 45 deg elevation from the upper left (the default); "
              "choose another with --light X Y Z")
    return 0


def _view(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from ..view import open_site, serve

    site = open_site(args.svbrdf, args.capture, title=args.svbrdf.name, cache=not args.no_cache)
    server = serve(site, args.port)
    print(f"torchspec view: http://127.0.0.1:{server.server_address[1]}/ (Ctrl-C to stop)", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
        site.close()
    return 0


def _info(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import json

    from ..info import UNUSABLE, format_report, inspect_capture

    report = inspect_capture(args.capture, progress=not args.quiet)  # the bar goes to stderr
    print(json.dumps(report, indent=2, allow_nan=False) if args.json else format_report(report))
    return 2 if report["verdict"] == UNUSABLE else 0


def _calibrate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import json

    from ..calibration.kernel import calibrate, kernel_outputs, write_kernel

    kernel_outputs(args.output, overwrite=args.overwrite, flag=OVERWRITE)
    device = device_option(parser, args)
    result = calibrate(args.capture, frames=args.frames, normal=args.normal, size=args.size, extent=args.extent,
                       symmetry=args.symmetry, mirror_alpha=args.mirror_alpha, device=device or "cpu")
    light = write_kernel(args.output, result, overwrite=True)  # checked above, before the calibration
    print(f"wrote {args.output} and {args.output.with_suffix('.json')}")
    print(result.summary())
    print(f"capture manifest light entry (kernel file beside capture.json): {json.dumps(light)}")
    return 0


def _dome_emulator(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import math

    from ..dome.emulator import serve

    return serve(speed=math.radians(args.speed), arm_speed=args.arm_speed, faults=args.fault,
                 stall_seconds=args.stall_seconds, homed=not args.unhomed)


def _acquire(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from ..dome.acquisition import PLAN, AcquisitionInterrupted, AcquisitionStopped, acquire, load_light, open_camera
    from ..dome.client import DomeClient

    check_output(args.output, overwrite=args.overwrite or args.resume, job=PLAN, flag=OVERWRITE)

    light = load_light(args.light)
    camera = open_camera(args.camera, light, channels=args.channels.split(","), pattern=args.pattern,
                         timeout=args.frame_timeout, trigger=args.trigger)
    try:
        with DomeClient(args.port, timeout=args.timeout, move_timeout=args.move_timeout) as client:
            capture = acquire(client, camera, args.output, light=light, layout=args.layout, radius=args.radius,
                              resume=args.resume, progress=not args.quiet, overwrite=args.overwrite)
    except (AcquisitionStopped, AcquisitionInterrupted) as stop:
        print(f"torchspec acquire: {stop} Continue with: {_rerun(args)}", file=sys.stderr)
        return INTERRUPTED if isinstance(stop, AcquisitionInterrupted) else 1
    print(f"wrote {args.output}: {len(capture.frames)} frames of {capture.width}x{capture.height} "
          f"{''.join(capture.channels)}")
    return 0


COMMANDS = {
    "demo": _demo,
    "simulate": _simulate,
    "fit": _fit,
    "render": _render,
    "export": _export,
    "view": _view,
    "info": _info,
    "calibrate": _calibrate,
    "dome-emulator": _dome_emulator,
    "acquire": _acquire,
    "import": _import,
    "calibrate-sphere": _calibrate_sphere,
}
"""Each subcommand's function: ``(parser, args) -> exit status``."""
