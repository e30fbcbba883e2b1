"""FitConfig nested by stage (torchspec.pipeline.settings, config_groups): configs/fit.yaml's layout,
the groups' own checks, the flat keys of before refused with their place now, old checkpoints."""

import json
import math
from dataclasses import asdict, replace
from pathlib import Path

import pytest
import yaml

from torchspec.cli import main
from torchspec.config import ConfigError, load_config
from torchspec.pipeline import (
    ComputeConfig,
    FitConfig,
    FlagsConfig,
    LadderConfig,
    MasksConfig,
    QuadratureConfig,
    StartConfig,
    TermConfig,
)
from torchspec.pipeline.checkpoint import STATE, open_checkpoint
from torchspec.pipeline.settings import GROUPS, MOVED, flat_settings, nested_settings

FIT_YAML = Path(__file__).parents[1] / "configs" / "fit.yaml"
OLD_KEYS = (
    "ladder smooth select_z predict_z folds fold_regions refit lobe_resolution lobe_support residual_term term_z "
    "broad_alpha resolve dual_rms dual_gate trust_rms flag_peak_misfit flag_astray flag_overshoot flag_reach init "
    "detect noise_floor naive_alpha saturation downsample crop grow shadow trim cut fri_method fri_coefficients "
    "fri_kernel path quadrature compile tile memory_gib dtype device threads"
).split()
"""The keys of the flat FitConfig (before the groups) that moved: all but model, calibrate,
uncertainty and lm (and shadows, which came after the groups, at the top)."""


def _flat(settings: dict) -> dict:
    """A nested settings record in the flat layout of before the groups (``lm`` nested, as it was)."""
    return flat_settings(settings)


def test_fit_yaml_writes_every_key_of_every_group_and_loads_as_the_defaults():
    written = yaml.safe_load(FIT_YAML.read_text())
    defaults = json.loads(json.dumps(asdict(FitConfig())))
    assert written == defaults  # every key, in its group, at its default value
    assert load_config(FIT_YAML, FitConfig) == FitConfig()
    assert list(written)[4:-1] == list(GROUPS)  # the groups in stage order, between the top keys and lm


def test_a_nested_mapping_round_trips():
    config = FitConfig(
        model="auto",
        masks=MasksConfig(saturation=0.9, grow=2, crop=(1, 2, 30, 40), downsample=2),
        start=StartConfig(init="grid", fri_kernel="pooled", broad_alpha=0.5),
        ladder=LadderConfig(models=("ward-iso", "ward-aniso"), smooth=10.0, dual_gate=None, folds=4),
        term=TermConfig(order=2, z=0.5),
        flags=FlagsConfig(overshoot=20.0),
        quadrature=QuadratureConfig(preset="render", path="reference", compile=False),
        compute=ComputeConfig(tile=512, dtype="float64", device="cpu", threads=1),
    )
    assert FitConfig.from_dict(asdict(config)) == config
    assert FitConfig.from_dict(yaml.safe_load(yaml.safe_dump(json.loads(json.dumps(asdict(config)))))) == config
    assert FitConfig.from_dict({}) == FitConfig()
    assert FitConfig.from_dict({"ladder": {"smooth": 10}}).ladder == LadderConfig(smooth=10.0)


def test_the_properties_read_the_groups():
    assert FitConfig().ladder_climbed == FitConfig().ladder.models
    assert FitConfig(model="ward-iso").ladder_climbed == ("ward-iso",)
    assert FitConfig(model="diffuse").ladder_climbed == ()
    assert FitConfig(model="ward-iso", uncertainty=False).noise_known is False
    rule = FitConfig(quadrature=QuadratureConfig(preset="render", path="reference", compile=True)).rule
    assert rule.path == "reference" and rule.compile is True
    assert FitConfig().rule == QuadratureConfig().rule


def test_the_flat_keys_are_the_old_fields():
    assert sorted(MOVED) == sorted(OLD_KEYS)
    assert all(place.split(".")[0] in GROUPS for place in MOVED.values())


