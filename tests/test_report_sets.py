"""`msk report` on a recording with sets: rest detection and the operator's marks split it as the view and the
dashboard do (msk_core.signal.sets), and the report has one row per set with reps, time under tension and peak and
mean activation per muscle group."""

from __future__ import annotations

import json

import pytest

from services.surfaces.dashboard import report
from services.transport import messages
from tests.dashboard_helpers import timed_recording

START_NS = 1_773_480_600_000_000_000
RATE_HZ = 20.0
# (start, end) s of each rep: three, a 25 s rest (longer than the session's 20 s), two, the operator's stop at 37 s,
# his start at 40 s, one more
REPS = [(1, 3), (3, 5), (5, 7), (32, 34), (34, 36), (41, 43)]
END_S = 45.0


def phase_at(t: float) -> float:
    for a, b in REPS:
        if a <= t < b:
            return (t - a) / (b - a)
    return -1.0


def two_sets_phase(t_s: float) -> float:
    """3 reps from 1 s and 3 from 21 s (as ``REPS``' first three)."""
    return phase_at(t_s % 20.0 + 1.0) if t_s % 20.0 < 6.0 else -1.0


def two_sets(tmp_path, facts: list, write) -> object:
    """A 40 s recording of ``facts`` and, every frame, ``write(session, t_s, phase)`` at :func:`two_sets_phase`."""
    recording = tmp_path / "session.mcap"
    with timed_recording(recording, START_NS) as session:
        session.load_events(facts)
        for k in range(int(40 * RATE_HZ)):
            t_s = k / RATE_HZ
            write(session, t_s, two_sets_phase(t_s))
    return recording


def write_session(path) -> None:
    facts = [
        (0.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, set_rest_s=20.0)),
        (37.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, set_mark="stop")),
        (40.0, messages.LoadEvent(barbell_mass_kg=65, exercise="bench_press", set_number=2, set_mark="start")),
    ]
    with timed_recording(path, START_NS) as recording:
        recording.load_events(facts)
        for k in range(int(END_S * RATE_HZ)):
            t_s = k / RATE_HZ
            phase = phase_at(t_s)
            # B high only at rest
            recording.joints_and_frame(t_s, phase, ["A", "B"], [0.2 + 0.6 * max(phase, 0.0), 0.9 if phase < 0 else 0.1])


def test_report_of_a_recording_with_sets(tmp_path):
    recording = tmp_path / "session.mcap"
    write_session(recording)
    summary = report.write_report(recording, tmp_path / "out")
    sets = summary["sets"]
    assert [(s["set"]["number"], len(s["reps"]), s["set"]["ended_by"]) for s in sets] == [
        (1, 3, "rest"),
        (2, 2, "operator"),
        (3, 1, "end of data"),
    ]
    assert [s["name"] for s in sets] == [
        "set 1: bench press, 60 kg",
        "set 2: bench press, 60 kg",
        "set 3: bench press, 65 kg",
    ]
    # set 1 by msk live's opening facts (not the operator), set 2 by its first rep after the rest, set 3 by the
    # operator's start mark
    assert [s["set"]["started_by"] for s in sets] == ["session", "rep", "operator"]
    first = sets[0]
    assert first["start_s"] == pytest.approx(START_NS / 1e9)  # msk live's facts started set 1
    assert first["end_s"] - first["start_s"] == pytest.approx(7.0, abs=0.1)  # at its last rep's end
    assert sets[1]["start_s"] - START_NS / 1e9 == pytest.approx(32.0, abs=0.1)  # the first rep after the rest
    assert sets[1]["end_s"] - START_NS / 1e9 == pytest.approx(37.0)  # the operator's stop
    assert [s["time_under_tension_s"] for s in sets] == pytest.approx([6.0, 4.0, 2.0], abs=0.2)
    figures = first["set"]
    assert figures["groups"] == ["A", "B"]
    assert figures["peak"] == pytest.approx([0.8, 0.1], abs=0.02)  # over the reps: B's 0.9 at rest not counted
    assert figures["mean"][0] == pytest.approx(0.5, abs=0.02) and figures["mean"][1] == pytest.approx(0.1)
    page = (tmp_path / "out" / "report.html").read_text()
    section = page[page.index("<section class='sets'>") :].split("</section>")[0]
    table, muscles = section.split("</table>")[:2]
    assert table.count("<tr>") == 1 + 3 and "<td>rest</td>" in table  # the header and one row per set
    assert "<td>session</td><td>rest</td>" in table and "<td>operator</td><td>end of data</td>" in table
    assert "<th>set 1</th><th>set 2</th><th>set 3</th>" in muscles  # per muscle (rows), the sets side by side
    assert "<tr><td>A</td><td>79 / 49</td>" in muscles
    assert json.loads((tmp_path / "out" / "report.json").read_text())["sets"][2]["set"]["reps"] == 1


