import json
import subprocess
import sys

import torchspec
from torchspec.cli import main


def test_version():
    out = subprocess.run([sys.executable, "-m", "torchspec", "--version"], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == f"torchspec {torchspec.__version__}"


def test_demo_writes_its_report(tmp_path, capsys):
    assert main(["demo", "-o", str(tmp_path), "--pixels", "2048"]) == 0
    summary = json.loads((tmp_path / "demo.json").read_text())
    assert summary["pixels"] == 2048
    assert summary["mse_over_crb"] < 1.3, summary
    assert (tmp_path / "demo.png").stat().st_size > 1000
    assert not list(tmp_path.glob(".*.part*")), "a temporary file was left behind"
    assert "MSE / CRB" in capsys.readouterr().out


def test_no_command_prints_help(capsys):
    assert main([]) == 2
    assert "usage: torchspec" in capsys.readouterr().out
