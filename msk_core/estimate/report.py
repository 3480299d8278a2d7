"""``msk evaluate`` report: per trial and method, activation RMSE against measured EMG, torque tracking, plots."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from msk_core.estimate.metrics import activation_rmse, torque_tracking
from msk_core.estimate.pipeline import TrialEstimate, estimate_trial, trial_phase
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.trial import TrialData

METHODS = ("proposed", "so", "hybrid", "prior")
# Published EMG-driven range for such lifts (the reference: R 0.88-0.94, RMSE 0.21-0.38 N·m/kg).
PUBLISHED_EMG_DRIVEN = {"r": (0.88, 0.94), "rmse_nm_per_kg": (0.21, 0.38)}


@dataclass
class MethodScore:
    trial: str
    method: str
    activation_rmse: dict[str, float]
    torque: dict[str, dict[str, float]]
    flag_counts: dict[str, int]
    frames: int


def evaluate(
    pack, subject: SubjectProfile, trials: list[TrialData], *, methods=METHODS, progress: bool = False, **options
) -> tuple[list[MethodScore], dict[tuple[str, str], TrialEstimate]]:
    """Every method over every trial; ``options`` go to each :class:`FrameEstimator` (solver, activation bounds)."""
    scores, runs = [], {}
    for trial in trials:
        for method in methods:
            run = estimate_trial(pack, trial, method, subject=subject, progress=progress, **options)
            runs[(trial.name, method)] = run
            scores.append(
                MethodScore(
                    trial=trial.name,
                    method=method,
                    activation_rmse=activation_rmse(run.activations, run.groups, trial.emg),
                    torque=torque_tracking(run.model_torques, run.torques, run.coordinates, trial.body_mass_kg),
                    flag_counts=run.flag_counts,
                    frames=trial.n_frames,
                )
            )
    return scores, runs


def markdown_table(scores: list[MethodScore]) -> str:
    groups = [g for g in scores[0].activation_rmse if g != "mean"] if scores else []
    coords = list(scores[0].torque) if scores else []
    head = ["trial", "method", "act. RMSE (mean)"] + groups
    for c in coords:
        head += [f"{c} R", f"{c} RMSE N·m", f"{c} RMSE N·m/kg"]
    head += ["flagged frames"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in scores:
        row = [s.trial, s.method, f"{s.activation_rmse['mean']:.4f}"] + [f"{s.activation_rmse[g]:.4f}" for g in groups]
        for c in coords:
            t = s.torque[c]
            row += [f"{t['r']:.3f}", f"{t['rmse_nm']:.2f}", f"{t['rmse_nm_per_kg']:.3f}"]
        flagged = {k: v for k, v in s.flag_counts.items()}
        row.append(", ".join(f"{k}: {v}" for k, v in flagged.items()) or "0")
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def plot_trial(trial: TrialData, runs: dict[tuple[str, str], TrialEstimate], subject: SubjectProfile, out: Path):
    """One PNG per measured muscle group: measured EMG, estimates per method, and the prior band mu +- sigma."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    written = []
    t = trial.time - trial.time[0]
    prior_at = [subject.prior.at(trial_phase(trial, i)) for i in range(trial.n_frames)]
    prior_mu = np.array([m for m, _ in prior_at])
    prior_sd = np.array([s for _, s in prior_at])
    groups = list(subject.groups)
    for g in trial.emg:
        j = groups.index(g)
        fig, ax = plt.subplots(figsize=(10, 3.2))
        ax.fill_between(t, prior_mu[:, j] - prior_sd[:, j], prior_mu[:, j] + prior_sd[:, j], color="0.85",
                        label="prior μ ± σ")
        ax.plot(t, trial.emg[g], color="k", lw=1.5, label="measured (EMG)")
        if (trial.name, "proposed") in runs:
            run = runs[(trial.name, "proposed")]
            a, s = run.activations[:, j], run.activation_std[:, j]
            ax.fill_between(t, a - s, a + s, color="C0", alpha=0.2, lw=0, label="proposed ± Laplace std")
        for method, style in (("proposed", "C0-"), ("so", "C3--"), ("hybrid", "C2:")):
            if (trial.name, method) in runs:
                ax.plot(t, runs[(trial.name, method)].activations[:, j], style, lw=1.2, label=method)
        ax.set_title(f"{trial.name}: {g}")
        ax.set_xlabel("time (s)")
        ax.set_ylabel("activation")
        ax.set_ylim(bottom=0)
        ax.legend(loc="upper right", fontsize=8, ncol=5)
        fig.tight_layout()
        path = out / f"{trial.name}_{g}.png"
        fig.savefig(path, dpi=80)
        plt.close(fig)
        written.append(path)
    # torque tracking plot
    fig, ax = plt.subplots(len(trial.torques[0]), 1, figsize=(10, 3 * len(trial.torques[0])), squeeze=False)
    for k, c in enumerate(runs[next(iter(k for k in runs if k[0] == trial.name))].coordinates):
        ax[k, 0].plot(t, trial.torques[:, k], "k", lw=1.5, label="inverse dynamics")
        for method, style in (("proposed", "C0-"), ("so", "C3--"), ("prior", "C1:")):
            if (trial.name, method) in runs:
                ax[k, 0].plot(t, runs[(trial.name, method)].model_torques[:, k], style, label=method)
        ax[k, 0].set_title(f"{trial.name}: {c} torque (N·m)")
        ax[k, 0].legend(fontsize=8)
    fig.tight_layout()
    path = out / f"{trial.name}_torque.png"
    fig.savefig(path, dpi=80)
    plt.close(fig)
    written.append(path)
    return written


