"""The terminal progress bars of the long commands: a :data:`msk_core.progress.Progress` callback drawn with tqdm.

A helper of the command modules (it registers no command). msk_core reports ``(done, total, task)``; this draws one
bar per task on stderr, a new task closing the bar of the previous one.
On a stream that is not a terminal (a log file, a CI job), where a bar's carriage returns pile up into one long line,
each task is one line when it starts and one when it ends, with its count and time.
"""

from __future__ import annotations

import sys
import time

from tqdm import tqdm


class ProgressBar:
    """A :data:`msk_core.progress.Progress` callback: one tqdm bar per task. ``leave``: keep finished bars on screen
    (False for the many short per-trial runs of ``msk estimate`` and ``msk evaluate``)."""

    def __init__(self, *, leave: bool = True) -> None:
        self.leave = leave
        self._bar: tqdm | None = None
        self._task: str | None = None
        self._lines = not sys.stderr.isatty()
        self._started = 0.0
        self._done = 0

    def __call__(self, done: int, total: int, task: str) -> None:
        if self._lines:
            self._line(done, total, task)
            return
        if self._bar is None or task != self._task or done < self._bar.n:
            self.close()
            self._bar = tqdm(total=total, desc=task, leave=self.leave)
            self._task = task
        self._bar.update(done - self._bar.n)
        if done >= total:
            self.close()

    def _line(self, done: int, total: int, task: str) -> None:
        if task != self._task or done < self._done:
            self.close()
            print(f"{task}: {total} ...", file=sys.stderr, flush=True)
            self._task, self._started = task, time.monotonic()
        self._done = done
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._lines and self._task is not None:
            seconds = time.monotonic() - self._started
            print(f"{self._task}: {self._done} done in {seconds:.1f} s", file=sys.stderr, flush=True)
        if self._bar is not None:
            self._bar.close()
        self._bar, self._task, self._done = None, None, 0
