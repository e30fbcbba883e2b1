"""Embedded ICC profiles honoured on import (torchspec.io.icc, torchspec.io.images): checked against
littleCMS (Pillow's ImageCms), the colour-management module the tools use."""

import io
import struct

import numpy as np
import pytest
import torch
from PIL import Image, ImageCms

from torchspec.io.icc import read_icc
from torchspec.io.images import ImageError, Transfer, read_photo
from torchspec.io.rti import import_rti

ADOBE = ((0.60974, 0.31111, 0.01947), (0.20528, 0.62567, 0.06087), (0.14919, 0.06322, 0.74457))
"""Adobe RGB (1998)'s colorants, D50-adapted (rXYZ, gXYZ, bXYZ of its profile)."""
GAMMA = 563 / 256


def _s15(*values):
    return b"".join(struct.pack(">i", round(v * 65536)) for v in values)


def matrix_profile(colorants=ADOBE, gamma=GAMMA, name="Test wide RGB", grey=False) -> bytes:
    """A minimal ICC v2 matrix/TRC display profile (the tags littleCMS needs), written by hand; or
    a grey one (``kTRC`` only)."""
    text = name.encode() + b"\0"
    desc = b"desc\0\0\0\0" + struct.pack(">I", len(text)) + text + b"\0" * 8 + b"\0\0\0" + b"\0" * 67
    xyz = [b"XYZ \0\0\0\0" + _s15(*c) for c in colorants]
    white = b"XYZ \0\0\0\0" + _s15(0.9642, 1.0, 0.8249)
    curve = b"curv\0\0\0\0" + struct.pack(">IH", 1, round(gamma * 256)) + b"\0\0"
    cprt = b"text\0\0\0\0" + b"none\0"
    tags = [(b"desc", desc), (b"wtpt", white), (b"cprt", cprt)]
    if grey:
        tags += [(b"kTRC", curve)]
    else:
        tags += [(b"rXYZ", xyz[0]), (b"gXYZ", xyz[1]), (b"bXYZ", xyz[2])]
        tags += [(b"rTRC", curve), (b"gTRC", curve), (b"bTRC", curve)]
    offset, table, body = 128 + 4 + 12 * len(tags), b"", b""
    for signature, data in tags:
        data += b"\0" * (-len(data) % 4)
        table += signature + struct.pack(">II", offset + len(body), len(data))
        body += data
    size = offset + len(body)
    header = struct.pack(">I4sI4s4s4s", size, b"none", 0x02100000, b"mntr", b"GRAY" if grey else b"RGB ", b"XYZ ")
    header += b"\0" * 12 + b"acsp" + b"\0" * 24 + struct.pack(">I", 0) + _s15(0.9642, 1.0, 0.8249)
    header += b"\0" * (128 - len(header))
    return header + struct.pack(">I", len(tags)) + table + body


def _codes(h=8, w=9, seed=0):
    codes = np.random.default_rng(seed).integers(30, 230, size=(h, w, 3), dtype=np.uint8)
    codes[0, 0] = (40, 200, 60)  # a saturated green: outside sRGB's gamut in Adobe RGB
    codes[0, 1] = 255  # white, clipped
    return codes


def test_matrix_profile_read_and_srgb_recognised():
    profile = read_icc(matrix_profile())
    assert profile.description == "Test wide RGB" and not profile.is_srgb
    white = profile.decode(torch.ones(3, dtype=torch.float64))
    assert white.tolist() == pytest.approx([1, 1, 1], abs=2e-3)  # white stays white (D50 to D65 relative)
    srgb = read_icc(ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes())
    assert srgb.is_srgb
    x = torch.linspace(0, 1, 11, dtype=torch.float64)[:, None].expand(-1, 3)
    assert (srgb.decode(x) - Transfer("srgb").decode(x)).abs().max() < 2e-3
    assert read_icc(b"not a profile") is None


def test_profile_matches_littlecms_and_changes_colours(tmp_path):
    """An Adobe RGB JPEG-free PNG: decoded by the profile, it agrees with littleCMS's conversion to
    sRGB (8-bit, in gamut) to the 8-bit quantisation, and differs from reading it as sRGB."""
    icc = matrix_profile()
    codes = _codes()
    Image.fromarray(codes).save(tmp_path / "a.png", icc_profile=icc)
    photo = read_photo(tmp_path / "a.png")
    assert photo.profile is not None and "embedded ICC profile 'Test wide RGB'" in photo.notes[0]
    ours, decoder = photo.decode(torch.from_numpy(photo.pixels).double(), None)
    assert decoder == "icc:Test wide RGB"
    source = ImageCms.ImageCmsProfile(io.BytesIO(icc))
    lcms = ImageCms.profileToProfile(Image.fromarray(codes), source, ImageCms.createProfile("sRGB"))
    reference = torch.from_numpy(np.asarray(lcms) / 255.0)  # 8-bit sRGB codes
    encoded = Transfer("srgb").encode(ours) * 255
    inside = ((ours > 0.002) & (ours < 0.998)).all(-1)  # littleCMS clips out-of-gamut colours
    assert inside.sum() > 20 and ((encoded - reference * 255).abs()[inside] <= 1.5).all()
    assert float(ours[0, 0, 0]) < 0  # the Adobe RGB green outside sRGB's gamut: kept, not clipped
    plain = Transfer("srgb").decode(torch.from_numpy(photo.pixels).double())
    assert (ours - plain).abs().max() > 0.05  # the profile changes the colours


