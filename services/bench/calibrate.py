"""Calibration of the demo subject (lift + isometric MVC trials) by the default "reduced" solve beside the joint solve
(L-BFGS-B on strengths and activations, Jacobi-preconditioned), and (full run) the joint solve beside the same
problem as written (``precondition=False``), in the same run: time, iterations, the distance between the optima and
the strength error against the generator's truth."""

from __future__ import annotations

import json
import time

import numpy as np

from services.bench import BenchResult

NAME = "calibrate"
DESCRIPTION = "calibration NLP on the demo lift + isometric MVC trials: reduced vs joint, preconditioned vs as written"


QUICK_ISOMETRIC = 2  # --quick: the lift and the first two MVC blocks (1761 frames: ~2 s + ~8 s CPU; all ten: ~56 s)


def _frames(exercise: str, n_isometric: int | None = None):
    from msk_core.estimate.pipeline import build_prior, calibration_frames
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack
    from services.sessions.demo_subject import RECORDINGS, calibration_trial_files

    pack = load_pack(exercise)
    truth = json.loads((RECORDINGS / "demo" / "truth.json").read_text())["exercises"][exercise]
    lift, isometric = calibration_trial_files(RECORDINGS, exercise)
    trials = [load_trial(lift / "trial.toml", pack)] + [load_trial(p, pack) for p in isometric[:n_isometric]]
    frames = calibration_frames(pack, trials, build_prior(pack, trials))
    return pack, frames, np.array([truth["f_max_n"][g] for g in pack.groups])


def run(quick: bool) -> list[BenchResult]:
    from msk_core.estimate.calibrate import CalibrationSettings

    results = []
    for exercise in ("bench_press",) if quick else ("bench_press", "deadlift"):
        pack, frames, f_true = _frames(exercise, QUICK_ISOMETRIC if quick else None)
        comparisons = [("reduced", CalibrationSettings(solver="reduced"), "joint", CalibrationSettings(solver="joint"))]
        if not quick:
            comparisons.append(
                (
                    "joint, preconditioned",
                    CalibrationSettings(solver="joint"),
                    "joint as written",
                    CalibrationSettings(solver="joint", precondition=False),
                )
            )
        solved: dict = {}  # settings -> (seconds, result): the joint solve is one's baseline and the other's subject
        for name, settings, baseline_name, baseline in comparisons:
            results.append(_compared(pack, frames, f_true, exercise, name, settings, baseline_name, baseline, solved))
    return results


def _timed(pack, frames, settings, solved: dict):
    """(seconds, result) of one calibration; the first reduced solve of a run compiles its kernel, so the reduced
    solve is timed as the better of two runs."""
    from msk_core.estimate.calibrate import calibrate

    key = repr(settings)
    if key not in solved:
        runs = []
        for _ in range(2 if settings.solver == "reduced" else 1):
            started = time.perf_counter()
            res = calibrate(pack.f_max_ref, frames, settings)
            runs.append((time.perf_counter() - started, res))
        solved[key] = min(runs, key=lambda run: run[0])
    return solved[key]


def _compared(pack, frames, f_true, exercise, name, settings, baseline_name, baseline, solved) -> BenchResult:
    """One calibration timed beside its baseline on the same frames."""
    (t_new, new), (t_base, base) = _timed(pack, frames, settings, solved), _timed(pack, frames, baseline, solved)
    return BenchResult(
        name=f"{exercise} calibration ({frames.torques.shape[0]} frames, {name})",
        value=t_new,
        unit="s",
        baseline_name=baseline_name,
        baseline_value=t_base,
        details={
            "iterations": new.iterations,
            "baseline_iterations": base.iterations,
            "max_abs_strength_difference": float(np.max(np.abs(new.scale - base.scale))),
            "objective": new.objective,
            "baseline_objective": base.objective,
            "strength_error_median": float(np.median(np.abs(new.f_max / f_true - 1.0))),
        },
    )
