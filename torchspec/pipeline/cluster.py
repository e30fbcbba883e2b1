"""The Dask driver: tile-parallel fitting on a cluster (:func:`fit_on_cluster`; ``torchspec fit
CAPTURE -o OUT --scheduler ADDRESS`` for an existing cluster, ``--workers N`` for a local one).

The fit is independent per tile, so the tiles of :func:`torchspec.pipeline.fit` are mapped over the
cluster's workers, each fitted by the same function as in-process
(:func:`torchspec.pipeline.tile.fit_tile`):

1. the client reads the manifest (no pixel), tiles the fit exactly as the in-process fit does
   (:func:`torchspec.pipeline.plan.plan`) and opens its checkpoint
   (:func:`torchspec.pipeline.checkpoint.open_checkpoint`, the same folder and format: either
   driver resumes the other's);
2. when the settings leave the sensor's clipping level to be found (``saturation: null``), tasks
   over bands of rows find it (:func:`torchspec.start.photometric.sample_masks` takes it from the whole
   stack); it is kept in the checkpoint for a resumed fit;
3. each task reads the rows of a run of consecutive tiles from every frame (and the ``grow`` rows
   around them when something clips: the saturated regions are grown in the image), masks them,
   fits each tile and writes it atomically into the checkpoint, skipping a tile already there: a
   task retried after an error or a lost worker redoes only the tiles that were not written;
4. the client loads each tile once, as its task completes, and assembles the maps
   (:func:`torchspec.pipeline.assembly.assemble`).

The maps equal the in-process fit's (``torch.equal``; the tiles' rounding is the same with one
torch thread per task, which each task pins). The capture and the output folder must be on a
filesystem every worker sees at the same path. Sizes and timings: ``docs/scale.md``.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import time
import uuid
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, replace
from pathlib import Path

import torch

from ..atomic import read_json, write_json
from ..errors import TorchspecError
from ..io import Capture
from ..model.lights import Lights
from ..model.residual_term import TermDomain
from ..progress import bar as progress_bar
from ..start.photometric import peak_of, sample_masks, saturation_level
from .assembly import assemble, run_stats
from .calibration import calibrates
from .checkpoint import FitInterrupted, job_record, open_checkpoint, read_tile, refuse_unfinished, tile_name
from .plan import RUNTIME_BYTES, plan, setup
from .result import Fit
from .settings import FitConfig
from .start import LightContext, light_context
from .tile import MASK_KINDS, FitInputs, TileInputs, TileResult, fit_tile

__all__ = ["ClusterError", "connect", "fit_on_cluster"]

LEVEL = "saturation.json"
"""The checkpoint's record of the clipping level found by the level pass (resumed fits skip it)."""
BAND_BYTES = 512 * 2**20
"""A level-pass task reads bands of rows of about this many bytes (all frames)."""
BLOCK_ROWS = 16
"""Rows of an EXR block with ZIP compression: the level pass reads whole blocks."""
TASK_ROWS = 32
"""A task fits the tiles of about this many rows (one read of them): the EXR blocks (16 rows with
ZIP) that it shares with its neighbours then add a fraction of its own rows to its reading."""
TASKS_PER_THREAD = 4
"""Tiles are grouped into at least this many tasks per worker thread, to balance the load."""
UNSET_ENVIRON = ("MALLOC_TRIM_THRESHOLD_",)
"""Dask's default worker environment that the local cluster leaves out: a fixed malloc trim
threshold turns off glibc's adaptive mmap threshold, and torch's large temporaries then cost a
page fault per page on every allocation (docs/scale.md)."""


class ClusterError(RuntimeError):
    """A distributed fit that cannot go on: the scheduler is unreachable, a worker cannot see the
    capture or the checkpoint, or a tile failed (the message names the tile and its pixels)."""


