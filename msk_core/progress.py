"""Progress of long offline computations, reported by callback: msk_core counts its steps, the caller shows them.

msk_core draws no progress bar (it is the science layer); the command line turns a :data:`Progress` callback into a
terminal bar (``services.commands.progress``).
"""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterator
from typing import TypeAlias, TypeVar

#: ``progress(done, total, task)``: ``done`` of the ``total`` steps of ``task`` are finished; ``task`` is a short
#: label naming the work and, in brackets, what a step is. Called with ``done = 0`` when a task starts.
Progress: TypeAlias = Callable[[int, int, str], None]

T = TypeVar("T")


def counted(items: Collection[T], progress: Progress | None, task: str) -> Iterator[T]:
    """The items in order, reporting ``progress(k, len(items), task)`` once the first ``k`` are done."""
    if progress is None:
        yield from items
        return
    total = len(items)
    progress(0, total, task)
    for done, item in enumerate(items, start=1):
        yield item
        progress(done, total, task)
