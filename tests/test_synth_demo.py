"""The shipped demo session (recordings/) is exactly what the generator makes, and the trial files load."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from google.protobuf.message import Message as ProtoMessage

from msk_core.estimate.trial import load_trial
from msk_core.model import load_pack
from msk_core.synth import Exercise, SynthConfig, generate_session
from msk_core.synth.files import write_session

ROOT = Path(__file__).resolve().parents[1] / "recordings"
REGENERATE = (
    "msk synth --exercise both --subject-seed 7 --reps 3 --loads bench_press=40,50 --loads deadlift=45,75 "
    "--out recordings/demo --mcap recordings/demo_session.mcap --quiet"
)


REL_TOL, ABS_TOL = 1e-4, 1e-5  # see _assert_same_numbers
NUMBER = re.compile(r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?")


def _last_digit(token: str) -> float:
    """The value of one unit in the last printed digit of a number as written (e.g. "1.25e-05" -> 1e-7)."""
    mantissa, _, exponent = token.lower().lstrip("+-").partition("e")
    decimals = len(mantissa.split(".", 1)[1]) if "." in mantissa else 0
    return 10.0 ** (int(exponent or 0) - decimals)


def _assert_same_numbers(shipped: str, fresh: str, what: str) -> None:
    """Same text around the numbers; each number equal up to rounding carried through the generator: numpy's
    vectorised sums round in a CPU-dependent order (1e-14 relative in the EMG maxima), and the true activations come
    out of an iterative solve that carries that into ~1e-5 of an activation (measured: 4.8e-6 between two CPUs).
    A change of the generator moves numbers by far more."""
    assert NUMBER.sub("#", shipped) == NUMBER.sub("#", fresh), f"{what}: text differs; regenerate: {REGENERATE}"
    for a, b in zip(NUMBER.findall(shipped), NUMBER.findall(fresh)):
        x, y = float(a), float(b)
        assert abs(x - y) <= max(REL_TOL * abs(x), ABS_TOL, 2 * _last_digit(a)), f"{what}: {a} != {b}; {REGENERATE}"


def _numbers(message, out: list) -> list:
    for _, value in message.ListFields():
        items = list(value) if hasattr(value, "__len__") and not isinstance(value, (str, bytes)) else [value]
        for item in items:
            if isinstance(item, ProtoMessage):
                _numbers(item, out)
            else:
                out.append(item)
    return out


def _assert_same_recording(shipped: Path, fresh: Path) -> None:
    from services.transport import messages
    from services.transport.mcap_io import read_messages

    a, b = list(read_messages(shipped)), list(read_messages(fresh))
    assert len(a) == len(b), (
        f"demo_session.mcap: {len(a)} messages shipped, {len(b)} generated; regenerate: {REGENERATE}"
    )
    for x, y in zip(a, b):
        assert (x.topic, x.type_name, x.log_time_ns) == (y.topic, y.type_name, y.log_time_ns), REGENERATE
        if x.data == y.data:
            continue
        nx, ny = (_numbers(messages.decode(m.type_name, m.data), []) for m in (x, y))
        assert len(nx) == len(ny), f"{x.topic} at {x.log_time_ns}: fields differ; regenerate: {REGENERATE}"
        for u, v in zip(nx, ny):
            if isinstance(u, float):
                assert abs(u - v) <= REL_TOL * abs(u) + ABS_TOL, (
                    f"{x.topic} at {x.log_time_ns}: {u} != {v}; {REGENERATE}"
                )
            else:
                assert u == v, f"{x.topic} at {x.log_time_ns}: {u!r} != {v!r}; regenerate: {REGENERATE}"


def test_demo_session_is_reproducible(tmp_path):
    """Generated again, the session equals the shipped files up to floating-point rounding (byte equality held on one
    CPU but not on another: numpy's vectorised sums depend on the CPU's instruction set)."""
    from services.sessions.synth_export import write_mcap

    cfg = SynthConfig(
        subject_seed=7, n_reps=3, loads_kg={Exercise.BENCH_PRESS: (40.0, 50.0), Exercise.DEADLIFT: (45.0, 75.0)}
    )
    session = generate_session(list(Exercise), cfg)
    write_session(session, tmp_path / "demo")
    write_mcap(session, tmp_path / "demo_session.mcap")
    shipped = sorted(p.relative_to(ROOT) for p in (ROOT / "demo").rglob("*") if p.is_file())
    fresh = sorted(p.relative_to(tmp_path) for p in (tmp_path / "demo").rglob("*") if p.is_file())
    assert shipped == fresh, f"recordings/ is stale; regenerate with: {REGENERATE}"
    for rel in fresh:
        ours, theirs = (ROOT / rel).read_bytes(), (tmp_path / rel).read_bytes()
        if ours != theirs:
            _assert_same_numbers(ours.decode(), theirs.decode(), str(rel))
    _assert_same_recording(ROOT / "demo_session.mcap", tmp_path / "demo_session.mcap")


def test_the_reproducibility_check_catches_a_real_change():
    _assert_same_numbers("a = 0.0805304\n", "a = 0.0805302\n", "rounding")  # as measured between two CPUs
    with pytest.raises(AssertionError):
        _assert_same_numbers("a = 0.0805304\n", "a = 0.0806304\n", "changed")  # 1e-4 of an activation
    with pytest.raises(AssertionError):
        _assert_same_numbers("f_max = 1523.25\n", "f_max = 1523.75\n", "changed")
    with pytest.raises(AssertionError):
        _assert_same_numbers("a = 1\n", "b = 1\n", "renamed")


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
