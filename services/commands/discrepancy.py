"""``msk discrepancy``: where the model and the measurement disagree, the missing effect named, added to the subject
profile, and the gap shrinking on held-out trials (docs/discrepancy.md)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from msk_core.errors import ConfigError
from services.commands.progress import ProgressBar


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "discrepancy",
        help="find what the model is missing (candidate effects scored on held-out trials), add it to the profile",
        description="Torque and activation gaps per sample, where they concentrate, a library of candidate effects "
        "fitted on the training trials and scored on the held-out trials; writes DIR/summary.json, "
        "DIR/report.md with plots and, with --out, the subject profile with the named effect(s).",
    )
    p.add_argument("--pack", required=True, help="model pack name or path")
    p.add_argument("--subject", required=True, type=Path, help="calibrated subject profile JSON")
    p.add_argument("--trial", action="append", required=True, type=Path, help="training trial TOML (repeatable)")
    p.add_argument(
        "--holdout",
        action="append",
        required=True,
        type=Path,
        help="held-out trial TOML (repeatable; needs measured torques)",
    )
    p.add_argument("--report", required=True, type=Path, help="output directory (summary.json, report.md, PNGs)")
    p.add_argument("--out", type=Path, default=None, help="write the profile with the named effect(s) here")
    p.add_argument(
        "--max-effects", type=int, default=1, help="greedy forward selection: up to this many effects (default 1)"
    )
    p.add_argument(
        "--recalibrate",
        action="store_true",
        help="fit the muscle- and joint-state candidates (passive force, passive joint moment, damping, "
        "active force-length, force-velocity) and the delay with a re-calibration of the training trials that has "
        "them in it (the delay: the EMG shifted by it), against the model without them re-calibrated the same way: "
        "for profiles whose calibration took such an effect into the strengths (groups at their bounds); costs one "
        "calibration per such candidate and step",
    )
    p.set_defaults(handler=run_discrepancy_command)


def run_discrepancy_command(args: argparse.Namespace) -> int:
    from msk_core.discrepancy.data import describe_left_out
    from msk_core.discrepancy.workflow import run_discrepancy
    from msk_core.estimate.profile import SubjectProfile
    from msk_core.model import load_pack
    from services.commands.estimate import load_trials, output_folder, refuse_in_sample
    from services.surfaces.reports.discrepancy import consistency_sentences, write_report

    if args.max_effects < 1:
        raise ConfigError("must be >= 1", field="--max-effects", value=args.max_effects)
    refuse_in_sample(args.trial, args.holdout, "--holdout")
    pack = load_pack(args.pack)
    profile = SubjectProfile.load(args.subject)
    train, holdout = load_trials(args.trial, pack), load_trials(args.holdout, pack)
    computed = [t.name for t in train if t.torque_source != "file"]
    if computed:  # the held-out trials' torques are measured ones: the gap then mixes two sources of torque
        print(
            f"note: the torques of training trial(s) {', '.join(computed)} are the pack's inverse dynamics, those of "
            "the held-out trials an inverse-dynamics file: a gap between the two sources adds to the one searched "
            "(give the training trials their `torques` file)",
            file=sys.stderr,
        )
    output_folder(args.report, "--report")
    result = run_discrepancy(
        pack,
        profile,
        train,
        holdout,
        max_effects=args.max_effects,
        progress=ProgressBar(),
        recalibrate=args.recalibrate,
    )
    report = write_report(result, args.report)
    s = result.summary
    effect = s["effect"] if isinstance(s["effect"], str) else ", ".join(s["effect"])
    print(f"named effect: {effect}")
    print(f"held-out RMS torque gap (fraction of capacity): before {s['gap_before']:.4f}, after {s['gap_after']:.4f}")
    if "activation_gap_before" in s:
        print(
            f"held-out RMS activation gap: before {s['activation_gap_before']:.4f}, "
            f"after {s['activation_gap_after']:.4f}"
        )
    for sentence in consistency_sentences(s):  # how sure, rep by rep (docs/discrepancy.md, Outputs)
        print(sentence)
    for c in s["candidates"][:5]:
        reps = c.get("holdout_reps") or {}
        print(
            f"  {c['effect']:16s} held-out reduction {c['holdout_mse_reduction']:+7.1%}  "
            f"reps improved {reps.get('improved', 0)}/{reps.get('reps', 0)}  dBIC train "
            f"{c['delta_bic_train']:8.1f}  held-out -2lnLR {c['minus2_ln_lr_holdout']:8.1f}  BIC {c['holdout_bic']:8.1f}  "
            f"{c['reason']}"
        )
    for trial, why in (s.get("frames_left_out") or {}).items():
        print(f"frames left out of {trial}: {describe_left_out(why)}")
    if s["calibration_at_bounds"]:
        _say_bounds(s, recalibrated=args.recalibrate)
    if args.out is not None:
        if result.profile_with_effects is None:
            print(f"no effect named: {args.out} not written (the profile stays as it is)")
        else:
            result.profile_with_effects.save(args.out)
            print(f"wrote {args.out}")
    print(f"wrote {report}")
    return 0


def _say_bounds(s: dict, *, recalibrated: bool) -> None:
    """The calibration's strengths at their bounds, and what re-calibrating could do about them."""
    print(
        "calibration strengths at their bounds (look at these coordinates first): "
        + ", ".join(
            f"{b['group']} {b['scale']:.2f} ({b['side']}; {'/'.join(b['coordinates'])})"
            for b in s["calibration_at_bounds"]
        )
    )
    if not recalibrated and s["effect"] == "none":
        print(
            "  the calibration may have taken a passive moment, damping or a force-length/velocity effect into "
            "these strengths: --recalibrate fits those candidates with a calibration that has them in it"
        )
    elif not recalibrated and "emd" in ([s["effect"]] if isinstance(s["effect"], str) else s["effect"]):
        named = s["parameters"].get("emd", s["parameters"])  # keyed by effect when several are named
        print(
            "  these strengths were calibrated at another delay than the one named, and the re-fit here cannot "
            "undo that: --recalibrate calibrates again with the EMG shifted by it (or msk calibrate --emd "
            f"{named.get('delay_total_s', 0.0):.3f})"
        )
