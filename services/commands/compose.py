"""``msk compose``: check that docker-compose.yml and docker-compose.secure.yml are what the declared session graph
generates (exit 1 and the differences otherwise), or rewrite them with ``--write``.

    msk compose            # in CI: fails when a compose file and services/transport/session_graph.py disagree
    msk compose --write    # after changing the graph or services/sessions/deploy_files.py

Which services exist and which role's config each secured service presents come from services/transport/session_graph.py;
the services' arguments, volumes and ports from services/sessions/deploy_files.py.
"""

from __future__ import annotations

import argparse

from services.commands import described


def register(subparsers: argparse._SubParsersAction) -> None:
    from services.sessions import deploy_files

    parser = described(
        subparsers.add_parser("compose", help="check or --write the compose files from the session graph"), __doc__
    )
    deploy_files.add_arguments(parser)
    parser.set_defaults(handler=deploy_files.run)
