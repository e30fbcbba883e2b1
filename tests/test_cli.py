import json
import subprocess
import sys

import pytest

import torchspec
from torchspec.cli import main
from torchspec.io import read_svbrdf


def test_version():
    out = subprocess.run([sys.executable, "-m", "torchspec", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"torchspec {torchspec.__version__}"


def test_demo_writes_maps_previews_and_a_report(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path), "--size", "24", "--quiet"]) == 0
    report = json.loads((tmp_path / "report.json").read_text())
    scores = report["scores"]
    # The fit's targets on the demo's own simulated painting, against its truth.
    assert scores["normal_deg"] < 0.5 and scores["kd"] < 0.03, scores
    assert scores["varnished_alpha"] < 0.1 and scores["matte_share_ks0"] > 0.95, scores
    assert scores["heldout_psnr_db"] > 40, scores
    assert read_svbrdf(tmp_path / "maps").svbrdf.shape == (24, 24)
    assert (tmp_path / "capture" / "truth" / "svbrdf.json").is_file()
    for name in ("report.png", "relit.png", "previews/normal.png", "previews/diffuse.png", "previews/specular.png",
                 "previews/roughness.png", "previews/model.png", "previews/normal_error.png"):
        assert (tmp_path / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n", name
    assert not list(tmp_path.rglob(".*.part*")), "a temporary file was left behind"
    assert "held-out frames predicted" in capsys.readouterr().out


def test_demo_size_is_checked(capsys):
    with pytest.raises(SystemExit):
        main(["demo", "--size", "2"])
    assert "--size must be in 8..4096" in capsys.readouterr().err


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "usage: torchspec" in capsys.readouterr().out


def test_the_model_choices_are_the_packages_models():
    from torchspec.cli import build_parser
    from torchspec.model.registry import MODELS

    fit = build_parser()._subparsers._group_actions[0].choices["fit"]
    (action,) = [a for a in fit._actions if a.dest == "model"]
    assert action.choices == ["auto", *MODELS]


def _simulation_config(tmp_path, text="scene: {kind: mirror, mirror: {width: 2, height: 2}}\n"
                       "layout: {kind: line, n: 4, theta_min_deg: 0.0, theta_max_deg: 10.0}\n"):
    config = tmp_path / "sim.yaml"
    config.write_text(text)
    return config


@pytest.mark.parametrize("exception", [RuntimeError("boom"), KeyError("boom"), ValueError("boom")])
def test_an_internal_error_is_reported_as_a_bug_with_its_traceback(tmp_path, capsys, monkeypatch, exception):
    import torchspec.simulate

    def fail(*args, **kwargs):
        raise exception

    monkeypatch.setattr(torchspec.simulate, "simulate", fail)
    argv = ["simulate", str(_simulation_config(tmp_path)), "-o", str(tmp_path / "out")]
    assert main(argv) == 70
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err and f"{type(exception).__name__}: " in err
    assert f"this is a bug in torchspec {torchspec.__version__}" in err
    assert f"torchspec simulate {tmp_path / 'sim.yaml'} -o {tmp_path / 'out'}" in err


def test_a_user_error_is_one_line_without_a_traceback(tmp_path, capsys):
    config = _simulation_config(tmp_path, "scene: {kind: mirror}\nlayout: {kind: line, n: -3}\n")
    assert main(["simulate", str(config), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("torchspec simulate: error: ") and "Traceback" not in err and "bug" not in err


def test_a_missing_file_is_the_users_error(tmp_path, capsys):
    assert main(["simulate", str(tmp_path / "nowhere.yaml"), "-o", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err
    assert "nowhere.yaml" in err and "Traceback" not in err


def test_an_option_value_with_a_minus_sign_is_the_options():
    """``--light -0.5,0.5,0.7`` (a direction to the left) is the value of --light, not an unknown option:
    argparse alone refuses it ("expected one argument")."""
    from torchspec.cli import negative_values

    assert negative_values(["render", "m", "--light", "-0.5,0.5,0.7", "--light", "0,0,1", "-o", "r"]) == [
        "render", "m", "--light=-0.5,0.5,0.7", "--light", "0,0,1", "-o", "r"
    ]
    plain = ["export", "m", "--light", "-0.5", "0.5", "0.707"]  # negative numbers: argparse takes them
    assert negative_values(plain) == plain
    assert negative_values(["fit", "c", "-o", "-out"]) == ["fit", "c", "-o", "-out"]  # not numbers: as given
    assert negative_values(["fit", "--quiet", "-1,2"]) == ["fit", "--quiet=-1,2"]  # argparse then refuses it
