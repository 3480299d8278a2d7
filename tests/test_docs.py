"""Every code block of the README and docs/ is exercised, so the documentation cannot rot (pyomeca's habit):

* ```python blocks run, in order, in one namespace per file (``REPO``, ``SHARED`` and ``TMP`` are defined; the
  working directory is a fresh temporary folder);
* shell blocks (```sh, or no language) are command lines: every ``msk ...`` line is parsed by the real ``msk``
  argument parser (sub-command, flags and choices must exist) and every ``python3 dev.py ...`` line names a dev.py
  command; any other line makes the block a script, which must pass ``bash -n`` (label prose and diagrams ```text);
* ```toml and ```json blocks must parse.
"""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
FENCE = re.compile(r"^```([\w+-]*)[^\n]*\n(.*?)^```\s*$", flags=re.S | re.M)
SHELL = ("", "sh", "shell", "bash", "console")
# Docs whose python blocks subscribe to a running session: the named test runs them against one (a replay) and checks
# what they print; test_python_blocks_run only compiles them.
RUN_AGAINST_A_SESSION = {"apps.md": "tests/test_apps_docs.py"}


def _blocks(path: Path) -> list[tuple[str, str, int]]:
    text = path.read_text()
    return [(m.group(1), m.group(2), text.count("\n", 0, m.start()) + 1) for m in FENCE.finditer(text)]


def _command_lines(block: str) -> list[str]:
    lines = []
    for raw in block.replace("\\\n", " ").splitlines():  # a trailing backslash continues the command
        line = raw.split(" #", 1)[0].strip() if not raw.lstrip().startswith("#") else ""
        line = line.removeprefix("$ ").rstrip("&").strip()
        if line:
            lines.append(line)
    return lines


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_shell_toml_and_json_blocks(doc: Path) -> None:
    import dev
    from services.cli import build_parser

    parser = build_parser()
    for language, block, line_no in _blocks(doc):
        where = f"{doc.relative_to(REPO)} line {line_no}"
        if language in SHELL:
            for line in _command_lines(block):
                try:
                    words = shlex.split(line)
                except ValueError:  # a line of a larger script (quotes across lines): bash -n judges it
                    words = ["-"]
                if words[0] == "msk":
                    try:
                        parser.parse_args(words[1:])
                    except SystemExit:
                        pytest.fail(f"{where}: `{line}` is not a valid msk command line")
                elif words[:2] == ["python3", "dev.py"]:
                    assert words[2] in ("demo", "test", "bench"), f"{where}: dev.py has no command {words[2]!r}"
                    assert "python3 dev.py" in dev.__doc__
                else:  # a script: its syntax must hold (its msk lines are parsed above)
                    checked = subprocess.run(["bash", "-n"], input=block, text=True, capture_output=True)
                    assert checked.returncode == 0, f"{where}: not a valid shell script: {checked.stderr}"
        elif language == "toml":
            tomllib.loads(block)
        elif language == "json":
            json.loads(block)


@pytest.mark.parametrize(
    "doc", [d for d in DOCS if any(lang == "python" for lang, _, _ in _blocks(d))], ids=lambda p: p.name
)
def test_python_blocks_run(doc: Path, shared_dir: Path, tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    namespace: dict[str, object] = {"REPO": REPO, "SHARED": shared_dir, "TMP": tmp_path, "__name__": "__docs__"}
    for language, block, line_no in _blocks(doc):
        if language != "python":
            continue
        if doc.name in RUN_AGAINST_A_SESSION:  # here it would wait its whole timeout for a session nobody runs
            assert doc.name in (REPO / RUN_AGAINST_A_SESSION[doc.name]).read_text(), RUN_AGAINST_A_SESSION[doc.name]
            compile(block, f"{doc.relative_to(REPO)}:{line_no}", "exec")
            continue
        try:
            exec(compile(block, f"{doc.relative_to(REPO)}:{line_no}", "exec"), namespace)
        except Exception as exc:  # the message says which block failed
            pytest.fail(f"{doc.relative_to(REPO)} block at line {line_no} failed: {exc!r}\n{block}")


def test_signal_doc_prints_what_it_says(shared_dir: Path, tmp_path: Path, monkeypatch, capsys) -> None:
    test_python_blocks_run(REPO / "docs" / "signal.md", shared_dir, tmp_path, monkeypatch)
    out = capsys.readouterr().out
    assert "group delay 53." in out and "Coordinates True" in out


def test_readme_starts_with_the_two_setup_commands() -> None:
    language, block, _ = _blocks(REPO / "README.md")[0]
    assert language in SHELL and _command_lines(block) == ["python3 dev.py demo", "python3 dev.py test"]


def test_the_role_table_of_deployment_md_is_the_access_control_the_graph_gives() -> None:
    from services.transport import security

    text = (REPO / "docs" / "deployment.md").read_text()
    # the role table only: from its header to the first line that is not a table row (other tables name roles too)
    table = text[text.index("| role (CN `msk-<role>`) |") :].split("\n\n", 1)[0]
    rows = re.findall(r"^\| (\w+) \| (.*?) \| (.*?) \| (.*?) \|$", table, re.M)
    documented = {
        role: (re.findall(r"`([^`]+)`", publish), re.findall(r"`([^`]+)`", subscribe), re.findall(r"`([^`]+)`", tokens))
        for role, publish, subscribe, tokens in rows
        if role in security.ROLE_POLICIES
    }
    assert set(documented) == set(security.ROLE_POLICIES)
    for role, policy in security.ROLE_POLICIES.items():
        assert documented[role] == (
            list(policy.publish),
            list(policy.subscribe),
            [t.rsplit("/", 1)[1] for t in policy.tokens],
        ), role
