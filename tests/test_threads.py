"""The thread policy of a fit on a shared machine (torchspec.threads, FitConfig.compute.threads)."""

from __future__ import annotations

import pytest
import torch

from torchspec.config import ConfigError, from_mapping
from torchspec.pipeline import FitConfig
from torchspec.threads import CpuMeter, choose_threads, fit_threads, quiet_waits, waits_spin


@pytest.mark.parametrize(
    ("cores", "others", "ceiling", "expected"),
    [
        (2, 0.0, 2, 2),  # a quiet machine: every core
        (2, 0.4, 2, 2),  # a light neighbour: still both
        (2, 0.6, 2, 1),  # a neighbour on most of a core
        (2, 2.0, 2, 1),  # a neighbour on both cores: one thread, never none
        (2, 5.0, 2, 1),
        (2, None, 2, 2),  # unknown (not Linux): as quiet
        (8, 2.2, 4, 4),  # at most torch's own count
        (8, 2.6, 8, 5),
        (2, 0.0, 1, 1),  # torch.set_num_threads(1) is kept
    ],
)
def test_choose_threads(cores, others, ceiling, expected):
    assert choose_threads(cores, others, ceiling) == expected


def test_quiet_waits_sets_passive_only_where_nothing_was_chosen():
    env = {}
    assert quiet_waits(env, modules={}) and env == {"OMP_WAIT_POLICY": "passive"}
    for chosen in ({"OMP_WAIT_POLICY": "active"}, {"GOMP_SPINCOUNT": "1000"}):
        env = dict(chosen)
        assert not quiet_waits(env, modules={}) and env == chosen
    env = {}
    assert not quiet_waits(env, modules={"torch": torch}) and env == {}  # too late: its runtime read the environment


def test_meter_reads_the_busy_ticks_of_its_own_cores(tmp_path):
    stat = tmp_path / "stat"
    # user nice system idle iowait irq softirq steal: busy = all but idle and iowait
    stat.write_text(
        "cpu  999 0 0 0 0 0 0 0\ncpu0 100 1 10 5000 70 2 3 4\ncpu1 50 0 5 6000 0 0 0 0\n"
        "cpu2 700 0 0 0 0 0 0 0\nintr 1\n"
    )
    meter = CpuMeter(str(stat), cores=[0, 1])
    wall, busy, own = meter.reading()
    ticks = 100 + 1 + 10 + 2 + 3 + 4 + 50 + 5
    assert busy == pytest.approx(ticks / CpuMeter.clock_ticks)
    assert CpuMeter(str(tmp_path / "missing"), cores=[0]).reading() is None
    assert CpuMeter(str(tmp_path / "missing"), cores=[0]).others() is None


def test_meter_counts_the_others_use_without_its_own():
    meter = CpuMeter(cores=[0, 1])
    readings = iter([(10.0, 5.0, 1.0), (12.0, 8.0, 2.0), (13.0, 8.5, 2.5)])
    meter.reading = lambda: next(readings)
    meter.last = next(readings)
    assert meter.others() == pytest.approx((3.0 - 1.0) / 2.0)  # 3 busy core-s, 1 of them its own, in 2 s
    assert meter.others() == pytest.approx(0.0)  # its own work only


@pytest.mark.parametrize(
    ("environ", "spin"),
    [
        ({}, True),  # libgomp's default: ~3 ms
        ({"OMP_WAIT_POLICY": "passive"}, False),
        ({"OMP_WAIT_POLICY": "ACTIVE"}, True),
        ({"GOMP_SPINCOUNT": "300000"}, True),
        ({"GOMP_SPINCOUNT": "1000"}, False),
        ({"GOMP_SPINCOUNT": "infinite"}, True),
    ],
)
def test_waits_spin(environ, spin):
    assert waits_spin(environ) == spin


class _Meter:
    def __init__(self, others):
        self.cores, self.value = [0, 1], others

    def others(self):
        return self.value


@pytest.mark.parametrize(
    ("setting", "policy", "others", "expected"),
    [
        (1, "passive", None, 1),
        ("auto", "active", 2.0, 1),
        ("auto", "active", 0.0, None),
        ("auto", "passive", 2.0, None),
    ],
)
def test_fit_threads_sets_and_restores(monkeypatch, setting, policy, others, expected):
    monkeypatch.setenv("OMP_WAIT_POLICY", policy)  # what fit_threads reads of how torch's threads wait
    before = torch.get_num_threads()
    expected = min(before, 2) if expected is None else expected
    with fit_threads(setting, meter=_Meter(others)) as count:
        assert count == expected == torch.get_num_threads()
    assert torch.get_num_threads() == before


def test_fit_config_threads():
    assert FitConfig().compute.threads == "auto"
    assert from_mapping({"compute": {"threads": 3}}, FitConfig).compute.threads == 3
    assert from_mapping({"compute": {"threads": "auto"}}, FitConfig).compute.threads == "auto"
    for bad in (0, -1, "four", 2.5, True):
        with pytest.raises(ConfigError, match="compute: threads must be 'auto' or a number"):
            from_mapping({"compute": {"threads": bad}}, FitConfig)


def test_cli_refuses_a_bad_thread_count(tmp_path, capsys):
    from torchspec.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["fit", str(tmp_path), "-o", str(tmp_path / "maps"), "--threads", "two"])
    assert stop.value.code == 2 and "--threads must be 'auto' or a number; got 'two'" in capsys.readouterr().err