@contextlib.contextmanager
def connect(scheduler: str | None = None, *, workers: int | None = None, timeout: float = 30.0) -> Iterator:
    """A Dask client: of the cluster whose scheduler is at ``scheduler``, or of a local cluster
    of ``workers`` processes (one thread each, on the loopback interface) that lives as long as
    the context.

    The local cluster's workers run without ``MALLOC_TRIM_THRESHOLD_`` (:data:`UNSET_ENVIRON`;
    the rest of Dask's ``distributed.nanny.pre-spawn-environ``, one OpenMP/BLAS thread, is kept).
    Workers of an existing cluster are started by their owner: :func:`fit_on_cluster` restores glibc's
    adaptive thresholds in them instead (docs/scale.md).

    Args:
        scheduler: the scheduler's address, e.g. ``tcp://10.0.0.5:8786``.
        workers: the number of local worker processes (instead of ``scheduler``).
        timeout: seconds to wait for the scheduler.

    Raises:
        TorchspecError: neither or both of ``scheduler`` and ``workers``, or ``workers < 1``.
        ClusterError: the scheduler cannot be reached (the message names the address).

    Example:
        >>> with connect(workers=2) as client:  # doctest: +SKIP
        ...     result = fit_on_cluster("painting", client, checkpoint="maps/.torchspec-fit")
    """
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError as error:
        raise ClusterError(
            f"a fit on a Dask cluster needs dask and distributed; got {error}. Install them: "
            "pip install 'torchspec[dask]'."
        ) from error
    if (scheduler is None) == (workers is None):
        raise TorchspecError(f"connect needs one of scheduler and workers; got {scheduler=}, {workers=}.")
    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=timeout, set_as_default=False)
        except (OSError, TimeoutError) as error:
            raise ClusterError(
                f"the Dask scheduler at {scheduler} must be reachable; got {type(error).__name__}: {error}. Check the "
                f"address and port, or start a cluster there (`dask scheduler`, then `dask worker {scheduler}`)."
            ) from error
        with client:
            yield client
        return
    if workers < 1:
        raise TorchspecError(f"workers must be >= 1; got {workers}.")
    environ = {f"distributed.nanny.pre-spawn-environ.{name}": None for name in UNSET_ENVIRON}
    with dask.config.set(environ):  # read by each nanny as it starts (and kept for its restarts)
        cluster = LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1", dashboard_address=None
        )
    with cluster, Client(cluster, set_as_default=False) as client:
        yield client


@dataclass(frozen=True)
class _Job:
    """What every task of a fit needs (pickled with each task: a few kB)."""

    capture: Capture
    picked: list[int]
    config: FitConfig
    tile: int
    lights: Lights
    view: torch.Tensor
    ctx: LightContext
    folder: Path
    level: float | None = None  # the clipping level given to sample_masks
    halo: int = 0  # rows read around a task's own: the saturated regions' growth

    @property
    def domain(self) -> TermDomain:
        """The residual term's encoding (:attr:`torchspec.pipeline.records.Setup.domain`)."""
        return TermDomain.of_source(self.capture.extra.get("source"))

    @property
    def pixels(self) -> int:
        return self.capture.height * self.capture.width

    def stop(self, first: int) -> int:
        return min(first + self.tile, self.pixels)

    def rows(self, firsts: list[int]) -> tuple[int, int]:
        """The rows that tiles ``firsts`` (consecutive) cover."""
        w = self.capture.width
        return firsts[0] // w, -(-self.stop(firsts[-1]) // w)

    def read(self, rows: tuple[int, int]) -> torch.Tensor:
        """Rows of the picked frames, ``(K, C, rows, W)``, on the fit's device and dtype."""
        # NaN or Inf pixels are masked and counted by the tiles (stats["masked_samples"]), and
        # reported once by the client: a warning per frame and task would flood the workers' logs.
        return self.capture.read_frames(
            self.picked, rows=rows, dtype=self.view.dtype, device=self.view.device, nonfinite="ignore"
        )

    def describe(self, first: int) -> str:
        stop, w = self.stop(first), self.capture.width
        return f"tile {first // self.tile} (pixels {first}..{stop - 1}, rows {first // w}..{(stop - 1) // w})"


