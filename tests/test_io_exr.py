from __future__ import annotations

import os
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import OpenEXR
import pytest
import torch

from torchspec.io import ExrError, read_exr, write_exr


def _image(height=5, width=7, count=3, seed=0):
    return np.random.default_rng(seed).normal(size=(height, width, count)).astype(np.float32)


def _leftovers(folder):
    return [p.name for p in folder.iterdir() if ".part" in p.name]


def test_round_trip_is_exact_float32_contiguous(tmp_path):
    image = _image()
    write_exr(tmp_path / "a.exr", image, ["R", "G", "B"])
    back = read_exr(tmp_path / "a.exr")
    assert back.dtype == np.float32 and back.flags["C_CONTIGUOUS"] and back.shape == (5, 7, 3)
    np.testing.assert_array_equal(back, image)
    header = OpenEXR.File(str(tmp_path / "a.exr"), header_only=True).header()
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION
    assert not _leftovers(tmp_path)


@pytest.mark.parametrize(
    "view",
    [
        lambda a: a.transpose(1, 0, 2),  # strides swapped
        lambda a: a[:, ::2],  # every other column
        lambda a: a[::-1],  # negative stride
        lambda a: np.asfortranarray(a),
    ],
    ids=["transposed", "strided", "flipped", "fortran"],
)
def test_non_contiguous_input_is_written_as_seen(tmp_path, view):
    image = view(_image(6, 8))
    assert not image.flags["C_CONTIGUOUS"]
    write_exr(tmp_path / "a.exr", image, ["R", "G", "B"])
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), image)


def test_torch_input_any_dtype_and_grad(tmp_path):
    image = torch.rand(4, 3, 2, dtype=torch.float64, requires_grad=True)
    write_exr(tmp_path / "a.exr", image.permute(1, 0, 2), ["X", "Y"])
    back = read_exr(tmp_path / "a.exr", ["X", "Y"])
    expected = image.detach().permute(1, 0, 2).float().numpy()
    np.testing.assert_array_equal(back, expected)


def test_one_channel_from_2d(tmp_path):
    image = _image(4, 5, 1)[:, :, 0]
    write_exr(tmp_path / "y.exr", image, "Y")
    back = read_exr(tmp_path / "y.exr")
    assert back.shape == (4, 5, 1)
    np.testing.assert_array_equal(back[:, :, 0], image)


@pytest.mark.parametrize(
    "written, expected",
    [
        (["B", "A", "G", "R"], ["R", "G", "B", "A"]),
        (["Z", "Y", "X"], ["X", "Y", "Z"]),
        (["A", "Y", "X"], ["X", "Y", "A"]),
        (["beta", "alpha"], ["alpha", "beta"]),
    ],
)
def test_default_channel_order(tmp_path, written, expected):
    image = np.stack([np.full((2, 3), i, np.float32) for i in range(len(written))], axis=-1)
    write_exr(tmp_path / "a.exr", image, written)
    back = read_exr(tmp_path / "a.exr")
    assert [written[int(v)] for v in back[0, 0]] == expected


def test_read_subset_in_given_order(tmp_path):
    image = _image()
    write_exr(tmp_path / "a.exr", image, ["R", "G", "B"])
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr", ["B", "R"]), image[:, :, [2, 0]])


def test_half_and_uint_channels_come_back_float32(tmp_path):
    half = np.linspace(0, 1, 12, dtype=np.float16).reshape(3, 4)
    uint = np.arange(12, dtype=np.uint32).reshape(3, 4)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"H": OpenEXR.Channel(half), "U": OpenEXR.Channel(uint)}).write(str(tmp_path / "a.exr"))
    back = read_exr(tmp_path / "a.exr", ["H", "U"])
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, np.stack([half.astype(np.float32), uint.astype(np.float32)], axis=-1))


def test_missing_file_is_named(tmp_path):
    with pytest.raises(ExrError, match=r"nothere\.exr must exist"):
        read_exr(tmp_path / "nothere.exr")


def test_not_an_exr_is_named(tmp_path):
    (tmp_path / "junk.exr").write_bytes(b"not an image" * 20)
    with pytest.raises(ExrError, match=r"junk\.exr is a text file, not an EXR"):
        read_exr(tmp_path / "junk.exr")
    (tmp_path / "bytes.exr").write_bytes(bytes(range(200, 256)) * 4)  # neither text nor a known format
    with pytest.raises(ExrError, match=r"bytes\.exr cannot be read as an OpenEXR image: it is truncated, damaged"):
        read_exr(tmp_path / "bytes.exr")


def test_a_jpeg_is_named_and_import_suggested(tmp_path):
    from PIL import Image

    Image.new("RGB", (8, 8)).save(tmp_path / "photo.exr", format="JPEG")
    with pytest.raises(ExrError, match=r"photo\.exr is a JPEG, not an EXR.*torchspec import SOURCE -o CAPTURE"):
        read_exr(tmp_path / "photo.exr")


def test_library_lines_become_a_sentence_naming_the_file(tmp_path, capfd):
    """A damaged chunk makes the OpenEXR library print EXR_ERR_... lines on file descriptor 2;
    they are kept off the terminal and summarised in the error, which names the file."""
    write_exr(tmp_path / "a.exr", _image(8, 8), ["R", "G", "B"])
    data = bytearray((tmp_path / "a.exr").read_bytes())
    # An 8-row image is one chunk: the offset table is one uint64 pointing just past itself, and
    # the chunk starts with its first scanline's y (int32, 0 here): corrupt that leader.
    table = next(p for p in range(len(data) - 8) if int.from_bytes(data[p : p + 8], "little") == p + 8)
    data[table + 8 : table + 12] = b"\x5a\x5a\x5a\x5a"
    (tmp_path / "bad.exr").write_bytes(bytes(data))
    capfd.readouterr()
    with pytest.raises(ExrError, match=r"bad\.exr is truncated or corrupt: the OpenEXR library could not") as error:
        read_exr(tmp_path / "bad.exr")
    assert "EXR_ERR" not in str(error.value) and "OpenEXR says: " in str(error.value), str(error.value)
    printed = capfd.readouterr()
    assert "EXR_ERR" not in printed.err and printed.out == "", printed


