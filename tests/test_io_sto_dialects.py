"""Storage files as OpenSim reads them: what OpenSim 4 reads is read, what it refuses is refused with a precise error.

Each file is written here as text; where the opensim package is installed, its ``TimeSeriesTable`` (the reader of
OpenSim 4's tools) reads the same file and the two are compared.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from msk_core.errors import FileFormatError
from msk_core.io import read_sto
from tests.test_model_gait2392 import EMG_MUSCLES  # the walk envelopes' labels, as the pack names them

HEADER = "Inverse Dynamics Generalized Forces\nversion=1\nnRows=3\nnColumns=3\ninDegrees=no\nendheader\n"
ROWS = "0.00\t1.5\t-2.0\n0.01\t1.6\t-2.1\n0.02\t1.7\t-2.2\n"


def _opensim_table(path: Path):
    """OpenSim's TimeSeriesTable of the file, or the message it refuses it with (None without opensim)."""
    try:
        import opensim  # noqa: PLC0415 - optional
    except ImportError:
        return None
    opensim.Logger.setLevelString("error")
    try:
        return opensim.TimeSeriesTable(str(path))
    except Exception as exc:  # noqa: BLE001 - the SWIG wrapper raises a bare RuntimeError
        return str(exc)


@pytest.mark.parametrize(
    "label_line",
    [
        "\ttime\t\thip_flexion_r_moment\t\tknee_angle_r_moment",  # the real file: indented, two tabs between labels
        "time\t\thip_flexion_r_moment\t\tknee_angle_r_moment\t\t",
        "  time\t  hip_flexion_r_moment\t knee_angle_r_moment",  # labels padded with spaces
        "\t\ttime\thip_flexion_r_moment\tknee_angle_r_moment\t",
    ],
)
def test_label_lines_opensim_reads_are_read(tmp_path, label_line):
    path = tmp_path / "id.sto"
    path.write_text(HEADER + label_line + "\n" + ROWS)
    s = read_sto(path)
    assert s.columns == ["hip_flexion_r_moment", "knee_angle_r_moment"]
    np.testing.assert_array_equal(s.time, [0.0, 0.01, 0.02])
    np.testing.assert_array_equal(s.column("knee_angle_r_moment"), [-2.0, -2.1, -2.2])
    table = _opensim_table(path)
    if table is not None:
        assert not isinstance(table, str), table
        assert list(table.getColumnLabels()) == s.columns
        assert np.asarray(table.getDependentColumn("knee_angle_r_moment").to_numpy()).tolist() == [-2.0, -2.1, -2.2]


@pytest.mark.parametrize(
    ("rows", "line", "message"),
    [
        ("0.00\t\t1.5\t-2.0\n", 8, "expected 3 values, found 4"),  # an empty cell between two tabs in a row
        ("\t0.00\t1.5\t-2.0\n", 8, "expected 3 values, found 4"),  # a row that starts with a tab
        ("0.00\t1.5\n", 8, "expected 3 values, found 2"),
        ("0.00\t1.5\t-2.0\t7\n", 8, "expected 3 values, found 4"),
    ],
)
def test_rows_opensim_refuses_are_refused_naming_the_line(tmp_path, rows, line, message):
    path = tmp_path / "bad.sto"
    path.write_text(HEADER + "time\tq1\tq2\n" + rows)
    with pytest.raises(FileFormatError, match=message) as err:
        read_sto(path)
    assert err.value.line == line and "bad.sto" in str(err.value) and "line 7" in str(err.value)  # the label line
    table = _opensim_table(path)
    if table is not None:
        assert isinstance(table, str) and "Unexpected number of columns" in table, table


def test_a_label_line_that_is_not_time_first_is_refused_like_opensim(tmp_path):
    path = tmp_path / "frames.sto"
    path.write_text(HEADER + "\t\tframe\t\tq1\tq2\n" + ROWS)
    with pytest.raises(FileFormatError, match="first column must be 'time'") as err:
        read_sto(path)
    assert err.value.line == 7 and err.value.value == "frame"
    table = _opensim_table(path)
    if table is not None:
        assert isinstance(table, str) and "Expected = time" in table, table


def test_the_walk_emg_header_with_space_padded_labels(shared_dir):
    """The real walk envelopes: 'time\\t  soleus_r\\t med_gas_r ...' (labels padded with spaces)."""
    s = read_sto(shared_dir / "data" / "lowerlimb-walk" / "walk45_emgFilt.sto")
    assert s.columns == EMG_MUSCLES
    assert s.n_rows == 5904 and s.rate == pytest.approx(100.0)


def test_rows_separated_by_spaces_under_a_tab_separated_label_line_are_read_as_opensims_storage_reads_them(tmp_path):
    """OpenSim's ``Storage`` (the reader of its AnalyzeTool, static optimisation and inverse dynamics) splits a row at
    any whitespace; TimeSeriesTable would not, but a file those tools take is one a lab brings."""
    path = tmp_path / "spaces.sto"
    path.write_text(HEADER + "time\tq1\tq2\n" + ROWS.replace("\t", " "))
    s = read_sto(path)
    np.testing.assert_array_equal(s.column("q2"), [-2.0, -2.1, -2.2])
    try:
        import opensim  # noqa: PLC0415 - optional
    except ImportError:
        return
    storage, column = opensim.Storage(str(path)), opensim.ArrayDouble()
    storage.getDataColumn("q2", column)
    assert [column.get(i) for i in range(column.getSize())] == [-2.0, -2.1, -2.2]


def test_nan_and_infinity_as_other_c_runtimes_print_them_are_read(tmp_path):
    # MSVC's printf writes "-nan(ind)", older runtimes "1.#QNAN" / "-1.#IND" / "1.#INF": OpenSim reads them back
    path = tmp_path / "id.sto"
    path.write_text("id\nendheader\ntime\ta\tb\n0.0\t-nan(ind)\t1.#INF\n0.01\t1.#QNAN\t-1.#INF\n0.02\t-1.#IND\t2.5\n")
    storage = read_sto(path)
    assert np.isnan(storage.column("a")).all()
    assert storage.column("b").tolist() == [np.inf, -np.inf, 2.5]
    path.write_text("id\nendheader\ntime\ta\n0.0\tnan(what)\n")
    with pytest.raises(FileFormatError, match="not a number"):
        read_sto(path)


def test_simm_motion_headers_are_in_degrees_as_opensim_reads_them(tmp_path):
    path = tmp_path / "old.mot"
    path.write_text("name old.mot\ndatacolumns 2\ndatarows 2\nrange 0 0.01\nendheader\ntime\tknee\n0\t45\n0.01\t50\n")
    storage = read_sto(path)
    assert storage.in_degrees and storage.column("knee").tolist() == [45.0, 50.0]
    path.write_text("datacolumns 2\ndatarows 2\ninDegrees=no\nendheader\ntime\tknee\n0\t0.7\n0.01\t0.8\n")
    assert not read_sto(path).in_degrees  # a stated inDegrees wins