def _distant(begun):
    """``begun`` (a :class:`~torchspec.pipeline.records.Setup`), if its lights are distant and known.

    Raises:
        TorchspecError: near lights (frames with a ``position``), or lights to calibrate from the
            photographs (``FitConfig.calibrate``: :func:`~torchspec.pipeline.calibration.calibrates`),
            which a fit on a cluster does not handle yet; ``FitConfig.shadows: on`` (cast shadows need
            the whole image between fits: :mod:`~torchspec.pipeline.shadows`; ``auto`` is off there).
    """
    if begun.config.shadows == "on":
        raise TorchspecError(
            f"{begun.capture.manifest}: cast shadows (shadows: on) need the fit in one process; fit it without "
            "--scheduler / --workers, or with --shadows off (a fit on a cluster does not try them)."
        )
    if begun.positions is not None or calibrates(begun.config.calibrate, begun.capture.unknown):
        what = (
            "give near-light positions" if begun.positions is not None else "are to be calibrated from the photographs"
        )
        raise TorchspecError(
            f"{begun.capture.manifest}: its lights {what}, which a fit on a cluster does not handle yet; fit it in "
            "one process (without --scheduler / --workers)"
            + ("." if begun.positions is not None else ", or take the lights as written with --calibrate none.")
        )
    return begun


def fit_on_cluster(
    capture: Capture | str | Path,
    client,
    *,
    checkpoint: str | Path,
    config: FitConfig | None = None,
    frames: str | list[int] | None = None,
    progress: bool = False,
    resume: bool = False,
    retries: int = 2,
    tiles_per_task: int | None = None,
) -> Fit:
    """Fit SVBRDF maps to a capture on a Dask cluster: :func:`torchspec.pipeline.fit`, its tiles
    mapped over the cluster's workers.

    Args:
        capture: a :class:`~torchspec.io.Capture` or its folder, on a filesystem every worker
            sees at the same path.
        client: a ``distributed.Client`` (:func:`connect`).
        checkpoint: the folder the workers write the finished tiles to (atomically), on a
            filesystem every worker sees; the caller removes it once the maps are written. The
            in-process fit's format: either engine resumes the other's.
        config, frames, progress, resume: as for :func:`torchspec.pipeline.fit` (the bar counts pixels
            of finished tiles).
        retries: times a task that raised is tried again (a task whose worker was lost is
            rescheduled by Dask without counting).
        tiles_per_task: consecutive tiles one task reads and fits together (one read of their
            rows); by default those of about 32 rows (:data:`TASK_ROWS`), but no fewer than 4
            tasks per worker thread.

    Returns:
        :class:`~torchspec.pipeline.result.Fit`, equal to the in-process fit's; ``stats["distributed"]`` holds
        the cluster's size, the tasks, the bytes the workers read and the tiles a retried task
        found already written.

    Raises:
        ClusterError: a worker cannot see the capture or the checkpoint, or a tile failed after
            its retries (the message names the tile; the finished tiles stay in ``checkpoint``).
        CaptureError, ConfigError, TorchspecError: as :func:`torchspec.pipeline.fit`.
        FitInterrupted: a ``KeyboardInterrupt``; the finished tiles are saved.

    Example:
        >>> with connect(workers=2) as client:  # doctest: +SKIP
        ...     result = fit_on_cluster("painting", client, checkpoint="maps/.torchspec-fit")
        >>> write_fit("maps", result)  # doctest: +SKIP
    """
    started = time.perf_counter()
    refuse_unfinished(Path(checkpoint), resume)  # before any work
    begun = _distant(setup(capture, config, frames))
    config, picked, lights, view = begun.config, begun.picked, begun.lights, begun.view
    capture = replace(begun.capture, root=begun.capture.root.resolve())  # the workers' working folders differ
    k, c, h, w = len(picked), len(capture.channels), capture.height, capture.width
    pixels = h * w
    itemsize = torch.finfo(view.dtype).bits // 8
    config, tile = plan(config, k, c, h, w, itemsize, view.device)
    _warn_small_tiles(config, tile, k * c * pixels * itemsize)
    folder = Path(checkpoint).resolve()
    folder.mkdir(parents=True, exist_ok=True)
    _check_workers(client, capture, folder)  # before a job is recorded in the folder
    done = open_checkpoint(folder, job_record(capture, picked, config, tile, pixels), resume)
    _refuse_stale_tiles(folder, done)
    # Each task on the one thread its worker pins (workers, not threads, share the cores).
    one = replace(config, compute=replace(config.compute, threads=1))
    job = _Job(capture, picked, one, tile, lights, view, light_context(lights), folder)
    firsts = list(range(0, pixels, tile))
    todo = [first for first in firsts if first not in done]
    seconds: dict[str, float] = {}
    report = {"tasks": 0, "tiles_per_task": None, "bytes_read": 0, "tiles_found_written": 0, "read": 0.0, "masks": 0.0}
    parts = {first: done[first].to(view.device) for first in done}
    try:
        if todo:
            clock = time.perf_counter()
            job = _with_level(client, job, report, progress, retries)
            seconds["saturation_level"] = time.perf_counter() - clock
            report["tiles_per_task"] = tiles_per_task or _tiles_per_task(client, job, len(todo))
            resumed = pixels - sum(job.stop(first) - first for first in todo)
            with progress_bar(pixels, initial=resumed, unit="px", desc="fit", enabled=progress) as bar:
                for first, tile_out in _fit_on(client, job, todo, report, retries):
                    parts[first] = tile_out
                    bar.update(job.stop(first) - first)
    except KeyboardInterrupt as interrupt:
        raise FitInterrupted(len(parts), len(firsts), folder) from interrupt
    ordered = [parts[first] for first in firsts]
    stats = run_stats(
        capture=capture,
        picked=picked,
        config=config,
        device=view.device,
        pixels=pixels,
        tile=tile,
        resumed=len(done),
        seconds={**seconds, "read": report.pop("read"), "masks": report.pop("masks")},  # worker-seconds; total: wall
        masked=_masked(ordered, capture),
        lights=None,  # as written: lights to calibrate are refused above (_distant)
        cluster=_cluster_record(client, report),
    )
    return assemble(ordered, height=h, width=w, channels=capture.channels, stats=stats, started=started)


