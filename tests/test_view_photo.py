"""A capture's photographs in the viewer (torchspec/view/tiles.py ``frame_pyramid``, site.py
``Site.photo``): a frame larger than ``keep_texels`` is read lazily, in bands of its EXR's rows, with
the same tiles, bit for bit, as the frame read whole; a level-0 tile reads only the rows under it;
NaN and Inf show as 0; the photograph is the frame over its exposure times irradiance."""

from __future__ import annotations

import importlib
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
import torch

from torchspec.errors import TorchspecError
from torchspec.io import Capture, Frame, LightSpec, read_capture, write_capture
from torchspec.io import capture as capture_io
from torchspec.io.exr import write_exr
from torchspec.model.residual_term import encode
from torchspec.view import open_site, site
from torchspec.view.check import model_maps
from torchspec.view.site import NotMade
from torchspec.view.tiles import Pyramid, frame_pyramid, photo_jpeg, photo_pyramid, photo_tile, read_photo_jpeg

HEIGHT, WIDTH, TILE = 600, 520, 64  # levels (600, 520) .. (38, 33): 5, odd sizes at the coarse ones
KEEP = 150 * 130  # levels 2 and coarser held (level 2 made by the pass); 0 and 1 read on demand
EXPOSURE = (2.0, 0.25)
IRRADIANCE = ((0.5, 0.8, 1.25), (3.0, 1.0, 0.125))  # per frame and channel


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """Two frames of random values over a few decades, with a NaN, Inf and -Inf in frame 1 (written
    after the capture, which refuses them) and a negative value."""
    folder = tmp_path_factory.mktemp("photo") / "c"
    g = torch.Generator().manual_seed(5)
    values = torch.exp(torch.randn(2, 3, HEIGHT, WIDTH, generator=g) * 2)
    values[0, 1, 7, 9] = -0.5
    directions = ((0.0, 0.0, 1.0), (0.6, 0.0, 0.8))
    frames = [Frame(f"f{k}.exr", directions[k], IRRADIANCE[k], EXPOSURE[k]) for k in range(2)]
    capture = Capture(folder, WIDTH, HEIGHT, ("R", "G", "B"), (0.0, 0.0, 1.0), LightSpec("point"), frames)
    write_capture(folder, capture, values)
    bad = values[1].permute(1, 2, 0).numpy().copy()
    bad[3, 4, 0], bad[300, 200, 1], bad[599, 519, 2], bad[130, 70] = np.nan, np.inf, -np.inf, np.nan
    write_exr(folder / "f1.exr", bad, ["R", "G", "B"])
    return read_capture(folder)


def _whole(capture, k):
    """Frame ``k``'s pyramid read whole, as the viewer made it before frames were read lazily."""
    frame = capture.read_frames([k], nonfinite="ignore")[0]
    frame = torch.nan_to_num(frame, nan=0.0, posinf=0.0, neginf=0.0)
    return photo_pyramid(frame, capture.exposure()[k] * capture.irradiance()[k], TILE)


def _every_tile(pyramid):
    return [
        (level, row, column)
        for level in range(len(pyramid.levels))
        for row in range(pyramid.grid(level)[0])
        for column in range(pyramid.grid(level)[1])
    ]


def _pixels(data: bytes) -> np.ndarray:
    return np.frombuffer(data, dtype="<f2").reshape(TILE, TILE, 4)


@pytest.fixture
def reads(monkeypatch):
    """The bands of rows read from the frames' EXRs: ``(thread name, rows)``."""
    log, real = [], capture_io._read_rows

    def read_rows(path, channels, rows):
        log.append((threading.current_thread().name, tuple(rows)))
        return real(path, channels, rows)

    monkeypatch.setattr(capture_io, "_read_rows", read_rows)
    return log


@pytest.mark.parametrize("k", [0, 1])
def test_a_lazily_read_frame_has_the_tiles_of_the_frame_read_whole(capture, reads, k):
    lazy = frame_pyramid(capture, k, tile=TILE, keep_texels=KEEP)
    assert lazy.kept == 2 and lazy.read is not None
    whole = _whole(capture, k)
    assert lazy.levels == whole.levels and len(lazy.levels) == 5
    # asked for before the pass has made the coarse levels (they wait for it), then the rest
    for level, row, column in _every_tile(whole)[::-1]:
        assert lazy.tile(level, row, column) == whole.tile(level, row, column), (level, row, column)
    lazy.worker.join(60)
    assert lazy.error is None and all(made.is_set() for made in lazy.made)
    assert all(stop - start <= TILE for _, (start, stop) in reads)  # bands, never the whole frame


def test_a_frame_within_keep_texels_is_read_whole(capture, reads):
    with pytest.warns(UserWarning, match="negative value"):  # as the viewer always read frames
        pyramid = frame_pyramid(capture, 0, tile=TILE, keep_texels=HEIGHT * WIDTH)
    assert pyramid.kept == 0 and reads == []  # read_exr of the whole file, not bands
    whole = _whole(capture, 0)
    assert all(pyramid.tile(*t) == whole.tile(*t) for t in _every_tile(whole))


