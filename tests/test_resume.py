"""Interrupted fits: finished tiles are saved, and a resumed fit gives the maps of an
uninterrupted one, bit for bit (in process, and through the CLI killed by SIGKILL or stopped by
Ctrl-C)."""

import importlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from capture_cases import write_small_painting

from torchspec.cli import CHECKPOINT, main
from torchspec.io import read_svbrdf
from torchspec.pipeline import ComputeConfig, FitConfig, FitInterrupted, StartConfig, fit

TILE = importlib.import_module("torchspec.pipeline.tile")  # the per-tile engine
MAPS = ("normal", "diffuse", "specular", "roughness")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A 12 x 12 painting under 25 frames: 144 pixels, tiles of 36 (4 tiles)."""
    return write_small_painting(tmp_path_factory.mktemp("resume") / "capture")


CONFIG = FitConfig(compute=ComputeConfig(tile=36))


@pytest.fixture(scope="module")
def uninterrupted(capture):
    return fit(capture, config=CONFIG)


def _same(a, b):
    for name in MAPS:
        assert torch.equal(getattr(a.svbrdf, name), getattr(b.svbrdf, name)), name
    for name in ("residual", "quality", "status", "iterations", "lobe"):
        assert torch.equal(getattr(a, name), getattr(b, name)), name


def _interrupt_after(monkeypatch, tiles: int):
    calls = []
    real = TILE.fit_pixels

    def tile(*args, **kwargs):
        if len(calls) == tiles:
            raise KeyboardInterrupt
        calls.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(TILE, "fit_pixels", tile)


def _interrupted(capture, folder, monkeypatch, tiles: int = 1) -> None:
    """Leave in ``folder`` the checkpoint of a fit interrupted after ``tiles`` tiles."""
    _interrupt_after(monkeypatch, tiles)
    with pytest.raises(FitInterrupted):
        fit(capture, config=CONFIG, checkpoint=folder)
    monkeypatch.undo()


def test_a_resumed_fit_equals_an_uninterrupted_one(capture, uninterrupted, tmp_path, monkeypatch):
    folder = tmp_path / "tiles"
    _interrupt_after(monkeypatch, 2)
    with pytest.raises(FitInterrupted) as stop:
        fit(capture, config=CONFIG, checkpoint=folder)
    assert (stop.value.done, stop.value.total, stop.value.checkpoint) == (2, 4, folder)
    assert len(list(folder.glob("tile-*.pt"))) == 2
    monkeypatch.undo()
    resumed = fit(capture, config=CONFIG, checkpoint=folder, resume=True)
    assert resumed.stats["resumed_tiles"] == 2
    _same(resumed, uninterrupted)


def test_without_a_checkpoint_an_interrupt_stays_a_keyboard_interrupt(capture, monkeypatch):
    _interrupt_after(monkeypatch, 1)
    with pytest.raises(KeyboardInterrupt) as stop:
        fit(capture, config=CONFIG)
    assert not isinstance(stop.value, FitInterrupted)


def test_unfinished_tiles_are_never_dropped_silently(capture, tmp_path, monkeypatch):
    folder = tmp_path / "tiles"
    _interrupted(capture, folder, monkeypatch)
    with pytest.raises(ValueError, match=r"unfinished fit \(1 tile\(s\) done\).*--resume"):
        fit(capture, config=CONFIG, checkpoint=folder)


def _no_work(monkeypatch):
    """Make the start of a fit's work (its setup: the manifest, then reading, calibrating) or a
    cluster's start fail the test."""

    def no_work(*args, **kwargs):
        raise AssertionError("work began before the refusal")

    for where in ("in_process.setup", "cluster.setup", "connect"):
        monkeypatch.setattr(f"torchspec.pipeline.{where}", no_work)


def test_an_unfinished_fit_is_refused_before_any_work(capture, tmp_path, monkeypatch, capsys):
    """Without --resume (or --overwrite), an output holding an unfinished fit is refused before the
    frames are read or the lights calibrated (or a cluster started), by the API and the CLI."""
    from torchspec.pipeline import fit_on_cluster

    output = tmp_path / "maps"
    _interrupted(capture, output / CHECKPOINT, monkeypatch)
    _no_work(monkeypatch)
    with pytest.raises(ValueError, match=r"unfinished fit \(1 tile\(s\) done\).*--resume"):
        fit(capture, config=CONFIG, checkpoint=output / CHECKPOINT)
    with pytest.raises(ValueError, match=r"unfinished fit \(1 tile\(s\) done\).*--resume"):
        fit_on_cluster(capture, None, config=CONFIG, checkpoint=output / CHECKPOINT)
    for extra in ([], ["--workers", "1"]):
        assert main(["fit", str(capture), "-o", str(output), "--quiet", *extra]) == 2
        err = capsys.readouterr().err
        assert err.startswith("torchspec fit: error: ") and "unfinished fit (1 tile(s) done)" in err, err
    assert len(list((output / CHECKPOINT).glob("tile-*.pt"))) == 1


