from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import torchspec.io.svbrdf as svbrdf_module
from torchspec.io import Maps, SVBRDFError, read_exr, read_svbrdf, write_exr, write_svbrdf
from torchspec.model.brdf import SVBRDF

H, W = 6, 7


def _svbrdf(rotation=False, grey=False, seed=0) -> SVBRDF:
    generator = torch.Generator().manual_seed(seed)
    normal = torch.randn(H, W, 3, generator=generator) * 0.1 + torch.tensor([0.0, 0.0, 1.0])
    specular = torch.rand(H, W, 1 if grey else 3, generator=generator)
    specular[:2] = 0  # matte rows
    return SVBRDF(
        normal=normal / normal.norm(dim=-1, keepdim=True),
        diffuse=torch.rand(H, W, 3, generator=generator),
        specular=specular,
        roughness=torch.rand(H, W, 2, generator=generator) * 0.3 + 0.01,
        rotation=torch.rand(H, W, generator=generator) if rotation else None,
    )


def _assert_close(actual, expected, tolerance=0.0):
    err = (actual - expected).abs().max().item()
    assert err <= tolerance, f"max error {err:.3g}"


def test_round_trip(tmp_path):
    svbrdf = _svbrdf()
    write_svbrdf(tmp_path, svbrdf)
    maps = read_svbrdf(tmp_path)
    back = maps.svbrdf
    assert tuple(back.shape) == (H, W) and back.channels == ("R", "G", "B") and back.rotation is None
    for name in ("normal", "diffuse", "specular"):
        assert getattr(back, name).dtype == torch.float32
        _assert_close(getattr(back, name), getattr(svbrdf, name), 1e-6 if name == "normal" else 0.0)
    matte = (svbrdf.specular == 0).all(-1)
    _assert_close(back.roughness[~matte], svbrdf.roughness[~matte])
    assert (back.roughness[matte] == 0).all()
    assert maps.meta == {"format": "torchspec.svbrdf", "version": 1, "model": "ward"}
    assert maps.extra == {}
    assert read_exr(tmp_path / "roughness.exr").shape == (H, W, 2), "no A channel without rotation"
    assert not list(tmp_path.glob(".*"))


def test_rotation_goes_to_channel_a(tmp_path):
    svbrdf = _svbrdf(rotation=True)
    write_svbrdf(tmp_path, svbrdf)
    matte = (svbrdf.specular == 0).all(-1)
    rotation = read_svbrdf(tmp_path).svbrdf.rotation
    _assert_close(rotation[~matte], svbrdf.rotation[~matte])
    assert (rotation[matte] == 0).all()
    _assert_close(
        torch.from_numpy(read_exr(tmp_path / "roughness.exr", ["A"])[:, :, 0])[~matte], svbrdf.rotation[~matte]
    )


def test_grey_specular_is_replicated(tmp_path):
    svbrdf = _svbrdf(grey=True)
    write_svbrdf(tmp_path, svbrdf)
    assert read_exr(tmp_path / "specular.exr").shape == (H, W, 3)
    _assert_close(read_svbrdf(tmp_path).svbrdf.specular, svbrdf.specular.expand(H, W, 3))


def test_roughness_is_zero_where_ks_is_zero(tmp_path):
    svbrdf = _svbrdf(rotation=True)
    roughness = svbrdf.roughness.clone()
    roughness[0, 0] = float("nan")  # a matte pixel: its roughness is meaningless and must not be written
    rotation = svbrdf.rotation.clone()
    rotation[0, 1] = float("nan")
    write_svbrdf(
        tmp_path,
        SVBRDF(svbrdf.normal, svbrdf.diffuse, svbrdf.specular, roughness, rotation),
    )
    on_disk = read_exr(tmp_path / "roughness.exr", ["X", "Y", "A"])
    assert np.isfinite(on_disk).all() and (on_disk[:2] == 0).all()


