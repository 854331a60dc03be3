"""Long work as one object: progress fraction, stage, cancellation and timing.

Every stage of pmvir (decode, geometry, refine, the pipeline around them, the
CLI's progress bar and the service's Celery task) reports through a
:class:`Progress`. A step is a slice of its parent's bar; it is timed, and the
cancellation callable is polled whenever a step starts or reports:

>>> events = []
>>> progress = Progress(lambda stage, fraction, message: events.append((stage, round(fraction, 2), message)))
>>> with progress.step("decode", weight=0.5) as p:
...     p.update(0.5, "frame 1 of 2")
>>> with progress.step("geometry", weight=0.5) as p:
...     with p.step("poses", weight=0.5) as q:
...         q.update(1.0, "registered")
>>> events[1], events[-3], events[-1]
(('decode', 0.25, 'frame 1 of 2'), ('geometry', 0.75, 'poses: registered'), ('geometry', 1.0, 'geometry: done'))
>>> sorted(progress.timings)
['decode', 'geometry']

The reported fraction is overall (0..1 of the whole run) and never goes
backwards. The stage of an event is the name of its top-level step.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

from pmvir.errors import CanceledError, ConfigError

#: report(stage, overall fraction in [0, 1], message)
ReportFn = Callable[[str, float, str], None]
#: should_cancel() -> True to stop at the next step or report
CancelFn = Callable[[], bool]

__all__ = ["CancelFn", "Progress", "ReportFn"]


class _Sink:
    """What every step of one run shares: the callback, the cancel check and the last fraction."""

    def __init__(self, report: ReportFn | None, should_cancel: CancelFn | None):
        self.report = report
        self.should_cancel = should_cancel
        self.last = 0.0

    def emit(self, stage: str, fraction: float, message: str) -> None:
        self.last = max(self.last, min(max(fraction, 0.0), 1.0))
        if self.report is not None:
            self.report(stage, self.last, message)


class Progress:
    """Fraction done, the current stage, cancellation and step timings of long work.

    Args:
        report: called as ``report(stage, overall_fraction, message)``; the
            fraction never decreases. None reports nothing.
        should_cancel: polled at every :meth:`step` start and :meth:`update`;
            returning True raises :class:`~pmvir.errors.CanceledError`.

    Attributes:
        timings: seconds per finished child step, by name.
    """

    def __init__(self, report: ReportFn | None = None, *, should_cancel: CancelFn | None = None):
        self._sink = _Sink(report, should_cancel)
        self._path: tuple[str, ...] = ()
        self._lo, self._hi = 0.0, 1.0
        self._done = 0.0
        self.timings: dict[str, float] = {}

    @classmethod
    def none(cls) -> Progress:
        """A progress object that reports nothing and never cancels."""
        return cls()

    @property
    def stage(self) -> str:
        """The top-level step this object belongs to ('' at the root)."""
        return self._path[0] if self._path else ""

    @property
    def path(self) -> tuple[str, ...]:
        """Names of the steps from the root down to this one."""
        return self._path

    def check_cancel(self, where: str = "") -> None:
        """Raise CanceledError if the caller asked to stop.

        Args:
            where: appended to the message (e.g. ``"at iteration 12"``).
        """
        should = self._sink.should_cancel
        if should is not None and should():
            inside = " / ".join(self._path) or "the run"
            raise CanceledError(f"canceled during {inside}" + (f" {where}" if where else ""))

    def update(self, fraction: float, message: str = "") -> None:
        """Report that ``fraction`` (0..1) of this step is done; checks cancellation first."""
        self.check_cancel()
        f = min(max(float(fraction), 0.0), 1.0)
        self._sink.emit(self.stage, self._lo + (self._hi - self._lo) * f, self._label(message))

    def log(self, message: str) -> None:
        """Report a message without moving the bar."""
        self._sink.emit(self.stage, self._sink.last, self._label(message))

    @contextmanager
    def step(self, name: str, weight: float = 0.0) -> Iterator[Progress]:
        """A timed child step taking ``weight`` (0..1) of this step's bar.

        The child's fractions map onto that slice; when the block ends without an
        exception the slice counts as done and its time is kept in :attr:`timings`.
        """
        if not 0.0 <= weight <= 1.0:
            raise ConfigError(f"step weight must be in [0, 1], got {weight}")
        self.check_cancel(f"before {name}")
        child = Progress.__new__(Progress)
        child._sink = self._sink
        child._path = (*self._path, name)
        width = self._hi - self._lo
        child._lo = self._lo + width * self._done
        child._hi = self._lo + width * min(1.0, self._done + weight)
        child._done = 0.0
        child.timings = {}
        t0 = time.perf_counter()
        child.update(0.0, "started" if len(child._path) > 1 else f"{name}: started")
        yield child
        self.timings[name] = time.perf_counter() - t0
        self._done = min(1.0, self._done + weight)
        self._sink.emit(child.stage, child._hi, self._label(f"{name}: done"))

    def iterate(self, items: list, message: Callable[[int, object], str] | None = None) -> Iterator:
        """Yield ``items``, reporting ``(k + 1) / len(items)`` after each (with ``message(k, item)``)."""
        n = max(len(items), 1)
        for k, item in enumerate(items):
            yield item
            self.update((k + 1) / n, message(k, item) if message is not None else f"{k + 1}/{len(items)}")

    def _label(self, message: str) -> str:
        below_stage = "/".join(self._path[1:])
        if not below_stage:
            return message
        return f"{below_stage}: {message}" if message else below_stage
