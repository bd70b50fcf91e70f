"""Progress of a fit, stage by stage, each with its total known before it starts.

A fit reports its stages (the model's synthesis, the lookups and prefilter of a
quasi-interpolated level, each level's blocks and its errors at the nodes, the check
points, the write) to a :class:`Progress`: ``with progress.stage(name, total, unit) as
advance: ... advance(n)``. The base class is silent; :class:`BarProgress` draws one tqdm
bar a stage (count, rate, ETA) on a terminal; :class:`LineProgress` writes a plain line
when a stage starts, at most every ``interval`` seconds while it runs and when it ends
(for logs: ``-v`` on a stderr that is not a terminal). :func:`for_terminal` picks one
the way the commands do.
"""

from __future__ import annotations

import contextlib
import sys
import time

__all__ = ["Progress", "BarProgress", "LineProgress", "as_progress", "for_terminal"]


class Progress:
    """Stages of a long operation; this base reports nothing."""

    @contextlib.contextmanager
    def stage(self, name: str, total: int, unit: str = "step"):
        """A stage of ``total`` units; yields ``advance(n=1)``."""
        yield _ignore


def _ignore(n: int = 1) -> None:
    pass


class _Callback(Progress):
    """The older protocol: a callable told how many blocks (local problems) were just solved."""

    def __init__(self, callback):
        self.callback = callback

    @contextlib.contextmanager
    def stage(self, name, total, unit="step"):
        yield self.callback if unit == "block" else _ignore


def as_progress(progress) -> Progress:
    """``progress`` as a :class:`Progress`: None is silent; a callable gets the count of
    blocks solved (as before stages existed)."""
    if progress is None:
        return Progress()
    if isinstance(progress, Progress) or hasattr(progress, "stage"):
        return progress
    if callable(progress):
        return _Callback(progress)
    raise TypeError(f"progress must be None, a Progress or a callable, got {type(progress).__name__}")


class BarProgress(Progress):
    """One tqdm bar a stage on ``stream`` (count of total, rate and ETA)."""

    def __init__(self, stream=None):
        self.stream = stream or sys.stderr

    @contextlib.contextmanager
    def stage(self, name, total, unit="step"):
        from tqdm import tqdm

        with tqdm(total=total, desc=name, unit=f" {unit}", file=self.stream, leave=False,
                  dynamic_ncols=True) as bar:
            yield bar.update


_IRREGULAR_PLURALS = {"axis": "axes"}


def _count(n: int, unit: str) -> str:
    """``n`` units in words, the unit in the plural unless ``n`` is 1 ("1 store", "3 axes")."""
    return f"{n:,} {unit if n == 1 else _IRREGULAR_PLURALS.get(unit, unit + 's')}"


class LineProgress(Progress):
    """A line a stage when it starts and ends, and at most every ``interval`` seconds in
    between (count of total, elapsed, ETA from the rate so far)."""

    def __init__(self, stream=None, interval: float = 10.0, clock=time.monotonic):
        self.stream = stream or sys.stderr
        self.interval = interval
        self.clock = clock

    def _line(self, text):
        print(f"progress: {text}", file=self.stream, flush=True)

    @contextlib.contextmanager
    def stage(self, name, total, unit="step"):
        from tqdm import tqdm

        start = last = self.clock()
        done = 0
        self._line(f"{name}: {_count(total, unit)}")

        def advance(n=1):
            nonlocal done, last
            done += n
            now = self.clock()
            if now - last >= self.interval and done < total:
                last = now
                elapsed = now - start
                eta = elapsed / done * (total - done) if done else float("nan")
                self._line(f"{name}: {done:,}/{_count(total, unit)}, {tqdm.format_interval(elapsed)} elapsed, "
                           f"ETA {tqdm.format_interval(eta) if eta == eta else '?'}")

        yield advance
        self._line(f"{name}: {done:,}/{_count(total, unit)} in {self.clock() - start:.1f} s")


def for_terminal(quiet: bool, verbose: int, stream=None) -> Progress:
    """What a command shows on ``stream`` (stderr): nothing with ``quiet``; bars on a
    terminal; stage lines with ``verbose`` elsewhere (a log file, a pipe); else nothing."""
    stream = stream or sys.stderr
    if quiet:
        return Progress()
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        return BarProgress(stream)
    return LineProgress(stream) if verbose else Progress()
