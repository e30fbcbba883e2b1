"""The fit on a GPU (issue 36), in one command that runs in at most ``budget_s`` seconds:

1. ``bench_fit``'s simulated painting (``size x size`` pixels, ``grid x grid`` frames of a projected
   Gaussian light; cached): the default fit and the fit forced to ``ward-iso``, each twice in a fresh
   process on ``device``: cold (an empty ``TORCHINDUCTOR_CACHE_DIR``) and warm (the same cache
   again). Wall time of ``torchspec.fit`` (the frames read, to the maps in memory), its stages,
   pixels per second and the peak device memory (``torch.cuda.max_memory_allocated``; on the CPU
   the process's peak RSS).
2. The same capture fitted on the CPU with ``cpu_threads`` threads, and its agreement with the
   warm default fit on ``device``: the share of pixels with the same model, the normals' angle,
   k_d, k_s and alpha (relative) at the 99th percentile, and the untrusted pixels of one and not
   the other (:func:`torchspec.pipeline.flags.untrusted`).
3. A large capture as a light dome writes it: ``large_frames`` of the painting's frames (evenly
   spread over its list) tiled to ``large_width x large_height`` pixels, written as 8-bit sRGB JPEGs with a ``dirs.lp``,
   then ``torchspec import`` and ``torchspec fit`` (the default command, ``--device``) in fresh
   processes: wall time from the JPEGs to the written maps, split into the import and the fit's
   stages (``svbrdf.json``'s ``fit.seconds``).

Every part runs in a child process under the time that is left (a part that does not finish is
reported as such, with how long it ran): the JSON is written after each part.

    python experiments/bench_gpu.py [--config experiments/configs/bench_gpu.yaml] [--output experiments/results]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from _common import parse_args
from bench_fit import Settings as FitBenchSettings
from bench_fit import _capture

from torchspec.atomic import write_json
from torchspec.config import load_config
from torchspec.io import read_capture, read_svbrdf
from torchspec.model.geometry import angle
from torchspec.pipeline.flags import untrusted


@dataclass(frozen=True)
class Settings:
    size: int = 512  # the simulated painting: size x size pixels
    grid: int = 12  # grid x grid frames
    extent: float = 0.65
    kernel_sigma: float = 0.08
    photons_per_unit: float = 100000.0
    seed: int = 3
    cache: str = "/tmp/torchspec-bench-fit"  # the simulated capture's folder (shared with bench_fit)
    device: str = "cuda"
    cpu_threads: int = 16  # the CPU fit's torch threads (part 2)
    large_width: int = 6000  # part 3: the tiled capture's size (24 megapixels) ...
    large_height: int = 4000
    large_frames: int = 60  # ... and this many of the painting's frames, evenly spread over its list
    budget_s: float = 570.0  # the whole run's wall time; each part gets what is left (BENCH_GPU_BUDGET overrides)


_FIT = """
import json, os, resource, sys, time, torch
from torchspec.pipeline import FitConfig, fit, write_fit
settings = json.loads(sys.argv[1])
torch.set_num_threads(settings.pop("threads"))
config = FitConfig.from_dict(settings)
start = time.perf_counter()
result = fit(sys.argv[2], config=config)
if config.compute.device.startswith("cuda"):
    torch.cuda.synchronize()
seconds = time.perf_counter() - start
write_fit(sys.argv[3], result)
if config.compute.device.startswith("cuda"):
    peak = torch.cuda.max_memory_allocated() / 2**20
else:
    with open("/proc/self/status") as status:
        peak = next(int(line.split()[1]) for line in status if line.startswith("VmHWM:")) / 1024
from torch._dynamo.utils import counters
cache = {k: int(counters["inductor"].get("fxgraph_cache_" + k, 0)) for k in ("hit", "miss")}
print(json.dumps({"seconds": seconds, "peak_mb": peak, "stats": result.stats, "compile_cache": cache}, default=str))
"""


class Budget:
    """The run's wall-time budget: what is left of ``seconds`` from now."""

    def __init__(self, seconds: float):
        self.end = time.perf_counter() + seconds

    def left(self) -> float:
        return max(0.0, self.end - time.perf_counter())


