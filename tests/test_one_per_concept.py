"""One function per concept (issue 28): the repetition segmenter and the rest phase, the phase prior and its fitter,
the trial loader, the moment-arm clamp rule and the force factor each live in one module, and every consumer uses
that one. A second segmenter, prior fitter or trial loader written anywhere in msk_core/, services/ or drivers/
fails here."""

from __future__ import annotations

import ast
import functools
import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("msk_core", "services", "drivers")

# concept -> (the module that owns it, pattern of the names a definition of it would carry)
OWNERS = {
    "repetition segmenter": (
        "msk_core/signal/reps.py",
        r"detect_reps|find_reps|segment\w*rep|reps?_from|rep_spans|rep_phase|rep_?counter|"
        r"phase_?tracker",
    ),
    "phase prior and its fitter": ("msk_core/estimate/prior.py", r"fit\w*prior|prior\w*_from|phase_?priors?$"),
    "trial loader": ("msk_core/estimate/trial.py", r"load\w*_trial$"),
    "force factor": ("msk_core/estimate/effects.py", r"^force_factor$"),
    "moment-arm clamp rule": ("msk_core/estimate/pack.py", r"clamp_to_ranges"),
}
# a class of that name elsewhere that only delegates to the owner (checked below by behaviour)
DELEGATES = {("services/surfaces/dashboard/bridge.py", "RepCounter")}


@functools.cache
def _sources() -> tuple[tuple[str, ast.Module], ...]:
    """Every module of PACKAGES parsed, once per test process (the tests only read the trees)."""
    out = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            out.append((str(path.relative_to(ROOT)), ast.parse(path.read_text(), filename=str(path))))
    return tuple(out)


@pytest.mark.parametrize("concept", sorted(OWNERS))
def test_each_concept_is_defined_in_one_module(concept):
    owner, pattern = OWNERS[concept]
    elsewhere = []
    for where, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                if (
                    re.search(pattern, node.name, re.IGNORECASE)
                    and where != owner
                    and (where, node.name) not in DELEGATES
                ):
                    elsewhere.append(f"{where}:{node.lineno} {node.name}")
    assert not elsewhere, f"a second {concept} beside {owner}: {elsewhere}"


def test_rest_phase_and_clamp_tolerance_are_written_once():
    """The rest phase is defined only in msk_core.signal.reps, and the clamp tolerance is read only by the clamp
    rule (a second place applying the tolerance would be a second rule)."""
    rest, tolerance = [], []
    for where, tree in _sources():
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and "REST" in t.id and "PHASE" in t.id for t in node.targets
            ):
                rest.append(f"{where}:{node.lineno}")
            if isinstance(node, ast.Name) and node.id == "CLAMP_TOLERANCE" and where != "msk_core/estimate/pack.py":
                tolerance.append(f"{where}:{node.lineno}")
    assert [r.split(":")[0] for r in rest] == ["msk_core/signal/reps.py"], rest
    assert not tolerance, f"the clamp tolerance applied outside msk_core.estimate.pack.clamp_to_ranges: {tolerance}"


def test_consumers_use_the_one_segmenter_rest_phase_and_loader():
    import msk_core.estimate as estimate
    import msk_core.estimate.phase as phase
    import msk_core.estimate.trial as trial
    import msk_core.imu.stream as stream
    import msk_core.signal.reps as reps
    import services.surfaces.dashboard.bridge as bridge
    import services.surfaces.dashboard.report as report
    import services.surfaces.view as view

    assert phase.detect_reps is reps.detect_reps and phase.rep_phase is reps.rep_phase  # estimator, calibration
    assert trial.kinematic_phase is phase.kinematic_phase and trial.torque_phase is phase.torque_phase
    assert phase.PhaseTracker is reps.PhaseTracker and stream.PhaseTracker is reps.PhaseTracker  # live phase
    assert report.phase_rep_spans is reps.phase_rep_spans  # the session report's reps
    assert bridge.PhaseRepCounter is reps.PhaseRepCounter  # live
    import msk_core.signal.sets as sets

    assert sets.PhaseRepCounter is reps.PhaseRepCounter  # the set logic counts reps with the one segmenter
    assert view.SetTracker is sets.SetTracker and bridge.SetTracker is sets.SetTracker  # one set logic
    assert report.SetTracker is sets.SetTracker
    assert estimate.REST_PHASE is reps.REST_PHASE
    import msk_core.io as io

    assert not hasattr(io, "load_trial")  # the one trial loader is msk_core.estimate.trial.load_trial


def test_the_dashboards_rep_count_is_the_segmenters():
    """The bridge's per-set counter only adds sets to msk_core.signal.reps.PhaseRepCounter: on a random phase
    stream (reps of random length, rest, unknown phase, wraps, gaps) it counts exactly what the segmenter counts."""
    from msk_core.signal.reps import REST_PHASE, PhaseRepCounter
    from services.surfaces.dashboard.bridge import RepCounter

    rng = np.random.default_rng(28)
    t, samples = 0.0, []
    for _ in range(300):
        kind = rng.integers(4)
        if kind == 0:  # a rep of 0.1-1.5 s at 20 Hz
            n = int(rng.integers(2, 30))
            samples += [(t := t + 0.05, p) for p in np.linspace(0, 0.99, n)]
        elif kind == 1:
            samples += [(t := t + 0.05, REST_PHASE) for _ in range(int(rng.integers(1, 10)))]
        elif kind == 2:
            samples.append((t := t + 0.05, None))
        else:
            t += float(rng.uniform(0.2, 1.0))  # a gap in the stream
    ours, theirs = RepCounter(), PhaseRepCounter()
    ours.new_set()
    for time_s, p in samples:
        ours.update(time_s, p)
        theirs.update(time_s, p)
    assert ours.in_set == ours.total == theirs.count > 50
