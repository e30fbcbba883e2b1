"""The ``torchspec`` command."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from ._version import __version__

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="torchspec",
        description="Reflectance of nearly flat objects from a few HDR photographs under an extended light.",
    )
    parser.add_argument("--version", action="version", version=f"torchspec {__version__}")
    commands = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = commands.add_parser("demo", help="run the embedded default example and report accuracy and speed")
    demo.add_argument("-o", "--output", type=Path, default=None, help="folder for demo.json and demo.png")
    demo.add_argument("--pixels", type=int, default=65536, help="number of simulated pixels (default: 65536)")

    simulate = commands.add_parser("simulate", help="render a synthetic capture (with truth/) from a config")
    simulate.add_argument("config", type=Path, help="a simulation config (YAML), e.g. configs/sim_painting.yaml")
    simulate.add_argument("-o", "--output", type=Path, required=True, help="the capture folder to write")

    fit = commands.add_parser("fit", help="fit SVBRDF maps (normal, diffuse, specular, roughness) to a capture")
    fit.add_argument("capture", type=Path, help="the capture folder (with capture.json)")
    fit.add_argument("-o", "--output", type=Path, required=True, help="the folder of maps to write")
    fit.add_argument("--config", type=Path, default=None,
                     help="fit settings (YAML, keys of FitConfig), e.g. configs/fit.yaml")
    fit.add_argument("--frames", default=None,
                     help="frames to fit: 'all', a slice like '::2' (every second) or a list like '0,3,10-19'")
    fit.add_argument("--quiet", action="store_true", help="no progress bar")

    render = commands.add_parser("render", help="predict a capture's frames from SVBRDF maps")
    render.add_argument("svbrdf", type=Path, help="a folder of SVBRDF maps (e.g. a fit, or a capture's truth/)")
    render.add_argument("--capture", type=Path, required=True, help="the capture whose lights to render")
    render.add_argument("-o", "--output", type=Path, required=True, help="folder for the predicted frames")
    render.add_argument("--light", type=Path, default=None,
                        help="a JSON light description to use instead of the capture's (needed for 'unknown' kernels)")
    render.add_argument("--path", default="auto", choices=["auto", "point", "fast", "reference"],
                        help="quadrature path (default: auto)")
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    try:
        return _run(parser, args)
    except (ValueError, OSError) as exc:  # bad input: say what and where, no traceback
        print(f"torchspec {args.command}: error: {exc}", file=sys.stderr)
        return 2


def _run(parser: argparse.ArgumentParser, args: argparse.Namespace) -> int:
    if args.command == "demo":
        if args.pixels < 1:
            parser.error(f"--pixels must be >= 1; got {args.pixels}")
        from . import demo

        demo.run(args.output, pixels=args.pixels)
    elif args.command == "simulate":
        from .config import load_config
        from .simulate import SimulationConfig, simulate, write_simulation

        config = load_config(args.config, SimulationConfig)
        result = write_simulation(args.output, simulate(config, root=args.output))
        print(f"wrote {args.output}: {len(result.frames)} frames of {result.width}x{result.height} "
              f"{''.join(result.channels)}, with truth/")
    elif args.command == "fit":
        from .config import load_config
        from .fit import FitConfig, fit, write_fit

        config = load_config(args.config, FitConfig) if args.config is not None else FitConfig()
        result = fit(args.capture, config=config, frames=args.frames, progress=not args.quiet)
        write_fit(args.output, result)
        stats = result.stats
        print(f"wrote {args.output}: {stats['pixels']} pixels from {len(stats['frames'])} frames in "
              f"{stats['seconds']['total']:.1f} s ({stats['pixels_per_second']:.0f} pixels/s); "
              f"{stats['lobe_pixels']} with a lobe; solver: {stats['status']}; "
              f"median relative residual {stats['median_residual']:.2e}")
    elif args.command == "render":
        from .relight import render_capture

        report = render_capture(args.svbrdf, args.capture, args.output, light=args.light, path=args.path)
        print(f"wrote {report['frames']} frames to {args.output}")
        if report.get("psnr_db") is not None:
            print(f"  against the capture's frames: PSNR {report['psnr_db']:.2f} dB (peak = the capture's maximum), "
                  f"relative RMS error {100 * report['relative_rms']:.2f} %")
    return 0


if __name__ == "__main__":
    sys.exit(main())
