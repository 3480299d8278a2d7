"""Delsys EMGworks and Trigno Discover CSV readers on small files written to the documented layouts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import FileFormatError, InputError
from msk_core.io import read_delsys_csv, read_emgworks_csv, read_trigno_discover_csv
from msk_core.signal.emg import EmgFilterConfig, envelope_causal

EMG_DT = 0.0005192308  # 1925.926 Hz
ACC_DT = 0.00675  # 148.148 Hz
N_EMG, N_ACC = 260, 20


def _signals():
    rng = np.random.default_rng(0)
    emg = rng.standard_normal((N_EMG, 2)) * 1e-4  # volts
    acc = rng.standard_normal((N_ACC, 2))
    return emg, acc


def _write_emgworks(path: Path) -> None:
    emg, acc = _signals()
    labels = []
    for s in (1, 2):
        labels += ["X[s]", f'"Avanti sensor {s}: EMG {s}"', "X[s]", f'"Avanti sensor {s}: ACC.X {s}"']
    lines = ["Label: lift set 1,,,,,,,", ",".join(labels)]
    for i in range(N_EMG):
        cells = []
        for s in range(2):
            cells += [f"{i * EMG_DT:.10f}", repr(float(emg[i, s]))]
            cells += [f"{i * ACC_DT:.5f}", repr(float(acc[i, s]))] if i < N_ACC else ["", ""]
        lines.append(",".join(cells))
    path.write_text("\r\n".join(lines) + "\r\n")


def _write_discover(path: Path, *, period_row: bool = True) -> None:
    emg, acc = _signals()
    head = [
        "Application:,Trigno Discover (1.6.4)",
        "Date/Time:,11/21/2026 10:00:00 PM",
        f"Collection Length (seconds):,{N_EMG * EMG_DT:.4f}",
        "Avanti Sensor 1 (75923),,,,Avanti Sensor 2 (75924),,,",
        "sensor mode: 65,,,,sensor mode: 65,,,",
        "EMG 1 Time Series (s),EMG 1 (mV),ACC X Time Series (s),ACC X (G),"
        "EMG 1 Time Series (s),EMG 1 (mV),ACC X Time Series (s),ACC X (G)",
        ",1925.9259 Hz,,148.1481 Hz,,1925.9259 Hz,,148.1481 Hz",
    ]
    if period_row:
        head.append(",0.000519 s,,0.00675 s,,0.000519 s,,0.00675 s")
    lines = list(head)
    for i in range(N_EMG):
        cells = []
        for s in range(2):
            cells += [f"{i * EMG_DT:.10f}", repr(float(emg[i, s] * 1e3))]  # exported in mV
            cells += [f"{i * ACC_DT:.5f}", repr(float(acc[i, s]))] if i < N_ACC else ["", ""]
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def test_emgworks_csv(tmp_path: Path) -> None:
    p = tmp_path / "emgworks.csv"
    _write_emgworks(p)
    export = read_emgworks_csv(p)
    emg, acc = _signals()
    assert [c.name for c in export.channels] == ["EMG 1", "ACC.X 1", "EMG 2", "ACC.X 2"]
    assert export.channels[0].sensor == "Avanti sensor 1"
    assert export.channels[0].rate_hz == pytest.approx(1925.926, rel=1e-6)
    assert export.channels[1].rate_hz == pytest.approx(148.148, rel=1e-4)
    assert export.channels[1].values.shape == (N_ACC,)
    np.testing.assert_array_equal(export.channels[3].values, acc[:, 1])
    rec = export.recording()
    assert rec.labels == ["Avanti sensor 1: EMG 1", "Avanti sensor 2: EMG 2"] and rec.units == ["V", "V"]
    np.testing.assert_array_equal(rec.data, emg)
    assert read_delsys_csv(p).application == "EMGworks"
    with pytest.raises(InputError, match="different rates"):
        export.recording(emg_only=False)


@pytest.mark.parametrize("period_row", [True, False])
def test_trigno_discover_csv(tmp_path: Path, period_row: bool) -> None:
    p = tmp_path / "discover.csv"
    _write_discover(p, period_row=period_row)
    export = read_trigno_discover_csv(p)
    emg, acc = _signals()
    assert export.application == "Trigno Discover (1.6.4)"
    assert export.header["Collection Length (seconds)"] == f"{N_EMG * EMG_DT:.4f}"
    assert [(c.sensor, c.name, c.unit) for c in export.channels] == [
        ("Avanti Sensor 1 (75923)", "EMG 1", "mV"),
        ("Avanti Sensor 1 (75923)", "ACC X", "G"),
        ("Avanti Sensor 2 (75924)", "EMG 1", "mV"),
        ("Avanti Sensor 2 (75924)", "ACC X", "G"),
    ]
    assert export.channels[0].rate_hz == pytest.approx(1925.9259)
    np.testing.assert_array_equal(export.channels[1].values, acc[:, 0])
    rec = export.recording()  # mV -> V
    assert rec.units == ["V", "V"] and rec.rate_hz == pytest.approx(1925.9259)
    np.testing.assert_allclose(rec.data, emg, rtol=1e-12)
    raw = export.recording(to_volts=False)
    assert raw.units == ["mV", "mV"]
    assert read_delsys_csv(p).application.startswith("Trigno Discover")
    # the EMG chain runs on what the reader returns
    env = envelope_causal(rec.data, EmgFilterConfig(rate_hz=rec.rate_hz))
    assert env.shape == (N_EMG, 2) and np.all(np.isfinite(env))


def test_errors_name_line_and_field(tmp_path: Path) -> None:
    p = tmp_path / "discover.csv"
    _write_discover(p)
    lines = p.read_text().splitlines()
    cells = lines[20].split(",")
    cells[3] = "oops"
    lines[20] = ",".join(cells)
    p.write_text("\n".join(lines) + "\n")
    with pytest.raises(FileFormatError, match=r"line 21.*'ACC X \(G\)'.*oops"):
        read_trigno_discover_csv(p)
    q = tmp_path / "broken.csv"
    q.write_text("Application:,Trigno Discover (1.6.4)\nsensor,x\n")
    with pytest.raises(FileFormatError, match="rate row"):
        read_trigno_discover_csv(q)
    r = tmp_path / "notemgworks.csv"
    r.write_text("a,b\n1,2\n")
    with pytest.raises(FileFormatError, match="X\\[s\\]"):
        read_emgworks_csv(r)
