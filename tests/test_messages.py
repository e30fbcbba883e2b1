"""What a command-line user reads when the input is wrong (issue 22, point 9): the user's terms
(flags and commands, not Python arguments), one unit per message, what the input is when it is
plainly not a capture, the unknown key beside a missing one, a JPEG named as such, the library's
raw lines kept out, and a closed pipe taken quietly."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from torchspec.cli import PIPE_CLOSED, main
from torchspec.demo import scene
from torchspec.dome.protocol import _HINTS
from torchspec.simulate import simulate, write_simulation


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A simulated 8 x 8 painting (88 frames)."""
    root = tmp_path_factory.mktemp("messages") / "capture"
    write_simulation(root, simulate(scene(size=8), root=root))
    return root


def _copy(capture: Path, tmp_path: Path) -> Path:
    return Path(shutil.copytree(capture, tmp_path / "copy"))


def _info(path, capsys) -> str:
    assert main(["info", str(path), "--quiet"]) == 2
    return capsys.readouterr().out


def test_a_missing_folder_is_named_as_a_folder(tmp_path, capsys):
    out = _info(tmp_path / "nowhere", capsys)
    assert f"the capture folder {tmp_path / 'nowhere'} does not exist" in out and "capture.json must exist" not in out
    assert main(["fit", str(tmp_path / "nowhere"), "-o", str(tmp_path / "maps")]) == 2
    assert "the capture folder" in capsys.readouterr().err


def test_a_yaml_config_is_not_a_capture(tmp_path, capsys):
    config = tmp_path / "fit.yaml"
    config.write_text("model: auto\n")
    out = _info(config, capsys)
    assert "fit.yaml is a YAML config, not a capture" in out and "JSON" not in out


def test_a_misspelt_key_is_named_with_the_close_one(capture, tmp_path, capsys):
    root = _copy(capture, tmp_path)
    manifest = json.loads((root / "capture.json").read_text())
    manifest["frames"][3]["directon"] = manifest["frames"][3].pop("direction")
    (root / "capture.json").write_text(json.dumps(manifest))
    out = _info(root, capsys)
    assert "frames[3] must have the keys" in out and "['direction'] missing" in out
    assert "the unknown key(s) ['directon']. Did you mean 'direction' for 'directon'?" in out


def test_a_jpeg_frame_is_called_a_jpeg(capture, tmp_path, capsys):
    from PIL import Image

    root = _copy(capture, tmp_path)
    Image.new("RGB", (8, 8)).save(root / "frames" / "0002.exr", format="JPEG")
    assert main(["info", str(root), "--quiet"]) == 2
    out = capsys.readouterr().out
    assert "0002.exr is a JPEG, not an EXR" in out and "torchspec import SOURCE -o CAPTURE" in out


def test_cli_messages_use_flags_not_python_arguments():
    for code, hint in _HINTS.items():
        assert "()" not in hint, f"{code}: {hint}"


def test_a_closed_pipe_is_quiet(capture):
    """torchspec info CAPTURE --json | head -c 1: the reader stops; no 'Broken pipe' error, and the
    exit status is the shell's for a command stopped by a closed pipe (141), not 2 (unusable)."""
    command = [sys.executable, "-m", "torchspec", "info", str(capture), "--json", "--quiet"]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")]),
    }
    child = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    child.stdout.close()  # before the child writes: its first write meets a closed pipe
    err = child.stderr.read().decode()
    assert child.wait(timeout=120) == PIPE_CLOSED and err == "", err