def test_maps_with_meta_and_extra(tmp_path):
    model = torch.randint(0, 3, (H, W)).float()
    quality = torch.rand(H, W, 5)
    maps = Maps(_svbrdf(), meta={"model": "ward+lambert", "models": ["lambert", "ward"]}, extra={"model": model})
    write_svbrdf(tmp_path, maps, meta={"fit_seconds": 1.5}, extra={"quality": quality, "rgba": np.ones((H, W, 4))})
    meta = json.loads((tmp_path / "svbrdf.json").read_text())
    assert list(meta)[:3] == ["format", "version", "model"]
    assert meta["model"] == "ward+lambert" and meta["models"] == ["lambert", "ward"] and meta["fit_seconds"] == 1.5
    back = read_svbrdf(tmp_path / "svbrdf.json")
    assert back.meta == meta
    assert set(back.extra) == {"model", "quality", "rgba"}
    assert torch.equal(back.extra["model"], model)
    assert torch.equal(back.extra["quality"], quality)
    assert back.extra["rgba"].shape == (H, W, 4)
    assert read_exr(tmp_path / "model.exr").shape == (H, W, 1)


def test_reader_ignores_unknown_keys_files_and_part_files(tmp_path):
    write_svbrdf(tmp_path, _svbrdf(), meta={"whatever": {"nested": 1}})
    (tmp_path / "notes.txt").write_text("hello")
    (tmp_path / ".normal.exr.abc.part.exr").write_bytes(b"half")
    (tmp_path / "broken.exr").write_bytes(b"not an exr")
    with pytest.warns(UserWarning, match=r"skipping the unreadable extra map .*broken\.exr"):
        maps = read_svbrdf(tmp_path)
    assert maps.extra == {} and maps.meta["whatever"] == {"nested": 1}


def test_monochrome_and_sorted_channels(tmp_path):
    svbrdf = _svbrdf()
    mono = SVBRDF(svbrdf.normal, svbrdf.diffuse[..., :1], svbrdf.specular[..., :1], svbrdf.roughness, channels=("Y",))
    write_svbrdf(tmp_path / "mono", mono)
    assert read_svbrdf(tmp_path / "mono").svbrdf.channels == ("Y",)
    spectral = SVBRDF(
        svbrdf.normal, svbrdf.diffuse, svbrdf.specular, svbrdf.roughness, channels=("w600", "w450", "w500")
    )
    write_svbrdf(tmp_path / "spectral", spectral)
    back = read_svbrdf(tmp_path / "spectral").svbrdf
    assert back.channels == ("w450", "w500", "w600")
    _assert_close(back.diffuse, svbrdf.diffuse[..., [1, 2, 0]])


# --- read errors -----------------------------------------------------------------------------------


@pytest.fixture
def folder(tmp_path):
    write_svbrdf(tmp_path, _svbrdf())
    return tmp_path


def _meta(folder, **changes):
    meta = json.loads((folder / "svbrdf.json").read_text())
    meta.update(changes)
    (folder / "svbrdf.json").write_text(json.dumps({k: v for k, v in meta.items() if v is not None}))


def test_missing_meta(tmp_path):
    with pytest.raises(SVBRDFError, match=r"svbrdf\.json must exist; got no such file"):
        read_svbrdf(tmp_path)


@pytest.mark.parametrize(
    "changes, message",
    [
        (
            {"format": "torchspec.capture"},
            r"svbrdf\.json: format must be 'torchspec\.svbrdf'; got 'torchspec\.capture'",
        ),
        ({"version": 2}, r"svbrdf\.json: version must be a supported version \(1\); got 2"),
        ({"model": None}, r"svbrdf\.json: model must be a model name"),
    ],
)
def test_meta_errors(folder, changes, message):
    _meta(folder, **changes)
    with pytest.raises(SVBRDFError, match=message):
        read_svbrdf(folder)


def test_meta_not_json(folder):
    (folder / "svbrdf.json").write_text("{")
    with pytest.raises(SVBRDFError, match=r"svbrdf\.json must be valid JSON"):
        read_svbrdf(folder)


def test_missing_map(folder):
    (folder / "diffuse.exr").unlink()
    with pytest.raises(SVBRDFError, match=r"diffuse\.exr must exist"):
        read_svbrdf(folder)


def test_truncated_map(folder):
    file = folder / "roughness.exr"
    file.write_bytes(file.read_bytes()[:-20])
    with pytest.raises(SVBRDFError, match=r"roughness\.exr must be a readable map.*truncated"):
        read_svbrdf(folder)