def test_a_level_0_tile_reads_only_the_rows_under_it(capture, reads):
    pyramid = frame_pyramid(capture, 0, tile=TILE, keep_texels=KEEP)
    mine = threading.current_thread().name
    pyramid.tile(0, 4, 3)
    assert [rows for name, rows in reads if name == mine] == [(256, 320)]
    pyramid.tile(0, 4, 0)  # the same rows: the band read is kept
    pyramid.tile(0, 9, 8)  # the last row of tiles: 600 - 576 rows
    assert [rows for name, rows in reads if name == mine] == [(256, 320), (576, 600)]
    pyramid.tile(1, 2, 1)  # level 1: the 128 rows under it, in two bands, one of them kept
    assert [rows for name, rows in reads if name == mine] == [(256, 320), (576, 600), (320, 384)]
    pyramid.close()


def test_the_photograph_is_the_frame_over_exposure_times_irradiance_and_nonfinite_values_are_0(capture):
    for k in (0, 1):
        raw = capture.read_frames([k], nonfinite="ignore")[0].permute(1, 2, 0).numpy()
        scale = (EXPOSURE[k] * np.array(IRRADIANCE[k])).astype(np.float32)  # float64, then the frame's dtype
        expected = np.where(np.isfinite(raw), raw, 0) / scale
        pyramid = frame_pyramid(capture, k, tile=TILE, keep_texels=KEEP)
        for row, column in ((0, 0), (2, 1), (4, 3), (9, 8)):
            tile = _pixels(pyramid.tile(0, row, column))
            part = expected[row * TILE : (row + 1) * TILE, column * TILE : (column + 1) * TILE]
            h, w = part.shape[:2]
            assert np.array_equal(tile[:h, :w, :3], part.astype(np.float16))
            assert np.all(tile[:h, :w, 3] == 1) and not tile[h:].any() and not tile[:, w:].any()
        pyramid.close()
    negative = _pixels(frame_pyramid(capture, 0, tile=TILE, keep_texels=KEEP).tile(0, 0, 0))[7, 9, 1]
    assert negative == np.float16(np.float32(-0.5) / np.float32(2.0 * 0.8))  # kept, as the frame read whole


