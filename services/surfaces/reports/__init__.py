"""Report files people read after an offline command: Markdown, JSON and PNG plots (matplotlib, headless).

- :mod:`services.surfaces.reports.evaluation`: ``msk evaluate`` (scores per trial and method, activation and torque plots);
- :mod:`services.surfaces.reports.discrepancy`: ``msk discrepancy`` (named effect, candidates, gap plots);
- :mod:`services.surfaces.reports.demo`: ``msk demo`` (calibrated strength and the held-out trials' live activations
  against the generator's truth).

The numbers come from msk_core, which draws and writes nothing.
"""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any


def pyplot() -> ModuleType:
    """matplotlib.pyplot on the file-only Agg backend (no display needed); imported on first use, as it is slow."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path, dpi: int) -> Path:
    """Write ``fig`` (laid out tight) as the PNG ``path`` at ``dpi`` and close it, freeing its memory; returns
    ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    pyplot().close(fig)
    return path
