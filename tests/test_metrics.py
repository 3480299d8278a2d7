"""Torque tracking reports the gain beside R: R is blind to scale (the hybrid baseline's model torque was about
56 % of the inverse dynamics with R 1.000 in `msk evaluate`'s report)."""

from __future__ import annotations

import numpy as np

from msk_core.estimate.metrics import torque_tracking


def test_torque_tracking_reports_a_gain_that_r_cannot_show():
    t = np.linspace(0.0, 4.0, 400)
    reference = np.column_stack([40.0 * np.sin(2 * np.pi * t), 10.0 * np.cos(np.pi * t)])
    model = np.column_stack([0.56 * reference[:, 0], reference[:, 1] + 0.5])
    model[10, 0] = np.nan  # a failed frame is left out, not propagated
    tracking = torque_tracking(model, reference, ["shoulder", "elbow"], body_mass_kg=70.0)
    assert tracking["shoulder"]["r"] > 0.999 and abs(tracking["shoulder"]["gain"] - 0.56) < 1e-9
    assert tracking["shoulder"]["rmse_nm"] > 10.0  # what the gain explains
    assert abs(tracking["elbow"]["gain"] - 1.0) < 0.01 and tracking["elbow"]["rmse_nm"] < 0.6
    assert np.isnan(torque_tracking(model, np.zeros_like(reference), ["a", "b"], None)["a"]["gain"])


def test_every_flag_a_frame_can_carry_has_words_and_the_summary_says_them():
    from msk_core.estimate import live_emg
    from msk_core.estimate.flags import MEANINGS, flag_counts_text
    from msk_core.estimate.frame import FrameStatus
    from services.sessions.live import summary_text

    codes = {s.value for s in FrameStatus if s is not FrameStatus.SOLVED}
    codes |= {getattr(live_emg, name) for name in dir(live_emg) if name.startswith("FLAG_")}
    assert codes == set(MEANINGS)
    assert flag_counts_text({}) == "none"
    summary = {
        "duration_s": 12.0,
        "samples": {},
        "samples_lost": {},
        "joint_frames": 600,
        "envelopes": 0,
        "frames_estimated": {"so": 600},
        "flags": {"so": {"reserve": 12, "emg_gap": 3}},
    }
    text = summary_text(summary)
    assert (
        "so: 600 frames estimated; flagged frames: 12 torque beyond the muscles' capacity (reserve), 3 EMG gap "
        "(emg_gap)" in text
    ), text


def test_a_constant_estimate_to_rounding_has_no_r_and_no_lag():
    from msk_core.estimate.metrics import cross_correlation_lag, pearson_r

    measured = np.sin(np.arange(500) / 20.0)
    constant = 0.05 + 1e-17 * np.random.default_rng(0).normal(size=500)  # the prior at rest, last digits only
    assert np.isnan(pearson_r(constant, measured)) and np.isnan(
        cross_correlation_lag([constant], [measured], 0.01, 0.5)
    )
    assert pearson_r(0.05 + 0.01 * measured, measured) > 0.999
