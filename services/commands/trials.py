"""``msk trials RECORDING --out DIR --mvc-set N | --mvc-from FILE``: calibration trials from a recorded session.

A lab's first session with an athlete runs `msk live` without a profile (static optimisation only; the EMG is
recorded). This turns that recording into the trial files `msk calibrate` reads, one folder per set
(``DIR/set<N>/trial.toml`` with ``ik.sto``, the joint angles, and ``emg.sto``, the raw EMG on the same clock): then
``msk calibrate --pack PACK --trial DIR --out athlete.json``, and later sessions use that profile.

The EMG needs each electrode's MVC: record each muscle's maximal voluntary contraction as a set of its own (``msk set
start`` / ``msk set stop`` around it) and name those sets with ``--mvc-set`` (they are not exported as lift trials), or
take the divisors of an earlier profile or trial with ``--mvc-from``. The electrode map is the session file's
``[electrodes]`` (``--session-file``, the file `msk live` ran); without one, the channels of the ``--mvc-from``
profile (e.g. OUT/subject_session.json), else channels named as the pack's groups. Details: services/surfaces/trial_export.py.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from services.commands import described


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = described(
        subparsers.add_parser("trials", help="calibration trial files from a recorded session (one per set)"), __doc__
    )
    parser.add_argument("recording", type=Path, help="MCAP recording of `msk live` (OUT/session.mcap)")
    parser.add_argument("--out", type=Path, required=True, help="folder for the trial folders (set<N>/)")
    parser.add_argument("--session-file", type=Path, default=None, help="the session file `msk live` ran")
    parser.add_argument("--pack", default=None, help="model pack (default: the session file's)")
    parser.add_argument("--mvc-set", type=int, action="append", default=[], help="a set that was an MVC effort")
    parser.add_argument("--mvc-from", type=Path, default=None, help="MVC divisors of a profile JSON or trial TOML")
    parser.add_argument("--session", default=None, help="the session of a recording that holds several")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    from msk_core.errors import ConfigError
    from msk_core.model import load_pack
    from services.commands.estimate import output_folder
    from services.sessions.live_session import load_session_file
    from services.surfaces.trial_export import export_trials, given_divisors, profile_electrodes

    if args.mvc_set and args.mvc_from:
        raise ConfigError("give either MVC sets or --mvc-from, not both", field="--mvc-from", value=str(args.mvc_from))
    live = None if args.session_file is None else load_session_file(args.session_file, require_devices=False)
    pack_name = args.pack or (live.pack if live is not None else None)
    if pack_name is None:
        raise ConfigError("which pack: give --pack, or the session file (--session-file)", field="--pack")
    pack = load_pack(pack_name)
    mvc = None if args.mvc_from is None else given_divisors(args.mvc_from)
    if live is not None and live.electrodes:
        electrodes = dict(live.electrodes)
    else:  # the --mvc-from profile's channels and groups
        electrodes = {} if args.mvc_from is None else profile_electrodes(args.mvc_from)
    output_folder(args.out, "--out")
    trials = export_trials(
        args.recording,
        args.out,
        pack,
        electrodes=electrodes,
        mvc_sets=tuple(args.mvc_set),
        mvc=mvc,
        session=args.session,
    )
    for trial in trials:
        print(f"{trial.path}: {trial.window.name}, {trial.frames} joint frames, {trial.emg_channels} electrodes")
    print(f"calibrate: msk calibrate --pack {pack.name} --trial {args.out} --out athlete.json")
    return 0
