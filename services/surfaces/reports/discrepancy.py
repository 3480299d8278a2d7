"""The ``msk discrepancy`` report: summary.json, report.md and PNG plots of a :class:`DiscrepancyResult`, and the
sentences saying how consistently the named effect helps, rep by rep (printed by the command too)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from msk_core.discrepancy.data import describe_left_out
from msk_core.discrepancy.workflow import DiscrepancyResult
from msk_core.io.files import json_text
from services.surfaces.reports import pyplot, save_figure


def _relation_plot(path: Path, result: DiscrepancyResult, key: str, xlabel: str, scale: float = 1.0) -> None:
    """The mean torque gap against ``key`` (binned by the workflow) per coordinate, before and after; x times
    ``scale`` (radians shown as degrees)."""
    plt = pyplot()
    coords = result.data.coordinates
    fig, axes = plt.subplots(1, len(coords), figsize=(3.6 * len(coords), 3.2), squeeze=False)
    for ax, c in zip(axes[0], coords):
        for rel, label, style in ((result.relations_before, "before", "o-"), (result.relations_after, "after", "s--")):
            r = rel["coordinates"][c][key]
            if r.get("x"):
                ax.plot(np.asarray(r["x"], dtype=float) * scale, r["gap"], style, ms=3, label=label)
        ax.axhline(0, color="0.6", lw=0.8)
        ax.set_title(c, fontsize=9)
        ax.set_xlabel(xlabel)
    axes[0][0].set_ylabel("mean torque gap (fraction of capacity)")
    axes[0][0].legend(fontsize=8)
    save_figure(fig, path, dpi=90)


def _xcorr_plot(path: Path, result: DiscrepancyResult) -> None:
    plt = pyplot()
    xc = result.relations_before["xcorr"]
    fig, ax = plt.subplots(figsize=(5, 3.2))
    for c, corr in zip(result.data.coordinates, xc["corr"]):
        ax.plot(np.asarray(xc["lag_s"]) * 1000, corr, label=c)
    ax.axvline(0, color="0.6", lw=0.8)
    ax.set_xlabel("lag of the EMG-implied torque (ms; > 0: EMG leads)")
    ax.set_ylabel("correlation")
    ax.legend(fontsize=7)
    save_figure(fig, path, dpi=90)


def _before_after_bars(ax, per_name: dict, title: str, ylabel: str, rotation: int) -> None:
    names = list(per_name)
    x = np.arange(len(names))
    ax.bar(x - 0.2, [per_name[n]["before"] for n in names], 0.4, label="before")
    ax.bar(x + 0.2, [per_name[n]["after"] for n in names], 0.4, label="after")
    ax.set_xticks(x, names, rotation=rotation, fontsize=7)
    ax.set_title(title, fontsize=9)  # the long words in the title: as a y label they ran off the figure
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)


def _rms_plot(path: Path, summary: dict) -> None:
    plt = pyplot()
    per_c = summary["gap_per_coordinate"]
    per_g = summary.get("activation_gap_per_group", {})
    fig, axes = plt.subplots(1, 2 if per_g else 1, figsize=(10 if per_g else 5, 3.4), squeeze=False)
    _before_after_bars(axes[0][0], per_c, "held-out RMS torque gap", "fraction of capacity", 30)
    if per_g:
        _before_after_bars(axes[0][1], per_g, "held-out RMS activation gap", "estimate - EMG", 60)
    save_figure(fig, path, dpi=90)


def consistency_sentences(summary: dict) -> list[str]:
    """How sure, rep by rep: one sentence per named effect (greedy step) on the held-out reps it improves, and a
    warning when its evidence is mostly between the reps (set-up, rests) rather than in them."""
    out = []
    for step in summary["greedy_steps"]:
        win = next((c for c in step if c["accepted"]), None)
        if win is None:
            continue
        reps = win.get("holdout_reps") or {}
        if not reps.get("reps"):
            continue
        between = reps.get("between_reps_reduction")
        text = (
            f"{win['effect']} lowers the unexplained torque in {reps['improved']} of {reps['reps']} held-out reps "
            f"(median {reps['median_reduction']:.0%}, lowest {reps['min_reduction']:.0%})"
        )
        text += "." if between is None else f"; between reps (set-up, rests): {between:.0%}."
        if between is not None and between > 0 and reps["improved"] * 2 <= reps["reps"]:
            text += " Most of its evidence is outside the reps: check what the athlete did there."
        out.append(text)
    return out


def write_report(result: DiscrepancyResult, folder: Path) -> Path:
    """Write folder/summary.json, folder/report.md and its plots; returns the path of report.md."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    s = result.summary
    (folder / "summary.json").write_text(json_text(s, default=float))
    _relation_plot(folder / "gap_vs_angle.png", result, "angle", "joint angle (deg)", math.degrees(1.0))
    _relation_plot(folder / "gap_vs_velocity.png", result, "velocity", "joint velocity (deg/s)", math.degrees(1.0))
    _relation_plot(folder / "gap_vs_phase.png", result, "phase", "phase of the rep")
    _xcorr_plot(folder / "xcorr_vs_lag.png", result)
    _rms_plot(folder / "gap_rms.png", s)
    lines = _headline_lines(s) + _candidate_lines(s) + _gap_lines(result) + _calibration_lines(s) + _plot_lines()
    (folder / "report.md").write_text("\n".join(lines))
    return folder / "report.md"


