"""The demo's report against the synthetic generator's truth: the calibrated strength (a Markdown table per exercise
and one bar plot, F_max / truth per group) and the held-out trials' live activations (one plot per trial)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from msk_core.model.pack import names_for
from services.sessions.live_scoring import METHODS, MethodScore
from services.surfaces.reports import pyplot, save_figure


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
        names = names_for(exercise, list(rep["groups"]))
        for g, v in rep["groups"].items():
            lines.append(
                f"| {_named(names.group(g), g)} | {v['status']} | {v['f_max_n']:.0f} | {v['truth_n']:.0f} | {100 * (v['f_max_n'] / v['truth_n'] - 1):+.0f} % "
                f"| {v['reference_n']:.0f} | {100 * (v['reference_n'] / v['truth_n'] - 1):+.0f} % |"
            )
        lines.append("")
    return "\n".join(lines)


def _named(display: str, model: str) -> str:
    """A group as a coach reads it, with the model's name the tables and files use: "Brachioradialis (BRD)"."""
    return model if display == model else f"{display} ({model})"


STRENGTH_COLOURS = {"identified": "tab:green", "not_calibrated": "dimgrey"}


def plot_strength(calibration: dict, out: Path) -> Path:
    """F_max / truth per group: calibrated and the model's reference (1 = exact)."""
    plt = pyplot()
    fig, axes = plt.subplots(len(calibration), 1, figsize=(13, 4.6 * len(calibration)), squeeze=False)
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
        names = names_for(exercise, groups)
        ax.set_xticks(x, [names.group(g) for g in groups], rotation=45, ha="right", fontsize=8)
        ax.set_ylim(0.0, max(1.5, 1.05 * max(cal + ref)))
        ax.set_ylabel("F_max / truth")
        ax.set_title(
            f"{exercise}: median error {100 * rep['strength_error_median']:.0f} % "
            f"(reference {100 * rep['reference_error_median']:.0f} %)",
            fontsize=10,
        )
    from matplotlib.patches import Patch

    handles = [
        Patch(color="lightgrey", label="model reference"),
        Patch(color=STRENGTH_COLOURS["identified"], label="calibrated: identified"),
        Patch(color="tab:orange", label="calibrated: combination / unidentified / at bound"),
        Patch(color=STRENGTH_COLOURS["not_calibrated"], label="no EMG: kept at reference"),
    ]
    axes[0, 0].legend(handles=handles, loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)
    return save_figure(fig, out / "strength.png", dpi=100)


def plot_activations(curves: dict, scores: list[MethodScore], out: Path) -> list[Path]:
    """Per held-out trial: the live activations of each method against the truth, for the four groups that work
    hardest in the truth (where people look first); ``curves`` and ``scores`` from
    :func:`services.sessions.live_scoring.score`."""
    plt = pyplot()
    written = []
    exercises = {s.trial: s.exercise for s in scores}
    for trial in sorted({s.trial for s in scores if s.role == "held out"}):
        truth_t, _, truth, groups = curves[(trial, "proposed")]
        names = names_for(exercises[trial], list(groups))
        top = np.argsort(truth.max(axis=0))[::-1][:4]
        fig, axes = plt.subplots(len(top), 1, figsize=(10, 2.2 * len(top)), sharex=True)
        for ax, gi in zip(np.atleast_1d(axes), top):
            ax.plot(truth_t, truth[:, gi], color="black", lw=2, label="truth")
            for method, colour in zip(METHODS, ("tab:green", "tab:red", "tab:blue")):
                t, est, _, _ = curves[(trial, method)]
                ax.plot(t, est[:, gi], color=colour, lw=1, label=method)
            ax.set_title(f"{names.group(groups[gi])}: activation (0 to 1)", fontsize=9, loc="left")
            ax.set_ylim(0, 1)
        np.atleast_1d(axes)[0].legend(loc="upper right", ncol=4, fontsize=8)
        np.atleast_1d(axes)[-1].set_xlabel("time in trial (s)")
        fig.suptitle(f"{trial} (held out from calibration): live activations vs truth")
        written.append(save_figure(fig, out / f"{trial}.png", dpi=100))
    return written
