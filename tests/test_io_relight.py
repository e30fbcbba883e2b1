"""Relight's JSON light files (torchspec.io.relight): a RelightLab project (.relight) and a dome (.dome),
as RelightLab's Dome::toJson and Project::save write them."""

import json

import numpy as np
import pytest
import torch
from PIL import Image

from torchspec.io.lp import LightFileError
from torchspec.io.relight import read_relight
from torchspec.io.rti import RTIImportError, import_rti

DIRECTIONS = [(0.0, 0.0, 1.0), (0.6, 0.0, 0.8), (0.0, 0.6, 0.8), (-0.6, 0.0, 0.8)]


def _xyz(vectors):
    return [{"x": x, "y": y, "z": z} for x, y, z in vectors]


def _dome(configuration="directional", **extra):
    dome = {
        "label": "test dome",
        "notes": "",
        "imageWidth": 0.0,
        "domeDiameter": 0.0,
        "verticalOffset": 0.0,
        "lightConfiguration": configuration,
        "directions": _xyz(DIRECTIONS),
        "positionsSphere": [],
        "positions3d": [],
        "ledAdjust": [],
    }
    dome.update(extra)
    return dome


def _photos(folder, names):
    folder.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        Image.fromarray(np.full((4, 5, 3), 40 + 30 * k, np.uint8)).save(folder / name)


def _project(root, dome, skip=(), folder="images", names=None):
    names = names or [f"img{k}.jpg" for k in range(len(DIRECTIONS))]
    _photos(root / folder, names)
    project = {
        "application": "RelightLab",
        "version": "2024.1",
        "width": 5,
        "height": 4,
        "folder": folder,
        "images": [{"filename": name, "skip": k in skip} for k, name in enumerate(names)],
        "dome": dome,
        "spheres": [],
    }
    (root / "capture.relight").write_text(json.dumps(project, indent=4))
    return root / "capture.relight"


def test_project_directional(tmp_path):
    path = _project(tmp_path, _dome())
    lights = read_relight(path)
    assert [e.name for e in lights.entries] == [f"img{k}.jpg" for k in range(4)]
    assert np.allclose([e.direction for e in lights.entries], DIRECTIONS)
    assert lights.positions is None and lights.image_folder == (tmp_path / "images").resolve()
    imported = import_rti(tmp_path, tmp_path / "out")  # a folder holding a .relight: SOURCE like an .lp
    assert [p.name for p in imported.images] == [f"img{k}.jpg" for k in range(4)] and imported.positions is None
    assert torch.allclose(imported.capture.directions(), torch.tensor(DIRECTIONS, dtype=torch.float64))


def test_project_spherical_dome_positions(tmp_path):
    """A spherical dome: positions = direction * diameter / 2 + vertical offset, in image widths."""
    path = _project(tmp_path, _dome("spherical", imageWidth=200.0, domeDiameter=800.0, verticalOffset=-50.0), skip=(2,))
    with pytest.warns(UserWarning, match="marked skip are left out"):
        imported = import_rti(path, tmp_path / "out")
    assert [p.name for p in imported.images] == ["img0.jpg", "img1.jpg", "img3.jpg"]
    kept = torch.tensor([DIRECTIONS[k] for k in (0, 1, 3)], dtype=torch.float64)
    expected = (kept * 400 + torch.tensor([0.0, 0.0, -50.0], dtype=torch.float64)) / 200
    assert torch.allclose(imported.positions, expected)
    assert np.allclose(imported.capture.extra["source"]["positions"], expected.numpy())
    assert torch.allclose(imported.capture.directions(), kept)


def test_dome_lights3d_matched_by_order(tmp_path):
    """A .dome names no images: matched by order; lights3d positions give the directions."""
    positions = [(10.0, 0.0, 30.0), (0.0, 20.0, 25.0), (-5.0, -5.0, 40.0)]
    dome = _dome("lights3d", directions=[], positions3d=_xyz(positions), imageWidth=50.0)
    _photos(tmp_path / "rti", ["a.png", "b.png", "c.png"])
    (tmp_path / "rti" / "my.dome").write_text(json.dumps(dome))
    with pytest.warns(UserWarning, match="matched by order"):
        imported = import_rti(tmp_path / "rti", tmp_path / "out")
    truth = torch.tensor(positions, dtype=torch.float64)
    assert torch.allclose(imported.positions, truth / 50)
    assert torch.allclose(imported.capture.directions(), truth / truth.norm(dim=-1, keepdim=True))


def test_skipped_count_pairs_with_kept_images(tmp_path):
    """A dome of as many lights as images not skipped pairs with those."""
    names = [f"img{k}.jpg" for k in range(5)]
    path = _project(tmp_path, _dome(), skip=(1,), names=names)
    lights = read_relight(path)
    assert [e.name for e in lights.entries] == ["img0.jpg", "img2.jpg", "img3.jpg", "img4.jpg"]


@pytest.mark.parametrize(
    "change, match",
    [
        (lambda d: d.update(directions=_xyz(DIRECTIONS[:2])), "lists 2 light directions for 4 images"),
        (lambda d: d["directions"].__setitem__(1, {"x": 0, "y": 0, "z": 0}), r"images\[1\] \(img1\.jpg\) must give a"),
        (lambda d: d["directions"].__setitem__(2, {"x": 0, "y": "up"}), r"dome\.directions\[2\] must be an object"),
        (lambda d: d.update(lightConfiguration="conical"), "lightConfiguration must be"),
        (
            lambda d: d.update(lightConfiguration="lights3d", positions3d=_xyz(DIRECTIONS[:3])),
            "4 directions but 3 positions",
        ),
    ],
)
def test_bad_relight_files_name_file_and_place(tmp_path, change, match):
    dome = _dome()
    change(dome)
    path = _project(tmp_path, dome)
    with pytest.raises(LightFileError, match=match) as error:
        read_relight(path)
    assert str(path) in str(error.value)


def test_invalid_json_names_the_line(tmp_path):
    path = tmp_path / "a.relight"
    path.write_text('{\n  "images": [\n    {"filename": "a.jpg",}\n  ]\n}\n')
    with pytest.raises(LightFileError, match=r"a\.relight: line 3 column \d+ is not valid JSON"):
        read_relight(path)


def test_missing_project_image_named(tmp_path):
    path = _project(tmp_path, _dome())
    (tmp_path / "images" / "img2.jpg").unlink()
    with pytest.raises(RTIImportError, match=r"'img2\.jpg' \(images\[2\] \(img2\.jpg\)\)"):
        import_rti(path, tmp_path / "out")
    assert not (tmp_path / "out").exists()
