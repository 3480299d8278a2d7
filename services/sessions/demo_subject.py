"""The bundled synthetic subject: calibrated (strength per muscle group + the EMG prior) on the lighter-load trial and
the isometric MVC trials of ``recordings/demo`` (written by ``msk synth``) and scored against the generator's truth.
``msk demo`` calibrates it into its output folder; ``msk live --sim`` reuses one cached under the user cache folder
(:func:`sim_subject`); ``msk bench`` calibrates it too. Below both sessions: neither imports the other for it.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[2]
RECORDINGS = REPO_ROOT / "recordings"


def calibration_trial_files(recordings: Path, exercise: str) -> tuple[Path, list[Path]]:
    """The demo's calibration input for an exercise: the lighter lift's folder and the isometric MVC trial files."""
    from services.sessions.live_scoring import _trial_folders

    return _trial_folders(recordings, exercise)[0], sorted(
        (recordings / "demo" / exercise / "mvc").glob("*/trial.toml")
    )


def calibrate(recordings: Path, out: Path, exercise: str, log) -> tuple[Path, dict]:
    """Calibrate the bundled subject for ``exercise`` into OUT/subject_<exercise>.json; returns the path and a report
    of the strengths against the generator's truth (``recordings/demo/truth.json``)."""
    from msk_core.estimate.pipeline import calibrate_subject
    from msk_core.estimate.trial import load_trial
    from msk_core.model import load_pack

    pack = load_pack(exercise)
    training, isometric = calibration_trial_files(recordings, exercise)
    log(
        f"[{exercise}] calibrating on {training.name}"
        + (f" + {len(isometric)} isometric MVC trials" if isometric else "")
        + " ..."
    )
    started = time.perf_counter()
    trials = [load_trial(training / "trial.toml", pack)] + [load_trial(p, pack) for p in isometric]
    profile, result = calibrate_subject(pack, trials)
    path = out / f"subject_{exercise}.json"
    profile.save(path)
    truth = json.loads((recordings / "demo" / "truth.json").read_text())["exercises"][exercise]["f_max_n"]
    true_f = np.array([truth[g] for g in pack.groups])
    error = np.abs(profile.f_max / true_f - 1.0)
    measured = np.array([s != "not_calibrated" for s in result.status])
    identified = result.identified

    def median(mask: np.ndarray) -> float | None:
        return float(np.median(error[mask])) if np.any(mask) else None

    seconds = time.perf_counter() - started
    error_all, error_emg, error_identified = float(np.median(error)), median(measured), median(identified)
    identified_groups = [g for g, ok in zip(pack.groups, identified) if ok]
    reference_error = float(np.median(np.abs(np.asarray(pack.f_max_ref) / true_f - 1.0)))
    report = {
        "trials": {"lift": training.name, "isometric": len(isometric)},
        "groups": {
            g: {"f_max_n": float(f), "truth_n": float(t), "reference_n": float(r), "status": st}
            for g, f, t, r, st in zip(pack.groups, profile.f_max, true_f, pack.f_max_ref, result.status)
        },
        "seconds": seconds,
        "converged": bool(result.report().get("converged", True)),
        "strength_error_median": error_all,
        "strength_error_median_emg": error_emg,
        "strength_error_median_identified": error_identified,
        "identified_groups": identified_groups,
        "status": dict(zip(pack.groups, result.status)),
        "reference_error_median": reference_error,
    }

    def pct(x: float | None) -> str:
        return "n/a" if x is None else f"{100 * x:.0f} %"

    log(
        f"[{exercise}] calibrated in {seconds:.1f} s; median |F_max error| vs truth: all groups "
        f"{pct(error_all)}, EMG-measured ({int(measured.sum())}) "
        f"{pct(error_emg)}, identified ({int(identified.sum())}: "
        f"{', '.join(identified_groups) or 'none'}) {pct(error_identified)} "
        f"(model reference: {pct(reference_error)})"
    )
    return path, report


def science_digest() -> str:
    """A digest of what a calibrated profile depends on besides the recordings: the science code and the model packs
    (every ``.py`` and ``.json`` under ``msk_core``). A profile calibrated by other code is calibrated again."""
    import hashlib

    import msk_core

    root = Path(msk_core.__file__).parent
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".json") and "__pycache__" not in p.parts):
        digest.update(path.relative_to(root).as_posix().encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()[:12]


def sim_subject(pack: str, log) -> Path:
    """The bundled subject calibrated for ``pack`` as ``msk demo`` does, cached under the user cache folder and reused
    while it is newer than the bundled recordings and was calibrated by this science code (:func:`science_digest`
    names the file); profiles of other code are removed."""
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "msk-live" / "live-sim"
    path = cache / f"subject_{pack}_{science_digest()}.json"
    newest = max(p.stat().st_mtime for p in (RECORDINGS / "demo").rglob("*") if p.is_file())
    if path.is_file() and path.stat().st_mtime >= newest:
        log(f"reusing the calibrated bundled subject {path}")
        return path
    cache.mkdir(parents=True, exist_ok=True)
    for stale in [*cache.glob(f"subject_{pack}.json"), *cache.glob(f"subject_{pack}_{'?' * 12}.json")]:
        stale.unlink(missing_ok=True)  # calibrated by other code, or before the recordings changed
    made, _ = calibrate(RECORDINGS, cache, pack, log)
    return made.rename(path)
