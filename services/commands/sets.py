"""``msk set start|stop``: the operator starts the next set or ends the set under way, in a running ``msk live``.

Publishes one session fact (:class:`LoadEvent` with ``set_mark`` "start" or "stop") on ``msk/<session>/load``, as
``msk load`` does (the same facts in effect: load, exercise, athlete): the view, the dashboard, the recorder and the
report mark the set there (msk_core.signal.sets). Without an operator, sets start and end by rest detection; the
view's key (``s``/``e``) and the dashboard's buttons publish the same fact. Finds the session as the other attach
commands do (the only running one, or ``--session``/``--connect``).
"""

from __future__ import annotations

import argparse

from msk_core.errors import ConfigError
from services.commands.load import publish_facts
from services.sessions.facts import check_facts, new_facts
from services.transport.zenoh_session import add_zenoh_arguments


def run(args: argparse.Namespace) -> int:
    if args.set is not None and args.action != "start":
        raise ConfigError("a set number goes with start", field="--set", value=args.set)
    start = args.action == "start"
    check_facts(None, args.set)
    before: dict = {}  # the facts in effect before this mark, as the session announced them

    def mark(facts: dict):
        before.update(facts)
        return new_facts(
            facts,
            load_kg=None,
            set_number=args.set if start else None,
            next_set=start and args.set is None,
            exercise=None,
            athlete=None,
            set_mark=args.action,
        )

    session, event, key = publish_facts(args, mark, "msk set")
    if start:
        what = f"set {event.set_number} starts"
    elif before.get("resting"):  # as the session announced it: rest detection or a mark had ended the set already
        what = f"no set was under way (set {before.get('set_number', event.set_number)} had ended): nothing changes"
    else:
        what = "the set under way ends"
    print(f"msk set: {session}: {what} ({event.barbell_mass_kg:g} kg) -> {key}")
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "set", help="start the next set or end the set under way in a running session", description=__doc__
    )
    parser.add_argument("action", choices=["start", "stop"], help="start: the next set starts now; stop: it ends now")
    parser.add_argument("--set", type=int, default=None, metavar="N", help="with start: the set's number")
    parser.add_argument("--session", default=None, help="the session (default: the only running one)")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=run)
