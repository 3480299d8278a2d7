"""``msk synth``: generate a synthetic gym session with known truth (msk_core.synth).

Writes trial TOMLs + OpenSim storage files (for ``msk calibrate/estimate/evaluate``), ``truth.json``, an MCAP
recording ``session.mcap`` in the project's topics, and (with ``--device-streams``) Trigno/Xsens replay files.

Examples::

    msk synth --exercise deadlift --subject-seed 7 --effects emd=0.06 --out out/dl
    msk synth --exercise both --reps 3 --loads bench_press=40,60 --loads deadlift=45,75 --out out/demo
"""

from __future__ import annotations

import argparse
from pathlib import Path

from msk_core.errors import ConfigError, parse_pairs
from msk_core.synth import Exercise, SynthConfig, generate_session, parse_effects, parse_exercise
from msk_core.synth.effects import DEFAULTS
from msk_core.synth.files import EmgOutput, write_session
from services.commands import described
from services.commands.progress import ProgressBar


def _loads(values: list[str], exercises: list[Exercise]) -> dict[Exercise, tuple[float, ...]]:
    out: dict[Exercise, tuple[float, ...]] = {}
    for text in values:
        name, sep, numbers = text.partition("=")
        if not sep:
            if len(exercises) != 1:
                raise ConfigError("with --exercise both, write --loads EXERCISE=KG,KG", field="--loads", value=text)
            exercise, numbers = exercises[0], name
        else:
            exercise = parse_exercise(name.strip())
        try:
            loads = tuple(float(x) for x in numbers.split(",") if x.strip())
        except ValueError:
            raise ConfigError("loads must be numbers in kg separated by commas", field="--loads", value=text) from None
        if not loads or any(not 0 <= x <= 400 for x in loads):
            raise ConfigError("give at least one load, each within [0, 400] kg", field="--loads", value=text)
        out[exercise] = loads
    return out


def register(subparsers: argparse._SubParsersAction) -> None:
    p = described(
        subparsers.add_parser("synth", help="generate a synthetic bench-press/deadlift session with known truth"),
        __doc__,
    )
    p.add_argument("--exercise", default="both", choices=["bench_press", "deadlift", "both"])
    p.add_argument("--subject-seed", type=int, default=7, help="seed of the synthetic subject and every noise stream")
    p.add_argument(
        "--effects",
        default="",
        help="comma list of hidden effects, NAME or NAME=VALUE; known: "
        + ", ".join(f"{k} (default {v:g})" for k, v in DEFAULTS.items())
        + "; all off by default",
    )
    p.add_argument("--reps", type=int, default=8, help="repetitions per load (default 8)")
    p.add_argument(
        "--loads",
        action="append",
        default=[],
        metavar="[EXERCISE=]KG,KG",
        help="barbell loads (default bench_press 20,40,50,60; deadlift 35,45,65,75)",
    )
    p.add_argument(
        "--emg-output",
        choices=[e.value for e in EmgOutput],
        default=EmgOutput.ENVELOPE.value,
        help="emg.sto content: MVC-ready zero-phase envelope at the kinematics rate (default) or raw 2 kHz",
    )
    p.add_argument("--no-mcap", action="store_true", help="skip the MCAP recording")
    p.add_argument("--mcap", type=Path, default=None, help="MCAP path (default OUT/session.mcap)")
    p.add_argument("--device-streams", action="store_true", help="also write Trigno/Xsens replay files under raw/")
    p.add_argument("--session", default="synth", help="session name in the MCAP topics (msk/<session>/...)")
    p.add_argument(
        "--pack",
        action="append",
        default=[],
        metavar="EXERCISE=PACK",
        help="model pack (name or JSON path, e.g. a subject-scaled pack) for an exercise",
    )
    p.add_argument("--out", required=True, type=Path, help="output directory")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    exercises = list(Exercise) if args.exercise == "both" else [parse_exercise(args.exercise)]
    if args.reps < 1 or args.reps > 50:
        raise ConfigError("must be within 1..50", field="--reps", value=args.reps)
    pairs = parse_pairs(args.pack, field="--pack", form="EXERCISE=PACK")
    packs: dict[Exercise, object] = {parse_exercise(name.strip()): pack.strip() for name, pack in pairs.items()}
    config = SynthConfig(
        subject_seed=args.subject_seed,
        n_reps=args.reps,
        effects=parse_effects(args.effects),
        loads_kg=_loads(args.loads, exercises) or None,
    )
    session = generate_session(exercises, config, packs=packs, progress=None if args.quiet else ProgressBar())
    truth = write_session(session, args.out, emg_output=EmgOutput(args.emg_output))
    written = [truth]
    # services-level exports import MCAP and driver code, which msk_core must not
    from services.sessions.synth_export import write_device_streams, write_mcap

    if not args.no_mcap:
        written.append(write_mcap(session, args.mcap or args.out / "session.mcap", session_name=args.session))
    if args.device_streams:
        write_device_streams(session, args.out)
    for ex in session.exercises:
        for t in ex.trials:
            print(
                f"{t.name}: {len(t.rep_starts)} reps, {t.time[-1]:.1f} s, peak |torque| "
                + ", ".join(f"{c} {abs(t.torque_id[:, i]).max():.0f}" for i, c in enumerate(t.coordinates))
                + " N·m"
                + (f", {t.fallback_frames} frames beyond capacity" if t.fallback_frames else "")
            )
    print(
        "wrote " + ", ".join(str(p) for p in written) + f" and trial folders under {args.out} (the lifts, and each "
        "MVC contraction as an isometric trial under <exercise>/mvc/<channel>)"
    )
    return 0
