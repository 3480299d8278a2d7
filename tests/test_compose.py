"""docker-compose.yml stays true to the code: every node's command is a valid ``msk`` command line, every node joins
the router, and the files it names exist. (No Docker engine runs here, so the file is checked against the code.)"""

from __future__ import annotations

import os
import re
import shlex

import pytest
import yaml

from services.cli import build_parser


def _expand(text: str) -> str:
    """${VAR:-default} -> the default (what compose does with an empty environment)."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", text)


@pytest.fixture(scope="module")
def compose(repo_root):
    return yaml.safe_load((repo_root / "docker-compose.yml").read_text())


def test_every_msk_service_command_parses(compose, repo_root):
    parser = build_parser()
    msk_services = {name: s for name, s in compose["services"].items() if s.get("image", "").startswith("msk-live")}
    assert {"drivers", "kinematics", "estimator", "recorder", "trigno-sim", "replayer"} <= set(msk_services)
    for name, service in msk_services.items():
        argv = shlex.split(_expand(service["command"]))
        try:
            args = parser.parse_args(argv)
        except SystemExit as exit_:  # argparse exits on a bad command line
            pytest.fail(f"service {name!r}: `msk {' '.join(argv)}` does not parse (exit {exit_.code})")
        assert getattr(args, "handler", None) is not None, name
        if name != "trigno-sim":
            assert args.mode == "client" and args.connect == ["tcp/zenohd:7447"], f"{name} must join the router"


def test_compose_references_existing_files(compose, repo_root):
    assert (repo_root / "Dockerfile").is_file()
    replay = shlex.split(_expand(compose["services"]["replayer"]["command"]))
    assert (repo_root / replay[1]).is_file(), f"replayer plays {replay[1]}, which is not in the repository"
    dockerfile = (repo_root / "Dockerfile").read_text()
    for folder in ("msk_core", "drivers", "services", "recordings"):
        assert f"COPY {folder} " in dockerfile
