"""Benchmarks run by ``msk bench``. Each module here defines ``NAME``, ``DESCRIPTION`` and
``run(quick: bool) -> list[BenchResult]``; they are discovered, so adding one never edits a shared list.

Figures are reported as ratios against a baseline measured in the same run, because the machines are shared and noisy.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class BenchResult:
    """One measured figure next to its same-run baseline."""

    name: str
    value: float
    unit: str
    baseline_name: str = ""
    baseline_value: float = float("nan")
    target: str = ""
    passed: bool | None = None
    details: dict[str, float | str] = field(default_factory=dict)

    @property
    def ratio(self) -> float:
        """baseline / value for times (higher is better), as printed."""
        if not self.baseline_value or self.baseline_value != self.baseline_value:
            return float("nan")
        return self.baseline_value / self.value if self.value else float("inf")
