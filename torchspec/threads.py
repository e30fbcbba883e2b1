"""How many torch threads a fit runs on, on a machine other processes share (``FitConfig.compute.threads``).

Torch's CPU kernels run on an OpenMP pool (GNU libgomp in the Linux wheels). A thread that reaches
the end of a parallel region first spins (busy-waits) for the others, by default about 3 ms per
region before it sleeps. With more threads than free cores, every region then waits for a thread
the kernel has descheduled, while the spinning one burns the core the neighbour needed: on a 2-core
machine shared with other work, a 64 x 64 x 48 fit on 2 threads took 93 s against 16 s on 1
thread, and 273 s beside a neighbour keeping both cores busy (issue 21; ``experiments/bench_busy.py``).
So, by default:

- :func:`quiet_waits`: ``OMP_WAIT_POLICY=passive`` in the environment before torch loads its OpenMP
  runtime (``import torchspec`` does it first thing, unless the user chose a policy or
  ``GOMP_SPINCOUNT``, or torch was imported before): a waiting thread sleeps at once and leaves its
  core to whoever needs it. Every thread then does useful work or none, and the fit keeps torch's
  own count of threads (all cores): beside a neighbour keeping both cores busy, 2 threads were
  faster than 1 (they get two of the scheduler's shares), and the fit slowed by its share of the CPU.
- ``threads: auto`` (:func:`fit_threads`) where the waits spin (:func:`waits_spin`: torch loaded
  before torchspec, or a policy the user chose): each tile runs on the cores of this process's
  affinity that other processes left free while the previous tile ran (:class:`CpuMeter`), at most
  torch's own count (what ``torch.set_num_threads`` or ``OMP_NUM_THREADS`` chose), at least one.

This module imports nothing heavy at its top: :mod:`torchspec`'s ``__init__`` imports it before torch.
"""

from __future__ import annotations

import contextlib
import os
import sys
import time

__all__ = ["AUTO", "CpuMeter", "affinity_cores", "choose_threads", "fit_threads", "quiet_waits", "waits_spin"]

AUTO = "auto"
"""``FitConfig.compute.threads`` that adapts to the machine (:func:`fit_threads`)."""
SAMPLE_SECONDS = 0.1
"""A fresh measurement of the other processes' use of the cores spans this long ..."""
STALE_SECONDS = 5.0
"""... and is taken when the last one is older than this (else the use since the last one counts)."""
# /proc/stat's columns after the CPU's name: user nice system idle iowait irq softirq steal (guest
# time is already in user). Idle and iowait are free; steal is a core the hypervisor gave away.
_BUSY_COLUMNS = (0, 1, 2, 5, 6, 7)


def quiet_waits(environ=None, modules=None) -> bool:
    """Set ``OMP_WAIT_POLICY=passive`` in ``environ`` (``os.environ``) unless it names a policy or
    ``GOMP_SPINCOUNT``, or torch is already among ``modules`` (``sys.modules``: its OpenMP runtime
    read the environment as it loaded). Returns whether it was set. Child processes inherit it."""
    environ = os.environ if environ is None else environ
    modules = sys.modules if modules is None else modules
    if "torch" in modules or "OMP_WAIT_POLICY" in environ or "GOMP_SPINCOUNT" in environ:
        return False
    environ["OMP_WAIT_POLICY"] = "passive"
    return True


def waits_spin(environ=None) -> bool:
    """Whether torch's OpenMP threads spin at a barrier (libgomp's reading of ``environ``,
    ``os.environ``): unless ``OMP_WAIT_POLICY`` is ``passive`` or ``GOMP_SPINCOUNT`` is a count of at
    most 10000 spins (~0.1 ms)."""
    environ = os.environ if environ is None else environ
    policy = environ.get("OMP_WAIT_POLICY", "").strip().lower()
    if policy:
        return policy != "passive"
    count = environ.get("GOMP_SPINCOUNT", "").strip()
    return not (count.isdigit() and int(count) <= 10000)


