"""Fits on a Dask cluster (a LocalCluster of 2 worker processes on the loopback interface): the
maps equal the in-process fit's bit for bit (both with one torch thread), also when a worker is
killed mid-fit, and either engine resumes the other's checkpoint."""

import importlib
import json
import os
import signal
import socket
import sys
import threading
import time

import numpy as np
import pytest
import torch

pytest.importorskip("distributed")

import cloudpickle  # noqa: E402 (installed with distributed)
from capture_cases import write_small_painting  # noqa: E402

from torchspec.cli import CHECKPOINT, main  # noqa: E402
from torchspec.io import read_capture, read_svbrdf  # noqa: E402
from torchspec.io.exr import ExrError, read_exr, write_exr  # noqa: E402
from torchspec.pipeline import (  # noqa: E402
    ClusterError,
    ComputeConfig,
    FitConfig,
    FitInterrupted,
    LadderConfig,
    MasksConfig,
    connect,
    fit,
    write_fit,
)
from torchspec.pipeline import fit_on_cluster as fit_on  # noqa: E402

TILE = importlib.import_module("torchspec.pipeline.tile")  # the per-tile engine
MAPS = ("normal", "diffuse", "specular", "roughness")
CONFIG = FitConfig(compute=ComputeConfig(tile=7))  # 21 tiles of a 12 x 12 image, most across two rows
cloudpickle.register_pickle_by_value(sys.modules[__name__])  # _fail_on_workers runs on the workers


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A 12 x 12 painting under 25 frames (as tests/test_resume.py's)."""
    return write_small_painting(tmp_path_factory.mktemp("distributed") / "capture")


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """The in-process fits with one torch thread, as each task runs: the solver's BLAS products round
    differently with more threads (a few pixels of an in-process fit differ from its own one-thread run)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def client():
    with connect(workers=2) as client:
        yield client


@pytest.fixture(scope="module")
def reference(capture):
    return fit(capture, config=CONFIG)


def _equal(a, b, name):
    """Bit for bit, NaN where the other is NaN (a parameter that a pixel's model lacks)."""
    assert a.dtype == b.dtype and a.shape == b.shape, name
    same = (a == b) | (a.isnan() & b.isnan()) if a.is_floating_point() else a == b
    assert bool(same.all()), f"{name}: {int((~same).sum())} of {same.numel()} values differ"


def _same(a, b):
    for name in MAPS:
        _equal(getattr(a.svbrdf, name), getattr(b.svbrdf, name), name)
    for name in ("residual", "quality", "status", "iterations", "lobe", "model", "criterion"):
        _equal(getattr(a, name), getattr(b, name), name)
    for name in a.std:
        _equal(a.std[name], b.std[name], f"std {name}")
    assert a.stats["sensor_noise"] == b.stats["sensor_noise"]
    assert a.stats["masked_samples"] == b.stats["masked_samples"]


def test_a_two_worker_fit_equals_the_in_process_fit(capture, client, reference, tmp_path):
    result = fit_on(capture, client, checkpoint=tmp_path / "tiles", config=CONFIG)
    _same(result, reference)
    info = result.stats["distributed"]
    assert (info["workers"], info["threads"]) == (2, 2)
    assert info["tasks"] == 1 + -(-21 // info["tiles_per_task"])  # the level pass, then the tiles
    assert info["bytes_read"] > 0


def test_clipped_samples_are_grown_across_task_boundaries(capture, client, tmp_path):
    # A clipping level that some samples reach: the masks of a task's rows need the rows around them.
    level = float(read_capture(capture).read_frames().quantile(0.995))
    config = FitConfig(compute=ComputeConfig(tile=7), masks=MasksConfig(saturation=level, grow=1))
    local = fit(capture, config=config)
    assert local.stats["masked_samples"]["saturated"] > 0
    _same(fit_on(capture, client, checkpoint=tmp_path / "tiles", config=config, tiles_per_task=2), local)


def test_a_worker_killed_mid_fit_loses_no_tile(capture, client, reference, tmp_path):
    folder = tmp_path / "tiles"
    victim = next(iter(client.run(os.getpid).values()))
    outcome = {}

    def run():
        try:
            outcome["fit"] = fit_on(capture, client, checkpoint=folder, config=CONFIG, tiles_per_task=1)
        except BaseException as error:  # reported by the assertion below
            outcome["error"] = error

    thread = threading.Thread(target=run)
    thread.start()
    deadline = time.monotonic() + 120
    while len(list(folder.glob("tile-*.pt"))) < 3:
        assert thread.is_alive(), f"the fit ended before a worker could be killed: {outcome}"
        assert time.monotonic() < deadline, "no 3 tiles within 2 minutes"
        time.sleep(0.02)
    os.kill(victim, signal.SIGKILL)
    thread.join(timeout=300)
    assert "fit" in outcome, outcome
    assert victim not in client.run(os.getpid).values()  # the nanny started another process
    assert len(list(folder.glob("tile-*.pt"))) == 21
    _same(outcome["fit"], reference)


def test_either_engine_resumes_the_other(capture, client, reference, tmp_path, monkeypatch):
    folder = tmp_path / "tiles"
    calls = []
    real = TILE.fit_pixels

    def interrupt_after_five(*args, **kwargs):
        if len(calls) == 5:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(TILE, "fit_pixels", interrupt_after_five)
    with pytest.raises(FitInterrupted):
        fit(capture, config=CONFIG, checkpoint=folder)
    monkeypatch.undo()
    with pytest.raises(ValueError, match="unfinished fit"):  # as in-process: never dropped silently
        fit_on(capture, client, checkpoint=folder, config=CONFIG)
    resumed = fit_on(capture, client, checkpoint=folder, config=CONFIG, resume=True)
    assert resumed.stats["resumed_tiles"] == 5
    _same(resumed, reference)
    # Its checkpoint (complete, and the clipping level found) resumed in-process: nothing left to fit.
    (folder / "tile-000000000014.pt").unlink()
    again = fit(capture, config=CONFIG, checkpoint=folder, resume=True)
    assert again.stats["resumed_tiles"] == 20
    _same(again, reference)


def _bytes_read() -> int:
    with open("/proc/thread-self/io") as io:
        return next(int(line.split()[1]) for line in io if line.startswith("rchar"))


@pytest.mark.skipif(not os.path.exists("/proc/thread-self/io"), reason="counts the bytes read on Linux")
def test_a_band_of_rows_reads_only_its_blocks(tmp_path):
    image = np.random.default_rng(0).random((512, 300, 3), dtype=np.float32)
    path = tmp_path / "frame.exr"
    write_exr(path, image, ["R", "G", "B"])
    before = _bytes_read()
    band = read_exr(path, ["B", "R"], rows=(200, 216))
    read = _bytes_read() - before
    assert np.array_equal(band, image[200:216][:, :, [2, 0]])
    assert read < 0.1 * path.stat().st_size, f"read {read} bytes of {path.stat().st_size} for 16 rows of 512"
    with pytest.raises(ExrError, match=r"frame\.exr.*0 <= start < stop <= 512.*got 500:513"):
        read_exr(path, ["R"], rows=(500, 513))


def _fail_on_workers(pixels: int) -> None:
    """Make the tiles of ``pixels`` pixels fail in this (worker) process."""
    module = importlib.import_module("torchspec.pipeline.tile")
    real = getattr(module, "_real_tile", module.fit_pixels)
    module._real_tile = real

    def tile(tile_pixels, *args, **kwargs):
        if tile_pixels.y.shape[0] == pixels:
            raise FloatingPointError("injected")
        return real(tile_pixels, *args, **kwargs)

    module.fit_pixels = tile


def _heal_workers() -> None:
    module = importlib.import_module("torchspec.pipeline.tile")
    module.fit_pixels = getattr(module, "_real_tile", module.fit_pixels)


def test_a_failing_tile_is_named(capture, client, tmp_path):
    client.run(_fail_on_workers, 4)  # in tiles of 20 pixels, the last has 4
    try:
        with pytest.raises(
            ClusterError, match=r"tile 7 \(pixels 140\.\.143, rows 11\.\.11\).*FloatingPointError.*--resume"
        ):
            config = FitConfig(compute=ComputeConfig(tile=20))
            fit_on(capture, client, checkpoint=tmp_path / "tiles", config=config, retries=0)
    finally:
        client.run(_heal_workers)
    assert not (tmp_path / "tiles" / "tile-000000000140.pt").exists()


def test_an_unreachable_scheduler_is_named():
    with socket.socket() as probe:  # a loopback port that nothing listens on
        probe.bind(("127.0.0.1", 0))
        address = f"tcp://127.0.0.1:{probe.getsockname()[1]}"
    with pytest.raises(ClusterError, match=f"scheduler at {address} must be reachable"):
        with connect(address, timeout=1):
            pass


def test_the_cli_fits_on_a_scheduler(capture, client, reference, tmp_path, capsys):
    config = tmp_path / "fit.yaml"
    config.write_text("compute: {tile: 7}\n")
    output = tmp_path / "maps"
    code = main(["fit", str(capture), "-o", str(output), "--config", str(config), "--quiet",
                 "--scheduler", client.scheduler.address])  # fmt: skip
    assert code == 0, capsys.readouterr().err
    assert not (output / CHECKPOINT).exists()
    write_fit(tmp_path / "in-process", reference)
    maps, expected = read_svbrdf(output), read_svbrdf(tmp_path / "in-process")
    for name in MAPS:
        _equal(getattr(maps.svbrdf, name), getattr(expected.svbrdf, name), name)
    # svbrdf.json as JSON text: the same, timings and the cluster's own record (distributed) left out
    assert _without_timings(output) == _without_timings(tmp_path / "in-process")


def _without_timings(folder) -> str:
    meta = json.loads((folder / "svbrdf.json").read_text())
    for key in ("seconds", "pixels_per_second", "distributed"):
        meta["fit"].pop(key, None)
    return json.dumps(meta, indent=1)


def test_a_smoothed_choice_spans_the_tasks(capture, client, tmp_path):
    """FitConfig.ladder.smooth decides over the whole image after the tiles: the same maps from two workers
    as in process, with tiles across the rows whose neighbours sit in other tiles and tasks. (This
    capture has almost no noise: its lobes lower the criterion by ~1e8, and so must the weight.)"""
    config = FitConfig(compute=ComputeConfig(tile=7), ladder=LadderConfig(smooth=1e8))
    ours = fit(capture, config=config)
    _same(fit_on(capture, client, checkpoint=tmp_path / "tiles", config=config), ours)
    assert ours.stats["smoothed"] > 0