def _child(args: list[str], budget: Budget, env: dict | None = None) -> tuple[dict | None, float, str]:
    """Run ``python args`` (or a ``torchspec`` command) under the time left: ``(its last JSON line or
    None, seconds, a note: '' when it finished, else why not)``."""
    start = time.perf_counter()
    limit = budget.left()
    if limit < 5:
        return None, 0.0, "not started: no time left"
    try:
        done = subprocess.run(args, capture_output=True, text=True, timeout=limit, env=env, check=False)
    except subprocess.TimeoutExpired:
        return None, time.perf_counter() - start, f"not finished in {limit:.0f} s"
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        return None, seconds, f"failed (exit {done.returncode}): {done.stderr[-1500:]}"
    lines = [line for line in done.stdout.splitlines() if line.startswith("{")]
    return (json.loads(lines[-1]) if lines else {}), seconds, ""


def _fit(capture: Path, maps: Path, config: dict, threads: int, cache_dir: Path, budget: Budget) -> dict:
    env = {**os.environ, "TORCHINDUCTOR_CACHE_DIR": str(cache_dir)}
    settings = json.dumps({**config, "threads": threads})
    out, seconds, note = _child([sys.executable, "-c", _FIT, settings, str(capture), str(maps)], budget, env)
    if out is None:
        return {"note": note, "wall_seconds": seconds}
    stats = out["stats"]
    return {
        "seconds": out["seconds"],
        "pixels_per_second": stats["pixels"] / out["seconds"],
        "peak_mb": out["peak_mb"],
        "stage_seconds": stats["seconds"],
        "models": stats.get("models"),
        "compile_cache": out["compile_cache"],
        "device": stats.get("device"),
    }


def agreement(ours: Path, reference: Path) -> dict:
    """How the maps in ``ours`` agree with those in ``reference`` (part 2 of the module docstring)."""
    a, b = read_svbrdf(ours), read_svbrdf(reference)
    sa, sb = a.svbrdf.flatten(), b.svbrdf.flatten()
    same = (a.extra["model"].reshape(-1) == b.extra["model"].reshape(-1)).double().mean()
    normals = torch.rad2deg(angle(sa.normal.double(), sb.normal.double()))

    def relative(x, y):
        return float(((x.double() - y.double()).abs() / y.double().abs().clamp(min=1e-6)).flatten().quantile(0.99))

    ua = untrusted(a.extra["flags"].reshape(-1).to(torch.int64))
    ub = untrusted(b.extra["flags"].reshape(-1).to(torch.int64))
    return {
        "same_model": float(same),
        "normal_deg_p99": float(normals.quantile(0.99)),
        "kd_p99": relative(sa.diffuse, sb.diffuse),
        "ks_p99": relative(sa.specular, sb.specular),
        "alpha_p99": relative(sa.roughness, sb.roughness),
        "untrusted_only_one": int((ua != ub).sum()),
        "untrusted": [int(ua.sum()), int(ub.sum())],
    }


