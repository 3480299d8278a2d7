"""``msk load [KG] [--set N | --next-set] [--exercise PACK]``: change the session facts of a running ``msk live``.

Publishes one :class:`LoadEvent` on ``msk/<session>/load`` (the operator role's topic): the barbell load, the set
under way, the exercise and the athlete, starting from the facts in effect (which ``msk live`` keeps in its
announcement, services.sessions.discovery). The estimator applies the load from the next joint frame; views, dashboard,
recorder and report show the new facts. Without ``--connect``/``--zenoh-config`` it finds the session as the other
attach commands do (the only running one, or ``--session``).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable

from msk_core.errors import ConfigError
from msk_core.model.pack import available_packs, is_known_exercise
from services.sessions import discovery
from services.sessions.facts import check_facts, new_facts
from services.transport import messages, topics
from services.transport.zenoh_session import (
    SessionUnavailable,
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


def run(args: argparse.Namespace) -> int:
    if (
        args.load_kg is None
        and args.set is None
        and not args.next_set
        and args.exercise is None
        and args.athlete is None
    ):
        raise ConfigError("nothing to change: give KG, --set N, --next-set, --exercise or --athlete", field="KG")
    check_facts(args.load_kg, args.set)  # before looking for the session: a bad value is said as such
    if args.exercise is not None and not is_known_exercise(args.exercise):
        raise ConfigError(
            f"not a model pack (known: {', '.join(available_packs())})", field="--exercise", value=args.exercise
        )
    session, event, key = publish_facts(
        args,
        lambda facts: new_facts(
            facts,
            load_kg=args.load_kg,
            set_number=args.set,
            next_set=args.next_set,
            exercise=args.exercise,
            athlete=args.athlete,
        ),
        "msk load",
        complete=args.load_kg is not None and args.set is not None and args.exercise is not None,
    )
    print(
        f"msk load: {session}: {event.exercise or 'exercise unchanged'}, {event.barbell_mass_kg:g} kg, "
        f"set {event.set_number}" + (f", athlete {event.athlete}" if event.athlete else "") + f" -> {key}"
    )
    return 0


def publish_facts(
    args: argparse.Namespace,
    make_event: Callable[[dict], messages.LoadEvent],
    command: str,
    *,
    complete: bool = False,
) -> tuple[str, messages.LoadEvent, str]:
    """Find the session (``--session``, ``--connect``: as every attach command), make the LoadEvent from the facts in
    effect and publish it on ``msk/<session>/load``, waiting (bounded) for a reader; (session, event, key).

    ``complete``: the command gives every fact itself, so it may go where the facts in effect are unknown (a session
    that msk live does not announce on this machine); otherwise that is refused, since the event made from no facts
    would say no load and set 0 (the bar off, the set ended)."""
    options, info = discovery.attach_options(options_from_args(args), args.session, one_shot=True)
    session = args.session or (info.session if info is not None else None)
    if session is None:
        raise ConfigError(
            "no running msk live found (none announced in "
            f"{discovery.registry_dir()}); name the session and its endpoint with --session and --connect",
            field="--session",
        )
    from services.transport.roles import facts_refusal

    reason = facts_refusal(options.role, session)
    if reason is not None:
        raise ConfigError(
            f"{command} cannot change the session's facts: {reason} (the operator's config may: "
            "OUT/zenoh/operator.json5 of the secured msk live)",
            path=options.config_file,
            field="--zenoh-config",
        )
    facts = info.facts if info is not None else discovery.announced_facts(session)
    if not facts and not complete:
        raise ConfigError(
            f"{command} starts from the facts in effect (load, set, exercise, athlete), and session {session!r} does "
            f"not announce them on this machine (msk live writes them to OUT/session.json where it runs): run "
            f"{command} there, or give every fact: msk load KG --set N --exercise PACK",
            field="--session",
            value=session,
        )
    event = make_event(facts or {})
    key = topics.load_key(session)
    try:
        opened = open_session(options)
    except SessionUnavailable as error:  # a client whose endpoint nobody answers
        where = ", ".join(options.connect) or (str(options.config_file) if options.config_file else "the default")
        raise ConfigError(
            f"cannot reach session {session!r} at {where} ({error.reason}); is it running? "
            f"(running sessions are announced in {discovery.registry_dir()})",
            field="--session",
            value=session,
        ) from None
    with opened as zsession:
        publisher = declare_data_publisher(zsession, key, "msk.LoadEvent")
        deadline = time.monotonic() + READERS_TIMEOUT_S
        while not has_subscribers(publisher) and time.monotonic() < deadline:
            time.sleep(0.02)
        if not has_subscribers(publisher):
            print(
                f"{command}: waited {READERS_TIMEOUT_S:g} s for a reader of {key} at {discovery.where(options)}: "
                "0 readers; publishing anyway (is the session running?)",
                file=sys.stderr,
            )
        publish(publisher, event)
        time.sleep(FLUSH_S)
    return session, event, key


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