def write_report(pack, subject: SubjectProfile, trials: list[TrialData], out: Path, *, progress: bool = False,
                 **options) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    scores, runs = evaluate(pack, subject, trials, progress=progress, **options)
    plots = []
    for trial in trials:
        plots += plot_trial(trial, runs, subject, out)
    table = markdown_table(scores)
    lo_r, hi_r = PUBLISHED_EMG_DRIVEN["r"]
    lo_e, hi_e = PUBLISHED_EMG_DRIVEN["rmse_nm_per_kg"]
    md = [
        f"# Evaluation: pack {pack.name} v{pack.version}, subject calibrated on "
        f"{', '.join(Path(p).name for p in subject.provenance.get('trials', []))}",
        "",
        "Activation RMSE: estimated vs measured (normalised EMG envelope) activation, per group with EMG.",
        "Torque: model torque vs inverse dynamics (Pearson R, RMSE).",
        f"Published EMG-driven range for such lifts: R {lo_r}-{hi_r}, RMSE {lo_e}-{hi_e} N·m/kg.",
        "",
        table,
        "",
        "Plots: " + ", ".join(f"[{p.name}]({p.name})" for p in plots),
        "",
    ]
    (out / "report.md").write_text("\n".join(md))
    data = {
        "pack": {"name": pack.name, "version": str(pack.version)},
        "scores": [s.__dict__ for s in scores],
        "published_emg_driven": PUBLISHED_EMG_DRIVEN,
    }
    (out / "metrics.json").write_text(json.dumps(data, indent=2, default=float))
    return data


def strength_markdown(calibration: dict) -> str:
    """Per exercise: calibrated F_max against the generator's truth and the model's reference, with the status."""
    lines = []
    for exercise, rep in calibration.items():
        lines += [
            f"### {exercise}: calibrated on {rep['trials']['lift']}"
            + (f" + {rep['trials']['isometric']} isometric MVC trials" if rep["trials"]["isometric"] else "")
            + f" in {rep['seconds']:.1f} s",
            "",
            f"Median |F_max / truth - 1|: {100 * rep['strength_error_median']:.1f} % "
            f"(model reference {100 * rep['reference_error_median']:.1f} %).",
            "",
            "| group | status | calibrated F_max (N) | true F_max (N) | error | reference (N) | reference error |",
            "|---|---|---|---|---|---|---|",
        ]
        for g, v in rep["groups"].items():
            lines.append(
                f"| {g} | {v['status']} | {v['f_max_n']:.0f} | {v['truth_n']:.0f} | {100 * (v['f_max_n'] / v['truth_n'] - 1):+.0f} % "
                f"| {v['reference_n']:.0f} | {100 * (v['reference_n'] / v['truth_n'] - 1):+.0f} % |"
            )
        lines.append("")
    return "\n".join(lines)


STRENGTH_COLOURS = {"identified": "tab:green", "not_calibrated": "dimgrey"}


def plot_strength(calibration: dict, out: Path) -> Path:
    """F_max / truth per group: calibrated and the model's reference (1 = exact)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(calibration), 1, figsize=(13, 2.8 * len(calibration)), squeeze=False)
    for ax, (exercise, rep) in zip(axes[:, 0], calibration.items()):
        groups = list(rep["groups"])
        x = np.arange(len(groups))
        cal = [rep["groups"][g]["f_max_n"] / rep["groups"][g]["truth_n"] for g in groups]
        ref = [rep["groups"][g]["reference_n"] / rep["groups"][g]["truth_n"] for g in groups]
        ax.bar(x - 0.2, ref, 0.4, color="lightgrey")
        status = [rep["groups"][g]["status"] for g in groups]
        ax.bar(x + 0.2, cal, 0.4, color=[STRENGTH_COLOURS.get(st, "tab:orange") for st in status])
        ax.axhline(1.0, color="black", lw=1)
        ax.axhspan(0.9, 1.1, color="tab:green", alpha=0.08)
        ax.set_xticks(x, groups, rotation=45, ha="right", fontsize=8)
        ax.set_ylim(0.0, max(1.5, 1.05 * max(cal + ref)))
        ax.set_ylabel("F_max / truth")
        ax.set_title(f"{exercise}: median error {100 * rep['strength_error_median']:.0f} % "
                     f"(reference {100 * rep['reference_error_median']:.0f} %)", fontsize=10)
    from matplotlib.patches import Patch

    handles = [Patch(color="lightgrey", label="model reference"),
               Patch(color=STRENGTH_COLOURS["identified"], label="calibrated: identified"),
               Patch(color="tab:orange", label="calibrated: combination / unidentified / at bound"),
               Patch(color=STRENGTH_COLOURS["not_calibrated"], label="no EMG: kept at reference")]
    axes[0, 0].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    fig.tight_layout()
    path = out / "strength.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path
