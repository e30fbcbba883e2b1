"""A fit on a shared machine (issue 21, item 5): the same fit quiet and beside a neighbour that
keeps every core busy, for several thread settings; and, in the same run, the pixel-frames per
second of the default fit of each real RTI capture beside the synthetic benchmark's (fitted before
and after each capture: the ratio is against the mean of those two).

Every fit runs in a fresh process (``OMP_WAIT_POLICY`` and ``GOMP_SPINCOUNT`` are read as torch
loads its OpenMP runtime). The neighbour is ``neighbours`` processes each spinning a Python loop
(started a second before the fit, stopped after it). Each row of the busy table is a thread setting
(``FitConfig.compute.threads``) with its environment: the torch default before issue 21 (2 threads, libgomp's
default spin of ~3 ms at each barrier, which ``GOMP_SPINCOUNT=300000`` restores), 1 thread, and the
new default (``auto`` with passive waits). Repeated ``repeats`` times, alternating; the median is
reported, with the load average before each fit and the cores the other processes (the neighbour and
anything else on the machine) used during it.

The captures: ``small`` and ``synthetic`` are crops (pixels and frames) of the simulated painting of
``experiments/configs/bench_fit.yaml`` (simulated on the first run, then cached); the real ones are
imported from ``data`` with :func:`torchspec.io.rti.import_rti` (full size, or their top-left
``real_crop`` pixels) and fitted on every frame.

    python experiments/bench_busy.py [--config experiments/configs/bench_busy.yaml] [--output experiments/results]
        [--parts busy,real]

``data`` is relative to the current folder (``../shared/data/rti`` from the main checkout).
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import time
import warnings
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import torch
from _common import ROOT, parse_args

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_capture, write_capture
from torchspec.threads import CpuMeter


@dataclass(frozen=True)
class Variant:
    name: str
    threads: int | str  # FitConfig.compute.threads
    env: dict[str, str] = field(default_factory=dict)  # added to the fit's environment


@dataclass(frozen=True)
class Crop:
    size: int  # the top-left size x size pixels of the simulated painting ...
    frames: str  # ... and these frames (a SPEC of select_frames)


@dataclass(frozen=True)
class Settings:
    simulation: str  # the config of experiments/bench_fit.py whose painting is cropped
    small: Crop  # the capture of the busy table
    synthetic: Crop  # the synthetic benchmark beside the real captures
    data: str  # the folder of the real RTI captures
    captures: list[str]
    neighbours: int  # busy processes beside the fit
    repeats: int
    variants: list[Variant]
    scratch: str  # imported and cropped captures (kept between runs)
    real_crop: int = 0  # > 0: fit the top-left real_crop x real_crop pixels of each real capture (0: all)


NEIGHBOUR = "while True: pass"

CHILD = """
import json, sys, time, warnings
from torchspec.config import from_mapping
from torchspec.pipeline import FitConfig, fit
config = from_mapping(json.loads(sys.argv[2]), FitConfig)
with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    start = time.perf_counter()
    result = fit(sys.argv[1], config=config)
    seconds = time.perf_counter() - start
k = len(result.stats["frames"])
out = {"seconds": seconds, "pixels": result.stats["pixels"], "frames": k, "stage_seconds": result.stats["seconds"],
       "models_tried": result.stats["models_tried"], "models": result.stats["models"]}
