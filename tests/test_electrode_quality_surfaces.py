"""Each electrode's signal quality where people look: the terminal view's muscle table (state with the reason, in the
row of its muscle), the dashboard bridge (the ``electrodes`` entry) and the page in a headless Chromium (a row per
electrode under its muscle's name, coloured by state, the verdict's numbers in the tooltip)."""

from __future__ import annotations

import time

from services.surfaces.dashboard.bridge import DashboardState
from services.surfaces.view import ViewState
from services.transport import messages
from tests.test_view import screen_text

GROUPS = ["TriLat", "PMCla", "DelAnt"]


def estimator_status(states: dict[str, tuple[str, list[str]]]) -> messages.DeviceStatus:
    """The estimator's status with one electrode per group: group -> (state, reasons)."""
    return messages.DeviceStatus(
        device_id="estimator",
        kind="node",
        connected=True,
        electrodes=[
            messages.ElectrodeQuality(
                source="trigno",
                channel=f"sensor{k + 1:02d}.EMG",
                group=group,
                state=state,
                reasons=reasons,
                detail=f"{state}: {', '.join(reasons)} (numbers)" if reasons else state,
            )
            for k, (group, (state, reasons)) in enumerate(states.items())
        ],
    )


def frame(k: int = 0) -> messages.ActivationFrame:
    return messages.ActivationFrame(
        method="assisted",
        time_s=10.0 + k * 0.05,
        groups=GROUPS,
        activations=[0.4, 0.2, 0.3],
        measured_envelope=[0.35, float("nan"), 0.25],
        exercise="bench_press",
        flags=["electrode_bad"],
    )


def test_the_view_shows_each_electrode_state_with_its_reason_in_its_muscle_row():
    state = ViewState()
    state.on_message("msk/s/activations/assisted", frame())
    assert "┃ electrode" not in screen_text(state)  # no column before the estimator says anything
    state.on_message(
        "msk/s/status/estimator",
        estimator_status(
            {"TriLat": ("good", []), "PMCla": ("bad", ["flat line"]), "DelAnt": ("check", ["mains interference"])}
        ),
    )
    text = screen_text(state)
    assert "┃ electrode" in text
    rows = {line.split("│")[1].strip(): line for line in text.splitlines() if line.count("│") > 4}
    assert "good" in rows["Triceps brachii, lateral and medial heads"]
    assert "bad: flat line" in rows["Pectoralis major, clavicular part"]
    assert "check: mains interference" in rows["Deltoid, anterior part"]
    assert "bad electrode left out" in text  # the frame's flag, in words, in the session line


def test_the_bridge_forwards_the_electrodes_and_drops_them_with_the_node():
    dashboard = DashboardState("s")
    dashboard.on_message("msk/s/status/estimator", estimator_status({"TriLat": ("bad", ["saturation"])}))
    _, update = dashboard.changes(0)
    assert update["topics"]["electrodes"] == [
        {
            "source": "trigno",
            "channel": "sensor01.EMG",
            "group": "TriLat",
            "state": "bad",
            "reasons": ["saturation"],
            "detail": "bad: saturation (numbers)",
        }
    ]
    seq, _ = dashboard.changes(0)
    dashboard.on_message("msk/s/status/estimator", messages.DeviceStatus(device_id="estimator", kind="node"))
    seq, update = dashboard.changes(seq)
    assert update["topics"]["electrodes"] == []  # an estimator restarted without EMG: no stale rows
    dashboard.on_message("msk/s/status/kinematics", messages.DeviceStatus(device_id="kinematics", kind="node"))
    _, update = dashboard.changes(seq)
    assert "electrodes" not in update["topics"]  # other nodes' statuses leave the entry alone


# The words of the cells matched by a selector that the page draws on more than one line (split inside the word; a
# hyphenated word may break after its hyphen, "low-/frequency"), and the cells whose text runs past their edge.
WORDS_SPLIT_OR_OVERFLOWING = """(selector) => {
    const split = [], overflowing = [];
    for (const cell of document.querySelectorAll(selector)) {
        if (cell.scrollWidth > cell.clientWidth) overflowing.push(cell.textContent);
        const walker = document.createTreeWalker(cell, NodeFilter.SHOW_TEXT);
        for (let node = walker.nextNode(); node; node = walker.nextNode()) {
            for (const word of node.data.matchAll(/[^\\s-]+-?/g)) {
                const range = document.createRange();
                range.setStart(node, word.index);
                range.setEnd(node, word.index + word[0].length);
                const lines = new Set([...range.getClientRects()].map((r) => Math.round(r.top)));
                if (lines.size > 1) split.push(word[0]);
            }
        }
    }
    return [split, overflowing];
}"""


