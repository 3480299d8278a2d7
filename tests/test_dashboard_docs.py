"""Every `msk` line of the sh blocks of docs/dashboard.md parses with the real command line (flags and commands exist)."""

from __future__ import annotations

import re
import shlex

from services.cli import build_parser


def test_dashboard_doc_commands_parse(repo_root):
    text = (repo_root / "docs" / "dashboard.md").read_text()
    lines = [line for block in re.findall(r"```sh\n(.*?)```", text, flags=re.S) for line in block.splitlines()]
    commands = [shlex.split(line.split("#", 1)[0].rstrip(" &")) for line in lines if line.startswith("msk ")]
    assert {c[1] for c in commands} >= {"dashboard", "report", "estimator", "replay", "demo"}
    parser = build_parser()
    for command in commands:
        args = parser.parse_args(command[1:])
        assert args.handler is not None, command
    assert (repo_root / "docs" / "img" / "dashboard-live.png").stat().st_size > 20_000  # tests/test_live_dashboard.py
    assert (repo_root / "docs" / "img" / "report.png").stat().st_size > 20_000
