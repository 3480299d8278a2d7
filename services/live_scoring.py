"""Scoring a live run against the generator's truth: the activation frames an MCAP recording holds, cut into trials
by its load events and compared with each trial's true activations (RMSE per method and group, torque residual,
solver time, end-to-end latency), as a markdown table and plots. ``msk demo`` uses it; any recording of a synthetic
session (``msk synth``) can be scored the same way. Beside it, :mod:`msk_core.estimate.scores` scores trials offline.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msk_core.errors import InputError
from msk_core.io import read_sto
from services import messages
from services.mcap_io import read_messages

METHODS = ("proposed", "so", "hybrid")


@dataclass
class TrialWindow:
    exercise: str
    load_kg: float
    start_s: float
    end_s: float

    @property
    def name(self) -> str:
        return f"{self.exercise}_{self.load_kg:g}kg"


@dataclass
class MethodScore:
    exercise: str
    trial: str
    role: str  # "calibration" or "held out"
    method: str
    frames: int
    activation_rmse: float
    torque_rmse_nm: float
    flagged: int
    solve_us_median: float
    solve_us_p99: float
    latency_ms_median: float
    latency_ms_p99: float
    per_group_rmse: dict[str, float] = field(default_factory=dict)


def _trial_folders(recordings: Path, exercise: str) -> list[Path]:
    folders = sorted(p for p in (recordings / "demo" / exercise).iterdir() if (p / "trial.toml").is_file())
    if len(folders) < 2:
        raise InputError(
            "the demo needs two trials per exercise (calibration + held out)", path=recordings / "demo" / exercise
        )
    return sorted(folders, key=lambda p: float(p.name.rsplit("_", 1)[1].removesuffix("kg")))


def trial_windows(load_events: list) -> list[TrialWindow]:
    """Trials as the load events delimit them: a non-zero mass opens one, the next zero closes it."""
    windows, open_window = [], None
    for event in load_events:
        t = event.device_time_ns / 1e9
        if event.barbell_mass_kg > 0:
            open_window = TrialWindow(event.exercise, event.barbell_mass_kg, t, float("inf"))
        elif open_window is not None:
            open_window.end_s = t
            windows.append(open_window)
            open_window = None
    return windows


def score(recorded_mcap: Path, recordings: Path) -> tuple[list[MethodScore], dict]:
    frames: dict[str, list] = {m: [] for m in METHODS}
    load_events = []
    for recorded in read_messages(recorded_mcap):  # one pass over the recording for frames and load events
        if recorded.type_name == "msk.ActivationFrame":
            frame = recorded.decode(messages.ActivationFrame)
            frames[frame.method].append(frame)
        elif recorded.type_name == "msk.LoadEvent":
            load_events.append(recorded.decode(messages.LoadEvent))
    scores, curves = [], {}
    for window in trial_windows(load_events):
        folders = _trial_folders(recordings, window.exercise)
        folder = next((f for f in folders if f.name == window.name), None)
        if folder is None:
            continue
        role = "calibration" if folder == folders[0] else "held out"
        truth = read_sto(folder / "truth_activations.sto")
        for method in METHODS:
            inside = [
                f
                for f in frames[method]
                if window.start_s - 1e-6 <= f.time_s <= window.end_s + 1e-6 and set(f.groups) == set(truth.columns)
            ]
            if not inside:
                continue
            groups = list(inside[0].groups)
            t = np.array([f.time_s - window.start_s for f in inside])
            estimated = np.array([f.activations for f in inside])
            true = np.column_stack([np.interp(t, truth.time, truth.column(g)) for g in groups])
            ok = np.all(np.isfinite(estimated), axis=1)
            residual = np.array([[c.residual_nm for c in f.torques] for f in inside])
            solve = np.array([f.solve_time_s for f in inside]) * 1e6
            latency = np.array([(f.publish_ns - f.input_arrival_ns) / 1e6 for f in inside])
            per_group = {
                g: float(np.sqrt(np.mean((estimated[ok, i] - true[ok, i]) ** 2))) for i, g in enumerate(groups)
            }
            scores.append(
                MethodScore(
                    exercise=window.exercise,
                    trial=window.name,
                    role=role,
                    method=method,
                    frames=len(inside),
                    activation_rmse=float(np.sqrt(np.mean((estimated[ok] - true[ok]) ** 2))),
                    torque_rmse_nm=float(np.sqrt(np.mean(residual[ok] ** 2))),
                    flagged=int(sum(1 for f in inside if f.flags)),
                    solve_us_median=float(np.median(solve)),
                    solve_us_p99=float(np.percentile(solve, 99)),
                    latency_ms_median=float(np.median(latency)),
                    latency_ms_p99=float(np.percentile(latency, 99)),
                    per_group_rmse=per_group,
                )
            )
            curves[(window.name, method)] = (t, estimated, true, groups)
    return scores, curves


def markdown(scores: list[MethodScore]) -> str:
    lines = [
        "| trial | role | method | frames | activation RMSE | torque residual RMS (N·m) | flagged | solve µs (median / p99) | latency ms (median / p99) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in scores:
        lines.append(
            f"| {s.trial} | {s.role} | {s.method} | {s.frames} | {s.activation_rmse:.3f} | {s.torque_rmse_nm:.2f} | {s.flagged} | "
            f"{s.solve_us_median:.0f} / {s.solve_us_p99:.0f} | {s.latency_ms_median:.2f} / {s.latency_ms_p99:.2f} |"
        )
    return "\n".join(lines)


def plot(curves: dict, scores: list[MethodScore], out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    for trial in sorted({s.trial for s in scores if s.role == "held out"}):
        truth_t, _, truth, groups = curves[(trial, "proposed")]
        # The four groups that work hardest in the truth: where people look first.
        top = np.argsort(truth.max(axis=0))[::-1][:4]
        fig, axes = plt.subplots(len(top), 1, figsize=(10, 2.2 * len(top)), sharex=True)
        for ax, gi in zip(np.atleast_1d(axes), top):
            ax.plot(truth_t, truth[:, gi], color="black", lw=2, label="truth")
            for method, colour in zip(METHODS, ("tab:green", "tab:red", "tab:blue")):
                t, est, _, _ = curves[(trial, method)]
                ax.plot(t, est[:, gi], color=colour, lw=1, label=method)
            ax.set_ylabel(groups[gi])
            ax.set_ylim(0, 1)
        np.atleast_1d(axes)[0].legend(loc="upper right", ncol=4, fontsize=8)
        np.atleast_1d(axes)[-1].set_xlabel("time in trial (s)")
        fig.suptitle(f"{trial} (held out from calibration): live activations vs truth")
        fig.tight_layout()
        path = out / f"{trial}.png"
        fig.savefig(path, dpi=100)
        plt.close(fig)
        written.append(path)
    return written