def _headline_lines(s: dict) -> list[str]:
    """The named effect, the gaps before and after, how consistent, the frames left out."""
    effect = s["effect"] if isinstance(s["effect"], str) else ", ".join(s["effect"])
    lines: list[str] = [
        "# Discrepancy report",
        "",
        f"**Named effect: {effect}**",
        "",
        f"Held-out RMS torque gap ({s['gap_units']}): before {s['gap_before']:.4f}, after {s['gap_after']:.4f} "
        f"({1 - s['gap_after'] / s['gap_before']:.0%} smaller)."
        if s["gap_before"] > 0
        else "",
        "",
    ]
    lines += [x for sentence in consistency_sentences(s) for x in (f"How consistent: {sentence}", "")]
    left_out = s.get("frames_left_out") or {}
    if left_out:
        lines += [
            "Frames left out of the analysis (no activation explains them, or the inputs are incomplete): "
            + "; ".join(f"{t}: {describe_left_out(v)}" for t, v in left_out.items())
            + f" (of {s['frames']['training']} training and {s['frames']['holdout']} held-out frames kept).",
            "",
        ]
    if "activation_gap_before" in s:
        lines += [
            f"Held-out RMS activation gap (proposed estimate - EMG, groups with EMG): before "
            f"{s['activation_gap_before']:.4f}, after {s['activation_gap_after']:.4f}.",
            "",
        ]
    return lines