def test_ctrl_c_before_any_tile_says_so_in_one_line(capture, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the frames are read or the lights calibrated (before any tile), or in the first
    tile: one line saying nothing is written and the command to run again, exit 130, and no
    checkpoint left that would refuse that command."""
    import torchspec.pipeline.in_process as in_process

    output = tmp_path / "maps"

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(in_process, "calibrated", stopped)
    assert main(["fit", str(capture), "-o", str(output), "--quiet"]) == 130
    err = capsys.readouterr().err
    assert err.startswith("torchspec fit: interrupted before any tile was saved: nothing is written. Run it again "
                          "with: torchspec "), err
    assert err.count("\n") == 1 and "Traceback" not in err and not (output / CHECKPOINT).exists()
    monkeypatch.undo()
    _interrupt_after(monkeypatch, 0)  # in the first tile: the checkpoint holds its job, no tile
    assert main(["fit", str(capture), "-o", str(output), "--quiet", "--config", str(_config(tmp_path))]) == 130
    err = capsys.readouterr().err
    assert "interrupted before any tile was saved" in err and err.count("\n") == 1
    assert not (output / CHECKPOINT).exists()


def _config(tmp_path: Path) -> Path:
    path = tmp_path / "fit.yaml"
    path.write_text("compute: {tile: 36}\n")
    return path


def test_ctrl_c_after_the_tiles_says_what_is_saved(capture, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the maps are written: the tiles are saved, and the line says how to continue."""
    output = tmp_path / "maps"

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr("torchspec.pipeline.write_fit", stopped)
    assert main(["fit", str(capture), "-o", str(output), "--quiet", "--config", str(_config(tmp_path))]) == 130
    err = capsys.readouterr().err
    assert err.startswith(f"torchspec fit: interrupted: 4 tiles are saved in {output / CHECKPOINT}; continue with: ")
    assert err.rstrip().endswith("--resume") and err.count("\n") == 1


@pytest.mark.parametrize(
    "change, differs",
    [
        ({"frames": "::2"}, "frames"),
        ({"config": FitConfig(compute=ComputeConfig(tile=36), start=StartConfig(detect=4.0))}, "settings"),
    ],
)
def test_resuming_another_job_is_refused(capture, tmp_path, monkeypatch, change, differs):
    folder = tmp_path / "tiles"
    _interrupted(capture, folder, monkeypatch)
    kwargs = {"config": CONFIG, **change}
    with pytest.raises(ValueError, match=f"another job.*{differs}"):
        fit(capture, checkpoint=folder, resume=True, **kwargs)


def test_a_damaged_tile_is_named(capture, tmp_path, monkeypatch):
    folder = tmp_path / "tiles"
    _interrupted(capture, folder, monkeypatch)
    (tile,) = folder.glob("tile-*.pt")
    tile.write_bytes(b"not a tile")
    with pytest.raises(ValueError, match=tile.name):
        fit(capture, config=CONFIG, checkpoint=folder, resume=True)


# Through the command line, in a child process: killed outright (SIGKILL: nothing runs after
# it), or stopped by Ctrl-C (SIGINT), then resumed.


def _cli(capture: Path, output: Path, config: Path, *extra: str) -> subprocess.Popen:
    command = [sys.executable, "-m", "torchspec", "fit", str(capture), "-o", str(output), "--quiet"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    return subprocess.Popen(
        [*command, "--config", str(config), *extra],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # A shell starts background jobs with SIGINT ignored, and Python then keeps ignoring it:
        # give the child the default disposition, as a terminal's Ctrl-C finds it.
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def _wait_for_tiles(process: subprocess.Popen, folder: Path, count: int) -> None:
    deadline = time.monotonic() + 120
    while len(list(folder.glob("tile-*.pt"))) < count:
        assert process.poll() is None, f"the fit ended before it could be stopped: {process.communicate()}"
        assert time.monotonic() < deadline, "no tile was saved within 2 minutes"
        time.sleep(0.02)


@pytest.fixture(scope="module")
def tiny_tiles(tmp_path_factory):
    """Tiles of 4 pixels: 36 of them, so that the child is caught mid-fit."""
    path = tmp_path_factory.mktemp("config") / "fit.yaml"
    path.write_text("compute: {tile: 4}\n")
    return path


@pytest.fixture(scope="module")
def reference_maps(capture, tiny_tiles, tmp_path_factory):
    output = tmp_path_factory.mktemp("reference") / "maps"
    process = _cli(capture, output, tiny_tiles)
    out, err = process.communicate(timeout=300)
    assert process.returncode == 0, err
    assert not (output / CHECKPOINT).exists()  # removed once the maps are written
    return read_svbrdf(output)


@pytest.mark.parametrize("how", [signal.SIGKILL, signal.SIGINT])
def test_the_cli_resumes_a_stopped_fit_to_the_same_maps(capture, tiny_tiles, reference_maps, tmp_path, how):
    output = tmp_path / "maps"
    process = _cli(capture, output, tiny_tiles)
    _wait_for_tiles(process, output / CHECKPOINT, 3)
    process.send_signal(how)
    out, err = process.communicate(timeout=120)
    if how == signal.SIGINT:
        assert process.returncode == 130, err
        assert "interrupted" in err and "--resume" in err, err
    else:
        assert process.returncode == -signal.SIGKILL
    assert not (output / "svbrdf.json").exists()  # no maps that look complete
    assert len(list((output / CHECKPOINT).glob("tile-*.pt"))) >= 3

    again = _cli(capture, output, tiny_tiles)  # without --resume: refused, the tiles kept
    _, err = again.communicate(timeout=300)
    assert again.returncode == 2 and "--resume" in err, err

    resumed = _cli(capture, output, tiny_tiles, "--resume")
    _, err = resumed.communicate(timeout=300)
    assert resumed.returncode == 0, err
    maps = read_svbrdf(output)
    for name in MAPS:
        assert torch.equal(getattr(maps.svbrdf, name), getattr(reference_maps.svbrdf, name)), name
    assert not (output / CHECKPOINT).exists()