def test_report_plots_activation_in_percent(tmp_path, monkeypatch):
    """One unit in the report: its plots' activation axes in % (0-100), as its tables."""
    from matplotlib.figure import Figure

    axes: list[tuple[str, tuple[float, float], list[float]]] = []
    save = Figure.savefig

    def record(fig, *args, **kwargs):
        for ax in fig.axes:
            data = [float(y) for line in ax.get_lines() for y in line.get_ydata()]
            data += [float(v) for image in ax.get_images() for v in image.get_array().compressed()]
            axes.append((ax.get_ylabel() or ax.get_title(), ax.get_ylim(), data))
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    recording = tmp_path / "session.mcap"
    write_session(recording)
    report.write_report(recording, tmp_path / "out")
    activation = [a for a in axes if a[0].startswith("activation")]
    assert activation and all(label == "activation (%, so)" and ylim == (0, 108) for label, ylim, _ in activation)
    assert max(max(d) for _, _, d in activation) == pytest.approx(90.0)  # B at rest, 0.9: 90 %
    heat = [a for a in axes if a[0] == "peak activation per rep (%)"]
    assert heat and max(max(d) for _, _, d in heat) == pytest.approx(
        80.0, abs=2.0
    )  # A: 0.2 + 0.6 x phase, sampled at 20 Hz


def test_report_header_names_the_method_shown(tmp_path):
    """The report details the method every surface shows by default (services.sessions.live_session.default_method) and says
    which in its header."""
    recording = tmp_path / "session.mcap"
    write_session(recording)
    report.write_report(recording, tmp_path / "out")
    header = (tmp_path / "out" / "report.html").read_text().split("</header>")[0]
    assert "methods: so · method shown: so" in header


def test_a_load_corrected_for_a_set_after_its_last_rep_is_its_load(tmp_path):
    """`msk load 65 --set 1` after set 1's last rep, before the rest ended it: the view showed 65 kg for set 1, the
    report 55 kg (the set ends at its last rep, and the correction came after; found by exploratory QA)."""
    facts = [
        (0.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, set_rest_s=20.0)),
        (10.0, messages.LoadEvent(barbell_mass_kg=62.5, exercise="bench_press", set_number=1)),  # set 1 ended at 7 s
    ]
    recording = tmp_path / "session.mcap"
    with timed_recording(recording, START_NS) as session:
        session.load_events(facts)
        for k in range(int(20 * RATE_HZ)):
            t_s = k / RATE_HZ
            session.joints_and_frame(t_s, phase_at(t_s), ["A", "B"], [0.5, 0.1])
    (first,) = report.write_report(recording, tmp_path / "out")["sets"]
    assert first["name"] == "set 1: bench press, 62.5 kg", first["name"]


def test_two_athletes_on_one_rack_each_set_is_named_with_its_athlete(tmp_path):
    """Ana lifts set 1, Ben set 2 (``msk load --athlete Ben --next-set``): the header said "Ana, Ben" and no set said
    whose it was. Each set's name and its report.json entry now say it; a one-athlete session's names stay as they
    were (the header names the athlete)."""
    facts = [
        (0.0, messages.LoadEvent(barbell_mass_kg=60, exercise="bench_press", set_number=1, athlete="Ana")),
        (20.0, messages.LoadEvent(barbell_mass_kg=80, exercise="bench_press", set_number=2, athlete="Ben")),
    ]
    recording = two_sets(
        tmp_path, facts, lambda session, t_s, phase: session.joints_and_frame(t_s, phase, ["A", "B"], [0.5, 0.1])
    )
    summary = report.write_report(recording, tmp_path / "out")
    assert [(s["name"], s["athlete"], len(s["reps"])) for s in summary["sets"]] == [
        ("set 1 (Ana): bench press, 60 kg", "Ana", 3),
        ("set 2 (Ben): bench press, 80 kg", "Ben", 3),
    ], [(s["name"], s["athlete"], len(s["reps"])) for s in summary["sets"]]
    assert "set 2 (Ben)" in (tmp_path / "out" / "report.html").read_text()


def test_a_bench_press_then_a_deadlift_each_set_has_the_reps_of_its_own_packs_frames(tmp_path):
    """``msk demo`` then ``msk report``: the reps are counted on the activation frames' phase, and those came from the
    one pack with the most frames (the deadlift's), so both bench-press sets had 0 reps (found by QA of the docs).
    Every pack the primary method ran with now gives its frames, one after the other."""
    facts = [
        (0.0, messages.LoadEvent(barbell_mass_kg=40, exercise="bench_press", set_number=1)),
        (20.0, messages.LoadEvent(barbell_mass_kg=60, exercise="deadlift", set_number=2)),
    ]

    def write(session, t_s: float, phase: float) -> None:
        bench = t_s < 20.0
        frame = messages.ActivationFrame(
            time_s=START_NS / 1e9 + t_s,
            method="so",
            groups=["A", "B"] if bench else ["C", "D", "E"],
            activations=[0.5, 0.1] if bench else [0.4, 0.3, 0.2],
            exercise="bench_press" if bench else "deadlift",
            phase=phase,
        )
        session.write(frame, t_s, "activations/so")
        if not bench:  # the deadlift's frames outnumber the bench press's
            session.write(
                messages.ActivationFrame(
                    time_s=START_NS / 1e9 + t_s + 0.5 / RATE_HZ,
                    method="so",
                    groups=["C", "D", "E"],
                    activations=[0.4, 0.3, 0.2],
                    exercise="deadlift",
                    phase=phase,
                ),
                t_s + 0.5 / RATE_HZ,
                "activations/so",
            )

    recording = two_sets(tmp_path, facts, write)
    sets = report.write_report(recording, tmp_path / "out")["sets"]
    assert [(s["name"], len(s["reps"]), s["rep_source"]) for s in sets] == [
        ("set 1: bench press, 40 kg", 3, "phase of the activation frames"),
        ("set 2: deadlift, 60 kg", 3, "phase of the activation frames"),
    ], [(s["name"], len(s["reps"]), s["rep_source"]) for s in sets]
