"""Write a synthetic session as the project's trial files (TOML + OpenSim storage) plus a truth file (JSON).

Layout under ``out``::

    truth.json                          subject, effects, F_max truth, per-trial facts and file list
    <exercise>/mvc_emg.sto              MVC block (one channel after another)
    <exercise>/mvc/<channel>/           that channel's maximal contraction as an isometric trial (``isometric = true``):
        trial.toml  ik.sto  id.sto  emg.sto   test position, dynamometer joint torques, EMG of every site
    <exercise>/<exercise>_<load>kg/
        trial.toml                      read by msk calibrate / estimate / evaluate
        ik.sto  id.sto  emg.sto         kinematics (rad), inverse dynamics with the *reported* load, EMG
        truth_activations.sto           true activations per group
        truth_torques.sto               true ID torque (true load) and the muscle torque per coordinate

``emg.sto`` holds either the raw EMG at 2000 Hz (``EmgOutput.RAW``, large) or its zero-phase envelope at the
kinematics rate (``EmgOutput.ENVELOPE``, the default); ``[emg_max]`` in the TOML is the MVC amplitude (highest 0.5 s mean of the envelope) of the same
chain, so the trial loader normalises to MVC either way.
"""

from __future__ import annotations

import enum
import json
from pathlib import Path

import numpy as np
import tomli_w

from msk_core.io import write_sto
from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal, mvc_window_samples, windowed_peak
from msk_core.synth.session import ExerciseSession, Session, Trial

TRUTH_FORMAT = "msk-synth-truth/1"

# Storage files are written with values rounded far below every noise level (angles to 1e-8 rad, torques to 1 µN·m,
# activations to 1e-7, EMG to 0.1 nV): the text is then about half as long as full double precision.
_DECIMALS = {"angle": 8, "torque": 6, "activation": 7, "emg": 10}


def _r(x: np.ndarray, kind: str) -> np.ndarray:
    return np.round(np.asarray(x, dtype=float), _DECIMALS[kind])


MVC_ENVELOPE_RATE_HZ = 50.0  # the 6 Hz envelope needs no more; keeps the MVC file small


class EmgOutput(enum.Enum):
    ENVELOPE = "envelope"
    RAW = "raw"


def _envelope(emg: np.ndarray, rate_hz: float) -> np.ndarray:
    return envelope_zero_phase_noncausal(emg, EmgFilterConfig(rate_hz=rate_hz))


def mvc_maxima(channels: list[str], envelope: np.ndarray, rate_hz: float) -> dict[str, float]:
    """MVC amplitude per channel from the MVC recording's envelope (``_envelope`` of its raw EMG)."""
    peaks = windowed_peak(envelope, mvc_window_samples(rate_hz))
    return {ch: float(peaks[k]) for k, ch in enumerate(channels)}


def _downsample(time_hi: np.ndarray, x: np.ndarray, time_lo: np.ndarray) -> np.ndarray:
    return np.column_stack([np.interp(time_lo, time_hi, x[:, k]) for k in range(x.shape[1])])


