"""``msk bench discrepancy``: (1) one run of the discrepancy workflow on a demo-sized session (two deadlift trials of
~60 s, 19 groups), timed beside the plain per-frame estimator over the held-out trial in the same run; (2) the
detection matrix on synthetic sessions: every hidden effect of ``msk synth`` one at a time over three subject seeds and
both exercises, at stated sizes and at the generator's own defaults, no effect over eight seeds (one training load,
and two), and two at once - how often the right effect is named and by how much the held-out torque gap shrinks
(``--quick``: one seed); (3) the same questions on arm26 sessions built outside ``msk synth`` (another model,
static-optimisation recruitment, effects built on the muscle side): "none" without an effect, the right name with one."""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from services.bench import BenchResult

NAME = "discrepancy"
DESCRIPTION = "msk discrepancy on a demo-sized deadlift session (time) and the synthetic detection matrix"

#: hidden effect -> (generator setting, the candidate that should be named); sizes where the effect is well above
#: the generator's EMG noise floor (docs/discrepancy.md, "Synthetic detection")
CASES = {
    "emd": ("emd=0.15", "emd"),
    "fl_active": ("fl_active", "fl_active"),
    "fl_passive": ("fl_passive", "fl_passive"),
    "fv": ("fv", "fv"),
    "damping": ("damping=5", "damping"),
    "load_misreport": ("load_misreport=1.3", "load_misreport"),
    "crosstalk": ("crosstalk=0.4", "crosstalk"),
}
#: the same at the generator's default sizes (``msk synth --effects NAME``: emd 0.05 s, damping 0.5 N·m·s/rad, load
#: misreport 1.1, cross-talk 0.15); fl_active, fl_passive and fv are on/off, so the matrix above already has them
DEFAULT_CASES = {
    "emd": ("emd", "emd"),
    "damping": ("damping", "damping"),
    "load_misreport": ("load_misreport", "load_misreport"),
    "crosstalk": ("crosstalk", "crosstalk"),
}
#: the sized effects near the top of the generator's ranges, where their gap stands above the floor
LARGE_CASES = {
    "emd": ("emd=0.2", "emd"),
    "damping": ("damping=15", "damping"),
    "load_misreport": ("load_misreport=1.8", "load_misreport"),
    "crosstalk": ("crosstalk=0.5", "crosstalk"),
}
NONE_SEEDS = (1, 2, 3, 4, 5, 6, 7, 8)
LOADS = {"bench_press": (40.0, 60.0), "deadlift": (45.0, 75.0)}
LOADS_3 = {"bench_press": (40.0, 60.0, 50.0), "deadlift": (45.0, 75.0, 65.0)}  # load scale: train on two loads


def session(
    exercise: str, effects: str, seed: int, *, reps: int = 3, three_loads: bool = False, heavier_trains: bool = False
):
    """Generate, write and load a synthetic session and calibrate the subject on its training trials as a user would
    (``msk calibrate --emd 0``: the paper's model, no delay); returns (folder, pack, train, holdout, profile).
    ``heavier_trains``: the heavier load trains and the lighter is held out (one training load only)."""
    from msk_core.estimate.pipeline import calibrate_subject
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack
    from msk_core.synth import SynthConfig, generate_session, parse_effects
    from msk_core.synth.exercises import Exercise
    from msk_core.synth.files import write_session

    ex = Exercise(exercise)
    loads = (LOADS_3 if three_loads else LOADS)[exercise]
    if heavier_trains:
        if three_loads:
            raise ValueError("heavier_trains applies to one training load")
        loads = loads[::-1]
    folder = Path(tempfile.mkdtemp(prefix=f"bench_disc_{exercise}_"))
    cfg = SynthConfig(subject_seed=seed, n_reps=reps, effects=parse_effects(effects), loads_kg={ex: loads})
    write_session(generate_session([ex], cfg), folder)
    pack = load_pack(exercise)
    trials = [load_trial(folder / exercise / f"{exercise}_{x:g}kg" / "trial.toml", pack) for x in loads]
    train, holdout = trials[:-1], trials[-1:]
    profile, _ = calibrate_subject(pack, train, emd_s=0.0)
    return folder, pack, train, holdout, profile


