"""``msk bench discrepancy-recalibrate``: the synthetic detection matrix of ``msk bench discrepancy`` (every hidden
effect one at a time, three subject seeds, both exercises, at stated, default and large sizes and with the heavier load
training; no effect over eight seeds) with ``msk discrepancy --recalibrate``: how often the right effect is named, its
share of the attainable held-out shrink (the restated targets) and "none" on every effect-free session. Apart from
``msk bench discrepancy`` because it takes about twice as long (21 min against 9 on 2 cores, 28 Nov 2026), and it is
what decides whether the flag should be the default (docs/discrepancy.md, "Re-calibration")."""

from __future__ import annotations

import dataclasses

from services.bench import BenchResult
from services.bench.discrepancy import synthetic_matrix

NAME = "discrepancy-recalibrate"
DESCRIPTION = "the synthetic detection matrix of msk bench discrepancy with msk discrepancy --recalibrate"


def run(quick: bool) -> list[BenchResult]:
    results, _ = synthetic_matrix(quick, recalibrate=True)
    return [dataclasses.replace(r, name=f"--recalibrate: {r.name}") for r in results]
