"""The cache of a map folder's coarse levels (torchspec/view/cache.py): a second view reads them
instead of the maps, with the same tiles; a changed map, a damaged cache file, a read-only folder
and a folder that is not torchspec's are handled."""

from __future__ import annotations

import os
import threading

import numpy as np
import OpenEXR
import pytest

from torchspec import cli
from torchspec.io import read_svbrdf, write_svbrdf
from torchspec.io import svbrdf as svbrdf_io
from torchspec.view import Pyramid, cache, open_site
from torchspec.view.check import model_maps, with_term

OPTIONS = {"tile": 64, "keep_texels": 5000}  # levels (200, 300) .. (25, 38); 2 and 3 held: cached


@pytest.fixture(autouse=True)
def user_cache(tmp_path, monkeypatch):
    """The user's cache folder, in the test's folder."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    return tmp_path / "xdg"


@pytest.fixture
def maps(tmp_path):
    folder = tmp_path / "maps"
    write_svbrdf(folder, with_term(model_maps("ward-dual", 200, 300, seed=21), 2, seed=3))
    return folder


@pytest.fixture
def pass_reads(monkeypatch):
    """The row bands the pyramids' background passes read from the EXR files (not the sample of
    rows at start, nor the tiles read on demand)."""
    reads, real = [], svbrdf_io._read_band

    def band(path, channels, rows):
        if threading.current_thread().name == "torchspec-view-pyramid":
            reads.append((path.name, rows))
        return real(path, channels, rows)

    monkeypatch.setattr(svbrdf_io, "_read_band", band)
    return reads


def _view(folder, use_cache=True):
    """A lazily read pyramid of ``folder``, once its background work (the pass, the cache) is done."""
    pyramid = open_site(folder, cache=use_cache, **OPTIONS).pyramid
    pyramid.worker.join(120)
    assert not pyramid.worker.is_alive() and pyramid.error is None
    return pyramid


def _tiles(pyramid, levels=None) -> dict:
    out = {}
    for level in range(len(pyramid.levels)) if levels is None else levels:
        rows, columns = pyramid.grid(level)
        out.update({(level, r, c): pyramid.tile(level, r, c) for r in range(rows) for c in range(columns)})
    return out


def test_a_second_view_reads_the_cached_levels_not_the_maps(maps, pass_reads):
    first = _view(maps)
    assert first.kept == 2 and pass_reads  # the pass read the rows
    written = sorted(path.name for path in (maps / cache.FOLDER).iterdir())
    assert written == ["CACHEDIR.TAG", "level_2.bin", "level_3.bin", "levels.json"]
    pass_reads.clear()
    second = _view(maps)
    assert pass_reads == [] and second.store.found[0] == maps / cache.FOLDER
    assert _tiles(second) == _tiles(first)
    # and the tiles are those of the maps read whole, bit for bit
    assert _tiles(second, [2, 3]) == _tiles(Pyramid.of_maps(read_svbrdf(maps), tile=64), [2, 3])


def test_a_changed_map_file_is_never_shown_from_the_cache(maps, pass_reads):
    old = _tiles(_view(maps), [2, 3])
    stat = (maps / "roughness.exr").stat()
    os.utime(maps / "roughness.exr", ns=(stat.st_atime_ns, stat.st_mtime_ns + 1))  # touched
    pass_reads.clear()
    _view(maps)
    assert pass_reads  # made again
    new = with_term(model_maps("ward-dual", 200, 300, seed=22), 2, seed=4)
    write_svbrdf(maps, new, overwrite=True)
    pass_reads.clear()
    changed = _view(maps)
    whole = _tiles(Pyramid.of_maps(read_svbrdf(maps), tile=64), [2, 3])  # the new maps' tiles
    assert pass_reads and _tiles(changed, [2, 3]) == whole and whole != old
    pass_reads.clear()
    assert _tiles(_view(maps), [2, 3]) == _tiles(changed, [2, 3]) and pass_reads == []  # cached again


def _quality(path, value: np.ndarray) -> None:
    """``quality.exr`` uncompressed: its size depends on its shape only."""
    header = {"compression": OpenEXR.NO_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Y": OpenEXR.Channel(np.ascontiguousarray(value, dtype=np.float32))}).write(str(path))


def test_a_map_rewritten_with_its_size_and_time_kept_is_never_shown_from_the_cache(maps, pass_reads):
    path = maps / "quality.exr"
    _quality(path, np.full((200, 300), 0.25))
    first = _tiles(_view(maps), [2, 3])
    stat = path.stat()
    _quality(path, np.full((200, 300), 0.75))  # in place: same name, same size
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # and the same modification time
    assert (path.stat().st_size, path.stat().st_mtime_ns) == (stat.st_size, stat.st_mtime_ns)
    pass_reads.clear()
    again = _view(maps)
    whole = _tiles(Pyramid.of_maps(read_svbrdf(maps), tile=64), [2, 3])
    assert pass_reads and _tiles(again, [2, 3]) == whole and whole != first


@pytest.mark.parametrize("damage", ["truncated", "flipped", "index"])
def test_a_damaged_cache_is_made_again(maps, pass_reads, damage, capfd):
    first = _tiles(_view(maps))
    folder = maps / cache.FOLDER
    level = folder / "level_2.bin"
    data = level.read_bytes()
    if damage == "truncated":
        level.write_bytes(data[: len(data) // 2])
    elif damage == "flipped":  # same size, other bytes: found by the CRC
        level.write_bytes(data[:1000] + bytes(b ^ 0xFF for b in data[1000:1016]) + data[1016:])
    else:
        (folder / "levels.json").write_text('{"format": "torchspec.view.lev')
    capfd.readouterr()
    pass_reads.clear()
    again = _view(maps)
    assert pass_reads and _tiles(again) == first
    assert ("cannot be used" in capfd.readouterr().err) == (damage != "index")
    assert level.read_bytes() == data  # written again
    pass_reads.clear()
    assert _tiles(_view(maps)) == first and pass_reads == []


def test_a_read_only_maps_folder_caches_in_the_users_folder(maps, pass_reads, monkeypatch, user_cache):
    claim = cache._claim

    def read_only(folder):  # as the folder's mode says (a test run as root would write anyway)
        if folder.parent == maps:
            raise PermissionError(13, "Permission denied", str(folder))
        return claim(folder)

    monkeypatch.setattr(cache, "_claim", read_only)
    os.chmod(maps, 0o555)
    try:
        first = _tiles(_view(maps))
        pass_reads.clear()
        second = _view(maps)
    finally:
        os.chmod(maps, 0o755)
    assert not (maps / cache.FOLDER).exists()
    folder = cache.user_folder(maps)
    assert folder.parent == user_cache / "torchspec" / "view" and (folder / "levels.json").is_file()
    assert second.store.found[0] == folder and pass_reads == [] and _tiles(second) == first


def test_without_a_writable_cache_folder_the_view_works_and_says_so_once(maps, pass_reads, monkeypatch, capfd):
    def refused(folder):
        raise PermissionError(13, "Permission denied", str(folder))

    monkeypatch.setattr(cache, "_claim", refused)
    capfd.readouterr()
    first = _tiles(_view(maps))
    lines = capfd.readouterr().err.splitlines()
    assert len(lines) == 1 and "are not cached" in lines[0] and "Permission denied" in lines[0]
    pass_reads.clear()
    assert _tiles(_view(maps)) == first and pass_reads  # the pass, as without a cache


def test_no_cache_reads_and_writes_nothing(maps, pass_reads, user_cache, monkeypatch):
    _view(maps, use_cache=False)
    assert not (maps / cache.FOLDER).exists() and not user_cache.exists()
    _view(maps)  # a cache written ...
    pass_reads.clear()
    _view(maps, use_cache=False)
    assert pass_reads  # ... is not read
    # torchspec view --no-cache asks for none; without it, for the cache
    asked = []

    class Server:
        server_address = ("127.0.0.1", 0)

        def serve_forever(self):
            raise KeyboardInterrupt

        def server_close(self):
            pass

    monkeypatch.setattr("torchspec.view.serve", lambda site, port: Server())
    monkeypatch.setattr("torchspec.view.open_site", lambda *args, **options: asked.append(options["cache"]) or Site())
    assert cli.main(["view", str(maps), "--no-cache"]) == 0 and cli.main(["view", str(maps)]) == 0
    assert asked == [False, True]


class Site:
    def close(self):
        pass


def test_a_foreign_file_in_the_cache_folder_is_not_replaced(maps, pass_reads):
    foreign = maps / cache.FOLDER / "levels.json"
    foreign.parent.mkdir()
    foreign.write_text("someone else's")
    first = _tiles(_view(maps))
    assert foreign.read_text() == "someone else's" and sorted(foreign.parent.iterdir()) == [foreign]
    pass_reads.clear()
    second = _view(maps)  # from the user's cache folder
    assert second.store.found[0] == cache.user_folder(maps) and pass_reads == [] and _tiles(second) == first


def test_maps_held_whole_cache_their_coarser_levels_only(maps, pass_reads, tmp_path):
    first = open_site(maps, tile=64, cache=True).pyramid  # level 0 held: made by the pass
    first.worker.join(120)
    assert first.kept == 0 and sorted(first.store.shapes) == [1, 2, 3]
    pass_reads.clear()
    second = open_site(maps, tile=64, cache=True).pyramid
    second.worker.join(120)
    assert pass_reads == [] and not second.made[0].is_set()  # level 0's tiles: read on demand
    assert _tiles(second) == _tiles(first)
    write_svbrdf(tmp_path / "small", model_maps("ward-iso", 40, 60, seed=23))  # one level: nothing to cache
    _view(tmp_path / "small")
    assert not (tmp_path / "small" / cache.FOLDER).exists()


def test_closing_stops_the_pass_and_leaves_no_temporary_file(maps):
    site = open_site(maps, cache=True, **OPTIONS)
    site.close()
    assert not site.pyramid.worker.is_alive()
    folder = maps / cache.FOLDER
    assert not folder.exists() or not [path for path in folder.iterdir() if ".part" in path.name]