def detection_case(
    exercise: str,
    effects: str,
    seed: int,
    *,
    max_effects: int = 1,
    three_loads: bool = False,
    heavier_trains: bool = False,
    recalibrate: bool = False,
) -> dict:
    """One synthetic session through ``msk discrepancy`` (``recalibrate``: with ``--recalibrate``): the effects
    named, the held-out gap before and after and the shrink, the best candidate."""
    from msk_core.discrepancy import run_discrepancy

    folder, pack, train, holdout, profile = session(
        exercise, effects, seed, three_loads=three_loads, heavier_trains=heavier_trains
    )
    try:
        result = run_discrepancy(
            pack, profile, train, holdout, max_effects=max_effects, activation=False, recalibrate=recalibrate
        )
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    s = result.summary
    named = s["effect"] if isinstance(s["effect"], list) else ([] if s["effect"] == "none" else [s["effect"]])
    out = {
        "named": named,
        "shrink": 1.0 - s["gap_after"] / s["gap_before"],
        "gap_before": s["gap_before"],
        "gap_after": s["gap_after"],
        "top": s["candidates"][0]["effect"] if s["candidates"] else "none",
    }
    print(
        f"    {exercise} {effects} seed {seed}: named {'+'.join(named) or 'none'}, held-out gap {s['gap_before']:.4f} "
        f"-> {s['gap_after']:.4f} ({out['shrink']:.0%})",
        flush=True,
    )  # the matrix takes long: show each case
    return out


def _timing() -> list[BenchResult]:
    from msk_core.discrepancy import run_discrepancy
    from msk_core.estimate.pipeline import estimate_trial

    folder, pack, train, holdout, profile = session("deadlift", "emd=0.08", 11, reps=12)
    try:
        seconds = [float(t.time[-1] - t.time[0]) for t in train + holdout]
        started, cpu = time.perf_counter(), time.process_time()
        result = run_discrepancy(pack, profile, train, holdout, max_effects=2)
        elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu
        started = time.perf_counter()
        recal = run_discrepancy(pack, profile, train, holdout, max_effects=2, activation=False, recalibrate=True)
        elapsed_recal = time.perf_counter() - started
        started = time.perf_counter()
        run_discrepancy(pack, profile, train, holdout, max_effects=2, activation=False)
        elapsed_plain = time.perf_counter() - started
        started = time.perf_counter()
        estimate_trial(pack, holdout[0], "proposed", subject=profile)
        baseline = time.perf_counter() - started
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    size = f"deadlift, 2 trials ({seconds[0]:.0f} s + {seconds[1]:.0f} s), {len(pack.groups)} groups, max 2 effects"
    return [
        BenchResult(
            name=f"msk discrepancy, {size}, incl. held-out estimation before/after",
            value=elapsed,
            unit="s",
            baseline_name="one proposed estimation pass over the held-out trial",
            baseline_value=baseline,
            target="< 60 s",
            passed=elapsed < 60.0,
            details={
                "cpu_s": cpu,
                "named": json.dumps(result.summary["effect"]),
                "gap_before": result.summary["gap_before"],
                "gap_after": result.summary["gap_after"],
            },
        ),
        BenchResult(
            name=f"msk discrepancy --recalibrate, {size}, without the activation gaps (one calibration per muscle- or "
            "joint-state candidate and step)",
            value=elapsed_recal,
            unit="s",
            baseline_name="the same run without --recalibrate",
            baseline_value=elapsed_plain,
            target="reported (opt-in)",
            passed=None,
            details={"named": json.dumps(recal.summary["effect"]), "gap_after": recal.summary["gap_after"]},
        ),
    ]


SHARED = Path(os.environ.get("MSK_SHARED_DIR", Path(__file__).resolve().parents[2].parent / "shared"))
#: arm26 sessions built outside `msk synth`: the EMG of four measured muscles is the static-optimisation activation
#: (another recruitment than the generator's) divided by a known strength factor, times (1 + noise), the noise a
#: 6 Hz-low-passed Gaussian of the stated relative size; no effect is hidden
ARM26_STRENGTH = {"BIClong": 1.5, "BICshort": 1.3, "TRIlat": 0.8, "TRImed": 0.8}
ARM26_NOISE = (0.1, 0.2, 0.3)


