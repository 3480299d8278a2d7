"""The ``msk evaluate`` report: report.md (the scores table), metrics.json and PNG plots per trial. The scores and
the numbers plotted come from :mod:`msk_core.estimate.scores`."""

from __future__ import annotations

import json
from pathlib import Path

from msk_core.estimate.pipeline import TrialEstimate
from msk_core.estimate.profile import SubjectProfile
from msk_core.estimate.scores import PUBLISHED_EMG_DRIVEN, MethodScore, evaluate, prior_band
from msk_core.estimate.trial import TrialData
from msk_core.progress import Progress
from services.reports import pyplot


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
    plt = pyplot()
    written = []
    t = trial.time - trial.time[0]
    prior_mu, prior_sd = prior_band(trial, subject)
    groups = list(subject.groups)
    for g in trial.emg:
        j = groups.index(g)
        fig, ax = plt.subplots(figsize=(10, 3.2))
        ax.fill_between(
            t, prior_mu[:, j] - prior_sd[:, j], prior_mu[:, j] + prior_sd[:, j], color="0.85", label="prior μ ± σ"
        )
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


def write_report(
    pack, subject: SubjectProfile, trials: list[TrialData], out: Path, *, progress: Progress | None = None, **options
) -> dict:
    """Score every method over every trial and write out/report.md, out/metrics.json and the plots."""
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
