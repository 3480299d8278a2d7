"""OpenSim .sto/.mot reader and writer, on every real storage file in ../shared and on hand-made bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from msk_core.errors import FileFormatError, InputError
from msk_core.io import read_sto, write_sto

pytestmark = pytest.mark.needs_shared


def _storage_files(shared_dir: Path) -> list[Path]:
    return sorted([*shared_dir.glob("data/**/*.sto"), *shared_dir.glob("data/**/*.mot")])


def test_reads_every_shared_storage_file(shared_dir: Path) -> None:
    files = _storage_files(shared_dir)
    assert len(files) >= 15
    for f in files:
        s = read_sto(f)
        assert s.data.shape == (s.time.shape[0], len(s.columns)), f
        assert s.n_rows > 50, f
        assert "time" not in s.columns
        assert np.all(np.isfinite(s.data)), f
        assert np.all(np.diff(s.time) > 0), f


def test_header_dialects(shared_dir: Path) -> None:
    d = shared_dir / "data"
    ik = read_sto(d / "opensim-arm26/arm26_InverseKinematics.mot")
    assert ik.in_degrees and ik.name == "Coordinates" and ik.columns == ["r_shoulder_elev", "r_elbow_flex"]
    assert ik.column("r_elbow_flex")[-1] == pytest.approx(90.17066638)
    assert ik.header["version"] == "1"
    # comma-separated spreadsheet export with padded header and a false nRows=250 (88 rows really present)
    csv = read_sto(d / "pyomeca-upper/inverse_kin.mot")
    assert csv.in_degrees and csv.header["nRows"] == "250" and csv.n_rows == 88
    assert csv.time[0] == pytest.approx(1.56) and csv.columns[-1] == "box_transZ" and len(csv.columns) == 25
    # no version line, no inDegrees, trailing tab after the last label and value, Unix-epoch times
    emg = read_sto(d / "backmodel-lift/stoop5kg/emgFilt.sto")
    assert not emg.in_degrees and emg.columns[:2] == ["rectabd_r", "rectabd_l"] and emg.columns[-1] == "zeroEMG"
    assert emg.time[0] == pytest.approx(1667315607.814670085907, abs=1e-9)
    # padded first label '      time'
    idf = read_sto(d / "backmodel-lift/squat5kg/id.sto")
    assert idf.columns[6] == "L5_S1_Flex_Ext" and idf.column("L5_S1_Flex_Ext")[0] == pytest.approx(13.7422)
    walk = read_sto(d / "lowerlimb-walk/walk45_ik.sto")
    assert walk.in_degrees and walk.rate == pytest.approx(100.0)


def test_write_read_round_trip_is_lossless(tmp_path: Path, shared_dir: Path) -> None:
    src = read_sto(shared_dir / "data/backmodel-lift/squat5kg/ik.sto")
    out = write_sto(tmp_path / "ik.sto", src.time, src.columns, src.data, in_degrees=False, name="roundtrip")
    back = read_sto(out)
    assert back.columns == src.columns and back.name == "roundtrip" and not back.in_degrees
    np.testing.assert_array_equal(back.time, src.time)
    np.testing.assert_array_equal(back.data, src.data)
    assert back.header["nRows"] == str(src.n_rows) and back.header["nColumns"] == str(len(src.columns) + 1)


@pytest.mark.needs_opensim
def test_opensim_reads_what_we_write(tmp_path: Path) -> None:
    opensim = pytest.importorskip("opensim")
    t = np.linspace(0.0, 1.0, 11)
    data = np.column_stack([np.sin(t), 10.0 * t])
    out = write_sto(tmp_path / "q.mot", t, ["elbow_flex", "shoulder_elev"], data, in_degrees=True, name="Coordinates")
    table = opensim.TimeSeriesTable(str(out))
    assert list(table.getColumnLabels()) == ["elbow_flex", "shoulder_elev"]
    assert table.getNumRows() == 11
    assert table.getTableMetaDataAsString("inDegrees") == "yes"
    assert table.getDependentColumn("shoulder_elev")[7] == pytest.approx(7.0)
    assert np.asarray(table.getIndependentColumn())[-1] == pytest.approx(1.0)


def _write(tmp_path: Path, text: str) -> Path:
    p = tmp_path / "bad.sto"
    p.write_text(text)
    return p


def test_errors_name_file_line_and_field(tmp_path: Path) -> None:
    p = _write(tmp_path, "x\nversion=1\nendheader\ntime\ta\tb\n0\t1\t2\n0.1\t1\tabc\n")
    with pytest.raises(FileFormatError) as err:
        read_sto(p)
    msg = str(err.value)
    assert "bad.sto" in msg and "line 6" in msg and "'b'" in msg and "abc" in msg
    assert err.value.line == 6 and err.value.field == "b"

    with pytest.raises(FileFormatError, match="line 4.*expected 3 values, found 2"):
        read_sto(_write(tmp_path, "x\nendheader\ntime\ta\tb\n0\t1\n"))
    with pytest.raises(FileFormatError, match="endheader"):
        read_sto(_write(tmp_path, "time\ta\n0\t1\n"))
    with pytest.raises(FileFormatError, match="line 2.*inDegrees.*maybe"):
        read_sto(_write(tmp_path, "x\ninDegrees=maybe\nendheader\ntime\ta\n0\t1\n"))
    with pytest.raises(FileFormatError, match="first column must be 'time'"):
        read_sto(_write(tmp_path, "x\nendheader\nframe\ta\n0\t1\n"))
    with pytest.raises(InputError, match="cannot read"):
        read_sto(tmp_path / "missing.sto")
    with pytest.raises(InputError, match="no column 'c'.*a, b"):
        read_sto(_write(tmp_path, "x\nendheader\ntime a b\n0 1 2\n")).column("c")


def test_write_rejects_bad_input(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="shape"):
        write_sto(tmp_path / "a.sto", np.arange(3.0), ["a"], np.zeros((2, 1)))
    with pytest.raises(InputError, match="unique"):
        write_sto(tmp_path / "a.sto", np.arange(2.0), ["a", "a"], np.zeros((2, 2)))
    with pytest.raises(InputError, match="tabs"):
        write_sto(tmp_path / "a.sto", np.arange(2.0), ["a\tb"], np.zeros((2, 1)))


_LABEL = st.text(alphabet="abcdefghijklmnopqrstuvwxyzABCXYZ_0123456789.:()[]-", min_size=1, max_size=12).filter(
    lambda s: s.lower() != "time"
)


@settings(max_examples=30, deadline=None)
@given(
    st.lists(_LABEL, min_size=1, max_size=6, unique=True),
    st.integers(min_value=1, max_value=20),
    st.data(),
    st.booleans(),
)
def test_round_trip_property(tmp_path_factory, labels, n_rows, data, in_degrees) -> None:
    finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
    values = np.array(
        data.draw(
            st.lists(st.lists(finite, min_size=len(labels), max_size=len(labels)), min_size=n_rows, max_size=n_rows)
        )
    )
    time = np.cumsum(np.abs(np.array(data.draw(st.lists(st.floats(0.001, 1e6), min_size=n_rows, max_size=n_rows)))))
    path = tmp_path_factory.mktemp("prop") / "x.sto"
    write_sto(path, time, labels, values, in_degrees=in_degrees, name="prop")
    back = read_sto(path)
    assert back.columns == labels and back.in_degrees == in_degrees
    np.testing.assert_array_equal(back.time, time)
    np.testing.assert_array_equal(back.data, values)
