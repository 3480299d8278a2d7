"""docker-compose.yml stays true to the code: every node's command is a valid ``msk`` command line, every node joins
the router, and the files it names exist. (No Docker engine runs here, so the file is checked against the code.)"""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

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


# --- structure, and the secured variant (docker-compose.secure.yml layered on docker-compose.yml) --------------

_SERVICE_KEYS = {"image", "build", "restart", "depends_on", "environment", "command", "ports", "expose", "volumes",
                 "devices", "profiles", "stop_signal"}
#: compose service -> the certificate role it presents in the secured variant
SECURE_ROLES = {"drivers": "driver", "kinematics": "kinematics", "estimator": "estimator", "recorder": "recorder",
                "replayer": "replayer"}


def _check_structure(document: dict, name: str) -> None:
    """What ``docker compose config`` would reject first: unknown keys, dangling depends_on, malformed mounts."""
    assert set(document) <= {"services", "volumes", "networks"} | {k for k in document if k.startswith("x-")}, name
    services = document["services"]
    for service_name, service in services.items():
        unknown = set(service) - _SERVICE_KEYS
        assert not unknown, f"{name}: service {service_name!r} has keys compose does not know: {unknown}"
        for dependency in service.get("depends_on", []):
            assert dependency in services, f"{name}: {service_name} depends on unknown service {dependency!r}"
        for mount in service.get("volumes", []):
            parts = mount.split(":")
            assert 2 <= len(parts) <= 3 and parts[1].startswith("/"), f"{name}: {service_name}: bad volume {mount!r}"
            assert len(parts) == 2 or parts[2] in ("ro", "rw"), f"{name}: {service_name}: bad volume mode {mount!r}"
        for port in service.get("ports", []):
            # as compose does: ${VAR:-default} stands for its default when VAR is unset
            resolved = re.sub(r"\$\{\w+:-([^}]*)\}", r"\1", str(port))
            assert re.fullmatch(r"(127\.0\.0\.1:)?\d+:\d+", resolved), f"{name}: {service_name}: bad port {port!r}"


def _merge(base: dict, override: dict) -> dict:
    """docker compose -f base -f override: scalars and commands replaced, mounts appended, other mappings merged."""
    merged = {"services": {name: dict(service) for name, service in base["services"].items()}}
    for name, service in override["services"].items():
        target = merged["services"].setdefault(name, {})
        for key, value in service.items():
            if key == "volumes":
                target[key] = list(dict.fromkeys(target.get(key, []) + value))
            else:
                target[key] = value
    return merged


@pytest.fixture(scope="module")
def secure_compose(repo_root):
    return yaml.safe_load((repo_root / "docker-compose.secure.yml").read_text())


def test_compose_files_are_structurally_valid(compose, secure_compose):
    _check_structure(compose, "docker-compose.yml")
    _check_structure(secure_compose, "docker-compose.secure.yml")
    _check_structure(_merge(compose, secure_compose), "the merged secured deployment")


def test_secured_variant_runs_every_node_with_its_role_certificate(compose, secure_compose, tmp_path):
    """Every Zenoh node of the secured deployment joins only through its role's TLS config, and the configs it names
    are exactly those ``msk certs`` writes (the command in the file's header, run here)."""
    from services.cli import main

    merged = _merge(compose, secure_compose)
    parser = build_parser()
    pki_dir = tmp_path / "pki"
    assert main(["certs", "--out", str(pki_dir), "--pki-path", "/pki", "--router-host", "zenohd"]) == 0
    written = {p.name for p in (pki_dir / "zenoh").iterdir()}
    for name, role in SECURE_ROLES.items():
        service = merged["services"][name]
        args = parser.parse_args(shlex.split(_expand(service["command"])))
        assert args.mode is None and args.connect == [] and args.listen == [], f"{name}: flags would override the TLS config"
        assert str(args.zenoh_config) == f"/pki/zenoh/{role}.json5", name
        assert f"{role}.json5" in written, f"msk certs writes no config for role {role!r}"
        assert "./deploy/pki:/pki:ro" in service["volumes"], f"{name} does not mount the certificates"
        config = json.loads((pki_dir / "zenoh" / f"{role}.json5").read_text())
        assert config["connect"]["endpoints"] == ["tls/zenohd:7447"] and config["mode"] == "client"
    router = merged["services"]["zenohd"]
    args = parser.parse_args(shlex.split(router["command"]))
    assert args.command == "router" and str(args.zenoh_config) == "/pki/zenoh/router.json5"
    assert router["ports"] == ["7447:7447"]
    router_config = json.loads((pki_dir / "zenoh" / "router.json5").read_text())
    assert router_config["listen"]["endpoints"] == ["tls/0.0.0.0:7447"]
    assert router_config["access_control"]["default_permission"] == "deny"
    assert router_config["transport"]["link"]["tls"]["enable_mtls"] is True
    assert "msk certs --out deploy/pki --pki-path /pki --router-host zenohd" in (
        (Path(__file__).resolve().parents[1] / "docker-compose.secure.yml").read_text()
    )


def test_deployment_doc_commands_parse_and_certs_runs(repo_root, tmp_path, monkeypatch):
    """Every ``msk`` line of docs/deployment.md's sh blocks is a valid command line; its ``msk certs`` line runs."""
    from services.cli import main

    text = (repo_root / "docs/deployment.md").read_text()
    blocks = re.findall(r"```sh\n(.*?)```", text, re.S)
    lines = [line for block in blocks for line in block.splitlines() if line.startswith("msk ")]
    assert lines, "docs/deployment.md has no msk commands"
    parser = build_parser()
    for line in lines:
        args = parser.parse_args(shlex.split(line)[1:])
        assert getattr(args, "handler", None) is not None, line
    monkeypatch.chdir(tmp_path)
    certs = next(line for line in lines if line.startswith("msk certs "))
    assert main(shlex.split(certs)[1:]) == 0
    referenced = {Path(m) for line in lines for m in re.findall(r"--zenoh-config (\S+)", line)}
    for path in referenced:
        assert (tmp_path / path).is_file(), f"docs/deployment.md uses {path}, which msk certs did not write"