def test_import_records_the_profile(tmp_path):
    folder = tmp_path / "rti"
    folder.mkdir()
    for k in range(3):
        Image.fromarray(_codes(seed=k)).save(folder / f"f{k}.jpg", icc_profile=matrix_profile(), quality=95)
    (folder / "dirs.lp").write_text("3\nf0.jpg 0 0 1\nf1.jpg 0.6 0 0.8\nf2.jpg 0 0.6 0.8\n")
    with pytest.warns(UserWarning, match="embedded ICC profile 'Test wide RGB'"):
        imported = import_rti(folder, tmp_path / "out")
    source = imported.capture.extra["source"]
    assert source["icc_profiles"] == ["Test wide RGB"] * 3
    frame = imported.capture.read_frames([1], dtype=torch.float64)[0].permute(1, 2, 0)
    photo = read_photo(folder / "f1.jpg")
    expected, _ = photo.decode(torch.from_numpy(photo.pixels).double(), None)
    assert (frame[1:] - expected[1:].clamp(min=0)).abs().max() < 1e-6  # float32 EXR; out of gamut: clipped at 0
    assert any("outside the sRGB gamut" in note for note in imported.notes)
    assert (frame[0, 1] >= 1).all() and imported.saturated[1] >= 1  # the clipped white stays at the level
    with pytest.warns(UserWarning):
        given = import_rti(folder, tmp_path / "out2", transfer="srgb")  # an explicit transfer wins
    assert given.capture.extra["source"]["icc_profiles"] is None


def test_16_bit_tiff_with_profile(tmp_path):
    tifffile = pytest.importorskip("tifffile")
    values = np.random.default_rng(1).integers(2000, 60000, size=(4, 5, 3), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "a.tif", values, photometric="rgb", iccprofile=matrix_profile(gamma=1.8))
    photo = read_photo(tmp_path / "a.tif")
    assert photo.encoding == "16-bit" and photo.profile is not None
    linear, _ = photo.decode(torch.from_numpy(photo.pixels).double(), None)
    colorants = np.array(ADOBE).T
    from torchspec.io.icc import SRGB_D50

    v = values.astype(np.float64) / 65535
    expected = (v ** (round(1.8 * 256) / 256)) @ np.linalg.solve(SRGB_D50, colorants).T
    assert np.abs(linear.numpy() - expected).max() < 1e-4  # the profile's s15Fixed16 rounding


def test_srgb_profile_is_plain_srgb(tmp_path):
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    Image.fromarray(_codes()).save(tmp_path / "a.jpg", icc_profile=srgb)
    photo = read_photo(tmp_path / "a.jpg")
    assert photo.profile is None and photo.notes == ()


def test_other_profiles_converted_by_littlecms(tmp_path, monkeypatch):
    """A profile that is not a matrix/TRC one (here: one made to look so) is applied by littleCMS
    to 8-bit sRGB in a JPEG, with a note (the sRGB profile leaves the codes as they were, within a
    code); in a TIFF or PNG (16-bit possible) it is an error naming the file."""
    import torchspec.io.images as images

    monkeypatch.setattr(images, "read_icc", lambda data: None)
    srgb = ImageCms.ImageCmsProfile(ImageCms.createProfile("sRGB")).tobytes()
    Image.fromarray(_codes()).save(tmp_path / "a.tif", tiffinfo={34675: srgb})  # read by tifffile: 8 and 16 bits
    with pytest.raises(ImageError, match=r"a\.tif embeds an ICC profile that is not a matrix/TRC one"):
        read_photo(tmp_path / "a.tif")
    Image.fromarray(_codes()).save(tmp_path / "a.jpg", icc_profile=srgb, quality=100, subsampling=0)
    photo = read_photo(tmp_path / "a.jpg")
    assert "RGB image converted to 8-bit sRGB with its ICC profile 'sRGB built-in' (littleCMS)" in photo.notes[0]
    assert photo.profile is None and photo.encoding == "8-bit"
    plain = np.asarray(Image.open(tmp_path / "a.jpg").convert("RGB"), dtype=np.float64) / 255
    assert np.abs(photo.pixels - plain).max() <= 1.5 / 255


def test_grey_profile_decodes_a_greyscale_jpeg(tmp_path):
    codes = _codes()[:, :, 1]
    Image.fromarray(codes).save(tmp_path / "g.jpg", icc_profile=matrix_profile(gamma=1.8, name="Grey 1.8", grey=True))
    photo = read_photo(tmp_path / "g.jpg")
    assert photo.pixels.shape[2] == 1 and photo.profile.description == "Grey 1.8"
    linear, decoder = photo.decode(torch.from_numpy(photo.pixels).double(), None)
    assert decoder == "icc:Grey 1.8"
    gamma = round(1.8 * 256) / 256
    assert np.abs(linear.numpy() - photo.pixels.astype(np.float64) ** gamma).max() < 1e-6
