"""Time of ``torchspec fit`` against the number of Dask workers, and the inputs of the scale
estimate of ``docs/scale.md`` (bytes read and compute per tile, the scheduler's overhead per task).

A procedural painting of ``size x size`` pixels is rendered under a ``grid x grid`` layout of a
projected Gaussian light (144 frames by default), with shot noise, and written as a capture
(cached between runs). Each fit then runs in a fresh process:

- in-process (:func:`torchspec.pipeline.fit`) with ``threads`` torch threads;
- on a local cluster of ``workers`` processes of one thread each (:mod:`torchspec.pipeline.cluster`):
  the time to start the cluster and import torchspec in its workers, then the fit's;
- on one worker started with Dask's default ``MALLOC_TRIM_THRESHOLD_``, with and without the
  reset of glibc's thresholds that :func:`torchspec.pipeline.fit_on_cluster` applies in such a worker.

Every fit's maps are compared with the one-thread in-process fit's (``torch.equal``). The workers'
bytes read are counted by the kernel (``/proc/thread-self/io``), against the capture's size on
disk. The scheduler's overhead per task is the time of ``noop_tasks`` empty tasks on the largest
cluster, per task.

    python experiments/bench_scale.py [--config experiments/configs/bench_scale.yaml] [--output experiments/results]

Writes ``bench_scale.json`` and ``bench_scale.png`` (seconds against workers).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch
from _common import parse_args
from bench_fit import _capture  # the same simulated painting, cached by its settings

from torchspec.atomic import save_figure, write_json
from torchspec.config import load_config
from torchspec.pipeline import FitConfig


@dataclass(frozen=True)
class Settings:
    size: int  # the painting is size x size pixels
    grid: int  # grid x grid light centres ...
    extent: float  # ... over [-extent, extent]^2 of the l-plane
    kernel_sigma: float
    photons_per_unit: float
    seed: int
    cache: str  # folder for the simulated capture (reused when its settings match)
    workers: list[int] = field(default_factory=lambda: [1, 2])
    threads: list[int] = field(default_factory=lambda: [1, 2])
    noop_tasks: int = 2000
    malloc: bool = True  # the MALLOC_TRIM_THRESHOLD_ rows
    fit: FitConfig = field(default_factory=FitConfig)


# One fit in a fresh process: argv = engine, count, config (JSON), capture, maps file (torch.save), checkpoint.
_CHILD = """
import importlib, json, os, sys, time, torch
from torchspec.config import from_mapping
from torchspec.pipeline import FitConfig, fit
engine, count = sys.argv[1], int(sys.argv[2])
config = from_mapping(json.loads(sys.argv[3]), FitConfig)
capture, maps, checkpoint = sys.argv[4], sys.argv[5], sys.argv[6]
out = {}
if engine == "in-process":
    torch.set_num_threads(count)
    start = time.perf_counter()
    result = fit(capture, config=config)
    out["seconds"] = time.perf_counter() - start
else:
    import dask
    from distributed import Client, LocalCluster
    from torchspec.pipeline import connect
    from torchspec.pipeline import fit_on_cluster as fit_on
    start = time.perf_counter()
    if engine == "dask":
        context = connect(workers=count)
    else:  # Dask's own worker environment, MALLOC_TRIM_THRESHOLD_ included
        cluster = LocalCluster(n_workers=count, threads_per_worker=1, host="127.0.0.1", dashboard_address=None)
        context = Client(cluster, set_as_default=False)
    with context as client:
        client.run(importlib.import_module, "torchspec.pipeline.cluster")  # the workers' imports, outside the fit
        if engine == "dask-malloc-trim":  # as if the reset of glibc's thresholds had been done already
            client.run(lambda: importlib.import_module("torchspec.pipeline.cluster")._PINNED.append(True))
        out["environ"] = client.run(lambda: os.environ.get("MALLOC_TRIM_THRESHOLD_"))
        out["startup_seconds"] = time.perf_counter() - start
        start = time.perf_counter()
        result = fit_on(capture, client, checkpoint=checkpoint, config=config)
        out["seconds"] = time.perf_counter() - start
        if engine == "dask" and count == int(sys.argv[7]):  # the scheduler's overhead per task
            tasks = int(sys.argv[8])
            client.gather(client.map(lambda i: i, range(min(100, tasks)), pure=False))  # warm
            start = time.perf_counter()
            client.gather(client.map(lambda i: i, range(tasks), pure=False))
            out["noop_seconds_per_task"] = (time.perf_counter() - start) / tasks