def write_trial(
    trial: Trial,
    folder: Path,
    *,
    emg_max: dict[str, float],
    body_mass_kg: float,
    emg_rate_hz: float,
    emg_output: EmgOutput,
) -> dict:
    folder.mkdir(parents=True, exist_ok=True)
    name = f"msk-synth {trial.name}"
    write_sto(folder / "ik.sto", trial.time, trial.coordinates, _r(trial.q, "angle"), name=name)
    write_sto(
        folder / "id.sto",
        trial.time,
        [f"{c}_moment" for c in trial.coordinates],
        _r(trial.torque_reported, "torque"),
        name=name,
    )
    if emg_output is EmgOutput.RAW:
        write_sto(folder / "emg.sto", trial.emg_time, trial.channels, _r(trial.emg, "emg"), name=name)
    else:
        env = _downsample(trial.emg_time, _envelope(trial.emg, emg_rate_hz), trial.time)
        write_sto(folder / "emg.sto", trial.time, trial.channels, _r(env, "emg"), name=name)
    write_sto(folder / "truth_activations.sto", trial.time, trial.groups, _r(trial.activation, "activation"), name=name)
    write_sto(
        folder / "truth_torques.sto",
        trial.time,
        [f"{c}_id" for c in trial.coordinates] + [f"{c}_muscle" for c in trial.coordinates],
        _r(np.column_stack([trial.torque_id, trial.torque_muscle]), "torque"),
        name=name,
    )
    spec = {
        "name": trial.name,
        "kinematics": "ik.sto",
        "torques": "id.sto",
        "emg": "emg.sto",
        "emg_is_envelope": emg_output is EmgOutput.ENVELOPE,
        "load_kg": trial.reported_load_kg,
        "body_mass_kg": body_mass_kg,
        "emg_map": {ch: ch for ch in trial.channels},
        "emg_max": {ch: emg_max[ch] for ch in trial.channels},
    }
    (folder / "trial.toml").write_bytes(tomli_w.dumps(spec).encode())
    return {
        "name": trial.name,
        "trial": str(Path(folder.name) / "trial.toml"),
        "load_kg": trial.load_kg,
        "reported_load_kg": trial.reported_load_kg,
        "duration_s": float(trial.time[-1]),
        "rep_starts_s": [float(x) for x in trial.rep_starts],
        "rep_ends_s": [float(x) for x in trial.rep_ends],
        "peak_abs_torque_nm": dict(zip(trial.coordinates, map(float, np.abs(trial.torque_id).max(axis=0)))),
        "peak_activation": dict(zip(trial.groups, map(float, trial.activation.max(axis=0)))),
        "max_abs_torque_residual_nm": float(np.abs(trial.residual).max()),
        "frames_beyond_capacity": int(trial.fallback_frames),
        "imu": [{"tracker_id": s.tracker_id, "segment": s.segment, "body": s.body} for s in trial.imu],
    }


ISOMETRIC_RATE_HZ = 50.0  # isometric trials: a static pose and 6 Hz envelopes need no more


def write_isometric_trials(
    ex: ExerciseSession, folder: Path, *, emg_max: dict[str, float], envelope: np.ndarray, emg_output: EmgOutput
) -> list[dict]:
    """One isometric trial per MVC block (the contraction of one site, the EMG of all), under ``folder/mvc``;
    ``envelope`` is the whole MVC recording's (sliced per block, so no block starts with a filter transient)."""
    mvc = ex.mvc
    poses, torque = mvc.poses, mvc.torque  # simulated together, with a pack
    if poses is None or torque is None:
        return []
    out = []
    for k, ch in enumerate(mvc.channels):
        sl = mvc.block(k)
        t_hi = mvc.time[sl] - mvc.time[sl][0]
        t_lo = np.arange(0.0, t_hi[-1], 1.0 / ISOMETRIC_RATE_HZ)
        sub = folder / "mvc" / ch
        sub.mkdir(parents=True, exist_ok=True)
        name = f"msk-synth mvc {ch}"
        coords = mvc.coordinates
        write_sto(sub / "ik.sto", t_lo, coords, _r(np.repeat(poses[k][None], t_lo.size, 0), "angle"), name=name)
        write_sto(
            sub / "id.sto",
            t_lo,
            [f"{c}_moment" for c in coords],
            _r(_downsample(t_hi, torque[sl], t_lo), "torque"),
            name=name,
        )
        if emg_output is EmgOutput.RAW:
            write_sto(sub / "emg.sto", t_hi, mvc.channels, _r(mvc.emg[sl], "emg"), name=name)
        else:
            write_sto(sub / "emg.sto", t_lo, mvc.channels, _r(_downsample(t_hi, envelope[sl], t_lo), "emg"), name=name)
        spec = {
            "name": f"mvc_{ch}",
            "isometric": True,
            "kinematics": "ik.sto",
            "torques": "id.sto",
            "emg": "emg.sto",
            "emg_is_envelope": emg_output is EmgOutput.ENVELOPE,
            "body_mass_kg": ex.subject.mass_kg,
            "emg_map": {c: c for c in mvc.channels},
            "emg_max": {c: emg_max[c] for c in mvc.channels},
        }
        (sub / "trial.toml").write_bytes(tomli_w.dumps(spec).encode())
        out.append(
            {
                "channel": ch,
                "trial": str(Path("mvc") / ch / "trial.toml"),
                "pose_deg": dict(zip(coords, np.degrees(poses[k]).round(3).tolist())),
                "peak_abs_torque_nm": dict(zip(coords, map(float, np.abs(torque[sl]).max(axis=0)))),
            }
        )
    return out


