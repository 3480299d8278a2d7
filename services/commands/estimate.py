"""``msk calibrate``, ``msk estimate``, ``msk evaluate``: the seed method over trial files (see docs/estimation.md)."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from msk_core.errors import ConfigError, InputError
from msk_core.estimate.flags import flag_counts_text
from services.commands.progress import ProgressBar
from services.nodes.estimator_options import add_live_synergists_argument, add_solver_argument


def register(subparsers: argparse._SubParsersAction) -> None:
    cal = subparsers.add_parser(
        "calibrate",
        help="calibrate a subject profile (F_max per group, priors) from training trials",
        description="Calibrate per-group strength and the phase prior from training trials (TOML) with EMG.",
    )
    cal.add_argument("--pack", required=True, help="model pack name or path")
    cal.add_argument(
        "--trial",
        action="append",
        required=True,
        type=Path,
        help="training trial TOML (repeatable), or a folder: every trial.toml under it (e.g. the "
        "isometric MVC trials of msk synth's <exercise>/mvc)",
    )
    cal.add_argument("--out", required=True, type=Path, help="subject profile JSON to write")
    add_calibration_arguments(cal)
    cal.set_defaults(handler=run_calibrate)

    est = subparsers.add_parser(
        "estimate",
        help="estimate activations of a trial, frame by frame",
        description="Per-frame activation estimation over a trial; writes activations and torques as OpenSim .sto.",
    )
    est.add_argument("--pack", required=True, help="model pack name or path")
    est.add_argument("--subject", type=Path, default=None, help="subject profile JSON (needed for proposed/prior)")
    est.add_argument("--trial", required=True, type=Path, help="trial TOML")
    est.add_argument("--method", choices=["proposed", "so", "hybrid", "prior"], default="proposed")
    est.add_argument(
        "--out",
        required=True,
        type=Path,
        help="activations .sto (torques go to <stem>_torques.sto, Laplace std to <stem>_std.sto)",
    )
    add_solver_arguments(est)
    est.set_defaults(handler=run_estimate)

    ev = subparsers.add_parser(
        "evaluate",
        help="compare methods against measured EMG and torques; write a report with plots",
        description="Activation RMSE per method and trial, torque tracking, plots; markdown + PNG + JSON. With "
        "--leave-out: for each group with an electrode, calibrate without it (--train trials, calibration settings "
        "as msk calibrate's) and score its estimate on the held-out trials (summary.json, report.md, a plot per "
        "group), beside the paper's protocol (every electrode in calibration, none at estimation).",
    )
    ev.add_argument("--pack", required=True, help="model pack name or path")
    ev.add_argument("--subject", type=Path, default=None, help="subject profile JSON (not with --leave-out)")
    ev.add_argument(
        "--trial", action="append", required=True, type=Path, help="evaluation (held-out) trial TOML (repeatable)"
    )
    ev.add_argument("--report", required=True, type=Path, help="output directory")
    ev.add_argument(
        "--leave-out",
        action="append",
        default=[],
        metavar="all|GROUP",
        help="leave-one-electrode-out: every group with an electrode (all) or the named ones (repeatable, or "
        "comma-separated); needs --train",
    )
    ev.add_argument(
        "--train",
        action="append",
        default=[],
        type=Path,
        help="training trial TOML or folder for the leave-out calibrations (repeatable)",
    )
    add_solver_arguments(ev)
    add_calibration_arguments(ev)
    ev.set_defaults(handler=run_evaluate)


def add_calibration_arguments(parser: argparse.ArgumentParser) -> None:
    """The calibration settings (``msk calibrate``; ``msk evaluate --leave-out`` calibrates with the same ones)."""
    parser.add_argument("--alpha", type=float, default=0.5, help="lower bound of the strength factors (default 0.5)")
    parser.add_argument("--beta", type=float, default=2.5, help="upper bound of the strength factors (default 2.5)")
    parser.add_argument("--bins", type=int, default=20, help="phase bins of the prior (default 20)")
    parser.add_argument(
        "--calibrate",
        choices=["emg", "all"],
        default="emg",
        help="which groups get a strength factor (default: those with EMG)",
    )
    parser.add_argument(
        "--strength-prior-std",
        type=float,
        default=0.3,
        help="N(1, s^2) prior on each calibrated strength factor (default 0.3; 0 = off)",
    )
    parser.add_argument(
        "--identify-max-std",
        type=float,
        default=0.15,
        help="a strength factor whose data-only relative Laplace std exceeds this is reported "
        "unidentified (default 0.15; 0 = off)",
    )
    parser.add_argument(
        "--emd",
        default="auto",
        metavar="auto|SECONDS",
        help="electromechanical delay applied to the EMG: estimated from the trials (auto, default) or "
        "given in seconds (0 = none)",
    )
    parser.add_argument(
        "--identify",
        choices=["report", "shrink", "truncate"],
        default="report",
        help="strength directions the data do not determine: report only (plain MAP, default), shrink "
        "to the reference (strength prior weighed by the residuals' autocorrelation time) or "
        "truncate (set to the reference); see docs/estimation.md",
    )
    parser.add_argument(
        "--emg-relative-std",
        type=float,
        default=0.1,
        help="EMG noise grows with the envelope: std = sqrt(0.05^2 + (r e)^2) (default r = 0.1; 0 = constant 0.05)",
    )
    parser.add_argument(
        "--no-emg-prior",
        choices=["min_effort", "synergist", "wide"],
        default="min_effort",
        help="prior of groups without EMG: static optimisation's share over the reps (default), the "
        "measured group with the most similar moment arms, or the wide N(0, 0.5^2)",
    )
    parser.add_argument(
        "--synergist",
        action="append",
        default=[],
        metavar="GROUP=MEASURED",
        help="explicit prior source for a group without EMG (repeatable; overrides --no-emg-prior)",
    )
    parser.add_argument(
        "--no-emg-strength",
        choices=["reference", "measured", "synergist"],
        default="reference",
        help="strength of groups without EMG in the profile: the pack's reference (default), the measured "
        "groups' common calibrated factor, or the factor of the measured group with the most similar moment arms "
        "(else the common one); with the minimal-effort prior re-derived at those strengths",
    )


def calibration_options(args: argparse.Namespace) -> dict[str, Any]:
    """The calibration settings of :func:`add_calibration_arguments`, checked, as keyword arguments of
    :func:`msk_core.estimate.pipeline.calibrate_subject` (and :func:`msk_core.estimate.leave_out.leave_one_out`)."""
    from msk_core.estimate.calibrate import CalibrationSettings
    from msk_core.estimate.pipeline import PriorSettings

    if args.bins < 2:
        raise ConfigError("need at least 2 phase bins", field="--bins", value=args.bins)
    synergists = {}
    for item in args.synergist:
        group, sep, measured = item.partition("=")
        if not sep or not group or not measured:
            raise ConfigError("expected GROUP=MEASURED_GROUP", field="--synergist", value=item)
        synergists[group.strip()] = measured.strip()
    if not args.strength_prior_std >= 0:
        raise ConfigError("must be >= 0 (0 = off)", field="--strength-prior-std", value=args.strength_prior_std)
    if not args.identify_max_std >= 0:
        raise ConfigError("must be >= 0 (0 = off)", field="--identify-max-std", value=args.identify_max_std)
    if not args.emg_relative_std >= 0:
        raise ConfigError(
            "must be >= 0 (0 = constant EMG noise)", field="--emg-relative-std", value=args.emg_relative_std
        )
    settings = CalibrationSettings(
        strength_bounds=(args.alpha, args.beta),
        calibrate=args.calibrate,
        strength_prior_std=args.strength_prior_std or None,
        identify_max_std=args.identify_max_std or None,
        identify=args.identify,
        emg_relative_std=args.emg_relative_std or None,
    )
    if args.emd == "auto":
        emd_s: float | str = "auto"
    else:
        try:
            emd_s = float(args.emd)
        except ValueError:
            raise ConfigError("expected 'auto' or a delay in seconds", field="--emd", value=args.emd) from None
        if not 0 <= emd_s <= 0.5:
            raise ConfigError("must be in [0, 0.5] s", field="--emd", value=args.emd)
    return {
        "settings": settings,
        "prior_settings": PriorSettings(n_bins=args.bins, no_emg=args.no_emg_prior, synergists=synergists),
        "emd_s": emd_s,
        "no_emg_strength": args.no_emg_strength,
    }


def add_solver_arguments(parser: argparse.ArgumentParser) -> None:
    """The numerical paths of the per-frame estimate (docs/estimation.md, "Solvers and dynamics")."""
    add_solver_argument(parser)
    parser.add_argument(
        "--dynamics",
        choices=["compiled", "pinocchio"],
        default="pinocchio",
        help="moment arms and inverse dynamics: numpy + pinocchio (default offline) or the compiled "
        "numba kernels (the live node's default); they agree to ~1e-13",
    )
    parser.add_argument(
        "--activation-bounds",
        choices=["unit", "model"],
        default="unit",
        help="activations within [0, 1] (default), or within each group's OpenSim min_control / "
        "max_control from the pack, as OpenSim's StaticOptimization bounds them",
    )
    add_live_synergists_argument(parser)


def estimator_options(args: argparse.Namespace, pack) -> dict:
    """FrameEstimator keyword arguments for the solver flags."""
    options: dict = {"hot_start": args.solver == "active-set", "live_synergists": args.live_synergists == "on"}
    if args.activation_bounds == "model":
        options["a_min"], options["a_max"] = pack.min_control, pack.max_control
    return options


def _pack(name: str, dynamics: str = "pinocchio"):
    from msk_core.model import Evaluator, load_pack

    return load_pack(name, evaluator=Evaluator.COMPILED if dynamics == "compiled" else Evaluator.NUMPY)


def _trial_files(paths: list[Path]) -> list[Path]:
    """Trial TOMLs; a folder stands for every ``trial.toml`` under it (sorted)."""
    files = []
    for path in paths:
        if path.is_dir():
            found = sorted(path.rglob("trial.toml"))
            if not found:
                raise InputError("folder holds no trial.toml", path=path, field="--trial")
            files.extend(found)
        else:
            files.append(path)
    return files


#: Folders :func:`output_folder` made in this process: those still empty when a command fails or is interrupted are
#: removed again (:func:`remove_unfilled_folders`), not left behind as if there were a report
MADE_FOLDERS: list[Path] = []


def output_folder(path: Path, flag: str) -> Path:
    """``path`` made as a folder before the work that fills it (minutes of calibration): a :class:`ConfigError`
    naming ``flag`` when it is a file, or cannot be made."""
    if not path.exists():
        MADE_FOLDERS.append(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except (FileExistsError, NotADirectoryError):
        raise ConfigError(
            "is a file, not a folder: name a folder for the report", field=flag, value=str(path)
        ) from None
    except OSError as error:
        raise ConfigError(f"cannot make the folder: {error.strerror}", field=flag, value=str(path)) from None
    return path


def remove_unfilled_folders() -> None:
    """Remove the folders :func:`output_folder` made that are still empty (a command failed or was interrupted)."""
    while MADE_FOLDERS:
        folder = MADE_FOLDERS.pop()
        try:
            folder.rmdir()  # only when empty
        except OSError:
            pass


def output_file(path: Path, flag: str, example: str) -> Path:
    """``path``'s folder made before the work that writes it (:func:`output_folder`): a :class:`ConfigError` naming
    ``flag`` when ``path`` is a folder (it was found only after the calibration, as an error about a hidden temporary
    file) or its folder cannot be made."""
    if path.is_dir():
        raise ConfigError(f"is a folder: name the file to write, e.g. {path / example}", field=flag, value=str(path))
    output_folder(path.parent, flag)
    return path


def load_trials(paths: list[Path], pack) -> list:
    """The trials of ``paths`` (a folder: every ``trial.toml`` under it), saying on stderr what loading left out of
    each (frames beyond the torque file, EMG not measured): a user should not find it only in the numbers."""
    import sys

    from msk_core.estimate.trial import load_trial, trial_notes

    trials = [load_trial(path, pack) for path in _trial_files(paths)]
    seen: dict[str, Path] = {}
    for trial in trials:  # reports, plots and the leave-out's tables are keyed by the trial's name
        if trial.name in seen:
            raise ConfigError(
                f"two trials are named {trial.name!r} ({seen[trial.name]} and {trial.path}): their results would "
                "overwrite each other; give each its own `name = ...`",
                path=trial.path,
                field="name",
                value=trial.name,
            )
        seen[trial.name] = trial.path
    for trial in trials:
        for note in trial_notes(trial):
            print(f"trial {trial.name} ({trial.path}): {note}", file=sys.stderr)
    return trials


def all_at_bound_warning(statuses: list[str]) -> str | None:
    """A word when every group with EMG ended its strength at a bound: the data constrained none of them, and the
    calibration still says converged (its projected gradient is 0 there). Found with held-out data: EMG 0.5 s off
    its torques gave 10 of 10 at a bound, "converged after 1 iteration". The real lifts and walk: 4-7 of 8, 5 of 9."""
    measured = [st for st in statuses if st != "not_calibrated"]
    if len(measured) < 2 or any(st != "at_bound" for st in measured):
        return None
    return (
        f"warning: all {len(measured)} muscles with EMG ended at a strength bound: the trials did not constrain any; "
        "check that the EMG lines up with the torques (start/end, the files' clocks) and is normalised"
    )


def run_calibrate(args: argparse.Namespace) -> int:
    from msk_core.estimate.calibrate import IdentifyMode
    from msk_core.estimate.pipeline import calibrate_subject

    options = calibration_options(args)
    pack = _pack(args.pack)
    output_file(args.out, "--out", "subject.json")  # before the calibration's minutes, as msk estimate does
    trials = load_trials(args.trial, pack)
    print(
        f"calibrating {pack.name} v{pack.version} on {sum(t.n_frames for t in trials)} frames "
        f"of {len(trials)} trial(s)"
        + (f" ({sum(t.isometric for t in trials)} isometric)" if any(t.isometric for t in trials) else "")
        + "...",
        flush=True,
    )
    profile, result = calibrate_subject(pack, trials, **options)
    profile.save(args.out)
    print(
        f"{result.method}: converged={result.converged} after {result.iterations} iterations "
        f"({result.message}); projected gradient {result.projected_gradient:.2e}; objective {result.objective:.4g} "
        f"(" + ", ".join(f"{k} {v:.4g}" for k, v in result.terms.items()) + ")"
    )
    emd = profile.calibration["emd"]
    print(f"electromechanical delay: {1000 * emd['delay_s']:.0f} ms ({emd['source']})")
    for g, info in result.identifiability(pack.groups).items():
        # relative, as the status judges it (the legend below)
        std = "" if info["rel_std_data"] is None else f"  rel. std (data) {info['rel_std_data']:6.3f}"
        print(
            f"  {g:16s} scale {info['scale']:6.3f}  F_max {info['scale'] * pack.f_max_ref[pack.groups.index(g)]:9.1f} N"
            f"{std:24s}  {info['status']}"
        )
    counts = {s: result.status.count(s) for s in dict.fromkeys(result.status)}
    print(
        "strength: "
        + ", ".join(f"{n} {s}" for s, n in counts.items())
        + (
            ""
            if result.settings.identify_max_std is None
            else f" (identified: data-only relative Laplace std <= {result.settings.identify_max_std}; "
            f"unidentified directions: {IdentifyMode(result.settings.identify).value})"
        )
    )
    if (warning := all_at_bound_warning(result.status)) is not None:
        print(warning)
    vague = [g for g, st in zip(pack.groups, result.status) if st in ("unidentified", "combination")]
    if vague and not any(t.isometric for t in trials):
        print(
            f"hint: the trials do not separate the strength of {', '.join(vague)} from their synergists'; isometric "
            "MVC trials with measured torque (trial key `isometric = true`, docs/estimation.md) do"
        )
    print(f"wrote {args.out}")
    return 0 if result.converged else 1


def run_estimate(args: argparse.Namespace) -> int:
    from msk_core.estimate.pipeline import estimate_trial
    from msk_core.estimate.prior import load_scale_line
    from msk_core.estimate.profile import SubjectProfile
    from msk_core.io import write_sto

    pack = _pack(args.pack, args.dynamics)
    subject = SubjectProfile.load(args.subject) if args.subject else None
    if subject is None and args.method in ("proposed", "prior"):
        raise ConfigError(f"method {args.method!r} needs --subject (a calibrated profile)", field="--subject")
    if args.trial.is_dir():
        raise ConfigError("msk estimate takes one trial file, not a folder", field="--trial", value=str(args.trial))
    output_file(args.out, "--out", "activations.sto")
    if args.out.suffix.lower() != ".sto":  # its content is an OpenSim table whatever the name says
        raise ConfigError(
            "msk estimate writes OpenSim .sto tables (and _torques.sto, _std.sto beside it): name it .sto",
            field="--out",
            value=str(args.out),
        )
    (trial,) = load_trials([args.trial], pack)
    run = estimate_trial(
        pack, trial, args.method, subject=subject, progress=ProgressBar(leave=False), **estimator_options(args, pack)
    )
    write_sto(args.out, run.time, run.groups, run.activations, name=f"activations_{run.method}")
    torque_path = args.out.with_name(f"{args.out.stem}_torques.sto")
    cols, data = [], []
    for j, c in enumerate(run.coordinates):
        cols += [f"{c}_id", f"{c}_model", f"{c}_residual"]
        data += [run.torques[:, j], run.model_torques[:, j], run.residual[:, j]]
    write_sto(torque_path, run.time, cols, np.column_stack(data), name=f"torques_{run.method}")
    std_path = args.out.with_name(f"{args.out.stem}_std.sto")
    write_sto(std_path, run.time, run.groups, run.activation_std, name=f"activation_std_{run.method}")
    print(
        f"{trial.n_frames} frames, flagged: {flag_counts_text(run.flag_counts)}; median solve "
        f"{np.median(run.solve_time_s) * 1e6:.1f} µs, {np.median(run.iterations):.0f} iterations"
    )
    if run.load_scale is not None:
        print(load_scale_line(trial.name, run.load_scale))
    print(f"wrote {args.out}, {torque_path} and {std_path} (Laplace std per activation)")
    return 0


def run_evaluate(args: argparse.Namespace) -> int:
    from msk_core.estimate.profile import SubjectProfile
    from services.surfaces.reports.evaluation import write_report

    if args.leave_out:
        return run_leave_out(args)
    if args.train:
        raise ConfigError("training trials are for --leave-out (a profile is given by --subject)", field="--train")
    if args.subject is None:
        raise ConfigError("needs --subject (a calibrated profile), or --leave-out with --train", field="--subject")
    pack = _pack(args.pack, args.dynamics)
    subject = SubjectProfile.load(args.subject)
    trials = load_trials(args.trial, pack)
    missing = [t.path for t in trials if not t.emg]
    if missing:
        raise ConfigError("evaluation trials need EMG (the measured activation)", path=missing[0], field="emg")
    output_folder(args.report, "--report")
    write_report(pack, subject, trials, args.report, progress=ProgressBar(leave=False), **estimator_options(args, pack))
    append_trial_notes(args.report / "report.md", trials)
    print((args.report / "report.md").read_text())
    return 0


def append_trial_notes(report: Path, trials) -> None:
    """What loading left out of or found in the trials (:func:`trial_notes`), at the end of a report: said only on
    stderr before, so a report of a trial without a complete repetition (every frame scored as rest) did not say so
    (found with held-out data)."""
    from msk_core.estimate.trial import trial_notes

    lines = [f"- {trial.name} ({trial.path}): {note}" for trial in trials for note in trial_notes(trial)]
    if lines:
        with report.open("a") as out:
            out.write("\n## Notes on the trials\n\n" + "\n".join(lines) + "\n")


def refuse_in_sample(training: list[Path], held_out: list[Path], field: str) -> None:
    """A held-out trial that is also a training trial: :class:`InputError` naming it and ``field`` (its score would
    be an in-sample one reported as held out)."""
    train_paths = [p.resolve() for p in training]
    for p in held_out:
        if p.resolve() in train_paths:
            raise InputError(
                "a held-out trial must not also be a training trial (the score would not be held out)",
                path=p,
                field=field,
                value=str(p),
            )


def leave_out_group(pack, name: str) -> str:
    """The pack group ``--leave-out`` names: its model name, in any case, or its display name ("Tibialis anterior");
    otherwise a ConfigError with the closest names."""
    from msk_core.errors import close_names
    from msk_core.estimate.pack import NamedPackLike

    groups = list(pack.groups)
    displayed = [pack.display_names.group(g) for g in groups] if isinstance(pack, NamedPackLike) else []
    shown = {d.casefold(): g for d, g in zip(displayed, groups)}
    found = {g.casefold(): g for g in groups}.get(name.casefold()) or shown.get(name.casefold())
    if found is not None:
        return found
    near = close_names(name, groups + displayed)
    raise ConfigError(
        f"not a group of pack {pack.name!r}"
        + (f"; did you mean {', '.join(near)}?" if near else "")
        + " (all: every group with an electrode in the training and the held-out trials)",
        field="--leave-out",
        value=name,
    )


def run_leave_out(args: argparse.Namespace) -> int:
    """``msk evaluate --leave-out``: calibrations without each electrode in turn, scored on the held-out trials."""
    from msk_core.estimate.leave_out import leave_one_out
    from services.surfaces.reports.evaluation import write_leave_out_report

    if args.subject is not None:
        raise ConfigError(
            "--leave-out calibrates its own profiles from --train; leave --subject out", field="--subject"
        )
    if not args.train:
        raise ConfigError("--leave-out needs training trials (--train)", field="--train")
    refuse_in_sample(args.train, args.trial, "--trial")
    names = [n.strip() for item in args.leave_out for n in item.split(",") if n.strip()]
    if not names:
        raise ConfigError("expected all or group names", field="--leave-out", value=args.leave_out)
    options = calibration_options(args)
    pack = _pack(args.pack, args.dynamics)
    train, held = load_trials(args.train, pack), load_trials(args.trial, pack)
    missing = [t.path for t in held if not t.emg]
    if missing:
        raise ConfigError("evaluation trials need EMG (the measured activation)", path=missing[0], field="emg")
    if not any(t.emg for t in train if not t.isometric):
        raise ConfigError(
            "a leave-one-out needs EMG in the training trials too: a left-out group is one whose electrode the "
            "calibration could have used (no training trial with reps has an [emg_map])",
            path=next((t.path for t in train if not t.isometric and not t.emg), train[0].path),
            field="emg",
        )
    output_folder(args.report, "--report")
    groups = None if "all" in names else [leave_out_group(pack, n) for n in names]
    print(
        f"leave-one-electrode-out on {pack.name}: {sum(t.n_frames for t in train)} training frames of {len(train)} "
        f"trial(s), {sum(t.n_frames for t in held)} held-out frames of {len(held)} trial(s)",
        flush=True,
    )
    result = leave_one_out(
        pack, train, held, groups=groups, progress=ProgressBar(), **options, **estimator_options(args, pack)
    )
    write_leave_out_report(pack, result, args.report)
    append_trial_notes(args.report / "report.md", [*train, *held])
    print((args.report / "report.md").read_text())
    print(f"wrote {args.report / 'summary.json'} ({result.seconds:.0f} s)")
    return 0