def affinity_cores() -> list[int]:
    """The CPUs this process may run on."""
    if hasattr(os, "sched_getaffinity"):
        return sorted(os.sched_getaffinity(0))
    return list(range(os.cpu_count() or 1))


def choose_threads(cores: int, others: float | None, ceiling: int) -> int:
    """Threads for ``cores`` cores of which other processes keep ``others`` cores' worth busy
    (``None``: unknown, taken as none): the free cores rounded to the nearest, at most ``ceiling``,
    at least 1.

    Example:
        >>> choose_threads(2, 0.1, 2), choose_threads(2, 0.7, 2), choose_threads(8, 2.2, 4)
        (2, 1, 4)
    """
    free = cores - max(0.0, others or 0.0)
    return max(1, min(ceiling, cores, int(free + 0.5)))


class CpuMeter:
    """The cores' worth of CPU that processes other than this one used on this process's cores,
    from Linux's ``/proc/stat`` and this process's own CPU time, between two readings."""

    clock_ticks = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    """``/proc/stat``'s units per second."""

    def __init__(self, stat: str = "/proc/stat", cores: list[int] | None = None):
        self.stat = stat
        self.cores = affinity_cores() if cores is None else cores
        self.last = None  # (wall, busy seconds of the cores, own CPU seconds)

    def reading(self) -> tuple[float, float, float] | None:
        """``(wall, busy, own)`` seconds now, or ``None`` where ``/proc/stat`` cannot be read."""
        names = {f"cpu{k}" for k in self.cores}
        try:
            with open(self.stat, encoding="ascii") as lines:
                rows = [line.split() for line in lines if line.startswith("cpu")]
        except OSError:
            return None
        ticks = sum(sum(int(row[1 + i]) for i in _BUSY_COLUMNS if 1 + i < len(row)) for row in rows if row[0] in names)
        times = os.times()
        return time.monotonic(), ticks / self.clock_ticks, times.user + times.system

    def others(self) -> float | None:
        """Cores' worth the other processes used since the last call (over a fresh
        :data:`SAMPLE_SECONDS` when that is older than :data:`STALE_SECONDS` or there was none);
        ``None`` where it cannot be measured (not Linux)."""
        now = self.reading()
        if now is None:
            return None
        if self.last is None or now[0] - self.last[0] > STALE_SECONDS:
            self.last = now
            time.sleep(SAMPLE_SECONDS)
            now = self.reading()
        wall, busy, own = (a - b for a, b in zip(now, self.last, strict=True))
        self.last = now
        return max(0.0, (busy - own) / wall) if wall > 0 else None


_METER: list[CpuMeter] = []


@contextlib.contextmanager
def fit_threads(setting: int | str, *, meter: CpuMeter | None = None):
    """Run the block (a tile of a fit whose ``FitConfig.compute.threads`` is ``setting``) on a number of
    torch intra-op threads, and restore torch's own count after it: ``setting`` when a number; ``auto``:
    torch's count (what ``torch.set_num_threads``, ``OMP_NUM_THREADS`` or a cluster's worker chose)
    where the waits are passive, else (:func:`waits_spin`) :func:`choose_threads` of
    :func:`affinity_cores` and what ``meter`` (this process's :class:`CpuMeter` by default) measured
    since the last tile, at most torch's count. Yields the count."""
    import torch

    before = torch.get_num_threads()
    if setting == AUTO and not waits_spin():
        count = before
    elif setting == AUTO:
        if meter is None:
            if not _METER:
                _METER.append(CpuMeter())
            meter = _METER[0]
        count = choose_threads(len(meter.cores), meter.others(), before)
    else:
        count = int(setting)
    if count != before:
        torch.set_num_threads(count)
    try:
        yield count
    finally:
        if count != before:
            torch.set_num_threads(before)