#: hidden effects built on the muscle side of the arm26 sessions (not `msk synth`'s formulas): the muscles produce
#: the torque the effect leaves them, the EMG follows static optimisation of that torque, the reported torque stays
#: the inverse-dynamics one
#: each is named by the candidate of the same name
ARM26_EFFECTS = (
    "emd",  # the EMG leads the force by 60 ms
    "damping",  # joint damping 0.15 x RMS(torque) / RMS(velocity) per coordinate: muscles also overcome it
    "passive_joint",  # an elastic moment rising exponentially (0.3 rad) toward each coordinate's smallest angle in the
    # motion, 30 % of the training torque's RMS there: the muscles produce the rest
    "fl_active",  # active force-length, a parabola 1 - ((l - 1) / 0.6)^2 (floor 0.1; not the candidate's Gaussian):
    # the same force takes activation / factor
)
ARM26_EMD_S = 0.06


def arm26_session(
    folder: Path, noise: float, seed: int, reps: int = 4, effect: str | None = None, calibrate: bool = True
):
    """(pack, train, holdout, profile): the arm26 tutorial motion forward and back, ``reps`` times, with the tutorial's
    inverse-dynamics torques x5 (training) and x7 (held out), EMG as above (with ``effect`` hidden as in
    ARM26_EFFECTS), calibrated with ``--emd 0`` (``calibrate=False``: profile None). The files stay in ``folder``:
    ``train.toml`` and ``held.toml`` are trial files for the CLI."""
    from scipy.signal import butter, sosfiltfilt

    from msk_core.estimate.effects import fibre_length
    from msk_core.estimate.pipeline import calibrate_subject, estimate_trial
    from msk_core.estimate.trial import load_trial
    from msk_core.io import read_sto, write_sto
    from msk_core.model import load_pack
    from msk_core.model.pack import OutOfRange

    if effect is not None and effect not in ARM26_EFFECTS:
        raise ValueError(f"unknown arm26 effect {effect!r}; known: {sorted(ARM26_EFFECTS)}")
    data = SHARED / "data" / "opensim-arm26"
    pack = load_pack("arm26")
    ik, tau = read_sto(data / "arm26_InverseKinematics.mot"), read_sto(data / "arm26_InverseDynamics.sto")
    t_one = np.r_[ik.time, 2 * ik.time[-1] - ik.time[::-1][1:]]
    q_one, tau_one = np.vstack([ik.data, ik.data[::-1][1:]]), np.vstack([tau.data, tau.data[::-1][1:]])
    span = t_one[-1]
    t = np.r_[np.concatenate([t_one[:-1] + k * span for k in range(reps)]), reps * span]
    q = np.vstack([q_one[:-1]] * reps + [q_one[-1:]])
    torques = np.vstack([tau_one[:-1]] * reps + [tau_one[-1:]])
    write_sto(folder / "ik.mot", t, ik.columns, q, in_degrees=True)
    sos = butter(3, 6.0 / (0.5 / float(np.median(np.diff(t)))), output="sos")
    # the effect's body constants, from the training torque (the same body in both trials)
    coords = list(pack.coordinates)
    q_rad = np.column_stack([np.radians(q[:, ik.columns.index(c)]) for c in coords])
    qd = np.gradient(q_rad, t, axis=0)
    tau_c = np.column_stack([torques[:, tau.columns.index(c + "_moment")] for c in coords]) * 5.0
    rms = lambda x: np.sqrt(np.mean(x**2, axis=0))  # noqa: E731
    trials = []
    for name, factor, stream in (("train", 5.0, seed), ("held", 7.0, 1000 + seed)):
        write_sto(folder / f"id_{name}.sto", t, tau.columns, factor * torques)
        toml = folder / f"{name}.toml"
        toml.write_text(
            f'kinematics = "ik.mot"\ntorques = "id_{name}.sto"\nphase_signal = "r_elbow_flex"\nbody_mass_kg = 70.0\n'
        )
        muscle = factor * torques.copy()  # what the muscles must produce
        if effect == "damping":
            b = 0.15 * rms(tau_c) / np.maximum(rms(qd), 1e-9)
            for n, c in enumerate(coords):
                muscle[:, tau.columns.index(c + "_moment")] += b[n] * qd[:, n]
        elif effect == "passive_joint":
            k = 0.3 * rms(tau_c)
            for n, c in enumerate(coords):
                muscle[:, tau.columns.index(c + "_moment")] -= k[n] * np.exp(-(q_rad[:, n] - q_rad[:, n].min()) / 0.3)
        so_toml = toml
        if effect in ("damping", "passive_joint"):
            write_sto(folder / f"muscle_{name}.sto", t, tau.columns, muscle)
            so_toml = folder / f"muscle_{name}.toml"
            so_toml.write_text(toml.read_text().replace(f"id_{name}.sto", f"muscle_{name}.sto"))
        so = estimate_trial(pack, load_trial(so_toml, pack), "so")
        act = so.activations
        if effect == "fl_active":
            lengths, _ = pack.lengths_and_moment_arms_many(q_rad, out_of_range=OutOfRange.CLAMP)
            l_norm = fibre_length(lengths, pack.optimal_fiber_lengths, pack.tendon_slack_lengths)
            phi = np.clip(1.0 - ((l_norm - 1.0) / 0.6) ** 2, 0.1, 1.0)
            act = act / np.column_stack([np.interp(so.time, t, phi[:, j]) for j in range(phi.shape[1])])
        if effect == "emd":  # the EMG at t is the activation at t + delay
            act = np.column_stack([np.interp(so.time + ARM26_EMD_S, so.time, act[:, j]) for j in range(act.shape[1])])
        rng = np.random.default_rng(stream)
        emg = []
        for g, k in ARM26_STRENGTH.items():
            wobble = sosfiltfilt(sos, rng.normal(size=so.time.size))  # low-passed noise, scaled to ``noise`` RMS
            emg.append(np.clip(act[:, so.groups.index(g)] / k * (1.0 + noise * wobble / wobble.std()), 0.0, None))
        write_sto(folder / f"emg_{name}.sto", so.time, [f"ch_{g}" for g in ARM26_STRENGTH], np.column_stack(emg))
        toml.write_text(
            toml.read_text()
            + f'emg = "emg_{name}.sto"\nemg_is_envelope = true\n[emg_map]\n'
            + "".join(f'ch_{g} = "{g}"\n' for g in ARM26_STRENGTH)
        )
        trials.append(load_trial(toml, pack))
    profile = calibrate_subject(pack, trials[:1], emd_s=0.0)[0] if calibrate else None
    return pack, trials[:1], trials[1:], profile


