""".anc and C3D analog readers on the real files, and .anc errors."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import FileFormatError, InputError
from msk_core.io import read_anc, read_c3d_analogs


def test_rajagopal_anc(shared_dir: Path) -> None:
    rec = read_anc(shared_dir / "data/rajagopal-walk/emg_walk_raw.anc")
    assert rec.labels[:3] == ["F1X", "F1Y", "F1Z"] and rec.labels[-10:] == [
        "SOL",
        "GAS",
        "TA",
        "MH",
        "BF",
        "VL",
        "VM",
        "RF",
        "GMAX",
        "GMED",
    ]
    assert rec.rate_hz == 2000.0 and rec.data.shape == (4780, 28)
    assert rec.header["Board_Type"] == "NI USB-6225" and rec.header["#Channels"] == "28"
    assert rec.channel_info["Range"][rec.index("MH")] == "1000"
    assert rec.time[-1] == pytest.approx(2.3895) and np.allclose(np.diff(rec.time), 0.0005)
    assert rec.channel("TA")[:3].tolist() == [-350.0, -998.0, -1450.0]
    sub = rec.select(["TA", "SOL"])
    assert sub.labels == ["TA", "SOL"] and sub.channel_info["Range"] == ["2500", "2500"]


def test_pyomeca_c3d(shared_dir: Path) -> None:
    rec = read_c3d_analogs(shared_dir / "data/pyomeca-upper/markers_analogs.c3d")
    assert rec.rate_hz == 2000.0 and rec.data.shape == (11600, 38)
    assert rec.time[1] - rec.time[0] == pytest.approx(0.0005)
    emg = rec.channel("Delt_ant.EMG1")
    assert 1e-4 < np.abs(emg).max() < 1e-2  # volts: Trigno range is about +-11 mV
    assert np.all(rec.channel("Sensor 12.EMG12") == 0.0)  # unused slot


def test_anc_errors(tmp_path: Path) -> None:
    p = tmp_path / "bad.anc"
    p.write_text("File_Type:\tAnalog R/C ASCII\nName\tA\tB\nRate\t100\t100\n0.0\t1\t2\n0.01\t1\tx\n")
    with pytest.raises(FileFormatError, match=r"bad.anc, line 5, field 'B': not a number \(got 'x'\)"):
        read_anc(p)
    p.write_text("Name\tA\tB\nRate\t100\t200\n0.0\t1\t2\n")
    with pytest.raises(FileFormatError, match="different rates"):
        read_anc(p)
    p.write_text("hello\n")
    with pytest.raises(FileFormatError, match="not an .anc file"):
        read_anc(p)
    with pytest.raises(InputError, match="no such C3D"):
        read_c3d_analogs(tmp_path / "none.c3d")
