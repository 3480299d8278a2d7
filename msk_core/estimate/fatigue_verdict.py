"""When a muscle reads as tiring: the verdict on an electrode's fatigue index over a set
(:class:`msk_core.estimate.live_fatigue.ElectrodeFatigueReport`), the rule every surface colours. Apart from the
fatigue tracking so that a page reads it without the signal chain's imports (scipy.signal: ~0.7 s)."""

from __future__ import annotations

import math

#: A muscle reads as tiring once its median frequency has fallen this much since the set's first reps ...
TIRING_CHANGE_PCT = -10.0
#: ... over at least this many reps, with a falling trend beyond two standard errors of its slope: two reps'
#: difference is rep-to-rep scatter (it lit the dashboard amber after 2 reps of a simulated set that does not tire)
TIRING_MIN_REPS = 3


def tiring(median_hz: list[float], slope_hz_per_rep: float, slope_se_hz_per_rep: float, change_pct: float) -> bool:
    """Whether an electrode's median frequency says its muscle tires over the set (the rule the surfaces colour)."""
    reps = sum(1 for v in median_hz if math.isfinite(v))
    falling = math.isfinite(slope_hz_per_rep) and (
        not math.isfinite(slope_se_hz_per_rep) or slope_hz_per_rep + 2.0 * slope_se_hz_per_rep < 0.0
    )
    return bool(reps >= TIRING_MIN_REPS and math.isfinite(change_pct) and change_pct <= TIRING_CHANGE_PCT and falling)
