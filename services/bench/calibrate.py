"""Calibration of the demo subject (lift + isometric MVC trials) with the Jacobi-preconditioned joint solve, beside the
same problem solved as written (``precondition=False``), in the same run: time, iterations, the distance between the
two optima and the strength error against the generator's truth."""

from __future__ import annotations

import json
import time

import numpy as np

from services.bench import BenchResult

NAME = "calibrate"
DESCRIPTION = "calibration NLP on the demo lift + isometric MVC trials: preconditioned vs as written (same run)"


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
    from msk_core.estimate.calibrate import CalibrationSettings, calibrate

    results = []
    for exercise in ("bench_press",) if quick else ("bench_press", "deadlift"):
        pack, frames, f_true = _frames(exercise, QUICK_ISOMETRIC if quick else None)
        runs = {}
        for precondition in (True, False):
            started = time.perf_counter()
            res = calibrate(pack.f_max_ref, frames, CalibrationSettings(precondition=precondition))
            runs[precondition] = (time.perf_counter() - started, res)
        (t_pre, pre), (t_raw, raw) = runs[True], runs[False]
        results.append(
            BenchResult(
                name=f"{exercise} calibration ({frames.torques.shape[0]} frames, preconditioned)",
                value=t_pre,
                unit="s",
                baseline_name="as written",
                baseline_value=t_raw,
                details={
                    "iterations": pre.iterations,
                    "baseline_iterations": raw.iterations,
                    "max_abs_strength_difference": float(np.max(np.abs(pre.scale - raw.scale))),
                    "objective": pre.objective,
                    "baseline_objective": raw.objective,
                    "strength_error_median": float(np.median(np.abs(pre.f_max / f_true - 1.0))),
                },
            )
        )
    return results