def test_info_says_the_outer_rows_fell_outside_the_radius(capture, capsys):
    """A 12 x 12 grid within |l| <= 0.8 (the demo's, and acquire's default) lights 88 positions of
    a 10 x 10 grid: info says so instead of calling it a 10 x 10 grid."""
    assert main(["info", str(capture), "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "layout grid 10 x 10 (88 of its 100 positions: those beyond the radius are left out)" in out
    assert "planned   a 12 x 12 grid within |l| <= 0.8; 2 of its 12 rows and 2 of its 12 columns" in out
    assert "so the frames form a 10 x 10 grid" in out


def test_the_planned_grid_of_an_acquisition():
    from torchspec.info import _planned_grid

    assert _planned_grid({"name": "torchspec acquire", "layout": "grid:12x12", "radius": 0.8}) == {
        "columns": 12,
        "rows": 12,
        "radius": 0.8,
    }
    assert _planned_grid({"name": "torchspec acquire", "layout": "line:9", "radius": 0.8}) is None
    assert _planned_grid(None) is None


def test_warnings_are_one_line_for_the_command(capture, tmp_path):
    """torchspec as a command shows a warning as 'torchspec COMMAND: warning: ...', without the Python
    file and source line of the default format."""
    root = _copy(capture, tmp_path)
    manifest = json.loads((root / "capture.json").read_text())
    manifest["comment"] = "an unknown top-level key: warned about"
    (root / "capture.json").write_text(json.dumps(manifest))
    command = [sys.executable, "-m", "torchspec", "render", str(root / "truth"), "--capture", str(root)]
    path = os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")])
    done = subprocess.run(
        [*command, "-o", str(tmp_path / "out")], capture_output=True, text=True, env={**os.environ, "PYTHONPATH": path}
    )
    assert done.returncode == 0, done.stderr
    assert "torchspec render: warning: " in done.stderr and "unknown top-level key(s) ['comment']" in done.stderr
    assert ".py:" not in done.stderr and "warnings.warn" not in done.stderr, done.stderr


@pytest.mark.parametrize("given", ["folder", "dirs.lp", "lights.txt"])
def test_an_rti_folder_or_light_file_given_to_fit_says_import_it_first(tmp_path, capsys, given):
    """Issue 37, point 3: pointed at an RTI folder (photographs + .lp) or its light file, ``fit``
    and ``info`` say to run ``torchspec import`` first, not that capture.json is missing or that
    the .lp is not JSON."""
    rti = tmp_path / "rti"
    rti.mkdir()
    (rti / "image00.jpg").write_bytes(b"")
    (rti / ("lights.txt" if given == "lights.txt" else "dirs.lp")).write_text("1\nimage00.jpg 0 0 1\n")
    path = rti if given == "folder" else rti / given
    assert main(["fit", str(path), "-o", str(tmp_path / "maps")]) == 2
    err = capsys.readouterr().err
    assert f"import it first with: torchspec import {path} -o CAPTURE" in err
    assert "capture.json must exist" not in err and "JSON" not in err
    assert f"torchspec import {path}" in _info(path, capsys)
    assert not (tmp_path / "maps").exists()


@pytest.mark.parametrize(
    "command, stops",
    [
        (["import", "{tmp}/rti", "-o", "{tmp}/imported"], "torchspec.io.rti.read_photo"),
        (["info", "{capture}"], "torchspec.info.inspect_capture"),
        (["render", "{capture}/truth", "--capture", "{capture}", "-o", "{tmp}/r"], "torchspec.relight.render_image"),
        (["export", "{capture}/truth", "-o", "{tmp}/web", "--to", "web"], "torchspec.export.export"),
    ],
)
def test_ctrl_c_anywhere_is_one_line_and_exit_130(capture, tmp_path, monkeypatch, capsys, command, stops):
    """Ctrl-C in any command (here in the middle of its work): one line naming the command, exit 130,
    no traceback; an interrupted import leaves nothing behind."""
    from PIL import Image

    rti = tmp_path / "rti"
    rti.mkdir()
    lines = ["4"]
    for k, (x, y) in enumerate([(0.5, 0), (0, 0.5), (-0.5, 0), (0, -0.5)]):
        Image.new("RGB", (4, 4), (40 * k, 80, 120)).save(rti / f"img{k}.png")
        lines.append(f"img{k}.png {x} {y} 0.866")
    (rti / "dirs.lp").write_text("\n".join(lines) + "\n")

    def stopped(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(stops, stopped)
    argv = [part.format(tmp=tmp_path, capture=capture) for part in command]
    assert main([*argv, "--quiet"] if command[0] != "export" else argv) == 130
    assert capsys.readouterr().err == f"torchspec {command[0]}: interrupted (Ctrl-C).\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rti"]  # nothing written, no temporary left
