"""`msk replay` of a file that is not an MCAP recording says so and fails (it is not a recording cut short)."""

from __future__ import annotations

import pytest

from services.cli import main as msk


@pytest.mark.parametrize("content", [b"", b"time,emg\n0.0,1.0\n", b"\x89PNG\r\n\x1a\n" + bytes(64)])
def test_replay_of_a_non_mcap_file_names_it_and_exits_non_zero(tmp_path, zenoh_endpoint, capsys, content):
    path = tmp_path / "session.mcap"
    path.write_bytes(content)
    code = msk(["replay", str(path), "--rate", "max", "--wait-subscribers", "0", "--listen", zenoh_endpoint])
    err = capsys.readouterr().err
    assert code != 0
    assert "not an MCAP recording" in err and str(path) in err
    assert "cut short" not in err


def test_replay_of_a_truncated_mcap_still_replays_its_readable_part(tmp_path, zenoh_endpoint, capsys, repo_root):
    whole = (repo_root / "recordings" / "demo_session.mcap").read_bytes()
    path = tmp_path / "cut.mcap"
    path.write_bytes(whole[: len(whole) * 3 // 5])  # past the first complete chunks
    code = msk(["replay", str(path), "--rate", "max", "--wait-subscribers", "0", "--listen", zenoh_endpoint])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "cut short" in err and "published 0 " not in err
