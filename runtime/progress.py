"""Progress, as every long call reports it: `progress(ProgressEvent(stage, done, total, unit, detail))`.

The library never prints; a caller that wants a bar passes a callback (the command lines pass one that draws
tqdm on stderr, cli/common.py `TerminalProgress`). The browser's `onProgress({stage, done, total})` is the same.
"""

from __future__ import annotations

from typing import Callable, NamedTuple


class ProgressEvent(NamedTuple):
    stage: str  # "render" (a reveal or view), "hide", "fit"
    done: int  # units done so far (can go back: a hide that solves a part again retracts it)
    total: int
    unit: str  # "ray", "px", "it" (fit steps) or "s" (a fit's seconds)
    detail: str = ""  # e.g. a fit's current loss


ProgressFn = Callable[[ProgressEvent], None]


class Counter:
    """Turns increments into ProgressEvents for `report` (None: counts silently)."""

    def __init__(self, report: ProgressFn | None, stage: str, total: int, unit: str, done: int = 0):
        self.report, self.stage, self.total, self.unit, self.done = report, stage, total, unit, done

    def __call__(self, increment: int, detail: str = "") -> None:
        self.done += increment
        if self.report is not None:
            self.report(ProgressEvent(self.stage, self.done, self.total, self.unit, detail))
