"""The shipped demo session (recordings/) is exactly what the generator makes, and the trial files load."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate.trial import load_trial
from msk_core.model import load_pack
from msk_core.synth import Exercise, SynthConfig, generate_session
from msk_core.synth.files import write_session

ROOT = Path(__file__).resolve().parents[1] / "recordings"
REGENERATE = ("msk synth --exercise both --subject-seed 7 --reps 3 --loads bench_press=40,50 --loads deadlift=45,75 "
              "--out recordings/demo --mcap recordings/demo_session.mcap --quiet")


def test_demo_session_is_reproducible(tmp_path):
    from services.synth_export import write_mcap

    cfg = SynthConfig(subject_seed=7, n_reps=3,
                      loads_kg={Exercise.BENCH_PRESS: (40.0, 50.0), Exercise.DEADLIFT: (45.0, 75.0)})
    session = generate_session(list(Exercise), cfg)
    write_session(session, tmp_path / "demo")
    write_mcap(session, tmp_path / "demo_session.mcap")
    shipped = sorted(p.relative_to(ROOT) for p in (ROOT / "demo").rglob("*") if p.is_file())
    fresh = sorted(p.relative_to(tmp_path) for p in (tmp_path / "demo").rglob("*") if p.is_file())
    assert shipped == fresh, f"recordings/ is stale; regenerate with: {REGENERATE}"
    for rel in [*fresh, Path("demo_session.mcap")]:
        assert (ROOT / rel).read_bytes() == (tmp_path / rel).read_bytes(), f"{rel} is stale; regenerate: {REGENERATE}"


@pytest.mark.parametrize("exercise", ["bench_press", "deadlift"])
def test_demo_trials_load_with_the_estimation_reader(exercise):
    truth = json.loads((ROOT / "demo" / "truth.json").read_text())
    entry = truth["exercises"][exercise]
    pack = load_pack(entry["pack"])
    for t in entry["trials"]:
        data = load_trial(ROOT / "demo" / t["trial"], pack)
        assert data.load_kg == t["reported_load_kg"] and data.time.size > 100
        assert set(data.emg) == set(entry["channels"])
        # MVC-normalised envelopes are on the activation scale
        peaks = np.array([np.nanmax(v) for v in data.emg.values()])
        assert np.all(peaks < 1.5) and peaks.max() > 0.1
        assert data.rep_index.max() + 1 == truth["n_reps"]
