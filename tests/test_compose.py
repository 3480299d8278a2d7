"""docker-compose.yml stays true to the code: every node's command is a valid ``msk`` command line, every node joins
the router, and the files it names exist. (No Docker engine runs here, so the file is checked against the code.)

Both compose files and the router's access control are what the declared session graph (services/transport/session_graph.py)
generates: the committed files equal ``services.sessions.deploy_files``' output, every secured service presents the role of
its graph declaration, and every key a participant publishes or reads is one its role may."""

from __future__ import annotations

import json
import re
import shlex
from pathlib import Path

import pytest
import yaml

from services.cli import build_parser
from services.sessions import deploy_files
from services.transport import security, session_graph, topics


def _expand(text: str) -> str:
    """${VAR:-default} -> the default (what compose does with an empty environment)."""
    return re.sub(r"\$\{[A-Z_]+:-([^}]*)\}", r"\1", text)


@pytest.fixture(scope="module")
def compose(repo_root):
    return yaml.safe_load((repo_root / "docker-compose.yml").read_text())


def test_every_msk_service_command_parses(compose, repo_root):
    parser = build_parser()
    msk_services = {name: s for name, s in compose["services"].items() if s.get("image", "").startswith("msk-live")}
    assert set(msk_services) == {d.service for d in deploy_files.DEPLOYMENTS.values()} | {"trigno-sim"}
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

_SERVICE_KEYS = {
    "image",
    "build",
    "restart",
    "depends_on",
    "environment",
    "command",
    "ports",
    "expose",
    "volumes",
    "devices",
    "profiles",
    "stop_signal",
}


def _graph_roles() -> dict[str, str]:
    """compose service -> the role its graph declarations run as, read from the declarations themselves (a service
    whose participants disagree on their role is reported, not resolved)."""
    roles: dict[str, set[str]] = {}
    for decl in [*session_graph.NODES.values(), *session_graph.CLIENTS.values()]:
        if decl.command:
            roles.setdefault(deploy_files.DEPLOYMENTS[decl.command].service, set()).add(decl.role)
    assert all(len(r) == 1 for r in roles.values()), f"participants of one service with several roles: {roles}"
    return {service: role.pop() for service, role in roles.items()}


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
    for name, role in _graph_roles().items():
        service = merged["services"][name]
        args = parser.parse_args(shlex.split(_expand(service["command"])))
        assert args.mode is None and args.connect == [] and args.listen == [], (
            f"{name}: flags would override the TLS config"
        )
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


# --- generated from the session graph ---------------------------------------------------------------------------


@pytest.mark.parametrize("name", [deploy_files.COMPOSE_FILE, deploy_files.SECURE_COMPOSE_FILE])
def test_committed_compose_file_is_what_the_graph_generates(repo_root, name):
    expected = deploy_files.generated_files()[name]
    committed = (repo_root / name).read_text()
    if committed != expected:
        diff = "".join(deploy_files.stale_files(repo_root).get(name, []))
        pytest.fail(
            f"{name} is not what services/transport/session_graph.py generates; run {deploy_files.WRITE_HINT}\n{diff}"
        )


def _secured_roles_mismatches(compose: dict, secure_compose: dict) -> list[str]:
    """Where the compose files disagree with the graph: a service missing or extra, a service running another
    command than its declarations', or a secured service presenting another role's config."""
    parser = build_parser()
    expected = _graph_roles()
    problems = []
    extra = set(compose["services"]) - {"zenohd", "trigno-sim"}
    if extra != set(expected):
        problems.append(f"docker-compose.yml runs {sorted(extra)}, the graph declares {sorted(expected)}")
    secured = set(secure_compose["services"]) - {"zenohd"}
    if secured != set(expected):
        problems.append(f"docker-compose.secure.yml secures {sorted(secured)}, the graph declares {sorted(expected)}")
    commands = {d.service: c for c, d in deploy_files.DEPLOYMENTS.items()}
    for name in sorted(secured & set(expected)):
        args = parser.parse_args(shlex.split(_expand(secure_compose["services"][name]["command"])))
        if args.command != commands[name]:
            problems.append(f"{name}: runs `msk {args.command}`, its declarations `msk {commands[name]}`")
        if str(args.zenoh_config) != deploy_files.role_config(expected[name]):
            problems.append(
                f"{name}: uses {args.zenoh_config}, its declarations run as role {expected[name]!r} "
                f"({deploy_files.role_config(expected[name])})"
            )
    return problems


def test_every_secured_service_uses_the_role_of_its_graph_declaration(compose, secure_compose):
    problems = _secured_roles_mismatches(compose, secure_compose)
    assert not problems, "\n".join(problems)


def _concrete(key: str) -> str:
    """A key a participant really uses for ``key`` (after ``msk/<session>/``): a chunk for each ``*``; every topic
    is what the recorder declares, ``msk/**``."""
    if key == session_graph.EVERY_TOPIC:
        return topics.ALL_TOPICS
    return f"{topics.ROOT}/lab/" + "/".join("c1" if part == "*" else part for part in key.split("/"))


