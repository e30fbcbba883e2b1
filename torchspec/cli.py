"""The ``torchspec`` command."""

from __future__ import annotations

import argparse
import io
import os
import shlex
import shutil
import sys
import traceback
import warnings
from dataclasses import replace
from pathlib import Path

from ._version import __version__
from .errors import TorchspecError
from .outputs import check_output
from .pipeline.checkpoint import CHECKPOINT

__all__ = ["BUG", "COMMANDS", "build_parser", "main"]

OVERWRITE = "--overwrite"
"""The option that lets a command write into an output that holds other work."""

BUG = 70
PIPE_CLOSED = 141
"""The exit status when the reader of stdout closed it (``torchspec info | head -2``): 128 + SIGPIPE,
what a shell reports for a command a closed pipe stopped, as ``yes | head`` does."""
"""The exit status of an internal error (a bug in torchspec): ``EX_SOFTWARE`` of ``sysexits.h``."""


def build_parser() -> argparse.ArgumentParser:
    """The parser of the ``torchspec`` command line: one subcommand per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="torchspec",
        description="Reflectance of nearly flat objects from a few HDR photographs under an extended light.",
    )
    parser.add_argument("--version", action="version", version=f"torchspec {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_simulation_commands(commands)
    _add_fit_command(commands)
    _add_map_commands(commands)
    _add_capture_commands(commands)
    _add_dome_commands(commands)
    _add_import_command(commands)
    return parser


# --- torchspec import (RTI captures: .lp + photographs) ------------------------------------------


def _add_import_command(commands) -> None:
    """``import``."""
    command = commands.add_parser("import", help="import an RTI capture: .lp light file + JPEG/PNG/TIFF/RAW photos")
    command.add_argument("source", type=Path, help="an .lp light file (or Relight .relight/.dome, or lights.txt), "
                                                   "or a folder holding one")
    command.add_argument("-o", "--output", type=Path, required=True, help="the capture folder to write")
    command.add_argument("--transfer", default=None, metavar="{auto,srgb,linear,gamma:G}",
                         help="the photographs' tone curve, decoded to linear (default: an embedded ICC profile, "
                              "else auto for 8 and 16-bit files: the camera's response estimated from the "
                              "photographs; linear for float and RAW)")
    command.add_argument("--overwrite", action="store_true", help="replace an OUTPUT that already holds files")
    command.add_argument("--quiet", action="store_true", help="no progress bar")
    sphere = commands.add_parser("calibrate-sphere", help="light directions (.lp) from photographs of a chrome sphere")
    sphere.add_argument("folder", type=Path, help="the sphere's photographs, one per light (natural order)")
    sphere.add_argument("-o", "--output", type=Path, required=True, help="the .lp to write (a .json beside)")
    where = sphere.add_mutually_exclusive_group()
    where.add_argument("--mask", type=Path, help="an image, white on the sphere (default: the outline is found)")
    where.add_argument("--circle", type=float, nargs=3, metavar=("CX", "CY", "R"), help="the sphere's outline, pixels")
    _add_device(sphere)


def _calibrate_sphere(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import torch

    from .io.images import read_photo
    from .io.rti import photographs
    from .sphere import Circle, circle_from_mask, find_sphere, sphere_directions, write_lp

    images = photographs(args.folder)
    if len(images) < 1:
        raise TorchspecError(f"{args.folder} must hold the sphere's photographs; got none.")
    device = _device(parser, args) or "cpu"
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

    from .io.rti import import_rti
    from .response import describe_response

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the notes are printed below, once each
        result = import_rti(args.source, args.output, transfer=args.transfer, overwrite=args.overwrite,
                            progress=not args.quiet)
    for note in result.notes:
        print(f"torchspec import: note: {note}", file=sys.stderr)
    estimated = result.transfer.name == "response"
    transfer = describe_response(result.response.to_json()) if estimated else result.transfer
    capture = result.capture
    print(f"wrote {args.output}: {len(capture.frames)} frames of {capture.width}x{capture.height} "
          f"{''.join(capture.channels)} from {result.light_file.path} (images matched by {result.matched}; "
          f"transfer {transfer}; {sum(result.saturated)} clipped pixels); check it with: torchspec info "
          f"{shlex.quote(str(args.output))}")
    return 0


# ----------------------------------------------------------------------------------------------------


def _add_device(command) -> None:
    """``--device``: where the command computes (:func:`torchspec.pipeline.plan.device_of`)."""
    command.add_argument("--device", default=None, metavar="auto|cpu|cuda[:N]",
                         help="where to compute: auto (the default: CUDA when torch sees a GPU, else the CPU), "
                              "cpu, cuda or cuda:N")


def _device(parser: argparse.ArgumentParser, args: argparse.Namespace):
    """``args.device`` checked before any work: the ``torch.device``, or ``None`` when not given."""
    if args.device is None:
        return None
    from .pipeline.plan import device_of

    try:
        return device_of(args.device)
    except TorchspecError as error:
        parser.error(f"--device: {error}")


def _add_overwrite(command, more: str = "") -> None:
    """The option :data:`OVERWRITE`: without it, an output that holds files is refused before any work."""
    command.add_argument(OVERWRITE, action="store_true",
                         help=f"write into an output that already holds files, replacing them{more}")


def _add_simulation_commands(commands) -> None:
    """``demo`` and ``simulate``."""
    demo = commands.add_parser(
        "demo", help="simulate a small painting, fit it, and write maps, previews, relit renders and a report"
    )
    demo.add_argument("-o", "--output", type=Path, default=None,
                      help="the folder to write (default: ./torchspec-demo)")
    demo.add_argument("--size", type=int, default=64, help="the painting's width and height in pixels (default: 64)")
    demo.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_device(demo)
    _add_overwrite(demo)

    simulate = commands.add_parser("simulate", help="render a synthetic capture (with truth/) from a config")
    simulate.add_argument("config", type=Path, help="a simulation config (YAML), e.g. configs/sim_painting.yaml")
    simulate.add_argument("-o", "--output", type=Path, required=True, help="the capture folder to write")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_device(simulate)
    _add_overwrite(simulate)


def _add_fit_command(commands) -> None:
    """``fit``."""
    fit = commands.add_parser("fit", help="fit SVBRDF maps (normal, diffuse, specular, roughness) to a capture")
    fit.add_argument("capture", type=Path, help="the capture folder (with capture.json)")
    fit.add_argument("-o", "--output", type=Path, required=True, help="the folder of maps to write")
    fit.add_argument("--config", type=Path, default=None,
                     help="fit settings (YAML, keys of FitConfig), e.g. configs/fit.yaml")
    fit.add_argument("--frames", default=None,
                     help="frames to fit: 'all', a slice like '::2' (every second) or a list like '0,3,10-19'")
    fit.add_argument("--quiet", action="store_true", help="no progress bar")
    fit.add_argument("--model", default=None,
                     choices=["auto", "diffuse", "ward-iso", "ward-iso-colour", "ward-aniso", "ward-dual"],
                     help="auto (default): each pixel's model by what it predicts of frames left out of its fit; "
                          "or one forced on every pixel")
    fit.add_argument("--calibrate", default=None, choices=["auto", "none", "gains", "positions", "dome"],
                     help="estimate the lights from the photographs with the maps: auto (default: what the capture's "
                          "manifest lists as unknown, e.g. an imported capture's irradiance, with a dome radius "
                          "where the photographs show one), none, gains (one per frame and channel), positions "
                          "(near lights' positions, and gains) or dome (one radius for every light, and gains)")
    fit.add_argument("--residual-term", default=None, choices=["auto", "0", "2", "3"], metavar="{auto,0,2,3}",
                     help="fit a smooth per-pixel residual term (hemispherical harmonics of order 2 or 3) where it "
                          "predicts left-out frames better, for relighting what the physical model cannot (cast "
                          "shadows); written to residual_term.exr, the physical maps unchanged (default auto: 3 "
                          "for a capture imported from photographs, else 0: off)")
    fit.add_argument("--threads", default=None, metavar="N|auto",
                     help="torch threads per tile: auto (the default: the cores other processes leave free, "
                          "measured before each tile) or a number")
    fit.add_argument("--resume", action="store_true",
                     help="continue an interrupted fit into the same OUTPUT (finished tiles are kept in OUTPUT/"
                          f"{CHECKPOINT})")
    _add_overwrite(fit, " (an unfinished fit there is dropped unless --resume)")
    cluster = fit.add_mutually_exclusive_group()
    cluster.add_argument("--scheduler", default=None, metavar="ADDRESS",
                         help="fit the tiles on the Dask cluster of this scheduler, e.g. tcp://10.0.0.5:8786 (CAPTURE "
                              "and OUTPUT on a filesystem every worker sees; docs/scale.md)")
    cluster.add_argument("--workers", type=int, default=None, metavar="N",
                         help="fit the tiles on a local Dask cluster of N worker processes (needs the dask extra: "
                              "pip install 'torchspec[dask]')")
    _add_device(fit)


def _add_map_commands(commands) -> None:
    """``render`` and ``export``: commands on a folder of SVBRDF maps."""
    render = commands.add_parser("render", help="predict a capture's frames from SVBRDF maps")
    render.add_argument("svbrdf", type=Path, help="a folder of SVBRDF maps (e.g. a fit, or a capture's truth/)")
    render.add_argument("--capture", type=Path, required=True, help="the capture whose lights to render")
    render.add_argument("-o", "--output", type=Path, required=True, help="folder for the predicted frames")
    render.add_argument("--light", type=Path, default=None,
                        help="a JSON light description to use instead of the capture's (needed for 'unknown' kernels)")
    render.add_argument("--path", default="auto", choices=["auto", "point", "fast", "reference"],
                        help="quadrature path (default: auto)")
    render.add_argument("--no-term", action="store_true",
                        help="leave out the maps' residual term (residual_term.exr): the physical model alone")
    render.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_device(render)
    _add_overwrite(render)

    export = commands.add_parser("export", help="export SVBRDF maps: a Mitsuba 3 scene, a glTF 2.0 quad, 16-bit "
                                 "PNG, OpenLIME's BRDF layer, an HSH .rti for RTIViewer or a web page")
    export.add_argument("svbrdf", type=Path, help="a folder of SVBRDF maps (e.g. a fit, or a capture's truth/)")
    export.add_argument("--to", required=True, metavar="{mitsuba,gltf,png16,openlime,rti,web}",
                        help="the format (see docs/export.md)")
    export.add_argument("-o", "--output", type=Path, required=True, help="the folder to write")
    export.add_argument("--light", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                        help="mitsuba: the directional emitter's direction towards the light (surface frame; "
                             "default: 45 deg elevation from the upper left, -0.5 0.5 0.707)")
    export.add_argument("--irradiance", type=float, nargs="+", default=None, metavar="E",
                        help="mitsuba: the emitter's irradiance, one number or one per channel (default: 1); "
                             "rti: the fitted lights' irradiance, one number (default: pi, a white Lambertian "
                             "surface facing the light shows 1)")
    export.add_argument("--capture", type=Path, default=None,
                        help="web: the capture the maps were fitted from (its photographs beside the relit fit)")
    _add_overwrite(export)

    view = commands.add_parser("view", help="relight SVBRDF maps in the browser: a page served on 127.0.0.1")
    view.add_argument("svbrdf", type=Path, help="a folder of SVBRDF maps (e.g. a fit)")
    view.add_argument("--capture", type=Path, default=None,
                      help="the capture the maps were fitted from: its photographs beside the relit fit")
    view.add_argument("--port", type=int, default=8000, help="the port on 127.0.0.1 (default: 8000; 0: any free)")
    view.add_argument("--no-cache", action="store_true",
                      help="neither read nor write the coarse levels' cache (MAPS/.torchspec-view/, or the user's "
                           "cache folder when MAPS is read-only): the pass over every row at each view")


def _add_capture_commands(commands) -> None:
    """``info`` and ``calibrate``: commands on a capture."""
    info = commands.add_parser("info", help="summarise and validate a capture (exit status 2 when unusable)")
    info.add_argument("capture", type=Path, help="the capture folder (with capture.json)")
    info.add_argument("--json", action="store_true", help="print the report as JSON instead of a summary")
    info.add_argument("--quiet", action="store_true", help="no progress bar")

    calibrate = commands.add_parser("calibrate", help="the light's kernel, tabulated, from a mirror captured under it")
    calibrate.add_argument("capture", type=Path, help="the mirror capture folder (its light may be 'unknown')")
    calibrate.add_argument("-o", "--output", type=Path, required=True,
                           help="the kernel EXR to write (channel Y; its light entry and statistics go beside, .json)")
    calibrate.add_argument("--size", type=int, default=32, help="table pixels per side, 8..64 (default: 32)")
    calibrate.add_argument("--extent", type=float, default=None,
                           help="the table's half-width in l units (default: from the data)")
    calibrate.add_argument("--normal", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                           help="the mirror's normal, if known (default: each pixel's reflection from its response)")
    calibrate.add_argument("--symmetry", default="auto", choices=["auto", "none", "radial"],
                           help="radial: a radially symmetric kernel (auto: for a line of frames)")
    calibrate.add_argument("--mirror-alpha", type=float, default=0.0,
                           help="the mirror's roughness (Ward alpha), deconvolved (default: 0, a perfect mirror)")
    calibrate.add_argument("--frames", default=None, help="frames to use, as for fit (default: all)")
    _add_device(calibrate)
    _add_overwrite(calibrate, " (the kernel EXR and its .json)")


def _add_dome_commands(commands) -> None:
    """``dome-emulator`` and ``acquire``."""
    emulator = commands.add_parser(
        "dome-emulator", help="a virtual light dome on a pseudo-terminal: prints its port, serves until Ctrl-C"
    )
    emulator.add_argument("--speed", type=float, default=30.0, metavar="DEG_PER_S",
                          help="angular speed of the light, degrees per second (default: 30)")
    emulator.add_argument("--arm-speed", type=float, default=0.25, help="arm extension per second (default: 0.25)")
    emulator.add_argument("--fault", action="extend", nargs="+", default=[], metavar="KIND[:COUNT[:COMMAND]]",
                          help="inject faults: drop, garble, corrupt, stall, disconnect or motor, e.g. drop:3 "
                               "or garble:1:MOVE (repeatable; docs/dome-protocol.md)")
    emulator.add_argument("--stall-seconds", type=float, default=1.0, help="how long a stall lasts (default: 1)")
    emulator.add_argument("--unhomed", action="store_true", help="start with the position unknown (HOME first)")

    acquire = commands.add_parser("acquire", help="acquire a capture with the light dome (resumable)")
    acquire.add_argument("--port", required=True, help="the dome's serial port (or the path dome-emulator prints)")
    acquire.add_argument("--layout", default="grid:12x12",
                         help="light positions: grid:NXxNY over |l| <= radius, or line:N along x (default: grid:12x12)")
    acquire.add_argument("--radius", type=float, default=0.8, help="the largest |l| of a light, < 1 (default: 0.8)")
    acquire.add_argument("--light", type=Path, required=True,
                         help="light config (YAML/JSON): the format's light block; intensity, irradiance, exposure")
    acquire.add_argument("--camera", required=True,
                         help="sim:CONFIG (a simulated camera, YAML) or folder:DIR (a tethered camera saving into DIR)")
    acquire.add_argument("--trigger", default=None, help="folder camera: a shutter command, run for each frame")
    acquire.add_argument("--pattern", default="*.exr", help="folder camera: the frame files' glob (default: *.exr)")
    acquire.add_argument("--channels", default="R,G,B", help="folder camera: the channels to read (default: R,G,B)")
    acquire.add_argument("--frame-timeout", type=float, default=60.0,
                         help="folder camera: seconds to wait for each frame (default: 60)")
    acquire.add_argument("--timeout", type=float, default=2.0, help="seconds to wait for each dome reply (default: 2)")
    acquire.add_argument("--move-timeout", type=float, default=60.0, help="seconds a motion may take (default: 60)")
    acquire.add_argument("-o", "--output", type=Path, required=True, help="the capture folder to write")
    acquire.add_argument("--resume", action="store_true", help="continue an interrupted acquisition in OUTPUT")
    acquire.add_argument("--quiet", action="store_true", help="no progress bar")
    _add_overwrite(acquire, " (start afresh; --resume continues an acquisition instead)")


def main(argv: list[str] | None = None) -> int:
    """Run the ``torchspec`` command line ``argv`` (default: ``sys.argv[1:]``).

    Returns:
        The exit status: 0 on success; 2 for a usage error or input torchspec refuses (a
        :class:`~torchspec.errors.TorchspecError`, or an ``OSError`` of a path), printed in one line
        without a traceback; 130 for an interrupted fit or acquisition; 70 (``EX_SOFTWARE``) for a bug,
        printed with its traceback and a request to report it.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _warning_line(args.command)
            status = COMMANDS[args.command](parser, args)
        sys.stdout.flush()  # a reader that stopped (torchspec info | head -2) shows here, not at exit
        return status
    except BrokenPipeError:  # the reader of stdout stopped reading: nothing to say, and no one to say it to
        _silence_stdout()
        return PIPE_CLOSED
    except (TorchspecError, OSError) as exc:  # the user's input or filesystem: say what and where, no traceback
        print(f"torchspec {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except Exception:  # anything else is a bug in torchspec
        traceback.print_exc()
        line = " ".join(shlex.quote(a) for a in (sys.argv[1:] if argv is None else argv))
        print(f"torchspec {args.command}: internal error: this is a bug in torchspec {__version__}; please report it "
              f"with the traceback above and the command line: torchspec {line}", file=sys.stderr)
        return BUG


def _silence_stdout() -> None:
    """Point stdout at /dev/null, so that Python's flush at exit does not fail on the closed pipe."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, io.UnsupportedOperation):  # no file descriptor (a captured stdout)
        pass


def _warning_line(command: str):
    """A ``warnings.showwarning`` that prints a warning as one line naming the command (no source line)."""

    def show(message, category, filename, lineno, file=None, line=None):
        print(f"torchspec {command}: warning: {message}", file=file or sys.stderr)

    return show


def _rerun() -> str:
    """The command line that continues the interrupted command of ``sys.argv``: the same, with ``--resume``."""
    again = " ".join(shlex.quote(a) for a in sys.argv[1:] if a != "--resume")
    return f"torchspec {again} --resume"


def _check_output(args: argparse.Namespace, path: Path | None = None, **rule) -> Path:
    """``args.output`` (or ``path``) checked before any work (:func:`torchspec.outputs.check_output`)."""
    return check_output(args.output if path is None else path, overwrite=args.overwrite, flag=OVERWRITE, **rule)


def _demo(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if not 8 <= args.size <= 4096:
        parser.error(f"--size must be in 8..4096; got {args.size}")
    from . import demo

    device = _device(parser, args)
    _check_output(args, args.output or demo.DEFAULT_OUTPUT)
    demo.run(args.output, size=args.size, progress=not args.quiet, overwrite=args.overwrite,
             device=str(device or "auto"))
    return 0


def _simulate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from .config import load_config
    from .simulate import SimulationConfig, simulate, write_simulation

    config = load_config(args.config, SimulationConfig)
    device = _device(parser, args)
    _check_output(args)
    simulation = simulate(config, root=args.output, progress=not args.quiet, device=device or "cpu")
    result = write_simulation(args.output, simulation, overwrite=args.overwrite)
    print(f"wrote {args.output}: {len(result.frames)} frames of {result.width}x{result.height} "
          f"{''.join(result.channels)}, with truth/")
    return 0


def _fit_on_cluster(args: argparse.Namespace, config, checkpoint: Path):
    """``torchspec fit --scheduler/--workers``: the same fit, its tiles on a Dask cluster."""
    from .pipeline import ClusterError, connect, fit_on_cluster

    try:
        with connect(args.scheduler, workers=args.workers) as client:
            return fit_on_cluster(args.capture, client, checkpoint=checkpoint, config=config, frames=args.frames,
                                  progress=not args.quiet, resume=args.resume)
    except ClusterError as error:  # printed by main like an unreadable file: the message names the address or tile
        raise OSError(str(error)) from error


def _fit(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from .config import load_config
    from .pipeline import FitConfig, FitInterrupted, fit, write_fit

    config = load_config(args.config, FitConfig) if args.config is not None else FitConfig()
    if args.model is not None:
        config = replace(config, model=args.model)
    if args.calibrate is not None:
        config = replace(config, calibrate=args.calibrate)
    if args.residual_term is not None:
        term = args.residual_term
        config = replace(config, residual_term=term if term == "auto" else int(term))
    if args.device is not None:
        config = replace(config, device=str(_device(parser, args)))
    if args.threads is not None:
        if args.threads != "auto" and not args.threads.isdigit():
            parser.error(f"--threads must be 'auto' or a number; got {args.threads!r}")
        config = replace(config, threads=args.threads if args.threads == "auto" else int(args.threads))
    checkpoint = args.output / CHECKPOINT
    if args.workers is not None and args.workers < 1:
        parser.error(f"--workers must be >= 1; got {args.workers}")
    _check_output(args, job=CHECKPOINT)  # its own checkpoint: --resume decides
    if args.overwrite and not args.resume:
        shutil.rmtree(checkpoint, ignore_errors=True)  # an unfinished fit there: dropped, as asked
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
    except FitInterrupted as stop:
        print(f"torchspec fit: interrupted: {stop.done} of {stop.total} tiles are saved in {stop.checkpoint}; "
              f"continue with: {_rerun()}", file=sys.stderr)
        return 130
    write_fit(args.output, result, overwrite=True)  # checked above, before the fit
    shutil.rmtree(checkpoint, ignore_errors=True)  # the maps are written: the tiles are no longer needed
    stats = result.stats
    print(f"wrote {args.output}: {stats['pixels']} pixels from {len(stats['frames'])} frames in "
          f"{stats['seconds']['total']:.1f} s ({stats['pixels_per_second']:.0f} pixels/s); "
          f"{stats['lobe_pixels']} with a lobe; solver: {stats['status']}; "
          f"median relative residual {stats['median_residual']:.2e}")
    return 0


def _render(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from .relight import render_capture

    device = _device(parser, args)
    _check_output(args)
    report = render_capture(args.svbrdf, args.capture, args.output, light=args.light, path=args.path,
                            overwrite=args.overwrite, progress=not args.quiet, term=not args.no_term,
                            device=str(device or "auto"))
    print(f"wrote {report['frames']} frames to {args.output}")
    if report.get("psnr_db") is not None:
        print(f"  against the capture's frames: PSNR {report['psnr_db']:.2f} dB (peak = the capture's maximum), "
              f"relative RMS error {100 * report['relative_rms']:.2f} %")
    return 0


def _export(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from .export import export

    _check_output(args)
    written = export(args.svbrdf, args.output, to=args.to, light=args.light, irradiance=args.irradiance,
                     overwrite=args.overwrite, capture=args.capture, progress=args.to == "web")
    print(f"wrote {written} ({args.to}; mappings and their limits: docs/export.md)")
    if args.to == "mitsuba" and args.light is None:
        print("  lit by a directional light at 45 deg elevation from the upper left (the default); "
              "choose another with --light X Y Z")
    return 0


def _view(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from .view import open_site, serve

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

    from .info import UNUSABLE, format_report, inspect_capture

    report = inspect_capture(args.capture, progress=not args.quiet)  # the bar goes to stderr
    print(json.dumps(report, indent=2, allow_nan=False) if args.json else format_report(report))
    return 2 if report["verdict"] == UNUSABLE else 0


def _calibrate(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import json

    from .calibrate import calibrate, kernel_outputs, write_kernel

    kernel_outputs(args.output, overwrite=args.overwrite, flag=OVERWRITE)
    device = _device(parser, args)
    result = calibrate(args.capture, frames=args.frames, normal=args.normal, size=args.size, extent=args.extent,
                       symmetry=args.symmetry, mirror_alpha=args.mirror_alpha, device=device or "cpu")
    light = write_kernel(args.output, result, overwrite=True)  # checked above, before the calibration
    print(f"wrote {args.output} and {args.output.with_suffix('.json')}")
    print(result.summary())
    print(f"capture manifest light entry (kernel file beside capture.json): {json.dumps(light)}")
    return 0


def _dome_emulator(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    import math

    from .dome.emulator import serve

    return serve(speed=math.radians(args.speed), arm_speed=args.arm_speed, faults=args.fault,
                 stall_seconds=args.stall_seconds, homed=not args.unhomed)


def _acquire(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    from .dome.acquisition import PLAN, AcquisitionInterrupted, AcquisitionStopped, acquire, load_light, open_camera
    from .dome.client import DomeClient

    check_output(args.output, overwrite=args.overwrite or args.resume, job=PLAN, flag=OVERWRITE)

    light = load_light(args.light)
    camera = open_camera(args.camera, light, channels=args.channels.split(","), pattern=args.pattern,
                         timeout=args.frame_timeout, trigger=args.trigger)
    try:
        with DomeClient(args.port, timeout=args.timeout, move_timeout=args.move_timeout) as client:
            capture = acquire(client, camera, args.output, light=light, layout=args.layout, radius=args.radius,
                              resume=args.resume, progress=not args.quiet, overwrite=args.overwrite)
    except (AcquisitionStopped, AcquisitionInterrupted) as stop:
        print(f"torchspec acquire: {stop} Continue with: {_rerun()}", file=sys.stderr)
        return 130 if isinstance(stop, AcquisitionInterrupted) else 1
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


if __name__ == "__main__":
    sys.exit(main())