print(json.dumps(out))
"""


def timed_fit(capture: Path, config: dict, env: dict | None = None) -> dict:
    """A fit of ``capture`` with the FitConfig keys ``config`` in a fresh process: its seconds, the
    pixel-frames per second, the load average before it and the cores others used during it."""
    environ = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    environ.update(env or {})
    environ["PYTHONPATH"] = str(ROOT) + os.pathsep + environ.get("PYTHONPATH", "")
    meter = CpuMeter()
    load = os.getloadavg()[0]
    meter.last = meter.reading()
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(capture), json.dumps(config)], capture_output=True, text=True, env=environ
    )
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    wall = time.monotonic() - meter.last[0]
    others = meter.others() or 0.0  # every process but this one, the fit included
    fit_cores = (after.ru_utime + after.ru_stime - before.ru_utime - before.ru_stime) / wall
    if done.returncode != 0:
        raise RuntimeError(f"the fit of {capture} failed:\n{done.stderr[-3000:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    out["pixel_frames_per_second"] = out["pixels"] * out["frames"] / out["seconds"]
    out["load_before"] = load
    out["others_cores"] = max(0.0, others - fit_cores)
    out["fit_cores"] = fit_cores
    return out


class Neighbour:
    """``count`` processes each keeping a core busy, for the length of a ``with`` block."""

    def __init__(self, count: int):
        self.count = count
        self.processes = []

    def __enter__(self):
        self.processes = [subprocess.Popen([sys.executable, "-c", NEIGHBOUR]) for _ in range(self.count)]
        time.sleep(1.0)  # running before the fit starts
        return self

    def __exit__(self, *exc):
        for process in self.processes:
            process.kill()
            process.wait()


def crop(source: Path, spec: Crop, folder: Path) -> Path:
    """The top-left ``spec.size`` pixels and ``spec.frames`` of the capture ``source`` (cached)."""
    from torchspec.pipeline import select_frames

    if (folder / "capture.json").exists():
        return folder
    capture = read_capture(source)
    picked = select_frames(spec.frames, len(capture.frames))
    stack = capture.read_frames(picked)[..., : spec.size, : spec.size]
    frames = [replace(capture.frames[k], file=f"frames/{i:04d}.exr") for i, k in enumerate(picked)]
    small = replace(capture, root=folder, width=spec.size, height=spec.size, frames=frames)
    write_capture(folder, small, stack, overwrite=True)
    return folder


def busy_table(settings: Settings, capture: Path) -> list[dict]:
    """Each variant quiet and beside the neighbour, ``repeats`` times alternating."""
    runs = {(v.name, busy): [] for v in settings.variants for busy in (False, True)}
    for repeat in range(settings.repeats):
        order = settings.variants if repeat % 2 == 0 else settings.variants[::-1]
        for variant in order:
            for busy in (False, True) if repeat % 2 == 0 else (True, False):
                if busy:
                    with Neighbour(settings.neighbours):
                        run = timed_fit(capture, {"compute": {"threads": variant.threads}}, variant.env)
                else:
                    run = timed_fit(capture, {"compute": {"threads": variant.threads}}, variant.env)
                runs[variant.name, busy].append(run)
                print(
                    f"  {variant.name:38s} {'busy ' if busy else 'quiet'} {run['seconds']:7.1f} s  "
                    f"load {run['load_before']:4.2f}  others {run['others_cores']:4.2f} cores",
                    flush=True,
                )
    rows = []
    for variant in settings.variants:
        row = {"variant": asdict(variant)}
        for busy, key in ((False, "quiet"), (True, "busy")):
            done = runs[variant.name, busy]
            row[key] = {
                "seconds": [r["seconds"] for r in done],
                "median_seconds": statistics.median(r["seconds"] for r in done),
                "load_before": [r["load_before"] for r in done],
                "others_cores": [r["others_cores"] for r in done],
                "fit_cores": [r["fit_cores"] for r in done],
            }
        row["pixel_frames_per_second"] = {
            key: done[0]["pixels"] * done[0]["frames"] / row[key]["median_seconds"]
            for key, done in (("quiet", runs[variant.name, False]), ("busy", runs[variant.name, True]))
        }
        row["slow_down"] = row["busy"]["median_seconds"] / row["quiet"]["median_seconds"]
        rows.append(row)
    best = min(row["quiet"]["median_seconds"] for row in rows)
    for row in rows:
        row["busy_over_best_quiet"] = row["busy"]["median_seconds"] / best
    return rows


def real_rates(settings: Settings, synthetic: Path, scratch: Path) -> list[dict]:
    """The default fit of the synthetic benchmark and of each real capture (imported at full size),
    interleaved: the synthetic fit before the first capture and after each, so that each capture's
    ``rate_over_synthetic`` is against the mean rate of the synthetic fits just before and after it
    (the host's speed drifts by up to 1.4x within minutes). Rows: the synthetic fits and the
    captures, in the order run."""
    from torchspec.io.rti import import_rti

    targets = []
    for name in settings.captures:
        folder = scratch / f"{name}-import"
        if not (folder / "capture.json").exists():
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                import_rti(Path(settings.data) / name, folder, overwrite=True)
        if settings.real_crop:
            folder = crop(folder, Crop(settings.real_crop, "all"), scratch / f"{name}-{settings.real_crop}")
        targets.append((name, folder))
    rows = [_rate_row("synthetic", synthetic)]
    for name, folder in targets:
        row = _rate_row(name, folder)
        after = _rate_row("synthetic", synthetic)
        around = [rows[-1]["pixel_frames_per_second"], after["pixel_frames_per_second"]]
        row["synthetic_around"] = around
        row["rate_over_synthetic"] = row["pixel_frames_per_second"] / statistics.mean(around)
        rows += [row, after]
    return rows


def _rate_row(name: str, folder: Path) -> dict:
    """One default fit of the capture in ``folder``, printed."""
    capture = read_capture(folder)
    run = timed_fit(folder, {})
    print(
        f"  {name:16s} {capture.width:4d} x {capture.height:<4d} x {run['frames']:3d}  {run['seconds']:7.1f} s  "
        f"{run['pixel_frames_per_second'] / 1e3:7.1f} k pixel-frames/s  load {run['load_before']:4.2f}  "
        f"others {run['others_cores']:4.2f} cores",
        flush=True,
    )
    return {"capture": name, "size": [capture.width, capture.height], **run}


def _print_busy(rows: list[dict]) -> None:
    print(
        f"\n{'variant':38s} {'quiet s':>8s} {'busy s':>8s} {'slow-down':>9s} {'/best quiet':>11s} {'quiet kpf/s':>11s}"
    )
    for row in rows:
        print(
            f"{row['variant']['name']:38s} {row['quiet']['median_seconds']:8.1f} {row['busy']['median_seconds']:8.1f} "
            f"{row['slow_down']:9.2f} {row['busy_over_best_quiet']:11.2f} "
            f"{row['pixel_frames_per_second']['quiet'] / 1e3:11.1f}"
        )


def _parts(parser) -> None:
    parser.add_argument(
        "--parts", default="busy,real", help="busy, real or both (the JSON keeps the other part of an earlier run)"
    )


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "bench_busy.yaml", argv, options=_parts)
    settings = load_config(args.config, Settings)
    parts = set(args.parts.split(","))
    sys.path.insert(0, str(ROOT / "experiments"))
    import bench_fit

    source = bench_fit._capture(load_config(ROOT / settings.simulation, bench_fit.Settings))
    scratch = Path(settings.scratch).expanduser()
    scratch.mkdir(parents=True, exist_ok=True)
    target = args.output / f"{Path(args.config).stem}.json"
    out = json.loads(target.read_text()) if target.exists() else {}
    out.update({"settings": asdict(settings), "torch": torch.__version__, "cores": os.cpu_count()})
    if "real" in parts:
        name = f"synthetic-{settings.synthetic.size}-{settings.synthetic.frames.replace(':', '_')}"
        synthetic = crop(source, settings.synthetic, scratch / name)
        print("\nthe default fit, no neighbour:")
        real = real_rates(settings, synthetic, scratch)
        for row in real:
            if "rate_over_synthetic" in row:
                print(
                    f"  {row['capture']:16s} {row['rate_over_synthetic']:.2f}x the synthetic benchmark's "
                    f"pixel-frames/s (the fits before and after it: {row['synthetic_around'][0] / 1e3:.1f} and "
                    f"{row['synthetic_around'][1] / 1e3:.1f} k)"
                )
        out["real"] = real
        write_json(target, out)
    if "busy" in parts:
        name = f"small-{settings.small.size}-{settings.small.frames.replace(':', '_')}"
        small = crop(source, settings.small, scratch / name)
        print(
            f"busy table: {small} ({settings.neighbours} neighbours, {settings.repeats} repeats); "
            f"{os.cpu_count()} cores"
        )
        out["busy"] = busy_table(settings, small)
        _print_busy(out["busy"])
        write_json(target, out)
    return out


if __name__ == "__main__":
    main()