def test_map_of_another_size(folder):
    write_exr(folder / "specular.exr", np.zeros((H, W - 1, 3)), ["R", "G", "B"])
    with pytest.raises(SVBRDFError, match=r"specular\.exr must have the size of normal\.exr, 6x7 .*got 6x6"):
        read_svbrdf(folder)


def test_specular_without_a_diffuse_channel(folder):
    write_exr(folder / "specular.exr", np.zeros((H, W, 1)), ["Y"])
    with pytest.raises(SVBRDFError, match=r"specular\.exr must be a readable map.*\['R', 'G', 'B'\]; it has \['Y'\]"):
        read_svbrdf(folder)


def test_roughness_without_y(folder):
    write_exr(folder / "roughness.exr", np.zeros((H, W, 2)), ["X", "A"])
    with pytest.raises(SVBRDFError, match=r"roughness\.exr must have channels X, Y .*got \['X', 'A'\]"):
        read_svbrdf(folder)


BAD_VALUES = {
    "nan-diffuse": ("diffuse.exr", (0, 0, 1), np.nan, r"diffuse\.exr must be finite; got 1 pixel"),
    "inf-normal": ("normal.exr", (slice(0, 2), 3), np.inf, r"normal\.exr must be finite; got 2 pixel"),
    "short-normal": ("normal.exr", (1, 2), 0.5, r"normal\.exr: normals must be unit .* row 1, column 2"),
    "negative-roughness": (
        "roughness.exr",
        (3, 3, 0),
        -0.1,
        r"roughness\.exr: roughness \(alpha\) must be >= 0; got 1",
    ),
    "negative-ks": ("specular.exr", (4, 4), -1.0, r"specular\.exr: k_s must be >= 0; got 1 pixel"),
}


@pytest.mark.parametrize("file, index, value, message", BAD_VALUES.values(), ids=BAD_VALUES.keys())
def test_bad_values_are_counted(folder, file, index, value, message):
    image = read_exr(folder / file)
    image[index] = value
    write_exr(folder / file, image, list({"normal.exr": "XYZ", "roughness.exr": "XY"}.get(file, "RGB")))
    with pytest.raises(SVBRDFError, match=message):
        read_svbrdf(folder)


def test_nearly_unit_normals_are_renormalised(folder):
    normal = read_exr(folder / "normal.exr", ["X", "Y", "Z"]) * 1.0005
    write_exr(folder / "normal.exr", normal, ["X", "Y", "Z"])
    _assert_close(read_svbrdf(folder).svbrdf.normal.norm(dim=-1), torch.ones(H, W), 1e-6)


# --- write errors ----------------------------------------------------------------------------------


def test_write_needs_image_dims(tmp_path):
    with pytest.raises(SVBRDFError, match=r"SVBRDF for .* must have leading dims \(H, W\); got \(42,\)"):
        write_svbrdf(tmp_path, _svbrdf().flatten())


def test_write_refuses_bad_values(tmp_path):
    svbrdf = _svbrdf()
    normal = svbrdf.normal.clone()
    normal[2, 3] = float("nan")
    with pytest.raises(SVBRDFError, match=r"SVBRDF\.normal for .*normal\.exr must be finite; got 1 pixel"):
        write_svbrdf(tmp_path, SVBRDF(normal, svbrdf.diffuse, svbrdf.specular, svbrdf.roughness))
    with pytest.raises(SVBRDFError, match=r"SVBRDF\.normal for .*normal\.exr: normals must be unit"):
        write_svbrdf(tmp_path, SVBRDF(svbrdf.normal * 2, svbrdf.diffuse, svbrdf.specular, svbrdf.roughness))
    with pytest.raises(SVBRDFError, match=r"roughness\.exr: SVBRDF\.roughness must be >= 0"):
        write_svbrdf(tmp_path, SVBRDF(svbrdf.normal, svbrdf.diffuse, svbrdf.specular, -svbrdf.roughness))
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize(
    "meta, extra, message",
    [
        ({"version": 2}, None, r"meta for .*svbrdf\.json: version must be 1"),
        ({"when": object()}, None, r"meta for .*svbrdf\.json must be JSON-serialisable"),
        (None, {"normal": torch.zeros(H, W)}, r"extra map names .* must not be one of \['normal'"),
        (None, {"a/b": torch.zeros(H, W)}, r"extra map names .* must be plain file stems"),
        (None, {"quality": torch.zeros(W, H)}, r"extra map 'quality' .* must have shape \(H, W\) .*got \(7, 6\)"),
    ],
)
def test_write_checks_meta_and_extra(tmp_path, meta, extra, message):
    with pytest.raises(SVBRDFError, match=message):
        write_svbrdf(tmp_path, _svbrdf(), meta=meta, extra=extra)
    assert not any(tmp_path.iterdir())