def test_the_page_lists_each_electrode_under_its_muscle_coloured_by_state(tmp_path, zenoh_endpoint):
    from tests.dashboard_helpers import ARTIFACTS, dashboard_in_chromium, require_chromium

    require_chromium()

    from msk_core.signal.quality import Fault
    from services.surfaces.dashboard.app import DashboardConfig
    from services.transport import topics
    from services.transport.zenoh_session import declare_data_publisher, publish

    session = "quality"
    rows = (
        "() => [...document.querySelectorAll('#electrodes tbody tr')].map(tr => [tr.dataset.channel, "
        "tr.dataset.state, tr.cells[0].textContent, tr.cells[2].textContent, tr.cells[2].className, tr.title, "
        "tr.cells[0].title])"
    )
    with dashboard_in_chromium(zenoh_endpoint, DashboardConfig(session=session)) as (zsession, browser, page, errors):
        frames = declare_data_publisher(zsession, topics.activations_key(session, "assisted"), "msk.ActivationFrame")
        status = declare_data_publisher(zsession, topics.status_key(session, "estimator"), "msk.DeviceStatus")
        states = {
            "TriLat": ("good", []),
            "PMCla": ("bad", ["flat line"]),
            "DelAnt": ("check", ["mains interference"]),
        }
        deadline, shown = time.monotonic() + 15, []
        while time.monotonic() < deadline and len(shown) < 3:  # until the page has subscribed and drawn them
            publish(frames, frame())
            publish(status, estimator_status(states))
            time.sleep(0.2)
            shown = page.evaluate(rows)
        assert len(shown) == 3, f"waited 15 s for 3 electrode rows; the page shows {shown}"
        page.locator(".panel.map").screenshot(path=str(ARTIFACTS / "dashboard-electrodes.png"))
        # the muscle in few words (the column is narrow), its whole display name in the tooltip
        assert [r[2] for r in shown] == ["Triceps lateral", "Pectoralis clavicular", "Deltoid anterior"]
        assert [r[6] for r in shown] == [
            "Triceps brachii, lateral and medial heads",
            "Pectoralis major, clavicular part",
            "Deltoid, anterior part",
        ]
        assert [(r[1], r[3], r[4]) for r in shown] == [
            ("good", "good", "q-good"),
            ("bad", "bad: flat line", "q-bad"),
            ("check", "check: mains interference", "q-check"),
        ]
        assert shown[1][5] == "bad: flat line (numbers)"
        colours = page.evaluate(
            "() => [...document.querySelectorAll('#electrodes td[class^=q-]')].map(td => getComputedStyle(td).color)"
        )
        assert len(set(colours)) == 3, colours  # three states, three colours
        # read from the rack: a state's words wrap whole ("check: mains / interference"), none split inside a word,
        # and the cell holds them (nothing cut off at its edge)
        for fault in Fault:  # every reason the estimator can give, on the check row
            states["DelAnt"] = ("check", [fault.value])
            publish(status, estimator_status(states))
            page.wait_for_function(
                "(text) => document.querySelector('#electrodes tr[data-channel=\"sensor03.EMG\"]').cells[2]"
                ".textContent === text",
                arg=f"check: {fault.value}",
                timeout=10000,
            )
            for width, height in ((1280, 800), (800, 1280)):  # the rack's landscape screen and a tablet upright
                page.set_viewport_size({"width": width, "height": height})
                page.wait_for_timeout(200)
                split, overflowing = page.evaluate(WORDS_SPLIT_OR_OVERFLOWING, "#electrodes td[class^=q-]")
                assert split == [] and overflowing == [], (fault, width, height, split, overflowing)
        states["PMCla"] = ("good", [])  # the electrode recovers
        publish(status, estimator_status(states))
        page.wait_for_function(
            "() => document.querySelector('#electrodes tr[data-channel=\"sensor02.EMG\"]').dataset.state === 'good'",
            timeout=10000,
        )
        assert not errors, errors
        browser.close()