torch.save({"svbrdf": result.svbrdf, "residual": result.residual, "criterion": result.criterion}, maps)
out["stats"] = result.stats
print(json.dumps(out, default=str))
"""


def _run(engine: str, count: int, settings: Settings, capture: Path, tmp: Path) -> tuple[dict, dict]:
    maps, checkpoint = tmp / f"{engine}-{count}.pt", tmp / f"{engine}-{count}-tiles"
    argv = [engine, str(count), json.dumps(asdict(settings.fit)), str(capture), str(maps), str(checkpoint)]
    argv += [str(max(settings.workers)), str(settings.noop_tasks)]
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TRIM_THRESHOLD_"}
    done = subprocess.run([sys.executable, "-c", _CHILD, *argv], capture_output=True, text=True, check=False, env=env)
    if done.returncode != 0:
        raise RuntimeError(f"the fit ({engine}, {count}) failed:\n{done.stderr[-3000:]}")
    out = json.loads(done.stdout.strip().splitlines()[-1])
    print(f"{engine:18s} {count}: {out['seconds']:7.1f} s", flush=True)
    return out, torch.load(maps, weights_only=False)


def _identical(a: dict, b: dict) -> bool:
    def same(x, y):
        return x.shape == y.shape and bool(((x == y) | (x.isnan() & y.isnan())).all())

    maps = all(same(getattr(a["svbrdf"], n), getattr(b["svbrdf"], n)) for n in ("normal", "diffuse", "specular"))
    return maps and same(a["svbrdf"].roughness, b["svbrdf"].roughness) and same(a["criterion"], b["criterion"])


def _disk_bytes(capture: Path) -> int:
    return sum(f.stat().st_size for f in (capture / "frames").glob("*.exr"))


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "bench_scale.yaml", argv)
    settings = load_config(args.config, Settings)
    capture = _capture(settings)
    pixels, disk = settings.size**2, _disk_bytes(capture)
    runs = [("in-process", n) for n in settings.threads] + [("dask", n) for n in settings.workers]
    if settings.malloc:
        runs += [("dask-malloc-trim", 1), ("dask-default", 1)]
    rows, reference = [], None
    with tempfile.TemporaryDirectory() as tmp:
        for engine, count in sorted(runs, key=lambda run: run != ("in-process", 1)):  # the reference first
            out, maps = _run(engine, count, settings, capture, Path(tmp))
            reference = reference if reference is not None else maps
            stats = out["stats"]
            tiles = -(-pixels // stats["tile_pixels"])
            row = {
                "engine": engine,
                "workers" if engine != "in-process" else "threads": count,
                "seconds": out["seconds"],
                "pixels_per_second": pixels / out["seconds"],
                "identical_to_one_thread_in_process": _identical(maps, reference),
                "tiles": tiles,
                "tile_pixels": stats["tile_pixels"],
                "stage_seconds": stats["seconds"],
                "compute_seconds_per_tile": sum(
                    v for k, v in stats["seconds"].items() if k in ("photometric", "specular_start", "lm")
                )
                / tiles,
            }
            if engine != "in-process":
                info = stats["distributed"]
                row.update(
                    startup_seconds=out["startup_seconds"],
                    worker_malloc_trim_threshold=sorted(set(out["environ"].values()), key=str),
                    tasks=info["tasks"],
                    tiles_per_task=info["tiles_per_task"],
                    bytes_read=info["bytes_read"],
                    bytes_read_per_tile=info["bytes_read"] / tiles,
                    bytes_read_over_disk=info["bytes_read"] / disk,
                )
            if "noop_seconds_per_task" in out:
                row["scheduler_seconds_per_task"] = out["noop_seconds_per_task"]
            rows.append(row)
    load = os.getloadavg()
    result = {
        "settings": asdict(settings),
        "torch": torch.__version__,
        "capture": {"pixels": pixels, "frames": settings.grid**2, "disk_bytes": disk},
        "cpus": os.cpu_count(),
        "load_average_after": load,
        "rows": rows,
    }
    write_json(args.output / f"{Path(args.config).stem}.json", result)
    _chart(rows, args.output / f"{Path(args.config).stem}.png", settings)
    return result


def _chart(rows: list[dict], path: Path, settings: Settings) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axis = plt.subplots(figsize=(5.5, 3.6))
    for engine, key, marker in (("in-process", "threads", "o"), ("dask", "workers", "s")):
        picked = sorted((row[key], row["seconds"]) for row in rows if row["engine"] == engine)
        if picked:
            label = "in-process (torch threads)" if engine == "in-process" else "Dask (worker processes)"
            axis.plot(*zip(*picked, strict=True), marker=marker, label=label)
    axis.set_xticks(sorted({row.get("workers", row.get("threads")) for row in rows}))
    axis.set_xlabel("threads / workers")
    axis.set_ylabel("fit seconds")
    title = f"{settings.size} x {settings.size} x {settings.grid**2} frames, on {os.cpu_count()} cores (shared)"
    axis.set_title(title, fontsize=10)
    axis.set_ylim(bottom=0)
    axis.legend(fontsize=8)
    figure.tight_layout()
    save_figure(figure, path)


if __name__ == "__main__":
    main()