def _candidate_lines(s: dict) -> list[str]:
    """The criterion and the table of candidates."""
    lines: list[str] = [
        f"Criterion: held-out MSE reduction >= {s['criterion']['min_holdout_mse_reduction']:.0%}, dBIC < "
        f"-{s['criterion']['bic_margin']:g} on the training trials and -2 ln LR < -{s['criterion']['bic_margin']:g} on "
        f"the held-out trials; with several training trials, none left out of the fit may favour the model without "
        f"the candidate by -2 ln LR > {s['criterion']['bic_margin']:g} "
        f"(N_eff = N / tau_int, tau_int the autocorrelation time of the candidate's gaps in frames; "
        f'{s["autocorrelation_frames"]:.1f} for the "none" model). Of those that pass, the one with the lowest '
        f"held-out BIC (-2 ln LR + its extra parameters x ln N_eff) is named. Docs: docs/discrepancy.md.",
        "",
        "## Candidates (first step, ranked by held-out BIC)",
        "",
        "| candidate | held-out MSE reduction | held-out reps improved | dBIC train | -2 ln LR held-out | held-out BIC "
        "| parameters | verdict |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for c in s["candidates"]:
        params = ", ".join(f"{k}={v:.3g}" if isinstance(v, float) else f"{k}=…" for k, v in c["parameters"].items())
        reps = c.get("holdout_reps") or {}
        lines.append(
            f"| {c['effect']} | {c['holdout_mse_reduction']:.1%} | "
            f"{reps.get('improved', 0)}/{reps.get('reps', 0)} | {c['delta_bic_train']:.1f} | "
            f"{c['minus2_ln_lr_holdout']:.1f} | {c['holdout_bic']:.1f} | {params} | {c['reason']} |"
        )
    return lines


def _r(value: float | None) -> str:
    """A correlation for the tables: "n/a" where it is not defined (a constant series, e.g. one held-out load)."""
    return "n/a" if value is None or not np.isfinite(value) else f"{value:+.2f}"


def _gap_lines(result: DiscrepancyResult) -> list[str]:
    """The gap per coordinate and where the gaps concentrate (correlations, cross-correlation lags)."""
    s = result.summary
    lines = ["", "## Gap per coordinate (held-out RMS)", "", "| coordinate | before | after |", "|---|---|---|"]
    lines += [f"| {c} | {v['before']:.4f} | {v['after']:.4f} |" for c, v in s["gap_per_coordinate"].items()]
    rel = result.relations_before["coordinates"]
    lines += [
        "",
        "## Where the gaps concentrate (before; correlation of the gap with ...)",
        "",
        "| coordinate | angle | velocity | load | xcorr peak lag (ms) |",
        "|---|---|---|---|---|",
    ]
    for c, lag in zip(result.data.coordinates, result.relations_before["xcorr"]["peak_lag_s"]):
        lines.append(
            f"| {c} | {_r(rel[c]['corr_angle'])} | {_r(rel[c]['corr_velocity'])} | "
            f"{_r(rel[c]['corr_load'])} | {lag * 1000:.0f} |"
        )
    groups = result.relations_before.get("groups", {})
    if groups:
        lines += ["", "| group (gap along its moment arms) | fibre length | lengthening velocity |", "|---|---|---|"]
        lines += [
            f"| {g} | {_r(v['corr_fibre_length'])} | {_r(v['corr_lengthening_velocity'])} |" for g, v in groups.items()
        ]
    return lines


def _calibration_lines(s: dict) -> list[str]:
    """Calibration strengths at their bounds and the re-calibrated strengths, when there are any."""
    lines: list[str] = []
    pinned = s.get("calibration_at_bounds") or []
    if pinned:
        lines += [
            "",
            "## Calibration strengths at their bounds",
            "",
            "The calibration pushed these strengths to the edge of their range: it absorbed torque it could not "
            "explain with activations (a missing effect, or groups whose strength the data cannot separate): "
            "look at the coordinates they cross first.",
            "",
            "| group | strength scale | bound | coordinates |",
            "|---|---|---|---|",
        ]
        lines += [f"| {b['group']} | {b['scale']:.2f} | {b['side']} | {', '.join(b['coordinates'])} |" for b in pinned]
    recal = s.get("recalibrated_strengths")
    if recal:
        lines += [
            "",
            "## Strengths re-calibrated with the named effect (--recalibrate)",
            "",
            "The written profile carries the strengths of a calibration of the training trials that had the "
            "named effect in it (docs/discrepancy.md, Re-calibration).",
            "",
            "| group | F_max before (N) | F_max after (N) | ratio |",
            "|---|---|---|---|",
        ]
        lines += [
            f"| {g} | {v['before']:.0f} | {v['after']:.0f} | {v['after'] / v['before']:.2f} |" for g, v in recal.items()
        ]
        terms = s.get("recalibrated_torque_terms") or {}
        if terms:
            lines += [
                "",
                "Fitted with them, the torque terms' coefficients (N·m per unit of each term, as in the "
                "effect's parameters):",
                "",
                "| term | coefficient |",
                "|---|---|",
            ]
            lines += [f"| {k} | {v:.4g} |" for k, v in terms.items()]
    return lines


def _plot_lines() -> list[str]:
    """Links to the plots write_report draws."""
    lines: list[str] = [
        "",
        "## Plots",
        "",
        "![gap vs angle](gap_vs_angle.png)",
        "",
        "![gap vs velocity](gap_vs_velocity.png)",
        "",
        "![gap vs phase](gap_vs_phase.png)",
        "",
        "![cross-correlation vs lag](xcorr_vs_lag.png)",
        "",
        "![RMS gaps before and after](gap_rms.png)",
        "",
    ]
    return lines
