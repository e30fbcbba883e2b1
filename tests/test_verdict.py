"""A fit's verdict in words (issue 37, point 1): the warnings a user can act on, in ``svbrdf.json``
and at the end of ``torchspec fit``, with PNG previews of the maps and one relit frame."""

import json

import pytest
from capture_cases import write_painting

from torchspec.cli import main
from torchspec.pipeline.flags import UNTRUSTED
from torchspec.pipeline.verdict import LOW_QUALITY_SHARE, REASONS, UNTRUSTED_SHARE, summary_lines, trust_warnings


def _stats(**flags) -> dict:
    return {
        "pixels": 1000,
        "frames": list(range(40)),
        "flags": {name: flags.get(name, 0) for name in UNTRUSTED},
        "low_quality": flags.get("low_quality", 0),
        "models": {"diffuse": 997, "ward-iso": 2, "ward-aniso": 1},
        "untrusted": sum(v for k, v in flags.items() if k in UNTRUSTED),
        "seconds": {"total": 2.0},
        "pixels_per_second": 500.0,
    }


def test_every_untrusted_flag_has_words_for_the_user():
    assert set(REASONS) == set(UNTRUSTED)


@pytest.mark.parametrize("name", UNTRUSTED)
def test_a_share_of_untrusted_pixels_above_the_limit_is_a_warning_naming_it(name):
    over = int(UNTRUSTED_SHARE * 1000) + 1
    found = trust_warnings(_stats(**{name: over}))
    assert len(found) == 1
    assert f"{over} of 1000 pixels ({over / 10:.1f} %) are untrusted ({name})" in found[0]
    assert REASONS[name][1] in found[0]  # what to do
    assert trust_warnings(_stats(**{name: over - 1})) == []  # at the limit: no warning


def test_low_quality_and_uncalibrated_lights_are_warnings():
    low = int(LOW_QUALITY_SHARE * 1000) + 1
    stats = _stats(low_quality=low)
    stats["lights"] = {"refused": "the lights were not calibrated"}
    found = trust_warnings(stats)
    assert found[0].startswith(f"{low} of 1000 pixels") and "quality below 0.5" in found[0]
    assert found[1] == "the lights were not calibrated"


def test_the_summary_names_models_trust_and_each_warning():
    stats = _stats(poor_fit=100)
    stats["warnings"] = trust_warnings(stats)
    lines = summary_lines(stats, "maps", capture="my capture")
    assert lines[0] == "wrote maps: 1000 pixels from 40 frames in 2.0 s (500 pixels/s)"
    assert lines[1] == "  models: diffuse 99.7 %, ward-iso 0.2 %, ward-aniso 1 pixel"
    assert lines[2].startswith("  trust: 10.0 % of pixels untrusted (quality 0)")
    assert lines[3] == f"  warning: {stats['warnings'][0]}"
    assert lines[-1].startswith("  next: torchspec view maps --capture 'my capture'")
    assert "  warnings: none" in summary_lines(_stats(), "maps")


@pytest.fixture(scope="module")
def painting(tmp_path_factory):
    return write_painting(tmp_path_factory.mktemp("verdict") / "painting", size=10, seed=5, grid=6)


def test_fit_writes_previews_and_ends_with_the_summary(painting, tmp_path, capsys):
    out = tmp_path / "maps"
    assert main(["fit", str(painting), "-o", str(out), "--quiet"]) == 0
    printed = capsys.readouterr().out.splitlines()
    meta = json.loads((out / "svbrdf.json").read_text())
    expected = summary_lines(meta["fit"], str(out), capture=str(painting))  # as svbrdf.json says
    assert printed[:-2] == expected[:-1] and printed[-1] == expected[-1]
    names = {p.stem for p in (out / "previews").glob("*.png")}
    assert {"normal", "diffuse", "specular", "roughness", "model", "quality", "relit"} <= names
    assert printed[-2].startswith(f"  previews: {out / 'previews'}/ (") and all(n in printed[-2] for n in names)
    assert "low_quality" in meta["fit"] and isinstance(meta["fit"]["warnings"], list)

    bare = tmp_path / "bare"
    assert main(["fit", str(painting), "-o", str(bare), "--quiet", "--no-previews"]) == 0
    assert not (bare / "previews").exists() and "previews:" not in capsys.readouterr().out
