"""experiments/stability.py on its small config (experiments/configs/stability_small.yaml): the flag rules'
catch and false-alarm rates, and the study's sanity (errors at the bound at high SNR, failures where
the methods' assumptions break)."""

import importlib
import json
import math
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).parents[1]


def _stability():
    if str(ROOT / "experiments") not in sys.path:
        sys.path.insert(0, str(ROOT / "experiments"))
    return importlib.import_module("stability")


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The small config (~15 s): the location methods on fewer trials, and the fit on every axis."""
    out = tmp_path_factory.mktemp("stability")
    config = ROOT / "experiments" / "configs" / "stability_small.yaml"
    return _stability().main(["--config", str(config), "--output", str(out)]), out


def _score(result, family, axis, value, method):
    row = next(r for r in result["rows"] if r["family"] == family and r["axis"] == axis and r["value"] == value)
    return row["methods"][method]


def test_the_fit_flags_catch_the_failures(small):
    """The package's own flags (Fit.flags: a flag of torchspec.pipeline.flags.UNTRUSTED, or no lobe fitted)
    against the failures of the fit (a peak more than 10 Cramer-Rao deviations from the truth) on
    every axis of the study but the skewed kernel: the issue's >= 90 % caught, <= 5 % of the good
    estimates flagged. (The full study: 97 % / 4.5 %.)"""
    result, _ = small
    rates = result["flags"]["fit"]["without_skew_axis"]
    assert rates["failures"] >= 30, f"only {rates['failures']} failures to catch"
    assert rates["catch"] >= 0.9, f"catch rate {rates['catch']:.3f}"
    assert rates["false_alarms"] <= 0.05, f"false alarms {rates['false_alarms']:.3f}"
    score = _score(result, "pipeline", "snr_db", 20.0, "fri+lm")
    assert 0.4 < score["median_error_over_crb"] < 1.5 and score["failure_rate"] < 0.05, score
    assert _score(result, "pipeline", "separation", 2.0, "fri+lm")["failure_rate"] > 0.5


@pytest.mark.xfail(strict=True, reason="a skewed kernel declared Gaussian biases every peak unseen (stability.md)")
def test_the_fit_flags_meet_the_target_with_a_skewed_kernel_too(small):
    """A skewed kernel declared symmetric leaves data that a shifted symmetric kernel explains within
    the noise: the per-pixel checks cannot see the bias (calibrate the kernel: torchspec calibrate)."""
    result, _ = small
    rates = result["flags"]["fit"]["all_cells"]
    assert rates["catch"] >= 0.9 and rates["false_alarms"] <= 0.05, rates


@pytest.mark.xfail(strict=True, reason="FRI alone: no flag rule found meets 90 % / 5 % (stability.md)")
def test_the_location_flags_meet_the_issue_target(small):
    """FRI alone is the fit's start, which the package does not flag: the study's rules for it (a
    local asymmetry under the peak, a peak far from the brightest sample) do not reach the target."""
    result, _ = small
    rates = result["flags"]["location"]["all_cells"]
    assert rates["catch"] >= 0.9 and rates["false_alarms"] <= 0.05, rates


def test_errors_sit_at_the_bound_at_high_snr(small):
    result, _ = small
    for snr in (20.0, 40.0):
        ratio = _score(result, "location", "snr_db", snr, "coherent")["median_error_over_crb"]
        assert 0.4 < ratio < 1.5, f"median |error| / CRB std {ratio:.3g} at {snr:g} dB"


def test_errors_grow_as_snr_falls_and_failures_follow_broken_assumptions(small):
    result, _ = small
    errors = [_score(result, "location", "snr_db", s, "coherent")["median_error"] for s in (40.0, 20.0, 0.0, -5.0)]
    assert errors == sorted(errors), f"median errors from 40 to -5 dB: {errors}"
    # Peak picking's parabola is biased: the bound overtakes it as the noise falls.
    rates = [_score(result, "location", "snr_db", s, "peak")["failure_rate"] for s in (0.0, 20.0, 40.0)]
    assert rates[0] < 0.05 < rates[2], f"peak picking's failure rates at 0, 20, 40 dB: {rates}"
    # A second lobe under the first moves a one-peak estimate; a skewed kernel moves FRI's.
    assert _score(result, "location", "separation", 3.0, "coherent")["failure_rate"] > 0.5
    assert _score(result, "location", "skew", 1.0, "coherent")["failure_rate"] > 0.5
    assert _score(result, "location", "skew", 1.0, "peak")["failure_rate"] < 0.05


def test_outputs(small):
    result, out = small
    saved = json.loads((out / "stability_small.json").read_text())
    assert saved["flags"]["location"]["all_cells"] == result["flags"]["location"]["all_cells"]
    assert (out / "stability_small.png").stat().st_size > 10000
    text = (out / "stability_small.md").read_text()
    assert "python experiments/stability.py --config experiments/configs/stability_small.yaml" in text
    assert "| coherent |" in text and "## Quality flags" in text


def test_local_asymmetry_sees_a_merged_lobe_not_noise():
    stability = _stability()
    generator = torch.Generator().manual_seed(0)
    t, step = stability._line(16, 1.2)
    x = torch.zeros(2000, dtype=torch.float64)
    one = stability._profile(t - x[:, None], 0.042, 0.084, 0.0)
    two = one + 0.5 * stability._profile(t - x[:, None] - 0.2, 0.042, 0.084, 0.0)
    sigma = 0.01
    for clean, low, high in ((one, 0.1, 1.5), (two, 20.0, math.inf)):
        y = clean + sigma * torch.randn(clean.shape, dtype=torch.float64, generator=generator)
        peak, _, _ = stability._fri_on_line(y, t, step, "coherent")
        value = float(stability.local_asymmetry(y, peak, float(t[0]), step, sigma).median())
        assert low < value < high, f"median local asymmetry {value:.3g}"


def test_config_keys_are_checked(tmp_path):
    config = tmp_path / "typo.yaml"
    config.write_text((ROOT / "experiments" / "configs" / "stability_small.yaml").read_text() + "trails: 5\n")
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['trails'\]"):
        _stability().main(["--config", str(config), "--output", str(tmp_path)])
