"""Atomic writes: the final name appears whole or not at all, with a new file's usual mode."""

import os
import stat

import pytest

from torchspec.atomic import atomic_path, write_json


def test_written_files_get_the_mode_of_a_new_file(tmp_path):
    mask = os.umask(0o022)
    try:
        write_json(tmp_path / "a.json", {"x": 1})
        (tmp_path / "plain").write_text("x")
    finally:
        os.umask(mask)
    mode = stat.S_IMODE((tmp_path / "a.json").stat().st_mode)
    assert mode == stat.S_IMODE((tmp_path / "plain").stat().st_mode) == 0o644


def test_an_interrupted_write_leaves_neither_the_file_nor_a_temporary(tmp_path):
    (tmp_path / "kept.txt").write_text("old")
    with pytest.raises(KeyboardInterrupt), atomic_path(tmp_path / "kept.txt") as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert (tmp_path / "kept.txt").read_text() == "old"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["kept.txt"]
