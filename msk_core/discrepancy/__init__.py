"""Where the model and the measurement disagree, which missing effect explains it, and how much the gap shrinks on
held-out trials once it is added (docs/discrepancy.md). Pure science: numpy only (the report and its plots:
:mod:`services.surfaces.reports.discrepancy`)."""

from msk_core.discrepancy.data import MAX_DELAY_S, SessionArrays, check_inputs, session_arrays
from msk_core.discrepancy.model import Candidate, candidate_library
from msk_core.discrepancy.select import BIC_MARGIN, MIN_REDUCTION, Selection, select_effects
from msk_core.discrepancy.workflow import DiscrepancyResult, run_discrepancy

__all__ = [
    "BIC_MARGIN",
    "Candidate",
    "DiscrepancyResult",
    "MAX_DELAY_S",
    "MIN_REDUCTION",
    "SessionArrays",
    "Selection",
    "candidate_library",
    "check_inputs",
    "run_discrepancy",
    "select_effects",
    "session_arrays",
]