def _arm26_named(noise: float, seeds: range, effect: str | None, label: str, *, recalibrate: bool = False) -> list[str]:
    """The effect named on each seed's arm26 session (``effect`` hidden, or none); prints the counts under ``label``.
    ``recalibrate``: as ``msk discrepancy --recalibrate``."""
    from msk_core.discrepancy import run_discrepancy

    named = []
    for seed in seeds:
        folder = Path(tempfile.mkdtemp(prefix="bench_disc_arm26_"))
        try:
            with contextlib.redirect_stderr(io.StringIO()):  # per-frame estimator flags
                pack, train, holdout, profile = arm26_session(folder, noise, seed, effect=effect)
                named.append(
                    run_discrepancy(pack, profile, train, holdout, activation=False, recalibrate=recalibrate).summary[
                        "effect"
                    ]
                )
        finally:
            shutil.rmtree(folder, ignore_errors=True)
    print(f"    arm26, {label}: {_counts(named)}", flush=True)
    return named


def _counts(named: list[str]) -> str:
    """``"none 9/10, fl_active 1/10"``."""
    return ", ".join(f"{e} {named.count(e)}/{len(named)}" for e in sorted(set(named)))


def _arm26(quick: bool) -> list[BenchResult]:
    """On sessions of another model, recruitment and noise than `msk synth`'s: "none" without a hidden effect, the
    right name with one of ARM26_EFFECTS (at 10 % and 20 % EMG noise)."""
    if not (SHARED / "data" / "opensim-arm26").is_dir():
        print(f"    arm26 sessions skipped: {SHARED / 'data' / 'opensim-arm26'} not found", flush=True)
        return []
    nulls: dict[str, float | str] = {}
    clean = []
    for noise in ARM26_NOISE:
        named = _arm26_named(noise, range(1, 3 if quick else 11), None, f"no effect, EMG noise {noise:.0%}")
        nulls[f"EMG noise {noise:.0%}"] = _counts(named)
        clean += [e == "none" for e in named]
    effects: dict[str, float | str] = {}
    hits = []
    for effect in ARM26_EFFECTS:
        for noise in (0.1, 0.2):
            label = f"{effect}, EMG noise {noise:.0%}"
            named = _arm26_named(noise, range(1, 2 if quick else 6), effect, f"hidden {label}")
            effects[label] = _counts(named)
            hits += [e == effect for e in named]
    # --recalibrate where the plain run cannot find the effect (the calibration took the passive moment into the
    # strengths), and on the noisiest effect-free sessions, where it has the most room to find something false
    recal: dict[str, float | str] = {}
    recal_hits, recal_clean = [], []
    for noise in (0.1, 0.2):
        label = f"passive_joint, EMG noise {noise:.0%}, --recalibrate"
        named = _arm26_named(noise, range(1, 2 if quick else 6), "passive_joint", f"hidden {label}", recalibrate=True)
        recal[label] = _counts(named)
        recal_hits += [e == "passive_joint" for e in named]
    for noise in (0.1, 0.3):
        named = _arm26_named(
            noise,
            range(1, 3 if quick else 11),
            None,
            f"no effect, EMG noise {noise:.0%}, --recalibrate",
            recalibrate=True,
        )
        recal[f"no effect, EMG noise {noise:.0%}, --recalibrate"] = _counts(named)
        recal_clean += [e == "none" for e in named]
    return [
        _named_share(
            "hidden passive joint moment on arm26, msk discrepancy --recalibrate: right effect named", recal_hits, recal
        ),
        _named_share(
            "no hidden effect on arm26, msk discrepancy --recalibrate: 'none' named", recal_clean, recal, all_cases=True
        ),
        _named_share(
            "no hidden effect, arm26 with static-optimisation EMG (not msk synth): 'none' named",
            clean,
            nulls,
            all_cases=True,
        ),
        _named_share("hidden effect on arm26 sessions (not msk synth): right effect named", hits, effects),
    ]


