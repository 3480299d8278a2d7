"""Every ```python block of docs/signal.md runs, in order, in one namespace (documentation that cannot rot)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest


def test_signal_doc_examples_run(shared_dir: Path, repo_root: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = (repo_root / "docs/signal.md").read_text()
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert len(blocks) >= 8
    namespace: dict[str, object] = {"SHARED": shared_dir, "TMP": tmp_path}
    for i, block in enumerate(blocks):
        try:
            exec(compile(block, f"docs/signal.md[block {i + 1}]", "exec"), namespace)
        except Exception as exc:  # pragma: no cover - the message says which block failed
            pytest.fail(f"docs/signal.md block {i + 1} failed: {exc!r}\n{block}")
    out = capsys.readouterr().out
    assert "group delay 53." in out and "Coordinates True" in out
