import re
from dataclasses import dataclass, field

import pytest

from torchspec.config import ConfigError, load_config


@dataclass(frozen=True)
class Inner:
    sigma: float
    name: str = "gaussian"


@dataclass(frozen=True)
class Outer:
    inner: Inner
    sizes: tuple[int, ...] = (2, 8)
    seed: int = 0
    label: str | None = None
    extra: list[float] = field(default_factory=list)


def test_loads_nested(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("inner: {sigma: 1}\nsizes: [3, 4]\nlabel: x\n")
    config = load_config(path, Outer)
    assert config == Outer(inner=Inner(sigma=1.0), sizes=(3, 4), label="x")


@pytest.mark.parametrize(
    "text,match",
    [
        ("inner: {sigma: 1}\nsead: 3\n", r"unknown key\(s\) \['sead'\]"),
        ("inner: {sigma: 1, sigmaa: 2}\n", r"\.inner has unknown key\(s\) \['sigmaa'\]"),
        ("sizes: [1]\n", "missing the key 'inner'"),
        ("inner: {sigma: one}\n", r"inner\.sigma must be a number"),
        ("inner: {sigma: 1}\nseed: 1.5\n", "seed must be an integer"),
        ("inner: {sigma: 1}\nsizes: 3\n", "sizes must be a list"),
        ("[1, 2]\n", "must be a mapping"),
        ("inner: {sigma: 1\n", "is not valid YAML"),
    ],
)
def test_errors_name_file_and_key(tmp_path, text, match):
    path = tmp_path / "bad.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError, match=match) as info:
        load_config(path, Outer)
    assert "bad.yaml" in str(info.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="cannot read config .*nope.yaml"):
        load_config(tmp_path / "nope.yaml", Outer)


def test_a_value_the_settings_refuse_names_the_file_and_the_key(tmp_path):
    from torchspec import FitConfig

    path = tmp_path / "fit.yaml"
    path.write_text("ladder: {smooth: -1}\n")
    with pytest.raises(ConfigError) as caught:
        load_config(path, FitConfig)
    assert str(caught.value).startswith(f"{path}.ladder: smooth must be >= 0")


@dataclass(frozen=True)
class Checked:
    width: int = 1

    def __post_init__(self):
        if self.width < 1:
            raise ValueError(f"width of the box must be >= 1; got {self.width}.")


def test_a_refusal_without_a_field_name_still_names_the_file(tmp_path):
    path = tmp_path / "box.yaml"
    path.write_text("width: 0\n")
    with pytest.raises(ConfigError, match=rf"^{re.escape(str(path))}: width of the box must be >= 1; got 0\.$"):
        load_config(path, Checked)
