"""A frame's flags: the EMG codes, and what every flag means in words. The session summary, the terminal view and the
dashboard say the words rather than the codes (the codes stay on the wire and in ``summary.json``).

Light on purpose (no numpy): the view and the dashboard import it at start. The solver flags are
:class:`msk_core.estimate.frame.FrameStatus` values; ``tests/test_metrics.py`` checks that every one has its words.
"""

from __future__ import annotations

FLAG_GAP = "emg_gap"
FLAG_STALLED = "emg_stalled"
FLAG_NO_MVC = "no_mvc"
FLAG_ELECTRODE_BAD = "electrode_bad"
FLAG_NOT_FINITE = "emg_not_finite"

MEANINGS: dict[str, str] = {
    "reserve": "torque beyond the muscles' capacity",
    "max_iter": "solver stopped at its iteration limit",
    "invalid_input": "unusable pose or torque",
    "solver_failed": "solver failed",
    FLAG_GAP: "EMG gap",
    FLAG_STALLED: "EMG late or stopped",
    FLAG_NO_MVC: "EMG without MVC",
    FLAG_ELECTRODE_BAD: "bad electrode left out",
    FLAG_NOT_FINITE: "EMG samples that were not numbers, taken as 0",
}


def flag_text(flag: str) -> str:
    """``flag`` in words (an unknown code as it is)."""
    return MEANINGS.get(flag, flag)


def flag_counts_text(counts: dict[str, int]) -> str:
    """e.g. ``"12 torque beyond the muscles' capacity (reserve), 3 EMG gap (emg_gap)"``; ``"none"``."""
    return ", ".join(f"{n} {flag_text(flag)} ({flag})" for flag, n in counts.items()) or "none"