@pytest.mark.parametrize("key", OLD_KEYS)
def test_a_flat_key_is_refused_with_its_place_now(key, tmp_path):
    group, name = MOVED[key].split(".")
    expected = f"key {key!r} has moved: write it as {group}: {{{name}: ...}}."
    with pytest.raises(ConfigError) as caught:
        FitConfig.from_dict({key: 1})
    assert str(caught.value) == f"FitConfig: {expected}"
    path = tmp_path / "fit.yaml"
    path.write_text(f"model: auto\n{key}: 1\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path, FitConfig)
    assert str(caught.value) == f"{path}: {expected}"


def test_the_cli_names_a_flat_keys_place(tmp_path, capsys):
    config = tmp_path / "fit.yaml"
    config.write_text("quadrature: render\n")
    capture = tmp_path / "capture"
    capture.mkdir()
    assert main(["fit", str(capture), "-o", str(tmp_path / "maps"), "--config", str(config)]) == 2
    assert "key 'quadrature' has moved: write it as quadrature: {preset: ...}" in capsys.readouterr().err


def test_a_group_given_as_a_mapping_in_python_is_refused():
    with pytest.raises(ConfigError, match=r"FitConfig.ladder must be a LadderConfig; got \{'smooth': 1\}"):
        FitConfig(ladder={"smooth": 1})


@pytest.mark.parametrize(
    "kind, values, message",
    [
        (MasksConfig, {"downsample": 0}, "downsample"),
        (StartConfig, {"init": "magic"}, "FitConfig.start.init must be one of"),
        (StartConfig, {"fri_kernel": "pooled", "fri_method": "ls"}, "FitConfig.start.fri_kernel 'pooled' weighs"),
        (StartConfig, {"detect": 0.0}, "FitConfig.start.detect must be > 0"),
        (StartConfig, {"broad_alpha": 1.5}, r"FitConfig.start.broad_alpha must be in \(0, 1\]"),
        (LadderConfig, {"models": ("ward-iso", "diffuse")}, "FitConfig.ladder.models must name one or more"),
        (LadderConfig, {"models": ("phong",)}, "FitConfig.ladder.models: each model must be one of"),
        (LadderConfig, {"smooth": -1.0}, "FitConfig.ladder.smooth must be >= 0 and finite"),
        (LadderConfig, {"predict_z": math.inf}, "FitConfig.ladder.predict_z must be >= 0 and finite"),
        (LadderConfig, {"folds": 1}, "FitConfig.ladder.folds must be >= 2"),
        (LadderConfig, {"refit": -1}, "FitConfig.ladder.refit must be >= 0"),
        (LadderConfig, {"resolve": 0.0}, "FitConfig.ladder.resolve must be > 0"),
        (LadderConfig, {"dual_gate": math.nan}, "FitConfig.ladder.dual_gate must be a finite number or None"),
        (LadderConfig, {"lobe_support": 2.0}, r"FitConfig.ladder.lobe_support must be in \[0, 1\]"),
        (TermConfig, {"order": 5}, "FitConfig.term.order must be auto, 0 .off. or an order in"),
        (TermConfig, {"z": -1.0}, "FitConfig.term.z must be >= 0 and finite"),
        (FlagsConfig, {"trust_rms": 0.0}, "FitConfig.flags.trust_rms must be > 0"),
        (QuadratureConfig, {"preset": "rough"}, "FitConfig.quadrature.preset must be one of"),
        (ComputeConfig, {"tile": -1}, "FitConfig.compute.tile must be >= 0"),
        (ComputeConfig, {"memory_gib": 0.0}, "FitConfig.compute.memory_gib must be > 0"),
        (ComputeConfig, {"dtype": "float16"}, "FitConfig.compute.dtype must be 'float32' or 'float64'"),
        (ComputeConfig, {"threads": 0}, "FitConfig.compute.threads must be 'auto' or a number >= 1"),
    ],
)
def test_each_group_checks_its_values_naming_the_full_key(kind, values, message):
    with pytest.raises(ValueError, match=message):
        kind(**values)


def test_a_refused_value_in_a_file_names_the_file_and_the_key(tmp_path):
    path = tmp_path / "fit.yaml"
    path.write_text("compute: {dtype: float16}\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path, FitConfig)
    assert str(caught.value).startswith(f"{path}.compute: dtype must be 'float32' or 'float64'")
    path.write_text("model: ward-iso\nladder: {smooth: 1.0}\n")  # across groups: FitConfig's own check
    with pytest.raises(ConfigError) as caught:
        load_config(path, FitConfig)
    assert str(caught.value).startswith(f"{path}: ladder.smooth regularises auto's choice of a lobe")
    path.write_text("ladder: {smooth: 1.0, ladder: [ward-iso]}\n")
    with pytest.raises(ConfigError, match=r"\.ladder has unknown key\(s\) \['ladder'\]"):
        load_config(path, FitConfig)


def test_a_record_of_the_flat_settings_is_nested():
    record = json.loads(json.dumps(asdict(FitConfig(ladder=LadderConfig(smooth=10.0)))))
    assert nested_settings(_flat(record)) == record
    assert nested_settings(record) == record  # nested already: as it is


def test_a_checkpoint_of_the_flat_settings_resumes(tmp_path):
    """A checkpoint written before the groups records its settings flat: the same job resumes."""
    job = json.loads(json.dumps({"torchspec": "x", "settings": asdict(FitConfig()), "frames": [0, 1]}))
    del job["settings"]["compute"]["threads"]
    folder = tmp_path / "checkpoint"
    folder.mkdir()
    (folder / STATE).write_text(json.dumps({**job, "settings": _flat(job["settings"])}))
    assert open_checkpoint(folder, job, resume=True) == {}
    other = {**job, "settings": json.loads(json.dumps(asdict(replace(FitConfig(), model="ward-iso"))))}
    del other["settings"]["compute"]["threads"]
    with pytest.raises(ValueError, match="its settings differ"):
        open_checkpoint(folder, other, resume=True)


class _Stop(BaseException):
    """Raised by the fit the command line calls: the settings it was given, and nothing run."""


def test_the_cli_flags_set_their_groups(tmp_path, monkeypatch):
    import torchspec.pipeline

    given = {}

    def fit(capture, *, config, **_):
        given["config"] = config
        raise _Stop

    monkeypatch.setattr(torchspec.pipeline, "fit", fit)
    capture = tmp_path / "capture"
    capture.mkdir()
    flags = "--model ward-iso --calibrate none --residual-term 2 --device cpu --downsample 2 --crop 1,2,8,9 --threads 1"
    with pytest.raises(_Stop):
        main(["fit", str(capture), "-o", str(tmp_path / "maps"), *flags.split()])
    config = given["config"]
    assert (config.model, config.calibrate, config.term.order) == ("ward-iso", "none", 2)
    assert (config.compute.device, config.compute.threads) == ("cpu", 1)
    assert (config.masks.downsample, config.masks.crop) == (2, (1, 2, 8, 9))
    others = replace(config, model="auto", calibrate="auto", term=TermConfig(), compute=ComputeConfig())
    others = replace(others, masks=MasksConfig())
    assert others == FitConfig()  # nothing else set
