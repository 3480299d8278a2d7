"""The terminal progress bars of the long commands: a :data:`msk_core.progress.Progress` callback drawn with tqdm.

A helper of the command modules (it registers no command). msk_core reports ``(done, total, task)``; this draws one
bar per task on stderr, a new task closing the bar of the previous one.
"""

from __future__ import annotations

from tqdm import tqdm


class ProgressBar:
    """A :data:`msk_core.progress.Progress` callback: one tqdm bar per task. ``leave``: keep finished bars on screen
    (False for the many short per-trial runs of ``msk estimate`` and ``msk evaluate``)."""

    def __init__(self, *, leave: bool = True) -> None:
        self.leave = leave
        self._bar: tqdm | None = None
        self._task: str | None = None

    def __call__(self, done: int, total: int, task: str) -> None:
        if self._bar is None or task != self._task or done < self._bar.n:
            self.close()
            self._bar = tqdm(total=total, desc=task, leave=self.leave)
            self._task = task
        self._bar.update(done - self._bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
        self._bar, self._task = None, None