def write_dome_capture(capture: Path, folder: Path, settings: Settings) -> int:
    """The painting's frames tiled to the large size, as 8-bit sRGB JPEGs with a ``dirs.lp`` (part 3):
    the number of frames written."""
    from PIL import Image

    source = read_capture(capture)
    count = min(settings.large_frames, len(source.frames))
    picked = [int(k) for k in np.linspace(0, len(source.frames) - 1, count).round()]
    folder.mkdir(parents=True)
    directions = source.directions()
    lines = [str(len(picked))]
    reps = (-(-settings.large_height // source.height), -(-settings.large_width // source.width))
    for i, k in enumerate(picked):
        frame = source.read_frames([k], dtype=torch.float32)[0].permute(1, 2, 0).numpy()  # (H, W, C)
        big = np.tile(frame, (*reps, 1))[: settings.large_height, : settings.large_width]
        big = np.clip(big / max(float(frame.max()), 1e-6), 0, 1)
        encoded = np.where(big <= 0.0031308, 12.92 * big, 1.055 * np.power(big, 1 / 2.4) - 0.055)
        name = f"frame_{i:03d}.jpg"
        Image.fromarray((encoded * 255 + 0.5).astype(np.uint8)).save(folder / name, quality=95)
        x, y, z = (float(v) for v in directions[k])
        lines.append(f"{name} {x:.6f} {y:.6f} {z:.6f}")
    (folder / "dirs.lp").write_text("\n".join(lines) + "\n")
    return len(picked)


def _large(capture: Path, scratch: Path, settings: Settings, budget: Budget) -> dict:
    photos, imported, maps = scratch / "dome", scratch / "dome-capture", scratch / "dome-maps"
    if budget.left() < 30:
        return {"note": f"not started: {budget.left():.0f} s left"}
    start = time.perf_counter()
    frames = write_dome_capture(capture, photos, settings)
    row = {"pixels": settings.large_width * settings.large_height, "frames": frames,
           "write_jpegs_seconds": time.perf_counter() - start}
    command = [sys.executable, "-m", "torchspec"]
    _, seconds, note = _child([*command, "import", str(photos), "-o", str(imported)], budget)
    row["import_seconds"], row["import_note"] = seconds, note
    if note:
        return row
    fit = [*command, "fit", str(imported), "-o", str(maps), "--quiet", "--device", settings.device]
    _, seconds, note = _child(fit, budget)
    row["fit_seconds"], row["fit_note"] = seconds, note
    if not note:
        meta = json.loads((maps / "svbrdf.json").read_text())
        row["fit_stage_seconds"] = meta["fit"]["seconds"]
        row["jpegs_to_maps_seconds"] = row["import_seconds"] + row["fit_seconds"]
    return row


def main(argv: list[str] | None = None) -> dict:
    args = parse_args(__doc__, "bench_gpu.yaml", argv)
    settings = load_config(args.config, Settings)
    budget = Budget(float(os.environ.get("BENCH_GPU_BUDGET", settings.budget_s)))
    fields = ("size", "grid", "extent", "kernel_sigma", "photons_per_unit", "seed", "cache")
    bench = FitBenchSettings(threads=settings.cpu_threads, scipy_pixels=0, **{k: getattr(settings, k) for k in fields})
    capture = _capture(bench, settings.device)  # simulated on the device when not cached
    out = {"settings": asdict(settings), "torch": torch.__version__, "gpu": _gpu(), "fits": {}}
    target = Path(args.output) / f"{Path(args.config).stem}.json"
    with tempfile.TemporaryDirectory(prefix="torchspec-bench-gpu-") as tmp:
        scratch = Path(tmp)
        for label, model in (("default", "auto"), ("ward-iso", "ward-iso")):
            cache_dir = scratch / f"inductor-{label}"
            for run in ("cold", "warm"):
                config = {"model": model, "compute": {"device": settings.device}}
                row = _fit(capture, scratch / f"maps-{label}-{run}", config, settings.cpu_threads, cache_dir, budget)
                out["fits"][f"{label} {run}"] = row
                _print(f"{label} {run}", row)
                write_json(target, out)
        on_cpu = {"compute": {"device": "cpu"}}
        cpu = _fit(capture, scratch / "maps-cpu", on_cpu, settings.cpu_threads, scratch / "i-cpu", budget)
        out["fits"]["default cpu"] = cpu
        _print("default cpu", cpu)
        if "seconds" in cpu and "seconds" in out["fits"]["default warm"]:
            out["agreement"] = agreement(scratch / "maps-default-warm", scratch / "maps-cpu")
            print("agreement with the CPU:", json.dumps(out["agreement"]))
        write_json(target, out)
        out["large"] = _large(capture, scratch, settings, budget)
        print("large capture:", json.dumps(out["large"], default=str))
    write_json(target, out)
    return out


def _gpu() -> str | None:
    return torch.cuda.get_device_name(0) if torch.cuda.is_available() else None


def _print(label: str, row: dict) -> None:
    if "seconds" not in row:
        print(f"{label:18s} {row['note']}")
        return
    print(f"{label:18s} {row['seconds']:8.1f} s {row['pixels_per_second']:10.0f} px/s {row['peak_mb']:9.0f} MB peak "
          f"(compile cache hits {row['compile_cache']['hit']}, misses {row['compile_cache']['miss']})")


if __name__ == "__main__":
    main()