def _named_share(name: str, right: list[bool], details: dict, *, all_cases: bool = False) -> BenchResult:
    """The share of cases in which the right effect (or 'none') was named first: passed when it is >= 0.9, or with
    ``all_cases`` when it was named in every case."""
    share = float(np.mean(right))
    return BenchResult(
        name=name,
        value=share,
        unit="fraction of cases",
        target="1.0" if all_cases else ">= 0.9",
        passed=all(right) if all_cases else bool(share >= 0.9),
        details=details,
    )


def _key(exercise: str, seed: int, three_loads: bool, heavier_trains: bool = False) -> tuple:
    return exercise, seed, three_loads, heavier_trains


def _effect_free_cases(quick: bool, recalibrate: bool = False) -> tuple[list[dict], dict[tuple, float]]:
    """The same subjects and noise without any hidden effect, with one and two training loads and with the direction
    reversed (the heavier load trains, the lighter is held out): the cases, and each one's held-out gap by
    :func:`_key`. That gap is what is left when an effect's own gap is removed completely, so 1 - gap(none) /
    gap_before(effect) is the shrink attainable in that case (``recalibrate`` changes what is named, not that gap)."""
    none_gap: dict[tuple, float] = {}
    none_cases = []
    for three in (False, True):  # one training load, and two (the held-out load between them)
        for exercise in ("bench_press", "deadlift"):
            for seed in (1,) if quick else NONE_SEEDS:
                c = detection_case(exercise, "none", seed, three_loads=three, recalibrate=recalibrate)
                c["case"] = f"{exercise}/{seed}{' (two training loads)' if three else ''}"
                none_cases.append(c)
                none_gap[_key(exercise, seed, three)] = c["gap_before"]
    for exercise in ("bench_press", "deadlift"):
        for seed in (1,) if quick else NONE_SEEDS:
            c = detection_case(exercise, "none", seed, heavier_trains=True, recalibrate=recalibrate)
            c["case"] = f"{exercise}/{seed} (heavier load trains)"
            none_cases.append(c)
            none_gap[_key(exercise, seed, False, True)] = c["gap_before"]
    return none_cases, none_gap


