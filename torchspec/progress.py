"""Progress bars of the commands: tqdm on stderr, with a rate and an estimate of the time left, in
units small enough to move (a fit's pixels, a render's rows, an acquisition's frames); quiet when
not asked for, and when stderr is not a terminal (a log or a pipe gets no carriage-return lines)."""

from __future__ import annotations

from tqdm.auto import tqdm

__all__ = ["bar"]


def bar(total: int, *, desc: str, unit: str, enabled: bool = True, **options) -> tqdm:
    """A tqdm bar over ``total`` ``unit`` s on stderr, shown when ``enabled`` and stderr is a terminal.

    Example:
        >>> with bar(3, desc="demo", unit="row", enabled=False) as progress:  # no bar, updates are free
        ...     progress.update(3)
        >>> progress.disable
        True
    """
    return tqdm(total=total, desc=desc, unit=unit, disable=None if enabled else True, **options)
