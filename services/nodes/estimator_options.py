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
