"""`msk demo` end to end on the embedded session (one exercise to keep it short): calibration, the live Zenoh graph
(recorder + estimator fed by the replayer), and the scored report."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from msk_core.errors import InputError
from services.sessions import demo
from services.transport.mcap_io import read_messages


def test_demo_runs_the_live_graph_and_scores_every_frame(tmp_path, repo_root):
    out = tmp_path / "demo"
    lines: list[str] = []
    summary = demo.main(out=out, exercises=["bench_press"], log=lines.append)
    graph = summary["graph"]
    assert graph["joints_from"] == "imu"
    # Joint angles come from the kinematics node (IMU at 60 Hz, the first 0.5 s of each set is its static calibration).
    kinematics = graph["kinematics"]["bench_press"]
    assert kinematics["calibrations"] == 2 and kinematics["incomplete"] == 0
    assert graph["estimated_frames"] == graph["joint_frames"] and graph["joint_frames"]["bench_press"] > 1000
    # Every replayed message, every computed joint frame and every activation frame reached the recorder.
    # the nodes' own status (kind "node": inputs taken and dropped) is recorded too; the count is of the data
    recorded = [
        r
        for r in read_messages(out / "live.mcap")
        if not (r.type_name == "msk.DeviceStatus" and r.decode().kind == "node")
    ]
    activations = [r for r in recorded if r.type_name == "msk.ActivationFrame"]
    joints = [r for r in recorded if r.type_name == "msk.JointAngles"]
    assert len(joints) == graph["joint_frames"]["bench_press"]  # lossless: all of them
    assert len(recorded) - len(activations) == graph["replayed"] + len(joints)  # the device data too
    # activation frames are newest-wins (docs/topics.md): a recorder starved of CPU may miss some, and then the
    # demo says how many rather than waiting on (CI once hung here for 5 min); on a machine that keeps up, none
    missed = 3 * graph["joint_frames"]["bench_press"] - len(activations)
    assert missed == graph["expected_messages"] - graph["recorded"] and len(recorded) == graph["recorded"]
    said = [line for line in lines if "the recorder missed" in line]
    assert said == [] if missed == 0 else said and f"missed {missed} data messages" in said[0], (missed, said)
    assert missed <= 0.01 * len(activations), missed
    scores = {(s["trial"], s["method"]): s for s in summary["scores"]}
    assert {m for _, m in scores} == {"proposed", "so", "hybrid"}
    assert {s["role"] for s in summary["scores"]} == {"calibration", "held out"}
    for (trial, method), s in scores.items():
        assert 0 < s["activation_rmse"] < 0.5, (trial, method)
    # Static optimisation matches the torques exactly unless a frame is beyond capacity (then flagged).
    for trial in {t for t, _ in scores}:
        so = scores[(trial, "so")]
        assert so["torque_rmse_nm"] < 0.5 or so["flagged"] > 0
    report = (out / "report.md").read_text()
    assert "| bench_press_50kg | held out | proposed |" in report
    assert (out / "bench_press_50kg.png").stat().st_size > 10_000
    assert (out / "strength.png").stat().st_size > 10_000
    strength_section = report.split("## Calibrated strength")[1]
    assert (
        "10 isometric MVC trials" in strength_section
        and "| Deltoid, anterior part (DelAnt) | identified |" in strength_section
    )
    profile = json.loads((out / "subject_bench_press.json").read_text())
    assert profile["pack"]["name"] == "bench_press"
    assert any("calibrated" in line for line in lines)
    # strength error vs truth over all groups, the EMG-measured ones and those the data identify (see profile)
    cal = summary["calibration"]["bench_press"]
    statuses = profile["calibration"]["strength"]
    assert cal["status"] == {g: v["status"] for g, v in statuses.items()}
    assert set(cal["identified_groups"]) == {g for g, v in statuses.items() if v["status"] == "identified"}
    assert 0 <= cal["strength_error_median"] < 1 and 0 <= cal["strength_error_median_emg"] < 1
    # with the isometric MVC trials: 7 % over all groups (3 unmeasured at the reference), model reference 16 %
    assert any("10 isometric MVC trials" in line for line in lines)
    assert cal["strength_error_median"] <= 0.10 < cal["reference_error_median"]
    # held out: the proposed method beats static optimisation (0.058 vs 0.069)
    held = {m: s["activation_rmse"] for (t, m), s in scores.items() if t == "bench_press_50kg"}
    assert held["proposed"] < held["so"], held
    assert any("EMG-measured" in line and "identified" in line for line in lines)


def test_demo_rejects_unknown_exercise(tmp_path):
    with pytest.raises(InputError, match="--exercise"):
        demo.main(out=tmp_path, exercises=["squat"], log=lambda _: None)


def test_cli_help_and_version(repo_root):
    version = subprocess.run(
        [sys.executable, "-m", "services.cli", "--version"], cwd=repo_root, capture_output=True, text=True, check=True
    )
    assert version.stdout.startswith("msk-live ")
    helptext = subprocess.run(
        [sys.executable, "-m", "services.cli", "--help"], cwd=repo_root, capture_output=True, text=True, check=True
    ).stdout
    for command in ("demo", "recorder", "replay", "estimator", "bench"):
        assert command in helptext
    bad = subprocess.run(
        [sys.executable, "-m", "services.cli", "replay", "missing.mcap", "--rate", "max"],
        cwd=repo_root,
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "missing.mcap" in bad.stderr and "not found" in bad.stderr


def test_the_sim_subject_is_calibrated_again_when_the_science_code_changes(tmp_path, monkeypatch):
    """``msk live --sim`` caches the bundled subject; a cache written by other science code (a new prior, a new
    calibration) must not be reused, and is removed."""
    from msk_core.estimate import SubjectProfile
    from services.sessions import demo_subject

    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    cache = tmp_path / "msk-live" / "live-sim"
    cache.mkdir(parents=True)
    (cache / "subject_bench_press.json").write_text("{}")  # the name an older version wrote
    logged: list[str] = []
    first = demo_subject.sim_subject("bench_press", logged.append)
    assert first.name == f"subject_bench_press_{demo_subject.science_digest()}.json"
    assert SubjectProfile.load(first).prior.load_newton is not None  # written by this code: the prior knows its load
    assert not (cache / "subject_bench_press.json").exists()
    assert demo_subject.sim_subject("bench_press", logged.append) == first
    assert logged[-1] == f"reusing the calibrated bundled subject {first}"
    monkeypatch.setattr(demo_subject, "science_digest", lambda: "0123456789ab")
    second = demo_subject.sim_subject("bench_press", logged.append)
    assert second.name == "subject_bench_press_0123456789ab.json" and not first.exists()
    assert [p.name for p in cache.iterdir()] == [second.name]


def test_a_recorder_that_stops_receiving_short_of_the_count_ends_the_wait_after_the_stall(monkeypatch):
    import threading
    import time

    from services.nodes.recorder import RecorderStats

    monkeypatch.setattr(demo, "RECORDER_STALL_S", 0.5)
    stats = RecorderStats()
    stats.written = 90

    def write_some_more() -> None:  # 5 more, then nothing: 5 of the 100 never come
        for _ in range(5):
            time.sleep(0.1)
            stats.written += 1

    writer = threading.Thread(target=write_some_more)
    writer.start()
    started = time.monotonic()
    demo._wait_recorded(stats, 100, timeout_s=30)  # noqa: SLF001 - the drain's last wait on its own
    writer.join()
    assert stats.written == 95 and 0.5 <= time.monotonic() - started < 5
