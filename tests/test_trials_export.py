"""`msk trials`: a recorded session's sets as the trial files `msk calibrate` reads (services/surfaces/trial_export.py),
on the demo recording, whose trials were made from the files of recordings/demo: the exported trials hold the
recorded angles and raw EMG, and a profile calibrated on them estimates the other set as well as one calibrated on
the original files."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from msk_core.estimate.pipeline import calibrate_subject, estimate_trial
from msk_core.estimate.trial import load_trial
from msk_core.io import read_sto
from msk_core.model import load_pack
from msk_core.signal.emg import EmgFilterConfig, envelope_zero_phase_noncausal
from services.cli import main
from services.transport.mcap_io import read_messages

RECORDINGS = Path(__file__).resolve().parents[1] / "recordings"
MCAP = RECORDINGS / "demo_session.mcap"
DEMO = RECORDINGS / "demo" / "bench_press"
START_S = 1_767_225_600.0  # the demo recording's first joint frame: the exported trials' time 0


@pytest.fixture(scope="module")
def pack():
    return load_pack("bench_press")


@pytest.fixture(scope="module")
def exported(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("trials")
    argv = ["trials", str(MCAP), "--pack", "bench_press", "--mvc-from", str(DEMO / "bench_press_40kg" / "trial.toml")]
    assert main([*argv, "--out", str(out)]) == 0
    return out


def _truth_rmse(profile, trial, truth_time_shift_s: float) -> float:
    """Mean over groups of the proposed estimate's RMSE against the generator's truth of the 50 kg set."""
    truth = read_sto(DEMO / "bench_press_50kg" / "truth_activations.sto")
    run = estimate_trial(load_pack("bench_press"), trial, "proposed", subject=profile)
    t = run.time - truth_time_shift_s
    return float(
        np.mean(
            [
                np.sqrt(np.mean((run.activations[:, j] - np.interp(t, truth.time, truth.column(g))) ** 2))
                for j, g in enumerate(run.groups)
            ]
        )
    )


def test_the_sets_are_exported_with_the_recorded_angles_and_raw_emg(exported, pack):
    assert sorted(p.name for p in exported.iterdir()) == ["set1", "set2"]  # the bench press sets, not the deadlift's
    trial = load_trial(exported / "set2" / "trial.toml", pack)
    assert (
        trial.name == "set2"
        and trial.load_kg == 50.0
        and sorted(trial.emg)
        == sorted(["PMCla", "PMSte", "DelAnt", "DelMed", "DelPos", "BicLong", "TriLong", "TriLat", "BRD", "LD"])
    )
    # the angles are the recorded joint frames of the set, on the time axis of the recording's first frame
    recorded = [
        r.decode()
        for r in read_messages(MCAP)
        if r.type_name == "msk.JointAngles" and list(r.decode().coordinates) == list(pack.coordinates)
    ]
    ik = read_sto(exported / "set2" / "ik.sto")
    # the set: from its load event to the next (LoadEvent times of the demo recording, ns)
    in_set = [j for j in recorded if 1_767_225_618_600_000_000 <= j.device_time_ns <= 1_767_225_633_670_000_000]
    assert ik.n_rows == len(in_set)
    np.testing.assert_allclose(ik.data, [list(j.q) for j in in_set])
    # the raw EMG rows are the recorded samples, placed by the arrival mapping (the synthetic receipts: 0.5 ms)
    emg = read_sto(exported / "set2" / "emg.sto")
    chunks = [r.decode() for r in read_messages(MCAP) if r.type_name == "msk.EmgChunk"]
    set_chunks = [c for c in chunks if c.n_channels == 10 and 18.6 - 1.0 <= c.device_time_ns / 1e9 - START_S <= 34.67]
    rows = np.concatenate([np.asarray(c.samples).reshape(c.n_samples, c.n_channels) for c in set_chunks])
    first = rows.shape[0] - emg.n_rows  # the exported span starts within the first chunk of the margin
    np.testing.assert_array_equal(emg.data[: min(emg.n_rows, rows.shape[0] - first)], rows[first : first + emg.n_rows])
    assert np.all(np.abs(np.diff(emg.time) - 1 / 2000) < 1e-6)  # one uniform sample rate, as the loader needs
    text = (exported / "set2" / "trial.toml").read_text()
    assert "EMG placed by the arrival mapping" in text and "[emg_max]  # each channel's divisor: the [emg_max]" in text


def test_a_profile_calibrated_on_the_exported_set_estimates_the_other_as_the_original_files_do(exported, pack):
    """Calibrated on the exported 40 kg set and on the original 40 kg files (the same data, the same MVC divisors):
    the 50 kg set's proposed activations against the generator's truth within 10 % of each other (measured: mean
    RMSE 0.0445 either way)."""
    from_export, _ = calibrate_subject(pack, [load_trial(exported / "set1" / "trial.toml", pack)])
    from_files, _ = calibrate_subject(pack, [load_trial(DEMO / "bench_press_40kg" / "trial.toml", pack)])
    exported_rmse = _truth_rmse(from_export, load_trial(exported / "set2" / "trial.toml", pack), 18.6)
    files_rmse = _truth_rmse(from_files, load_trial(DEMO / "bench_press_50kg" / "trial.toml", pack), 0.0)
    assert exported_rmse < 0.06 and abs(exported_rmse / files_rmse - 1.0) < 0.10, (exported_rmse, files_rmse)


def test_without_an_mvc_nothing_is_exported_and_the_error_says_how_to_record_one(tmp_path, capsys):
    out = tmp_path / "trials"
    assert main(["trials", str(MCAP), "--pack", "bench_press", "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "field '--mvc-set': the EMG needs each electrode's MVC" in error and "--mvc-from" in error, error
    assert not out.exists()


def test_an_mvc_set_gives_the_divisors_and_is_not_a_lift_trial(tmp_path, pack):
    """Set 1 named as the MVC effort: only set 2 is exported, each divisor the peak of the channel's zero-phase
    envelope over set 1's EMG, as computed here from the recorded samples."""
    out = tmp_path / "trials"
    assert main(["trials", str(MCAP), "--pack", "bench_press", "--mvc-set", "1", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["set2"]
    text = (out / "set2" / "trial.toml").read_text()
    assert "the peak of its envelope over set(s) [1] (MVC efforts)" in text
    chunks = [r.decode() for r in read_messages(MCAP) if r.type_name == "msk.EmgChunk" and r.decode().n_channels == 10]
    set1 = [c for c in chunks if c.device_time_ns / 1e9 - START_S <= 13.6 + 1.0]
    raw = np.concatenate([np.asarray(c.samples).reshape(c.n_samples, c.n_channels) for c in set1])
    peaks = envelope_zero_phase_noncausal(raw, EmgFilterConfig(rate_hz=2000.0)).max(axis=0)
    labels = list(set1[0].channel_labels)
    import tomllib

    divisors = tomllib.loads(text)["emg_max"]
    np.testing.assert_allclose([divisors[label] for label in labels], peaks, rtol=1e-9)
    assert load_trial(out / "set2" / "trial.toml", pack).n_frames > 1000


def test_the_live_estimators_stated_offset_places_the_emg(tmp_path, pack):
    """Beside `msk live`'s recording, its summary.json states the offset the estimator applied (e.g. by the
    accelerations): the export places the EMG by it, 100 ms later here than the arrival mapping's 0.5 ms."""
    copy = tmp_path / "live" / "session.mcap"
    copy.parent.mkdir()
    shutil.copy(MCAP, copy)
    clocks = {"emg/trigno-synth": {"offset_ms": 100.0, "method": "acceleration"}}
    (copy.parent / "summary.json").write_text(json.dumps({"clocks": clocks}))
    mvc = ["--mvc-from", str(DEMO / "bench_press_40kg" / "trial.toml")]
    assert main(["trials", str(copy), "--pack", "bench_press", *mvc, "--out", str(tmp_path / "a")]) == 0
    (copy.parent / "summary.json").unlink()
    assert main(["trials", str(copy), "--pack", "bench_press", *mvc, "--out", str(tmp_path / "b")]) == 0
    stated, arrival = (read_sto(tmp_path / x / "set1" / "emg.sto") for x in ("a", "b"))
    # the same rows (by sample), each 99.5 ms later
    shift = stated.time[0] - arrival.time[np.argmax(np.all(arrival.data == stated.data[0], axis=1))]
    assert shift == pytest.approx(0.0995, abs=1e-6)
    assert "placed by the offset of summary.json (acceleration)" in (tmp_path / "a" / "set1" / "trial.toml").read_text()
