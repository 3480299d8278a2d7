"""Options of the estimator that several command lines share: the estimator node's, ``msk live``'s, ``msk estimate``'s
and ``msk evaluate``'s. argparse only, so a command that takes them does not import the node (zenoh, the live EMG
path) at start-up."""

from __future__ import annotations

import argparse


def add_live_synergists_argument(parser: argparse.ArgumentParser) -> None:
    """``--live-synergists on|off``, as the estimator node, ``msk live``, ``msk estimate`` and ``msk evaluate`` read it."""
    parser.add_argument(
        "--live-synergists",
        choices=["on", "off"],
        default="on",
        help="assisted: a group without EMG whose measured synergist (most similar moment arms) has a live envelope "
        "follows it, scaled to its own prior level and weighted by the error that hypothesis shows between the "
        "measured synergists (docs/estimation.md, 'Live EMG and assisted'); default on",
    )


#: The per-frame QP paths (docs/estimation.md, "Solvers and dynamics").
SOLVERS = ("active-set", "piqp")


def add_solver_argument(parser: argparse.ArgumentParser, *, default: str | None = "active-set") -> None:
    """``--solver active-set|piqp``, as the estimator node, ``msk live`` (``default`` None: the session file's),
    ``msk estimate`` and ``msk evaluate`` read it."""
    parser.add_argument(
        "--solver",
        choices=SOLVERS,
        default=default,
        help="per-frame QP: the compiled active-set hot start, certified by its KKT conditions, with PIQP when it "
        "cannot certify (default), or the warm PIQP on every frame (docs/estimation.md, 'Solvers and dynamics')",
    )
