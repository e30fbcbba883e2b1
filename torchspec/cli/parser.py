"""The ``torchspec`` command line's parser: one subcommand per entry of
:data:`torchspec.cli.commands.COMMANDS`, each with its options and help."""

from __future__ import annotations

import argparse
from pathlib import Path

from .._version import __version__
from ..model.registry import MODELS
from ..pipeline.checkpoint import CHECKPOINT
from ..pipeline.settings import CALIBRATE

__all__ = ["OVERWRITE", "WORKFLOW", "add_device", "add_overwrite", "add_scale", "build_parser"]

OVERWRITE = "--overwrite"
"""The option that lets a command write into an output that holds other work."""

WORKFLOW = """\
from photographs to relit maps (an RTI folder: JPEGs and their .lp light file):
  torchspec import FOLDER -o CAPTURE          read the photographs and lights (or: FOLDER/dirs.lp)
  torchspec info CAPTURE                      check it: frames, lights, clipped pixels, a verdict
  torchspec fit CAPTURE -o MAPS               fit the maps; previews in MAPS/previews/
  torchspec view MAPS --capture CAPTURE       relight them in the browser

then: torchspec render MAPS (relit images), torchspec export MAPS --to rti|gltf|mitsuba|web|...
try it first on a simulated painting: torchspec demo
each command's options: torchspec COMMAND --help"""
"""The workflow ``torchspec --help`` shows under its commands."""


