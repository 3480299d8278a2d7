"""write_text_atomic: readers see the old file or the new one, never a part; a failed write leaves the old file."""

from __future__ import annotations

import stat
import threading

import pytest

from msk_core.io.files import write_text_atomic


def test_concurrent_readers_never_see_a_partial_file(tmp_path):
    path = tmp_path / "subject.json"
    versions = ["A" * 2_000_000 + "\n", "B" * 3_000_000 + "\n"]
    write_text_atomic(path, versions[0])
    seen: set[int] = set()
    stop = threading.Event()

    def read() -> None:
        while not stop.is_set():
            seen.add(len(path.read_text()))

    reader = threading.Thread(target=read)
    reader.start()
    try:
        for k in range(30):
            write_text_atomic(path, versions[k % 2])
    finally:
        stop.set()
        reader.join(10)
    assert seen <= {len(v) for v in versions}, sorted(seen)
    assert not [p.name for p in tmp_path.iterdir() if p.name != "subject.json"]  # no temporary file left


def test_a_failed_write_keeps_the_old_file(tmp_path, monkeypatch):
    path = tmp_path / "tokens.json"
    write_text_atomic(path, "old\n", mode=0o600)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600

    def fail(self, text):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(type(path), "write_text", fail)
    with pytest.raises(OSError, match="No space"):
        write_text_atomic(path, "new\n")
    monkeypatch.undo()
    assert path.read_text() == "old\n"
    assert [p.name for p in tmp_path.iterdir()] == ["tokens.json"]
