"""The ``msk`` command line: each command's module is imported only when that command runs (services/cli.py), and
what the command line lists without importing (names, help, aliases read from the modules' source) is what the modules
register."""

from __future__ import annotations

import argparse
import contextlib
import importlib
import io
import subprocess
import sys

import pytest

from services import cli
from services.commands import command_modules


def _registered(module: str) -> list[tuple[str, str | None, tuple[str, ...]]]:
    """What ``module.register`` adds to a fresh parser: (name, help, aliases) per command, in order."""
    subparsers = argparse.ArgumentParser().add_subparsers()
    importlib.import_module(module).register(subparsers)
    helps = {action.dest: action.help for action in subparsers._choices_actions}
    by_parser: dict[int, list[str]] = {}
    for name, parser in subparsers.choices.items():
        by_parser.setdefault(id(parser), []).append(name)
    return [(names[0], helps.get(names[0]), tuple(names[1:])) for names in by_parser.values()]


def _all_commands() -> list[str]:
    return [c.name for m in command_modules() for c in m.commands or ()]


def test_every_modules_commands_read_from_its_source_are_the_ones_it_registers():
    modules = command_modules()
    assert len(modules) >= 20, [m.module for m in modules]
    for entry in modules:
        assert entry.commands is not None, (
            f"{entry.module}: register() must call subparsers.add_parser with a literal name, help and aliases "
            "(services/commands/__init__.py reads them without importing the module)"
        )
        declared = [(c.name, c.help, c.aliases) for c in entry.commands]
        assert declared == _registered(entry.module), entry.module


def test_help_lists_every_command_as_the_full_parser_does():
    listed = cli.build_parser(["--help"]).format_help()
    assert listed == cli.build_parser().format_help()
    for name in ("demo", "live", "recorder", "replay", "estimator", "bench", "set"):
        assert f"    {name} " in listed or f"    {name}\n" in listed, name


@pytest.mark.parametrize("command", _all_commands())
def test_every_commands_help_from_the_parser_built_for_that_command(command):
    parser = cli.build_parser([command, "--help"])
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit) as stop:
        parser.parse_args([command, "--help"])
    assert stop.value.code == 0
    assert out.getvalue().startswith(f"usage: msk {command}"), out.getvalue()[:200]
    assert out.getvalue() == _full_help(command)


def _full_help(command: str) -> str:
    out = io.StringIO()
    with contextlib.redirect_stdout(out), pytest.raises(SystemExit):
        cli.build_parser().parse_args([command, "--help"])
    return out.getvalue()


def test_msk_record_is_the_former_name_of_msk_capture(tmp_path, capsys):
    """``msk record`` was in the docs before it became ``msk capture`` (beside ``msk recorder``): it still runs it."""
    assert [c.aliases for m in command_modules("record") for c in m.commands or () if c.name == "capture"] == [
        ("record",)
    ]
    args = cli.build_parser(["record"]).parse_args(["record", "--duration", "1", "--out", str(tmp_path / "x.mcap")])
    from services.commands import capture

    assert args.handler is capture.run
    assert cli.main(["record", "--duration", "1", "--out", str(tmp_path / "x.mcap")]) == 2
    assert "name at least one device" in capsys.readouterr().err


def test_an_unknown_command_is_refused_with_the_list_of_commands(capsys):
    with pytest.raises(SystemExit) as stop:
        cli.main(["no-such-command"])
    assert stop.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice: 'no-such-command'" in err and "replay" in err and "demo" in err


def test_msk_help_and_a_light_command_do_not_import_the_other_commands(repo_root):
    """A fresh interpreter: ``msk --help`` imports no command module, ``msk router --help`` only the router's, and
    neither the estimation stack (scipy, numba) that other commands need."""
    probe = (
        "import contextlib, io, sys\n"
        "from services.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()), contextlib.suppress(SystemExit):\n"
        "    main(sys.argv[1:])\n"
        "print(sorted(m for m in sys.modules if m.startswith('services.commands.') or m in ('scipy', 'numba')))\n"
    )
    for argv, expected in ((["--help"], []), (["router", "--help"], ["services.commands.router"])):
        run = subprocess.run(
            [sys.executable, "-c", probe, *argv], cwd=repo_root, capture_output=True, text=True, check=True
        )
        assert run.stdout.strip() == repr(expected), (argv, run.stdout, run.stderr[-2000:])