def build_parser() -> argparse.ArgumentParser:
    """The parser of the ``torchspec`` command line: one subcommand per entry of :data:`COMMANDS`."""
    parser = argparse.ArgumentParser(
        prog="torchspec",
        description="Reflectance maps (normal, diffuse, specular, roughness) of nearly flat objects - paintings, "
        "reliefs, coins - from photographs lit from many directions: an RTI capture (JPEG + .lp), a light dome's "
        "or OpenEXR frames.",
        epilog=WORKFLOW,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"torchspec {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    _add_import_command(commands)  # in the order of WORKFLOW: import, info, fit, render/export/view
    _add_capture_commands(commands)
    _add_fit_command(commands)
    _add_map_commands(commands)
    _add_simulation_commands(commands)
    _add_dome_commands(commands)
    return parser


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
    add_scale(command, "import", "averaged once decoded to linear values; recorded in capture.json's source.scale")
    sphere = commands.add_parser("calibrate-sphere", help="light directions (.lp) from photographs of a chrome sphere")
    sphere.add_argument("folder", type=Path, help="the sphere's photographs, one per light (natural order)")
    sphere.add_argument("-o", "--output", type=Path, required=True, help="the .lp to write (a .json beside)")
    where = sphere.add_mutually_exclusive_group()
    where.add_argument("--mask", type=Path, help="an image, white on the sphere (default: the outline is found)")
    where.add_argument("--circle", type=float, nargs=3, metavar=("CX", "CY", "R"), help="the sphere's outline, pixels")
    add_device(sphere)



def add_device(command) -> None:
    """``--device``: where the command computes (:func:`torchspec.pipeline.plan.device_of`)."""
    command.add_argument("--device", default=None, metavar="auto|cpu|cuda[:N]",
                         help="where to compute: auto (the default: CUDA when torch sees a GPU, else the CPU), "
                              "cpu, cuda or cuda:N")




def add_scale(command, verb: str, more: str) -> None:
    """``--downsample N`` and ``--crop X,Y,W,H`` (:class:`torchspec.io.scale.Scale`): a quick look at a large
    capture; ``verb`` what the command does with the pixels, ``more`` where it records the scale."""
    command.add_argument("--downsample", type=int, default=None, metavar="N",
                         help=f"{verb} boxes of N x N pixels, each their mean (a quick look at a large capture: "
                              f"about 1/N^2 of the memory and time; a box holding a clipped pixel is clipped); {more}")
    command.add_argument("--crop", default=None, metavar="X,Y,W,H",
                         help=f"{verb} only this region: X,Y its top-left corner, W,H its size, pixels of the full "
                              "image (before --downsample)")


def add_overwrite(command, more: str = "") -> None:
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
    add_device(demo)
    add_overwrite(demo)

    simulate = commands.add_parser("simulate", help="render a synthetic capture (with truth/) from a config")
    simulate.add_argument("config", type=Path, help="a simulation config (YAML), e.g. configs/sim_painting.yaml")
    simulate.add_argument("-o", "--output", type=Path, required=True, help="the capture folder to write")
    simulate.add_argument("--quiet", action="store_true", help="no progress bar")
    add_device(simulate)
    add_overwrite(simulate)


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
    fit.add_argument("--no-previews", action="store_true",
                     help="write the maps only, no PNG previews in OUTPUT/previews/")
    fit.add_argument("--model", default=None,
                     choices=["auto", *MODELS],
                     help="auto (default): each pixel's model by what it predicts of frames left out of its fit; "
                          "or one forced on every pixel")
    fit.add_argument("--calibrate", default=None, choices=list(CALIBRATE),
                     help="estimate the lights from the photographs with the maps: auto (default: what the capture's "
                          "manifest lists as unknown, e.g. an imported capture's irradiance, with a dome radius "
                          "where the photographs show one), none, gains (one per frame and channel), positions "
                          "(near lights' positions, and gains) or dome (one radius for every light, and gains)")
    fit.add_argument("--residual-term", default=None, choices=["auto", "0", "2", "3"], metavar="{auto,0,2,3}",
                     help="fit a smooth per-pixel residual term (hemispherical harmonics of order 2 or 3) where it "
                          "predicts left-out frames better, for relighting what the physical model cannot (cast "
                          "shadows); written to residual_term.exr, the physical maps unchanged (default auto: 3 "
                          "for a capture imported from photographs, else 0: off)")
    fit.add_argument("--shadows", default=None, choices=["auto", "on", "off"],
                     help="cast shadows: fit the maps with each light's visibility over a height field integrated "
                          "from the normals (written to height.exr), where it predicts left-out frames better; "
                          "auto (default) tries it on captures imported from photographs and where the frames hold "
                          "shadows, on always, off never")
    fit.add_argument("--threads", default=None, metavar="N|auto",
                     help="torch threads per tile: auto (the default: the cores other processes leave free, "
                          "measured before each tile) or a number")
    fit.add_argument("--resume", action="store_true",
                     help="continue an interrupted fit into the same OUTPUT (finished tiles are kept in OUTPUT/"
                          f"{CHECKPOINT})")
    add_overwrite(fit, " (an unfinished fit there is dropped unless --resume)")
    cluster = fit.add_mutually_exclusive_group()
    cluster.add_argument("--scheduler", default=None, metavar="ADDRESS",
                         help="fit the tiles on the Dask cluster of this scheduler, e.g. tcp://10.0.0.5:8786 (CAPTURE "
                              "and OUTPUT on a filesystem every worker sees; docs/scale.md)")
    cluster.add_argument("--workers", type=int, default=None, metavar="N",
                         help="fit the tiles on a local Dask cluster of N worker processes (needs the dask extra: "
                              "pip install 'torchspec[dask]')")
    add_scale(fit, "fit", "averaged as the frames are read; recorded in svbrdf.json's fit.scale")
    add_device(fit)


def _add_map_commands(commands) -> None:
    """``render`` and ``export``: commands on a folder of SVBRDF maps."""
    render = commands.add_parser("render", help="relight SVBRDF maps: a capture's frames (--capture), or new lights "
                                 "(--light X,Y,Z, --lights FILE.lp)")
    render.add_argument("svbrdf", type=Path, help="a folder of SVBRDF maps (e.g. a fit, or a capture's truth/)")
    render.add_argument("--capture", type=Path, default=None,
                        help="the capture whose frames to predict (and score); with --light or --lights, the capture "
                             "the maps were fitted from, where their svbrdf.json does not say its view and lights")
    render.add_argument("-o", "--output", type=Path, required=True, help="folder for the images")
    render.add_argument("--light", action="append", default=None, metavar="X,Y,Z",
                        help="render under a new light from this direction (x right, y up, z towards the camera; "
                             "normalised), e.g. --light 0.5,0,0.87; repeatable")
    render.add_argument("--lights", type=Path, default=None, metavar="FILE",
                        help="render under each light of a light file: an .lp (image names and directions), a "
                             "lights.txt of directions, a Relight .relight or .dome")
    render.add_argument("--light-model", type=Path, default=None, metavar="FILE",
                        help="a JSON light description (the light's kernel) to use instead of the capture's (needed "
                             "for 'unknown' kernels); formerly --light FILE")
    render.add_argument("--irradiance", type=float, nargs="+", default=None, metavar="E",
                        help="new lights: their irradiance, one number or one per channel (default: the median over "
                             "the fitted frames of exposure x irradiance x the calibrated gain: as bright as the "
                             "typical photograph)")
    render.add_argument("--format", default="auto", choices=["auto", "png", "exr"],
                        help="new lights: png (8 bits, encoded as the photographs), exr (float32, linear) or auto "
                             "(the default: png where the capture came from photographs, else exr)")
    render.add_argument("--srgb", action="store_true",
                        help="png: encode with the sRGB curve (default: as the photographs were recorded, e.g. with "
                             "the camera response the import estimated, so the images look like the photographs)")
    render.add_argument("--path", default="auto", choices=["auto", "point", "fast", "reference"],
                        help="quadrature path (default: auto)")
    render.add_argument("--no-term", action="store_true",
                        help="leave out the maps' residual term (residual_term.exr): the physical model alone")
    render.add_argument("--quiet", action="store_true", help="no progress bar")
    add_device(render)
    add_overwrite(render)

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
                             "rti: the fitted lights' irradiance, one number (default: the photographs' own, the "
                             "median exposure times irradiance of the frames fitted, as calibrated: as bright as "
                             "they are; pi without the capture, a white Lambertian surface facing the light shows 1)")
    export.add_argument("--capture", type=Path, default=None,
                        help="the capture the maps were fitted from: web: its photographs beside the relit fit; "
                             "rti: its photographs' brightness and encoding (default: the one svbrdf.json names)")
    export.add_argument("--quiet", action="store_true", help="no progress bar")
    add_overwrite(export)

    view = commands.add_parser("view", help="relight SVBRDF maps in the browser: a page served on 127.0.0.1")
    view.add_argument("svbrdf", type=Path, help="a folder of SVBRDF maps (e.g. a fit)")
    view.add_argument("--capture", type=Path, default=None,
                      help="the capture the maps were fitted from: its photographs beside the relit fit")
    view.add_argument("--port", type=int, default=8000, help="the port on 127.0.0.1 (default: 8000; 0: any free)")
    view.add_argument("--no-cache", action="store_true",
                      help="neither read nor write the coarse levels' cache (MAPS/.torchspec-view/, or the user's "
                           "cache folder when MAPS is read-only): the pass over every row at each view")
    view.add_argument("--quiet", action="store_true",
                      help="no progress bar (the page's address is printed all the same)")


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
    add_device(calibrate)
    add_overwrite(calibrate, " (the kernel EXR and its .json)")


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
    add_overwrite(acquire, " (start afresh; --resume continues an acquisition instead)")