def _participant_refusals() -> list[str]:
    """Every key a graph participant publishes or reads that the access control refuses to its role."""
    refusals = []
    for decl in [*session_graph.NODES.values(), *session_graph.CLIENTS.values()]:
        for action, keys in (("publish", decl.publish_keys()), ("subscribe", decl.subscribe_keys())):
            for key in keys:
                reason = security.refused(decl.role, action, _concrete(key))
                if reason is not None:
                    refusals.append(f"{decl.name}: {reason}")
    return refusals


def test_every_topic_of_a_participant_is_allowed_to_its_role():
    refusals = _participant_refusals()
    assert not refusals, "\n".join(refusals)


def _token_problems(policies: dict[str, security.RolePolicy]) -> list[str]:
    """A node whose role may not declare its readiness token, or a publishing node whose role may not watch the
    readers' tokens it waits for (services.nodes.readiness)."""
    problems = []
    for decl in session_graph.NODES.values():
        policy = policies[decl.role]
        token = f"{topics.ROOT}/*/{topics.GRAPH_CHUNK}/{decl.name}"
        if token not in policy.tokens:
            problems.append(f"{decl.name}: role {decl.role!r} may declare only {list(policy.tokens)}, not {token}")
        if decl.publishes and f"{topics.ROOT}/*/{topics.GRAPH_CHUNK}/*" not in policy.watch_tokens:
            problems.append(f"{decl.name}: role {decl.role!r} publishes but may not watch its readers' tokens")
    return problems


def test_every_node_may_declare_its_readiness_token():
    problems = _token_problems(security.ROLE_POLICIES)
    assert not problems, "\n".join(problems)


def _acl_mismatches(acl: dict, graph: dict[str, session_graph.RoleKeys]) -> list[str]:
    """Where the router's access control differs from the graph's keys: per role, the key expressions of its
    publish, subscribe, receive and readiness rules are the graph's keys under ``msk/*/`` (``**``: ``msk/**``)."""

    def full(keys: tuple[str, ...]) -> list[str] | None:  # None: the role has no such rule
        if not keys:
            return None
        return [topics.ALL_TOPICS if k == session_graph.EVERY_TOPIC else f"{topics.ROOT}/*/{k}" for k in keys]

    rules = {rule["id"]: rule["key_exprs"] for rule in acl["rules"]}
    problems = []
    subjects = {s["id"] for s in acl["subjects"]}
    if subjects != set(graph):
        problems.append(f"access control subjects {sorted(subjects)}, graph roles {sorted(graph)}")
    for role, keys in graph.items():
        expected = {
            "publish": full(keys.publish),
            "subscribe": full(keys.subscribe),
            "receive": full(keys.subscribe),
            "ready": full(keys.tokens),
        }
        for rule, key_exprs in expected.items():
            actual = rules.get(f"{role}-{rule}")
            if actual != key_exprs:
                problems.append(f"rule {role}-{rule}: {actual}, the graph gives {key_exprs}")
    return problems


def test_access_control_is_derived_from_the_graph():
    problems = _acl_mismatches(security.access_control(), session_graph.role_keys())
    assert not problems, "\n".join(problems)


def test_deploy_files_check_fails_on_a_stale_file_and_write_fixes_it(tmp_path, capsys):
    (tmp_path / deploy_files.COMPOSE_FILE).write_text(deploy_files.compose_text())
    (tmp_path / deploy_files.SECURE_COMPOSE_FILE).write_text(
        deploy_files.secure_compose_text().replace("/pki/zenoh/driver.json5", "/pki/zenoh/tablet.json5")
    )
    assert deploy_files.main(["--root", str(tmp_path)]) == 1
    out = capsys.readouterr().out
    assert "-      --zenoh-config /pki/zenoh/tablet.json5" in out
    assert "+      --zenoh-config /pki/zenoh/driver.json5" in out
    assert f"\n{deploy_files.SECURE_COMPOSE_FILE}: not what" in out and "--write" in out  # the plain file is fine
    assert deploy_files.main(["--root", str(tmp_path), "--write"]) == 0
    assert deploy_files.main(["--root", str(tmp_path)]) == 0
    assert (tmp_path / deploy_files.SECURE_COMPOSE_FILE).read_text() == deploy_files.secure_compose_text()


def test_a_graph_command_without_a_deployment_is_an_error():
    from msk_core.errors import ConfigError

    with pytest.raises(ConfigError, match="does not deploy"):
        deploy_files.graph_services({k: v for k, v in deploy_files.DEPLOYMENTS.items() if k != "kinematics"})
    with pytest.raises(ConfigError, match="no participant"):
        deploy_files.graph_services({**deploy_files.DEPLOYMENTS, "gone": deploy_files.Deployment("gone", ())})
