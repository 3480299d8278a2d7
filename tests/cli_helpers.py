"""Shared by the tests that call the ``msk`` command line in their own process (``services.cli.main``): the argument
lists several of them build."""

from __future__ import annotations

from pathlib import Path


def discrepancy_argv(pack: str, subject: Path, trial: Path, holdout: Path, *options: str) -> list[str]:
    """``msk discrepancy`` on one training and one held-out trial, then ``options`` (--report, --out, ...)."""
    return [
        "discrepancy",
        "--pack",
        pack,
        "--subject",
        str(subject),
        "--trial",
        str(trial),
        "--holdout",
        str(holdout),
        *options,
    ]