def test_meta_is_written_last(folder, monkeypatch):
    calls = []

    def failing_write(path, image, channels):
        calls.append(path)
        raise KeyboardInterrupt

    monkeypatch.setattr(svbrdf_module, "write_exr", failing_write)
    with pytest.raises(KeyboardInterrupt):
        write_svbrdf(folder, _svbrdf(seed=1), overwrite=True)
    assert calls and not (folder / "svbrdf.json").exists(), "a manifest over half-written maps"


def _two_lobes(svbrdf: SVBRDF) -> SVBRDF:
    generator = torch.Generator().manual_seed(9)
    ks2 = torch.rand(H, W, 1, generator=generator)
    ks2[:, :3] = 0  # no second lobe in these columns
    alpha2 = torch.rand(H, W, 2, generator=generator) * 0.3 + 0.1
    return SVBRDF(*(getattr(svbrdf, k) for k in ("normal", "diffuse", "specular", "roughness", "rotation")),
                  specular2=ks2, roughness2=alpha2)


def test_a_second_lobe_round_trips_and_is_named_in_the_meta(tmp_path):
    svbrdf = _two_lobes(_svbrdf())
    write_svbrdf(tmp_path, svbrdf)
    maps = read_svbrdf(tmp_path)
    back = maps.svbrdf
    _assert_close(back.specular2, svbrdf.specular2.expand(H, W, 3))  # grey, replicated to the channels
    lobe = (svbrdf.specular2 > 0).all(-1)
    _assert_close(back.roughness2[lobe], svbrdf.roughness2[lobe])
    assert (back.roughness2[~lobe] == 0).all()  # "no lobe": roughness 0
    assert maps.meta["second_lobe"] == {"specular": "specular2.exr", "roughness": "roughness2.exr"}
    assert maps.extra == {}
    # Written again without it: no stale second lobe stays behind, in the files or the meta.
    write_svbrdf(tmp_path, Maps(_svbrdf(), maps.meta), overwrite=True)
    again = read_svbrdf(tmp_path)
    assert again.svbrdf.specular2 is None and "second_lobe" not in again.meta
    assert not (tmp_path / "specular2.exr").exists() and not (tmp_path / "roughness2.exr").exists()


def test_a_second_lobe_needs_both_maps(tmp_path):
    write_svbrdf(tmp_path, _two_lobes(_svbrdf()), overwrite=True)
    (tmp_path / "roughness2.exr").unlink()
    with pytest.raises(SVBRDFError, match=r"specular2.exr \(a second lobe\) needs .*roughness2.exr"):
        read_svbrdf(tmp_path)


def test_a_negative_second_lobe_is_refused(tmp_path):
    bad = _two_lobes(_svbrdf())
    bad.specular2[0, 5, 0] = -0.1
    with pytest.raises(SVBRDFError, match=r"specular2.exr: SVBRDF.specular2 must be >= 0; got 1 pixel"):
        write_svbrdf(tmp_path, bad, overwrite=True)
    write_svbrdf(tmp_path, _two_lobes(_svbrdf()), overwrite=True)
    image = read_exr(tmp_path / "roughness2.exr")
    image[1, 4, 0] = float("nan")
    write_exr(tmp_path / "roughness2.exr", image, ["X", "Y"])
    with pytest.raises(SVBRDFError, match=r"roughness2.exr must be finite; got 1 pixel"):
        read_svbrdf(tmp_path)
