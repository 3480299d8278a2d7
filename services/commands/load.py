"""``msk load [KG] [--set N | --next-set] [--exercise PACK]``: change the session facts of a running ``msk live``.

Publishes one :class:`LoadEvent` on ``msk/<session>/load`` (the operator role's topic): the barbell load, the set
under way, the exercise and the athlete, starting from the facts in effect (which ``msk live`` keeps in its
announcement, services.discovery). The estimator applies the load from the next joint frame; views, dashboard,
recorder and report show the new facts. Without ``--connect``/``--zenoh-config`` it finds the session as the other
attach commands do (the only running one, or ``--session``).
"""

from __future__ import annotations

import argparse
import math
import sys
import time

from msk_core.errors import ConfigError
from msk_core.model.pack import available_packs, is_known_exercise
from services import discovery, messages, topics
from services.zenoh_session import (
    add_zenoh_arguments,
    declare_data_publisher,
    has_subscribers,
    open_session,
    options_from_args,
    publish,
)

#: How long to wait for a reader of the load topic (the recorder, the estimator) before publishing anyway.
READERS_TIMEOUT_S = 5.0
#: Time for the message to leave before the session closes.
FLUSH_S = 0.3


def new_facts(
    current: dict,
    *,
    load_kg: float | None,
    set_number: int | None,
    next_set: bool,
    exercise: str | None,
    athlete: str | None,
) -> messages.LoadEvent:
    """The LoadEvent that changes ``current`` (a session's facts: exercise, load_kg, set_number, athlete)."""
    if load_kg is not None and not (math.isfinite(load_kg) and load_kg >= 0):
        raise ConfigError("must be a finite mass >= 0 kg", field="KG", value=load_kg)
    if set_number is not None and set_number < 1:
        raise ConfigError("sets are counted from 1", field="--set", value=set_number)
    now = messages.now_ns()
    number = int(current.get("set_number", 0) or 0)
    if next_set:
        number += 1
    elif set_number is not None:
        number = set_number
    return messages.LoadEvent(
        barbell_mass_kg=float(load_kg if load_kg is not None else current.get("load_kg", 0.0)),
        exercise=exercise if exercise is not None else str(current.get("exercise", "")),
        set_number=number,
        athlete=athlete if athlete is not None else str(current.get("athlete", "")),
        device_time_ns=now,
        host_time_ns=now,
    )  # msk live maps the device clocks onto the host clock


def run(args: argparse.Namespace) -> int:
    if (
        args.load_kg is None
        and args.set is None
        and not args.next_set
        and args.exercise is None
        and args.athlete is None
    ):
        raise ConfigError("nothing to change: give KG, --set N, --next-set, --exercise or --athlete", field="KG")
    options, info = discovery.attach_options(options_from_args(args), args.session)
    session = args.session or (info.session if info is not None else None)
    if session is None:
        raise ConfigError(
            "no running msk live found (none announced in "
            f"{discovery.registry_dir()}); name the session and its endpoint with --session and --connect",
            field="--session",
        )
    if args.exercise is not None and not is_known_exercise(args.exercise):
        raise ConfigError(
            f"not a model pack (known: {', '.join(available_packs())})", field="--exercise", value=args.exercise
        )
    event = new_facts(
        info.facts if info is not None else {},
        load_kg=args.load_kg,
        set_number=args.set,
        next_set=args.next_set,
        exercise=args.exercise,
        athlete=args.athlete,
    )
    key = topics.load_key(session)
    with open_session(options) as zsession:
        publisher = declare_data_publisher(zsession, key, "msk.LoadEvent")
        deadline = time.monotonic() + READERS_TIMEOUT_S
        while not has_subscribers(publisher) and time.monotonic() < deadline:
            time.sleep(0.02)
        if not has_subscribers(publisher):
            print(
                f"msk load: waited {READERS_TIMEOUT_S:g} s for a reader of {key} at {discovery.where(options)}: "
                "0 readers; publishing anyway (is the session running?)",
                file=sys.stderr,
            )
        publish(publisher, event)
        time.sleep(FLUSH_S)
    print(
        f"msk load: {session}: {event.exercise or 'exercise unchanged'}, {event.barbell_mass_kg:g} kg, "
        f"set {event.set_number}" + (f", athlete {event.athlete}" if event.athlete else "") + f" -> {key}"
    )
    return 0


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "load", help="change load, set or exercise of a running session", description=__doc__
    )
    parser.add_argument("load_kg", nargs="?", type=float, default=None, metavar="KG", help="barbell mass in kg")
    parser.add_argument("--session", default=None, help="the session (default: the only running one)")
    number = parser.add_mutually_exclusive_group()
    number.add_argument("--set", type=int, default=None, metavar="N", help="the set under way now")
    number.add_argument("--next-set", action="store_true", help="the next set starts now")
    parser.add_argument("--exercise", default=None, metavar="PACK", help="the exercise (model pack) now under way")
    parser.add_argument("--athlete", default=None, help="who lifts")
    add_zenoh_arguments(parser)
    parser.set_defaults(handler=run)
