"""Outputs are protected (torchspec.outputs): every command that writes refuses an output holding
other work unless --overwrite, leaves it untouched, works with the flag, and refuses an output it
cannot write before any work (a file in the way)."""

import json

import pytest
import torch
from capture_cases import write_painting

import torchspec
from torchspec.cli import main
from torchspec.outputs import OutputError, check_output


def test_the_rule(tmp_path, monkeypatch):
    folder = tmp_path / "out"
    assert check_output(folder) == folder and not folder.exists(), "a check writes nothing"
    folder.mkdir()
    (folder / ".svbrdf.json.x1.part.json").write_text("{")  # a temporary of an interrupted atomic write
    check_output(folder)
    (folder / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match=rf"^the output {folder} holds 1 entry \(notes.txt\); add --overwrite"):
        check_output(folder, flag="--overwrite")
    with pytest.raises(OutputError, match="add overwrite=True"):
        check_output(folder)
    assert check_output(folder, overwrite=True) == folder
    (folder / ".torchspec-fit").mkdir()
    check_output(folder, job=".torchspec-fit")  # the command's own resumable job: its resume logic decides
    file = folder / "notes.txt"
    with pytest.raises(OutputError, match="must be a folder; got a file in the way"):
        check_output(file, overwrite=True)
    with pytest.raises(OutputError, match=rf"cannot write the output {file / 'a' / 'b'}: {file} is a file"):
        check_output(file / "a" / "b", overwrite=True)
    with pytest.raises(OutputError, match="exists; add overwrite=True"):
        check_output(file, folder=False)
    assert check_output(file, folder=False, overwrite=True) == file
    with pytest.raises(OutputError, match="must be a file; got a folder"):
        check_output(folder, folder=False, overwrite=True)

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")

    monkeypatch.setattr("tempfile.mkstemp", refuse)
    with pytest.raises(OutputError, match=rf"cannot write the output {tmp_path / 'new'}: {tmp_path} does not accept"):
        check_output(tmp_path / "new")


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A simulated 6 x 6 painting under a 5 x 5 grid, with truth."""
    return write_painting(tmp_path_factory.mktemp("outputs") / "capture", size=6)


@pytest.fixture(scope="module")
def maps(capture, tmp_path_factory):
    out = tmp_path_factory.mktemp("outputs") / "maps"
    assert main(["fit", str(capture), "-o", str(out), "--quiet"]) == 0
    return out


class _Calibration:
    """What write_kernel needs of a calibration (the calibration itself is test_calibrate's)."""

    table = torch.full((8, 8), 1.0 / 64, dtype=torch.float64)
    stats: dict = {}

    def light(self, file):
        return {"kernel": "tabulated", "file": file, "extent": 0.5}

    def summary(self):
        return "a stand-in calibration"


# Each command: its argv for an output, and the function whose call is its work (the check comes first).
COMMANDS = {
    "simulate": (lambda c, m, out: ["simulate", str(c.parent / "sim.yaml"), "-o", out], "torchspec.simulate.simulate"),
    "fit": (lambda c, m, out: ["fit", str(c), "-o", out, "--quiet"], "torchspec.pipeline.fit"),
    "render": (
        lambda c, m, out: ["render", str(c / "truth"), "--capture", str(c), "-o", out, "--quiet"],
        "torchspec.relight.render_capture",
    ),
    "export": (lambda c, m, out: ["export", str(m), "--to", "png16", "-o", out], "torchspec.export.export"),
    "calibrate": (
        lambda c, m, out: ["calibrate", str(c), "-o", f"{out}/kernel.exr"],
        "torchspec.calibration.kernel.calibrate",
    ),
    "demo": (lambda c, m, out: ["demo", "-o", out, "--size", "8", "--quiet"], "torchspec.demo.run"),
    "acquire": (
        lambda c, m, out: ["acquire", "--port", "/dev/null", "--light", "x.yaml", "--camera", "sim:x", "-o", out],
        "torchspec.dome.acquisition.load_light",
    ),
}


@pytest.fixture(scope="module")
def sim_config(capture):
    (capture.parent / "sim.yaml").write_text(
        "scene: {kind: mirror, mirror: {width: 2, height: 2}}\n"
        "layout: {kind: line, n: 4, theta_min_deg: 0.0, theta_max_deg: 10.0}\n"
    )


def _work_starts(monkeypatch, target):
    def started(*args, **kwargs):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(target, started)


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_an_output_holding_other_work_is_refused_before_any_work(
    command, capture, maps, sim_config, tmp_path, monkeypatch, capsys
):
    argv, work = COMMANDS[command]
    _work_starts(monkeypatch, work)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    target = out / "kernel.json" if command == "calibrate" else out  # the .json beside the kernel
    if command == "calibrate":
        (out / "kernel.json").write_text("{}")
    before = sorted(p.name for p in out.iterdir())
    assert main(argv(capture, maps, str(out))) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(target) in err and "--overwrite" in err, err
    assert sorted(p.name for p in out.iterdir()) == before and (out / "notes.txt").read_text() == "mine"

    blocker = tmp_path / "blocker"  # a file where a folder must be: found before the work
    blocker.write_text("in the way")
    assert main(argv(capture, maps, str(blocker / "out"))) == 2
    err = capsys.readouterr().err
    assert f"{blocker} is a file, not a folder" in err and "Traceback" not in err, err
    assert blocker.read_text() == "in the way"


@pytest.mark.parametrize("command", ["simulate", "fit", "render", "export", "calibrate"])
def test_overwrite_writes_into_it(command, capture, maps, sim_config, tmp_path, monkeypatch, capsys):
    argv, _ = COMMANDS[command]
    if command == "calibrate":
        monkeypatch.setattr("torchspec.calibration.kernel.calibrate", lambda *args, **kwargs: _Calibration())
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    if command == "calibrate":
        (out / "kernel.exr").write_text("an old kernel")
    assert main([*argv(capture, maps, str(out)), "--overwrite"]) == 0, capsys.readouterr().err
    written = {
        "simulate": "capture.json",
        "fit": "svbrdf.json",
        "render": "capture.json",
        "export": "png16.json",
        "calibrate": "kernel.json",
    }[command]
    assert (out / written).is_file() and (out / "notes.txt").read_text() == "mine"
    if command == "calibrate":
        assert json.loads((out / "kernel.json").read_text())["light"]["file"] == "kernel.exr"
        assert (out / "kernel.exr").read_bytes()[:4] == b"v/1\x01", "the kernel EXR replaced the old file"


def test_demo_overwrite_is_passed_on(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr("torchspec.demo.run", lambda output, **options: calls.append((output, options)))
    out = tmp_path / "demo"
    out.mkdir()
    (out / "report.json").write_text("{}")  # an earlier demo
    assert main(["demo", "-o", str(out), "--quiet", "--overwrite"]) == 0
    assert calls == [(out, {"size": 64, "progress": False, "overwrite": True, "device": "auto"})]


def test_a_fit_is_refused_over_earlier_maps_and_resumes_without_overwrite(capture, maps, tmp_path, capsys):
    out = tmp_path / "maps"
    assert main(["fit", str(capture), "-o", str(out), "--quiet", "--frames", "::2"]) == 0
    old = (out / "normal.exr").read_bytes()
    assert main(["fit", str(capture), "-o", str(out), "--quiet"]) == 2  # all frames over the ::2 fit
    assert f"the output {out} holds" in capsys.readouterr().err and (out / "normal.exr").read_bytes() == old
    # An unfinished fit there is the command's own job: --resume continues it, --overwrite drops it.
    (out / ".torchspec-fit").mkdir()
    (out / ".torchspec-fit" / "state.json").write_text(json.dumps({"another": "job"}))
    assert main(["fit", str(capture), "-o", str(out), "--quiet"]) == 2
    assert "unfinished fit" in capsys.readouterr().err
    assert main(["fit", str(capture), "-o", str(out), "--quiet", "--overwrite"]) == 0
    assert not (out / ".torchspec-fit").exists() and (out / "normal.exr").read_bytes() != old


def test_the_python_api_refuses_too(capture, maps, tmp_path):
    result = torchspec.read_svbrdf(maps)
    out = tmp_path / "maps"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    with pytest.raises(OutputError, match="overwrite=True"):
        torchspec.write_svbrdf(out, result.svbrdf)
    with pytest.raises(OutputError, match="overwrite=True"):
        torchspec.write_capture(out, torchspec.read_capture(capture), torch.zeros(25, 3, 6, 6))
    with pytest.raises(OutputError, match="overwrite=True"):
        torchspec.relight.render_capture(maps, capture, out)
    assert [p.name for p in out.iterdir()] == ["notes.txt"]
    torchspec.write_svbrdf(out, result.svbrdf, overwrite=True)
    assert torchspec.read_svbrdf(out).svbrdf.shape == (6, 6)


def test_progress_goes_to_a_terminal_only(capture, tmp_path, monkeypatch, capsys):
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    argv = ["render", str(capture / "truth"), "--capture", str(capture), "-o"]
    assert main([*argv, str(tmp_path / "a")]) == 0
    assert capsys.readouterr().err == "", "no bar into a pipe or a log"
    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main([*argv, str(tmp_path / "b")]) == 0
    shown = terminal.getvalue()
    assert "render: 100%" in shown and "6/6" in shown and "row" in shown, shown
    terminal.truncate(0)
    assert main([*argv, str(tmp_path / "c"), "--quiet"]) == 0
    assert terminal.getvalue() == ""


def test_simulate_shows_its_rows(tmp_path, sim_config, capture, monkeypatch):
    import io
    import sys

    class Terminal(io.StringIO):
        def isatty(self):
            return True

    terminal = Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    assert main(["simulate", str(capture.parent / "sim.yaml"), "-o", str(tmp_path / "sim")]) == 0
    assert "simulate: 100%" in terminal.getvalue() and "2/2" in terminal.getvalue()


def test_acquire_overwrite_starts_afresh(tmp_path):
    """The API's acquire with overwrite=True over another capture: the manifest lists the new frames only."""
    from test_dome_acquisition import _run

    from torchspec.dome.acquisition import AcquisitionError

    out = tmp_path / "capture"
    assert len(_run(out, layout="grid:3x3").frames) == 5
    with pytest.raises(AcquisitionError, match="--overwrite"):
        _run(out, layout="grid:4x4")
    assert len(_run(out, layout="grid:4x4", overwrite=True).frames) == 4
    assert len(torchspec.read_capture(out).frames) == 4


def test_an_output_over_its_capture_is_refused_before_any_work(capture, maps, tmp_path, capsys, monkeypatch):
    """``fit CAP -o CAP --overwrite`` (and an output inside the capture, or holding it), and
    ``render -o CAP``: refused in one line naming both, whatever --overwrite says, before any
    work; the capture is left as it was. The Python API refuses alike."""
    import shutil
    from dataclasses import fields

    from torchspec.pipeline import Fit

    cap = tmp_path / "work" / "capture"
    shutil.copytree(capture, cap)
    before = {p.relative_to(cap): p.stat().st_mtime_ns for p in cap.rglob("*")}

    def no_work(*args, **kwargs):
        raise AssertionError("the fit began")

    monkeypatch.setattr("torchspec.pipeline.in_process.setup", no_work)
    for out, where in ((cap, "is"), (cap / "maps", "lies inside"), (tmp_path / "work", "holds")):
        assert main(["fit", str(cap), "-o", str(out), "--quiet", "--overwrite"]) == 2
        err = capsys.readouterr().err
        assert err == (
            f"torchspec fit: error: the output {out} {where} the capture {cap}; writing there would mix the output "
            f"with what the command reads. Choose a folder outside {cap}.\n"
        )
    assert main(["render", str(maps), "--capture", str(cap), "-o", str(cap), "--quiet", "--overwrite"]) == 2
    assert f"the output {cap} is the capture {cap}" in capsys.readouterr().err
    with pytest.raises(OutputError, match="lies inside the capture"):
        torchspec.relight.render_capture(maps, cap, cap / "relit", overwrite=True)
    with pytest.raises(OutputError, match="is the maps' folder"):
        torchspec.relight.render_capture(maps, cap, maps, overwrite=True)
    result = Fit(**{f.name: None for f in fields(Fit)} | {"stats": {"capture": str(cap)}})
    with pytest.raises(OutputError, match="is the capture"):
        torchspec.write_fit(cap, result, overwrite=True)
    assert {p.relative_to(cap): p.stat().st_mtime_ns for p in cap.rglob("*")} == before