def write_session(session: Session, out: str | Path, *, emg_output: EmgOutput = EmgOutput.ENVELOPE) -> Path:
    """Write every exercise and the truth file. Returns the truth file's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cfg = session.config
    truth: dict = {
        "format": TRUTH_FORMAT,
        "subject_seed": cfg.subject_seed,
        "n_reps": cfg.n_reps,
        "rates_hz": {"kinematics": cfg.kinematics_rate_hz, "emg": cfg.emg_rate_hz, "imu": cfg.imu_rate_hz},
        "effects": cfg.effects.to_dict(),
        "effects_active": cfg.effects.active(),
        "recruitment": "min sum_g w_g(t) a_g^2, exact torque match, floors tone + c_g*effort (msk_core.synth.recruitment)",
        "exercises": {},
    }
    for ex in session.exercises:
        folder = out / ex.spec.exercise.value
        folder.mkdir(parents=True, exist_ok=True)
        mvc_envelope = _envelope(ex.mvc.emg, cfg.emg_rate_hz)  # once: maxima, mvc_emg.sto, isometric trials
        maxima = mvc_maxima(ex.mvc.channels, mvc_envelope, cfg.emg_rate_hz)
        if emg_output is EmgOutput.RAW:
            write_sto(folder / "mvc_emg.sto", ex.mvc.time, ex.mvc.channels, _r(ex.mvc.emg, "emg"), name="msk-synth mvc")
        else:
            t_lo = np.arange(0.0, ex.mvc.time[-1], 1.0 / MVC_ENVELOPE_RATE_HZ)
            env = _downsample(ex.mvc.time, mvc_envelope, t_lo)
            write_sto(folder / "mvc_emg.sto", t_lo, ex.mvc.channels, _r(env, "emg"), name="msk-synth mvc envelope")
        isometric = write_isometric_trials(ex, folder, emg_max=maxima, envelope=mvc_envelope, emg_output=emg_output)
        trials = [
            write_trial(
                t,
                folder / t.name,
                emg_max=maxima,
                body_mass_kg=ex.subject.mass_kg,
                emg_rate_hz=cfg.emg_rate_hz,
                emg_output=emg_output,
            )
            for t in ex.trials
        ]
        truth["exercises"][ex.spec.exercise.value] = {
            "pack": ex.pack_name,
            "subject": ex.subject.to_dict(),
            "f_max_n": dict(zip(ex.subject.groups, map(float, ex.f_max))),
            "channels": ex.mvc.channels,
            "emg_max": maxima,
            "mvc": str(Path(ex.spec.exercise.value) / "mvc_emg.sto"),
            "isometric_trials": [{**t, "trial": str(Path(ex.spec.exercise.value) / t["trial"])} for t in isometric],
            "trials": [{**t, "trial": str(Path(ex.spec.exercise.value) / t["trial"])} for t in trials],
        }
    path = out / "truth.json"
    path.write_text(json.dumps(truth, indent=2, sort_keys=True) + "\n")
    return path