def _attainable(
    none_gap: dict[tuple, float],
    exercise: str,
    seed: int,
    three_loads: bool,
    before: float,
    heavier_trains: bool = False,
) -> float:
    """The shrink of a held-out gap ``before`` attainable in this case (see :func:`_effect_free_cases`); an effect-free
    case not run yet is run and added to ``none_gap``."""
    key = _key(exercise, seed, three_loads, heavier_trains)
    if key not in none_gap:
        none_gap[key] = detection_case(exercise, "none", seed, three_loads=three_loads, heavier_trains=heavier_trains)[
            "gap_before"
        ]
    return 1.0 - none_gap[key] / before


def _detection_matrix() -> list[tuple[str, str, str, str, bool]]:
    """(key, setting, expected effect, label, heavier load trains) for each hidden-effect row of the matrix."""
    matrix = [(key, setting, expected, "", False) for key, (setting, expected) in CASES.items()]
    matrix += [
        (key, setting, expected, " (generator default size)", False)
        for key, (setting, expected) in DEFAULT_CASES.items()
    ]
    matrix += [(key, setting, expected, " (large size)", False) for key, (setting, expected) in LARGE_CASES.items()]
    matrix += [
        (key, setting, expected, " (heavier load trains)", True)
        for key, (setting, expected) in CASES.items()
        if key != "load_misreport"
    ]  # a load misreport needs two training loads
    return matrix


def _hidden_effect_result(
    row: tuple[str, str, str, str, bool],
    seeds: tuple[int, ...],
    none_gap: dict[tuple, float],
    every: list[dict],
    recalibrate: bool = False,
) -> BenchResult:
    """One row of the matrix: is the hidden effect named first, and how much of the held-out gap does it remove (its
    cases also added to ``every``, labelled, for :func:`_worth_naming_result`; ``recalibrate``: as
    ``msk discrepancy --recalibrate``)."""
    key, setting, expected, label, heavier = row
    cases = []
    for exercise in ("bench_press", "deadlift"):
        for seed in seeds:
            three = key == "load_misreport"
            c = detection_case(
                exercise, setting, seed, three_loads=three, heavier_trains=heavier, recalibrate=recalibrate
            )
            c["case"] = f"{exercise}/{seed}"
            c["attainable"] = _attainable(none_gap, exercise, seed, three, c["gap_before"], heavier)
            cases.append(c)
            every.append({**c, "expected": expected, "case": f"{setting}{label}, {exercise}/{seed}"})
    hits = [expected in c["named"][:1] for c in cases]
    shrink = float(np.median([c["shrink"] for c in cases]))
    return BenchResult(
        name=f"hidden {setting}{label}: right effect named",
        value=float(np.mean(hits)),
        unit="fraction of cases",
        target=">= 0.9 named, median held-out gap shrink >= 0.5",
        passed=bool(np.mean(hits) >= 0.9 and shrink >= 0.5),
        details={
            "median_shrink": shrink,
            "median_attainable_shrink": float(np.median([c["attainable"] for c in cases])),
            "wrong": sum(bool(c["named"]) and c["named"][0] != expected for c in cases),
            **_case_texts(cases),
        },
    )


#: The detection targets as restated after the issue of the workflow was blocked on its own (docs/discrepancy.md,
#: "Synthetic detection"): where removing the hidden effect altogether would take at least ATTAINABLE_MIN off the
#: held-out gap, the effect is named and its shrink reaches SHARE_OF_ATTAINABLE_MIN of that; "none" on every
#: effect-free session (the result of its own).
ATTAINABLE_MIN = 0.20
SHARE_OF_ATTAINABLE_MIN = 0.80