@pytest.mark.parametrize("keep", [0.5, 0.9, 0.999])
def test_truncated_file_raises_and_keeps_stdout_clean(tmp_path, capsys, keep):
    write_exr(tmp_path / "a.exr", _image(64, 64), ["R", "G", "B"])
    data = (tmp_path / "a.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: int(len(data) * keep)])
    # OpenEXR itself does not raise here: it returns a file with zero parts.
    with pytest.raises(ExrError, match=r"cut\.exr is truncated or corrupt"):
        read_exr(tmp_path / "cut.exr")
    assert capsys.readouterr().out == ""


def test_reads_from_many_threads_at_once_are_right_and_restore_the_outputs(tmp_path):
    """Descriptor 2 and ``sys.stdout`` are redirected around OpenEXR's calls: threads reading at
    once (good files, and truncated ones whose library lines the error keeps) each get their own
    answer, and both are what they were afterwards."""
    images = [_image(16, 12, seed=seed) for seed in range(4)]
    for i, image in enumerate(images):
        write_exr(tmp_path / f"{i}.exr", image, ["R", "G", "B"])
    data = (tmp_path / "0.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(data[: len(data) * 3 // 4])
    before, stdout = os.fstat(2), sys.stdout

    def read(job: int) -> bool:
        if job % 5 == 4:
            with pytest.raises(ExrError, match=r"cut\.exr is truncated or corrupt"):
                read_exr(tmp_path / "cut.exr")
            return True
        i = job % 4
        rows = (job % 7, 16 - job % 3)
        whole = np.array_equal(read_exr(tmp_path / f"{i}.exr"), images[i])
        return whole and np.array_equal(read_exr(tmp_path / f"{i}.exr", rows=rows), images[i][rows[0] : rows[1]])

    with ThreadPoolExecutor(8) as pool:
        results = list(pool.map(read, range(8 * 20)))
    after = os.fstat(2)
    assert all(results) and len(results) == 160
    assert (after.st_dev, after.st_ino) == (before.st_dev, before.st_ino) and sys.stdout is stdout


def test_missing_channel_lists_the_file_channels(tmp_path):
    write_exr(tmp_path / "a.exr", _image(), ["R", "G", "B"])
    with pytest.raises(ExrError, match=r"a\.exr must have channel\(s\) \['Y'\]; it has \['R', 'G', 'B'\]"):
        read_exr(tmp_path / "a.exr", ["R", "Y"])


def test_multi_part_is_rejected(tmp_path):
    parts = [OpenEXR.Part({"type": OpenEXR.scanlineimage}, {"Y": np.zeros((2, 3), "f")}, name) for name in "ab"]
    OpenEXR.File(parts).write(str(tmp_path / "multi.exr"))
    with pytest.raises(ExrError, match=r"multi\.exr must be a single-part EXR; got 2 parts"):
        read_exr(tmp_path / "multi.exr")


def test_write_checks_channel_count(tmp_path):
    with pytest.raises(ExrError, match=r"channels for .*a\.exr must name one channel per image channel \(3\); got 2"):
        write_exr(tmp_path / "a.exr", _image(), ["R", "G"])
    assert not (tmp_path / "a.exr").exists()


@pytest.mark.parametrize("shape", [(5,), (2, 3, 4, 1), (0, 3, 1)])
def test_write_checks_shape(tmp_path, shape):
    with pytest.raises(ExrError, match=r"image for .*a\.exr must have shape \(H, W, C\)"):
        write_exr(tmp_path / "a.exr", np.zeros(shape, np.float32), ["Y"])


def test_write_checks_channel_names(tmp_path):
    with pytest.raises(ExrError, match="distinct non-empty strings"):
        write_exr(tmp_path / "a.exr", _image(count=2), ["R", "R"])


def test_write_creates_folders(tmp_path):
    write_exr(tmp_path / "deep" / "er" / "a.exr", _image(), ["R", "G", "B"])
    assert read_exr(tmp_path / "deep" / "er" / "a.exr").shape == (5, 7, 3)


def _fail_halfway(self, name):
    with open(name, "wb") as f:
        f.write(b"v/1\x01" + b"\0" * 100)  # a half-written EXR
    raise RuntimeError("disk full")


def test_failed_write_leaves_no_file(tmp_path, monkeypatch):
    monkeypatch.setattr(OpenEXR.File, "write", _fail_halfway)
    with pytest.raises(ExrError, match=r"a\.exr could not be written; got RuntimeError: disk full"):
        write_exr(tmp_path / "a.exr", _image(), ["R", "G", "B"])
    assert not (tmp_path / "a.exr").exists()
    assert not _leftovers(tmp_path)


def test_failed_write_keeps_the_previous_file(tmp_path, monkeypatch):
    image = _image()
    write_exr(tmp_path / "a.exr", image, ["R", "G", "B"])
    monkeypatch.setattr(OpenEXR.File, "write", _fail_halfway)
    with pytest.raises(ExrError):
        write_exr(tmp_path / "a.exr", image + 1, ["R", "G", "B"])
    monkeypatch.undo()
    np.testing.assert_array_equal(read_exr(tmp_path / "a.exr"), image)
    assert not _leftovers(tmp_path)
