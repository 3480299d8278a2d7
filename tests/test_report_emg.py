"""`msk report` on a recording with the estimator's EMG electrode states and fatigue index: the first bench press set
of the demo recording (Trigno EMG at 2 kHz), its raw EMG judged by the estimator's own LiveQuality and LiveFatigue, one
electrode's signal flattened for 3 s (a flat line), their DeviceStatus written into the recording as the estimator
publishes it; the report has a table of electrode states and one of the median frequency per electrode and set."""

from __future__ import annotations

import json

import numpy as np
import pytest

from msk_core.estimate.emg_chunk import RawEmgChunk
from msk_core.estimate.live_fatigue import LiveFatigue
from msk_core.estimate.live_quality import LiveQuality
from services.nodes.estimator import electrode_fatigue, electrode_quality
from services.surfaces.dashboard import report
from services.transport import messages
from services.transport.mcap_io import McapRecorderWriter, read_messages
from tests.dashboard_helpers import DEMO_MCAP

FLAT = "LD"  # the electrode whose signal is flattened
FLAT_S = (4.0, 7.0)  # s after the set's first EMG sample


LABELS = ("PMCla", "PMSte", "DelAnt", "DelMed", "DelPos", "BicLong", "TriLong", "TriLat", "BRD", "LD")


def write_first_set_with_emg_status(path) -> float:
    """The demo recording up to its second load event, with the estimator's status (every 0.5 s of EMG) added; the
    electrode map as the demo's labels say (each channel is named after its muscle group). Returns the device time
    (s) of the first EMG sample."""
    electrode_map = {label: label for label in LABELS}
    quality, fatigue = LiveQuality(electrode_map), LiveFatigue(electrode_map)
    loads, origin_ns, next_status_ns, last_emg = 0, None, 0, None
    with McapRecorderWriter(path) as writer:

        def status(log_ns: int) -> None:
            s = messages.DeviceStatus(
                device_id="estimator",
                kind="node",
                connected=True,
                electrodes=[electrode_quality(r) for r in quality.report()],
                fatigue=[electrode_fatigue(r) for r in fatigue.report()],
            )
            writer.write("msk/synth/status/estimator", messages.type_name(s), messages.encode(s), log_ns, log_ns)

        for recorded in read_messages(DEMO_MCAP):
            data = recorded.data
            if recorded.type_name == "msk.LoadEvent":
                loads += 1
                if loads == 2:
                    break
                fatigue.start_set(loads)
            elif recorded.type_name == "msk.EmgChunk":
                c = recorded.decode(messages.EmgChunk)
                origin_ns = c.device_time_ns if origin_ns is None else origin_ns
                x = np.asarray(c.samples, dtype=float).reshape(c.n_samples, c.n_channels)
                t = (c.device_time_ns - origin_ns) / 1e9 + np.arange(c.n_samples) / c.sample_rate_hz
                x[(t >= FLAT_S[0]) & (t < FLAT_S[1]), list(c.channel_labels).index(FLAT)] = 0.0
                c.samples[:] = x.ravel().tolist()
                data = messages.encode(c)
                raw = RawEmgChunk(
                    c.source_id, c.channel_labels, c.sample_rate_hz, c.first_sample_index, c.device_time_ns, x, c.units
                )
                quality.add_chunk(raw)
                fatigue.add_chunk(raw)
                last_emg = (c.source_id, c.device_time_ns + int(c.n_samples / c.sample_rate_hz * 1e9))
            elif recorded.type_name == "msk.JointAngles" and last_emg is not None:
                j = recorded.decode(messages.JointAngles)
                fatigue.add_frame({last_emg[0]: min(last_emg[1], j.device_time_ns)}, j.phase)
            writer.write(recorded.topic, recorded.type_name, data, recorded.log_time_ns, recorded.publish_time_ns)
            if last_emg is not None and recorded.log_time_ns >= next_status_ns:
                status(recorded.log_time_ns)
                next_status_ns = recorded.log_time_ns + 500_000_000
        status(recorded.log_time_ns)
    assert origin_ns is not None
    return origin_ns / 1e9


@pytest.fixture(scope="module")
def emg_report(tmp_path_factory):
    out = tmp_path_factory.mktemp("report_emg")
    origin_s = write_first_set_with_emg_status(out / "session.mcap")
    summary = report.write_report(out / "session.mcap", out / "out")
    assert json.loads((out / "out" / "report.json").read_text())["fatigue"] == summary["fatigue"]
    return origin_s, summary, (out / "out" / "report.html").read_text()


def test_report_lists_every_electrode_with_its_state_and_episodes(emg_report):
    origin_s, summary, page = emg_report
    electrodes = summary["electrodes"]
    assert sorted(electrodes) == sorted(f"trigno-synth/{label}" for label in LABELS)
    flat = electrodes[f"trigno-synth/{FLAT}"]
    assert flat["episodes"] >= 1 and flat["check_s"] + flat["bad_s"] > 1.0
    assert any("flat" in r for e in flat["recent_episodes"] for r in e["reasons"]), flat
    first = flat["recent_episodes"][0]  # flagged within 1 s of the flat line's start, good again within 1 s of its end
    assert FLAT_S[0] <= first["start_s"] - origin_s <= FLAT_S[0] + 1.0, first
    assert FLAT_S[1] <= first["end_s"] - origin_s <= FLAT_S[1] + 1.0, first
    clean = [e for name, e in electrodes.items() if not name.endswith(FLAT)]
    assert all(e["episodes"] == 0 and e["state"] == "good" for e in clean), clean
    section = page[page.index("<section class='electrodes'>") :].split("</section>")[0]
    assert section.count("<tr>") == 1 + 10
    row = section[section.index(f"<td>trigno-synth/{FLAT}</td>") :].split("</tr>")[0]
    assert "<td>Latissimus dorsi</td>" in row and "flat" in row and f"<td>{flat['episodes']}</td>" in row


def test_report_gives_the_median_frequency_per_electrode_and_set(emg_report):
    _, summary, page = emg_report
    fatigue = summary["fatigue"]
    pmcla = fatigue["trigno-synth/PMCla"]
    assert len(pmcla) == 1 and pmcla[0]["set_number"] == 1 and pmcla[0]["reps"] == 3
    assert all(30.0 < v < 300.0 for v in pmcla[0]["median_hz"])
    section = page[page.index("<section class='fatigue'>") :].split("</section>")[0]
    row = section[section.index("<td>trigno-synth/PMCla</td>") :].split("</tr>")[0]
    first, last = pmcla[0]["median_hz"][0], pmcla[0]["median_hz"][-1]
    assert f"<td>{first:.1f}</td><td>{last:.1f}</td>" in row
    assert f"<td>{pmcla[0]['median_slope_hz_per_rep']:+.1f} (" in row and "Pectoralis major, clavicular part" in row