def _worth_naming_result(every: list[dict]) -> BenchResult:
    """The restated targets over every single-effect case of the matrix whose attainable shrink is at least
    :data:`ATTAINABLE_MIN`: the share named right with at least :data:`SHARE_OF_ATTAINABLE_MIN` of it; the misses
    in the details."""
    due = [c for c in every if c["attainable"] >= ATTAINABLE_MIN]
    met = [  # (1e-9: exactly 80 % is met, whatever the rounding of the product)
        c["expected"] in c["named"] and c["shrink"] >= SHARE_OF_ATTAINABLE_MIN * c["attainable"] - 1e-9 for c in due
    ]
    misses = [c for c, ok in zip(due, met, strict=True) if not ok]
    return BenchResult(
        name=(
            f"hidden effects worth naming (attainable shrink >= {ATTAINABLE_MIN:.0%}): named right, with >= "
            f"{SHARE_OF_ATTAINABLE_MIN:.0%} of the attainable"
        ),
        value=float(np.mean(met)) if met else 1.0,
        unit="fraction of cases",
        target="1.0",
        passed=all(met),
        details={"cases": len(due), "met": int(sum(met)), **_case_texts(misses)},  # the misses, by case
    )


def _case_texts(cases: list[dict]) -> dict[str, str]:
    """Per detection case, the effects named and the share of the held-out gap they remove of what is attainable."""
    return {
        c["case"]: f"{'+'.join(c['named']) or 'none'} ({c['shrink']:.0%} of {c['attainable']:.0%} attainable)"
        for c in cases
    }


def _two_effects_result(seeds: tuple[int, ...], none_gap: dict[tuple, float]) -> BenchResult:
    """emd=0.15 and fl_passive hidden together, --max-effects 2: are both named."""
    pair = []
    for exercise in ("bench_press", "deadlift"):
        for seed in seeds:
            c = detection_case(exercise, "emd=0.15,fl_passive", seed, max_effects=2)
            c["case"] = f"{exercise}/{seed}"
            c["attainable"] = _attainable(none_gap, exercise, seed, False, c["gap_before"])
            pair.append(c)
    both = [set(c["named"]) == {"emd", "fl_passive"} for c in pair]
    return _named_share(
        "two hidden effects (emd=0.15 + fl_passive), --max-effects 2: both named", both, _case_texts(pair)
    )


def run(quick: bool) -> list[BenchResult]:
    results = _timing()
    r = results[0]
    print(f"    {r.name}: {r.value:.1f} s wall, {r.details['cpu_s']:.1f} s CPU", flush=True)
    print(f"    {results[1].name}: {results[1].value:.1f} s against {results[1].baseline_value:.1f} s", flush=True)
    results += _arm26(quick)
    seeds = (1,) if quick else (1, 2, 3)
    matrix, none_gap = synthetic_matrix(quick)
    return results + matrix + [_two_effects_result(seeds, none_gap)]


def synthetic_matrix(quick: bool, recalibrate: bool = False) -> tuple[list[BenchResult], dict[tuple, float]]:
    """The hidden effects of the matrix one at a time, the restated targets over them, and "none" on the effect-free
    sessions (``recalibrate``: as ``msk discrepancy --recalibrate``); also each effect-free case's held-out gap."""
    seeds = (1,) if quick else (1, 2, 3)
    none_cases, none_gap = _effect_free_cases(quick, recalibrate)
    every: list[dict] = []
    results = [_hidden_effect_result(row, seeds, none_gap, every, recalibrate) for row in _detection_matrix()]
    results.append(_worth_naming_result(every))
    clean = [not c["named"] for c in none_cases]
    details = {c["case"]: f"{'+'.join(c['named']) or 'none'} (gap {c['gap_before']:.4f})" for c in none_cases}
    results.append(_named_share("no hidden effect: 'none' named", clean, details, all_cases=True))
    return results, none_gap
