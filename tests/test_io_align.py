"""backmodel-lift: 1000 Hz EMG envelopes, ~15 Hz ik and id aligned on their shared Unix timestamps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import InputError
from msk_core.io import align_to_kinematics, read_sto, resample_linear, window_mean

EMG = ["rectabd_r", "rectabd_l", "iliocost_r", "iliocost_l", "longlumb_r", "longlumb_l", "longthor_r", "longthor_l"]


@pytest.mark.parametrize("trial", ["squat5kg", "stoop5kg"])
def test_backmodel_lift_aligns(shared_dir: Path, trial: str) -> None:
    folder = shared_dir / "data/backmodel-lift" / trial
    emg, ik, id_ = (read_sto(folder / f) for f in ("emgFilt.sto", "ik.sto", "id.sto"))
    aligned = align_to_kinematics(emg, ik, id_, emg_columns=EMG)
    assert aligned.emg.shape == (aligned.time.shape[0], 8) and aligned.emg_columns == EMG
    assert aligned.time.shape[0] >= 400  # ~27 s at ~15 Hz, nearly every kinematics row kept
    assert 14.0 < (aligned.time.shape[0] - 1) / (aligned.time[-1] - aligned.time[0]) < 16.0
    np.testing.assert_array_equal(aligned.ik.time, aligned.time)
    assert aligned.id is not None
    assert np.max(np.abs(aligned.id.time - aligned.time)) <= 1e-3
    # EMG value at a kinematics time lies between the two raw EMG samples around it
    for k in (10, 200, aligned.time.shape[0] - 5):
        t = aligned.time[k]
        i = np.searchsorted(emg.time, t)
        lo = np.minimum(emg.select(EMG)[i - 1], emg.select(EMG)[i])
        hi = np.maximum(emg.select(EMG)[i - 1], emg.select(EMG)[i])
        assert np.all(aligned.emg[k] >= lo - 1e-15) and np.all(aligned.emg[k] <= hi + 1e-15)
    # the ik/id rows kept are the original ones
    row = np.searchsorted(ik.time, aligned.time[50])
    np.testing.assert_array_equal(aligned.coordinate("pelvis_tilt")[50], ik.column("pelvis_tilt")[row])
    l5 = aligned.id.column("L5_S1_Flex_Ext")
    assert l5.max() > 150.0  # N m: the lifts load the lumbar joint
    # during lifts (high L5 moment) the back extensors are more active than at rest
    busy = l5 > np.percentile(l5, 75)
    quiet = l5 < np.percentile(l5, 25)
    assert aligned.emg_channel("iliocost_r")[busy].mean() > 1.5 * aligned.emg_channel("iliocost_r")[quiet].mean()
    assert id_.n_rows == 405


def test_resample_and_window_mean() -> None:
    ts = np.array([0.0, 1.0, 2.0, 5.0, 6.0])
    xs = np.array([0.0, 10.0, 20.0, 50.0, 60.0])
    out = resample_linear(ts, xs, np.array([-1.0, 0.5, 1.0, 3.0, 5.5, 7.0]), max_gap_s=1.5)
    np.testing.assert_allclose(out[[1, 2, 4], 0], [5.0, 10.0, 55.0])
    assert np.isnan(out[[0, 3, 5], 0]).all()  # before, inside the 3 s gap, after
    t = np.arange(100) * 0.01
    w = window_mean(t, t[:, None], np.array([0.1, 0.2, 0.3]))
    np.testing.assert_allclose(w[1:, 0], [0.155, 0.255])
    with pytest.raises(InputError, match="strictly increasing"):
        resample_linear(np.array([0.0, 0.0]), np.array([1.0, 2.0]), np.array([0.0]))


def test_no_overlap_is_an_error(shared_dir: Path) -> None:
    folder = shared_dir / "data/backmodel-lift"
    emg = read_sto(folder / "squat5kg/emgFilt.sto")
    ik = read_sto(folder / "stoop5kg/ik.sto")  # recorded 12 minutes earlier
    with pytest.raises(InputError, match="do not overlap"):
        align_to_kinematics(emg, ik)