def _cluster_record(client, report: dict) -> dict:
    """``stats["distributed"]``: the scheduler, the workers and their threads, and ``report``."""
    threads = client.nthreads()
    return {"scheduler": client.scheduler.address, "workers": len(threads), "threads": sum(threads.values()), **report}


def _refuse_stale_tiles(folder: Path, done: dict) -> None:
    """A worker skips a tile that is already written: only the recorded job's tiles may be."""
    stale = sorted({int(p.stem.split("-")[1]) for p in folder.glob("tile-*.pt")} - set(done))
    if stale:
        raise TorchspecError(f"{folder} holds tiles of no recorded job (first pixels {stale[:3]}); remove {folder}.")


def _warn_small_tiles(config: FitConfig, tile: int, stack_bytes: int) -> None:
    """Warn when the frame stack leaves no room in ``memory_gib`` for the tiles it sizes."""
    if not config.compute.tile and stack_bytes + RUNTIME_BYTES > config.compute.memory_gib * 2**30:
        warnings.warn(
            f"the frame stack ({stack_bytes / 2**30:.1f} GiB) leaves no room in compute.memory_gib "
            f"({config.compute.memory_gib}), so tiles fall to {tile} pixels (the in-process fit's rule, kept so "
            "that both fit alike); set the config's compute.tile (e.g. 16384 pixels; docs/scale.md).",
            stacklevel=3,
        )


def _masked(parts: list[TileResult], capture: Capture) -> dict[str, int] | None:
    """The masked samples per kind over the tiles (``None`` when a tile lacks the count), with a
    warning for NaN or Inf samples (the workers do not warn per frame)."""
    if not all(part.masked is not None for part in parts):
        return None
    masked = {name: sum(part.masked[name] for part in parts) for name in MASK_KINDS}
    if masked["nonfinite"]:
        warnings.warn(
            f"{masked['nonfinite']} sample(s) with NaN or Inf were masked; `torchspec info {capture.root}` names "
            "their frames.",
            stacklevel=3,
        )
    return masked


def _fit_on(client, job: _Job, todo: list[int], report: dict, retries: int) -> Iterator[tuple[int, TileResult]]:
    """Fit tiles ``todo`` on the cluster, in runs of ``report["tiles_per_task"]`` per task;
    yields each tile's first pixel and output (loaded from the checkpoint, once) as its task
    completes, and adds the tasks' counts to ``report``."""
    size = report["tiles_per_task"]
    runs = [todo[i : i + size] for i in range(0, len(todo), size)]
    report["tasks"] += len(runs)
    for firsts, summary in _map(client, _fit_tiles, job, runs, retries, lambda run: f"tiles {_span(job, run)}"):
        for name in ("read", "masks"):
            report[name] += summary[name]
        report["bytes_read"] += summary["bytes"]
        report["tiles_found_written"] += len(summary["found"])
        for first in firsts:
            yield first, read_tile(job.folder / tile_name(first))[1].to(job.view.device)


