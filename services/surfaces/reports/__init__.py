"""Report files people read after an offline command: Markdown, JSON and PNG plots (matplotlib, headless).

- :mod:`services.surfaces.reports.evaluation`: ``msk evaluate`` (scores per trial and method, activation and torque plots);
- :mod:`services.surfaces.reports.discrepancy`: ``msk discrepancy`` (named effect, candidates, gap plots);
- :mod:`services.surfaces.reports.strength`: calibrated strength against the generator's truth (``msk demo``).

The numbers come from msk_core, which draws and writes nothing.
"""

from __future__ import annotations

from types import ModuleType


def pyplot() -> ModuleType:
    """matplotlib.pyplot on the file-only Agg backend (no display needed); imported on first use, as it is slow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