def test_non_finite_pixels_of_a_lazily_read_frame_are_0_in_every_level(capture):
    pyramid = frame_pyramid(capture, 1, tile=TILE, keep_texels=KEEP)
    pixels = {(y, x, c) for y, x, c in ((3, 4, 0), (300, 200, 1), (599, 519, 2))} | {(130, 70, c) for c in range(3)}
    for y, x, c in pixels:
        assert _pixels(pyramid.tile(0, y // TILE, x // TILE))[y % TILE, x % TILE, c] == 0
    pyramid.worker.join(60)
    # no NaN or Inf spreads to the coarse levels (their float32 planes: a tile's float16 overflows)
    assert all(torch.isfinite(pyramid.block(*t)).all() for t in _every_tile(pyramid))


def test_a_photographs_tile_is_a_jpeg_of_its_own_size_with_its_scale(capture):
    """Issue 37: float16 tiles padded to 256 x 256 made a web export's photographs 280 times their
    JPEGs. A tile is now a JPEG of the tile's own size: the sRGB codes of the value over the
    tile's largest, that scale in its comment."""
    pyramid = frame_pyramid(capture, 0, tile=TILE, keep_texels=KEEP)
    for level, row, column in ((0, 0, 0), (0, 9, 8), (4, 0, 0)):
        block = pyramid.block(level, row, column)  # (4, h, w)
        data = photo_tile(pyramid, level, row, column)
        assert data[:2] == b"\xff\xd8" and data == photo_jpeg(block)
        values, scale = read_photo_jpeg(data)
        assert values.shape == (*block.shape[1:], 3)  # (24, 8) at the corner tile, not (64, 64)
        assert scale == float(block[:3].max())  # exactly: the float's repr in the comment
    assert pyramid.block(0, 9, 8).shape[1:] == (24, 8)
    zero = photo_jpeg(torch.zeros(4, 3, 5))  # a black tile: scale 1
    assert read_photo_jpeg(zero)[1] == 1.0 and not read_photo_jpeg(zero)[0].any()
    with pytest.raises(TorchspecError, match="torchspec scale="):
        read_photo_jpeg(b"\xff\xd8\xff\xda")
    pyramid.close()


def test_a_photographs_jpeg_holds_its_srgb_codes_within_a_code():
    """A smooth photograph (a lit gradient with some texture): the JPEG's codes within a code of the
    exact 8-bit sRGB codes of value / scale on average, at most 6 off."""
    y, x = torch.meshgrid(torch.linspace(0, 1, 40), torch.linspace(0, 1, 56), indexing="ij")
    value = torch.stack([0.05 + 0.9 * x * y, 0.3 + 0.2 * torch.sin(9 * x), 0.4 * (1 - y) + 0.1 * torch.cos(7 * y)])
    value = value * 2.5  # a photograph over its exposure times irradiance: any scale
    values, scale = read_photo_jpeg(photo_jpeg(torch.cat([value, torch.ones(1, 40, 56)])))
    assert scale == pytest.approx(2.5 * 0.95)
    exact = np.round(encode((value / scale).clamp(0, 1)).permute(1, 2, 0).double().numpy() * 255)
    error = np.abs(encode(torch.from_numpy(values / scale)).numpy() * 255 - exact)
    print(f"smooth tile: codes off by {error.mean():.2f} on average, {error.max():.0f} at most")
    assert error.mean() < 1 and error.max() <= 6


@pytest.fixture
def gate(monkeypatch):
    """An event that the pyramids' background passes wait for before each band (not holding the
    lock of the pyramid's reads: a tile's rows are read meanwhile)."""
    opened, real = threading.Event(), Pyramid._pause

    def pause(self):
        assert opened.wait(60)
        real(self)

    monkeypatch.setattr(Pyramid, "_pause", pause)
    yield opened
    opened.set()


def test_the_site_serves_a_large_photograph_lazily_and_503_until_its_level_is_made(capture, gate, monkeypatch):
    monkeypatch.setattr(site, "WAIT", 0.01)
    view = open_site(model_maps("diffuse", HEIGHT, WIDTH), capture, tile=TILE)
    view.keep_texels = KEEP
    whole = _whole(capture, 1)
    assert view.file("/photo/1/0/4_3.jpg", wait=False) == photo_tile(whole, 0, 4, 3)  # read on demand
    assert view.file("/photo/1/1/2_1.jpg", wait=False) == photo_tile(whole, 1, 2, 1)
    with pytest.raises(NotMade):  # the pass waits at the gate
        view.file("/photo/1/4/0_0.jpg", wait=False)
    gate.set()
    view.photo(1).worker.join(60)
    assert all(view.file(f"/photo/1/{level}/{r}_{c}.jpg", wait=False) == photo_tile(whole, level, r, c)
               for level, r, c in _every_tile(whole))  # fmt: skip
    assert view.file("/photo/1/0/4_3.bin") is None  # a photograph's tile is a JPEG
    view.close()


def test_a_photograph_dropped_from_the_kept_ones_stops_its_pass_and_is_made_again(capture, gate, monkeypatch):
    monkeypatch.setattr(site, "PHOTO_CACHE", 1)
    view = open_site(model_maps("diffuse", HEIGHT, WIDTH), capture, tile=TILE)
    view.keep_texels = KEEP
    first, photo = view.photo(0), view.photo
    answer, given, asked = {}, [], threading.Event()

    def photo_of(k):  # the pyramids the request is given
        given.append(photo(k))
        asked.set()
        return given[-1]

    view.photo = photo_of
    waiting = threading.Thread(target=lambda: answer.update(tile=view.file("/photo/0/4/0_0.jpg")))
    waiting.start()  # waits for the coarsest level of frame 0, whose pass waits at the gate
    assert asked.wait(60) and given == [first]
    photo(1)  # frame 0 dropped: its pass is asked to stop
    assert first.closing.is_set()
    gate.set()
    waiting.join(60)
    first.worker.join(60)
    assert not first.worker.is_alive() and isinstance(first.error, site.Stopped)
    assert answer["tile"] == photo_tile(_whole(capture, 0), 4, 0, 0)  # from frame 0's pyramid made again
    assert len(given) == 2 and given[1] is not first
    view.close()


@pytest.mark.slow
def test_the_large_photograph_experiment_runs(tmp_path):
    """experiments/view_photo_large.py on a small frame: both modes serve the same tiles."""
    sys.path.insert(0, str(Path(__file__).parents[1] / "experiments"))
    try:
        experiment = importlib.import_module("view_photo_large")
    finally:
        sys.path.pop(0)
    config = tmp_path / "tiny.yaml"
    config.write_text(
        f"size: [{HEIGHT}, {WIDTH}]\nband_rows: 64\nfolder: {tmp_path / 'c'}\nviewport: [300, 200]\n"
        f"place: [0.7, 0.3]\nkeep_texels: {KEEP}\n"
    )
    result = experiment.main(["--config", str(config), "--output", str(tmp_path)])
    assert result["same_tiles"] and set(result["sessions"]) == {"lazy", "whole"}
    # the view: x 364 +- 150, y 180 +- 100: rows 0-1, columns 0-2 of the viewer's 256-texel tiles
    assert all(s["view_tiles"] == 2 * 3 and s["overview_tile_s"] > 0 for s in result["sessions"].values())