def _span(job: _Job, firsts: list[int]) -> str:
    return f"{firsts[0] // job.tile}..{firsts[-1] // job.tile}"


def _check_workers(client, capture: Capture, folder: Path) -> None:
    """Every worker must see the capture and be able to write into the checkpoint folder."""
    answers = client.run(_sees, str(capture.manifest), str(folder))
    blind = {worker: problem for worker, problem in answers.items() if problem}
    if blind:
        worker, problem = next(iter(blind.items()))
        raise ClusterError(
            f"every worker must see the capture and the checkpoint at the same paths; {len(blind)} of "
            f"{len(answers)} cannot, e.g. {worker}: {problem}. Put both on a filesystem they share."
        )
    if not answers:
        raise ClusterError(f"the cluster of {client.scheduler.address} has no worker; start some (`dask worker`).")


def _sees(manifest: str, folder: str) -> str | None:
    if not os.path.isfile(manifest):
        return f"no file {manifest}"
    if not os.access(folder, os.W_OK):
        return f"cannot write into {folder}"
    return None


def _tiles_per_task(client, job: _Job, count: int) -> int:
    """Tiles of about :data:`TASK_ROWS` rows per task, but at least :data:`TASKS_PER_THREAD`
    tasks per worker thread."""
    threads = max(1, sum(client.nthreads().values()))
    block = -(-TASK_ROWS * job.capture.width // job.tile)
    return max(1, min(block, count // (TASKS_PER_THREAD * threads)))


def _map(client, task, job: _Job, items: list, retries: int, label) -> Iterator:
    """``task(job, item)`` for every item on the cluster, yielding the results as they complete;
    the outstanding tasks are cancelled if the caller stops or a task fails. ``label(item)`` names
    an item in the tasks' keys and errors."""
    from distributed import KilledWorker, as_completed

    tag = uuid.uuid4().hex[:8]
    # The job travels once (a task's result, recomputed if its worker is lost), not with every task.
    shared = client.submit(_identity, job, key=f"torchspec-job-{tag}", pure=False)
    futures = {}
    for item in items:
        key = f"torchspec-{label(item).replace(' ', '-')}-{tag}"
        futures[client.submit(task, shared, item, key=key, retries=retries, pure=False)] = item
    saved = f"The finished tiles are saved in {job.folder}: continue with --resume."
    try:
        for future in as_completed(futures, loop=client.loop):
            try:
                result = future.result()
            except KilledWorker as error:
                raise ClusterError(
                    f"the task of {label(futures[future])} killed every worker that ran it ({error}); give the workers "
                    f"more memory, or lower the config's tile. {saved}"
                ) from error
            except ClusterError as error:  # a tile's, named by the worker
                raise ClusterError(f"{error}. {saved}") from error
            except Exception as error:  # outside the task's own code
                raise ClusterError(
                    f"the task of {label(futures[future])} failed ({type(error).__name__}: {error}). {saved}"
                ) from error
            yield result
    finally:
        client.cancel([*futures, shared])


def _identity(job: _Job) -> _Job:
    return job


def _with_level(client, job: _Job, report: dict, progress: bool, retries: int) -> _Job:
    """``job`` with the clipping level its masks use and the rows read around a task's own."""
    config = job.config
    if config.masks.saturation is not None:
        level = float(config.masks.saturation)
    elif (job.folder / LEVEL).is_file():
        saved = read_json(job.folder / LEVEL, TorchspecError, f"Remove {job.folder} to start over.")["level"]
        level = math.inf if saved is None else float(saved)
    else:
        h, row = job.capture.height, len(job.picked) * len(job.capture.channels) * job.capture.width
        rows = BLOCK_ROWS * max(1, BAND_BYTES // (BLOCK_ROWS * row * job.view.element_size()))
        bands = [(r, min(r + rows, h)) for r in range(0, h, rows)]
        peaks = []
        with progress_bar(len(bands), unit="band", desc="saturation level", enabled=progress) as bar:
            for top, count, read in _map(client, _peak_of_rows, job, bands, retries, lambda rows: f"rows {rows[0]}"):
                # on the CPU: the workers' Python numbers, reduced to one Python float below
                peaks.append((torch.tensor(top, dtype=job.view.dtype), torch.tensor(count)))
                report["bytes_read"] += read
                bar.update()
        level = float(saturation_level(peaks))
        write_json(job.folder / LEVEL, {"level": level if math.isfinite(level) else None})
        report["tasks"] += len(bands)
    # Nothing clips (an infinite level): no saturated region to grow, no rows around a task's own.
    halo = config.masks.grow if config.masks.grow > 0 and math.isfinite(level) else 0
    return replace(job, level=level, halo=halo)


# What runs on the workers.


def _peak_of_rows(job: _Job, rows: tuple[int, int]) -> tuple[float, int, int]:
    """The largest value of ``rows`` of the picked frames, how many share it, and the bytes read."""
    before = _bytes_read()
    _pin()
    top, count = peak_of(job.read(rows))
    return float(top), int(count), _bytes_read() - before


def _fit_tiles(job: _Job, firsts: list[int]) -> tuple[list[int], dict]:
    """Fit and write tiles ``firsts`` (consecutive) that are not written yet, reading their rows
    once; returns ``firsts`` and what was read and found."""
    before = _bytes_read()
    _pin()
    todo = [first for first in firsts if not (job.folder / tile_name(first)).is_file()]
    summary = {"found": [f for f in firsts if f not in todo], "bytes": 0, "read": 0.0, "masks": 0.0}
    if not todo:
        return firsts, summary
    top, bottom = job.rows(todo)
    rows = (max(top - job.halo, 0), min(bottom + job.halo, job.capture.height))
    clock = time.perf_counter()
    try:
        band = job.read(rows)  # (K, C, rows, W)
    except Exception as error:
        raise ClusterError(
            f"{job.describe(todo[0])} to {job.describe(todo[-1])}: reading rows {rows[0]}..{rows[1] - 1} of "
            f"{job.capture.root} failed: {type(error).__name__}: {error}"
        ) from error
    summary["read"] = time.perf_counter() - clock
    clock = time.perf_counter()
    config = job.config
    masks = sample_masks(band, saturation=job.level, grow=config.masks.grow, shadow=config.masks.shadow)
    flat_masks = masks.flat()  # each (K, rows W)
    flat = band.flatten(2)  # (K, C, rows W)
    summary["masks"] = time.perf_counter() - clock
    offset = rows[0] * job.capture.width
    # gains None: the lights as written (_distant refuses lights to calibrate)
    shared = FitInputs(
        view=job.view, channels=job.capture.channels, config=config, folder=job.folder, domain=job.domain
    )
    for first in todo:
        at = slice(first - offset, job.stop(first) - offset)
        values, tile_masks = flat[:, :, at], flat_masks.of_pixels(at)
        inputs = TileInputs(first=first, values=values, masks=tile_masks, lights=job.lights, ctx=job.ctx)
        try:
            fit_tile(inputs, shared)
        except Exception as error:
            raise ClusterError(
                f"{job.describe(first)} of {job.capture.root} failed on worker {_worker()}: "
                f"{type(error).__name__}: {error}"
            ) from error
    summary["bytes"] = _bytes_read() - before
    return firsts, summary


_PINNED = []


def _pin() -> None:
    """One torch thread per task (a worker runs one task per thread), and glibc's adaptive malloc
    thresholds back in a worker started with ``MALLOC_TRIM_THRESHOLD_`` (Dask's default)."""
    torch.set_num_threads(1)
    if _PINNED:
        return
    _PINNED.append(True)
    if os.environ.get("MALLOC_TRIM_THRESHOLD_") is not None:
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL("libc.so.6")
            # M_MMAP_THRESHOLD (-3) and M_TRIM_THRESHOLD (-1) where glibc's dynamic rule lets them
            # grow: a 32 MiB mmap threshold, twice that for trimming.
            libc.mallopt(-3, 32 * 2**20)
            libc.mallopt(-1, 64 * 2**20)


def _bytes_read() -> int:
    """Bytes this thread has read through system calls (Linux; 0 elsewhere)."""
    try:
        with open("/proc/thread-self/io", encoding="ascii") as io:
            return next(int(line.split()[1]) for line in io if line.startswith("rchar"))
    except (OSError, StopIteration, ValueError):
        return 0


def _worker() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "?"
