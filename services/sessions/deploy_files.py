"""``docker-compose.yml`` and ``docker-compose.secure.yml``, generated from the declared session graph.

Which services exist and, in the secured file, which role's Zenoh config each one presents come from
:mod:`services.transport.session_graph`: one compose service per distinct ``command`` of its participants (the two driver nodes
are one ``msk drivers`` process, so one ``drivers`` service), run as the role of the declarations whose command it is.
The router (``zenohd``) and the Trigno simulator (``trigno-sim``) are not participants of a session and are fixed
here. What the graph does not say (a service's arguments, volumes, ports, profiles) is a deployment choice, kept in
:data:`DEPLOYMENTS`.

    python -m services.sessions.deploy_files           # exit 1 and a diff when a committed file is not what the graph makes
    python -m services.sessions.deploy_files --write   # rewrite both files (also: msk compose --write)
"""

from __future__ import annotations

import argparse
import difflib
import json
import re
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml

from msk_core.errors import ConfigError, MskError
from services.transport import session_graph

REPO_ROOT = Path(__file__).resolve().parents[2]
COMPOSE_FILE = "docker-compose.yml"
SECURE_COMPOSE_FILE = "docker-compose.secure.yml"
WRITE_HINT = "python -m services.sessions.deploy_files --write (or msk compose --write)"

#: how every node of the plain file joins the router
PLAIN_NETWORK = "--mode client --connect tcp/zenohd:7447"
#: where the secured services find the certificates and the Zenoh configs ``msk certs --pki-path /pki`` writes
PKI_MOUNT = "./deploy/pki:/pki:ro"
PKI_CONFIGS = "/pki/zenoh"

Value = str | tuple[str, ...] | dict[str, str]


@dataclass(frozen=True)
class Field:
    """One key of a compose service (or of an ``x-`` fragment), with an optional comment line above it."""

    key: str
    value: Value
    comment: str = ""


@dataclass(frozen=True)
class Service:
    """One compose service as written: the fragment it merges (``<<: *name``), its command (folded over lines) and
    its other keys, in that order."""

    name: str
    merge: str = ""
    command: tuple[str, ...] = ()
    fields: tuple[Field, ...] = ()


@dataclass(frozen=True)
class Deployment:
    """What the graph does not say about the service of one graph command: the service's name, the command's
    arguments (lines after ``msk <command>``, without the network flags) and the plain file's other keys."""

    service: str
    args: tuple[str, ...]
    fields: tuple[Field, ...] = ()


SESSION = "--session ${MSK_SESSION:-lab}"
PACK = "--pack ${MSK_PACK:-bench_press}"

#: per graph command (``NodeDecl.command``): its compose service, in the order the files list them (data flow). A
#: command the graph declares needs an entry; an entry for a command the graph no longer declares is an error too
#: (:func:`graph_services`).
DEPLOYMENTS: dict[str, Deployment] = {
    "drivers": Deployment(
        "drivers",
        (SESSION, "--trigno ${TRIGNO_HOST:-trigno-sim}", "--xsens ${XSENS_DEVICE:-/dev/ttyUSB0}"),
        (Field("devices", ("${XSENS_DEVICE:-/dev/ttyUSB0}:${XSENS_DEVICE:-/dev/ttyUSB0}",)),),
    ),
    "kinematics": Deployment("kinematics", (f"{SESSION} {PACK}",)),
    "estimator": Deployment("estimator", (f"{SESSION} {PACK}", "--method so --method hybrid")),
    "recorder": Deployment(
        "recorder",
        ("--out /data/${MSK_SESSION:-lab}.mcap",),
        (
            Field("volumes", ("./data:/data",)),
            Field("stop_signal", "SIGINT"),
        ),
    ),
    "dashboard": Deployment(
        "dashboard",
        (f"{SESSION} --host 0.0.0.0 --port 8080",),
        (
            Field(
                "ports",
                ("${MSK_DASHBOARD_BIND:-127.0.0.1}:${MSK_DASHBOARD_PORT:-8080}:8080",),
                comment="this host only by default, as `msk dashboard`; MSK_DASHBOARD_BIND=0.0.0.0 serves the tablets "
                "on the gym network",
            ),
        ),
    ),
    "replay": Deployment(
        "replayer",
        (f"recordings/demo_session.mcap {SESSION} --rate 1 --exclude msk/*/joints",),
        (
            Field("profiles", ("replay",)),
            Field("restart", "no"),
        ),
    ),
}

#: the parts of every msk service of the plain file (``<<: *msk-node``)
MSK_NODE = (
    Field("build", "."),
    Field("image", "msk-live:0.1.0"),
    Field("restart", "unless-stopped"),
    Field("depends_on", ("zenohd",)),
    Field("environment", {"RUST_LOG": "warn"}),
)
ROUTER = Service(
    "zenohd",
    fields=(
        Field("image", "eclipse/zenoh:1.10.2"),
        Field("restart", "unless-stopped"),
        Field("ports", ("7447:7447",)),
    ),
)
TRIGNO_SIM = Service(
    "trigno-sim",
    merge="msk-node",
    command=("sim trigno --from synthetic:3600:7 --host 0.0.0.0",),
    fields=(
        Field("profiles", ("sim",)),
        Field("depends_on", ()),
        Field("expose", ("50040", "50041", "50043", "50044")),
    ),
)
SECURE_ROUTER = Service(
    "zenohd",
    command=(f"router --zenoh-config {PKI_CONFIGS}/router.json5",),
    fields=(
        Field("image", "msk-live:0.1.0"),
        Field("build", "."),
        Field("stop_signal", "SIGINT"),
        Field("volumes", (PKI_MOUNT,)),
    ),
)

COMPOSE_HEADER = """\
# msk-live on one host: a Zenoh router, the device drivers, the kinematics node (IMU -> joint angles), the estimator
# and the recorder.
#   docker compose up                     # live: Trigno at $TRIGNO_HOST, Xsens on $XSENS_DEVICE
#   docker compose --profile sim up       # the same graph fed by the Trigno simulator (real TCP, synthetic EMG)
#   docker compose --profile replay up    # replay recordings/demo_session.mcap (session "synth" renamed to $MSK_SESSION)
# Across machines, with TLS and access control: docker-compose.secure.yml on top of this file (docs/deployment.md).
# Every node is a Zenoh client of the router, so they find each other by its service name.
# The coaches' page (msk dashboard) is on http://127.0.0.1:8080/ of the host.
"""
SECURE_HEADER = """\
# msk-live across machines, secured: TLS with mutual authentication and access control (docs/deployment.md).
# Layered on docker-compose.yml; make the certificates and configs once, then start:
#   msk certs --out deploy/pki --pki-path /pki --router-host zenohd --router-host gym-router.local
#   docker compose -f docker-compose.yml -f docker-compose.secure.yml up
# The router listens on TLS only (port 7447) and admits a node only with a certificate signed by deploy/pki/ca.pem;
# the certificate's common name (msk-<role>) decides what the node may publish and subscribe to: each service uses
# the config of the role its participants declare in services/transport/session_graph.py.
"""
GENERATED_NOTE = f"# Generated from services/transport/session_graph.py by services/sessions/deploy_files.py: edit those, then run\n#   {WRITE_HINT}\n"


# --- the graph's services ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GraphService:
    """The compose service of one graph command: the participants it runs and the role they run as."""

    command: str
    role: str
    participants: tuple[str, ...]
    deployment: Deployment


def graph_services(deployments: dict[str, Deployment] = DEPLOYMENTS) -> list[GraphService]:
    """One per distinct ``command`` of the declared participants, in the order of ``deployments``."""
    by_command: dict[str, list[session_graph.NodeDecl]] = {}
    for decl in [*session_graph.NODES.values(), *session_graph.CLIENTS.values()]:
        if decl.command:
            by_command.setdefault(decl.command, []).append(decl)
    stale = sorted(set(deployments) - set(by_command))
    if stale:
        raise ConfigError(
            f"services/sessions/deploy_files.py deploys commands no participant of services/transport/session_graph.py "
            f"declares (declared: {sorted(by_command)})",
            field="DEPLOYMENTS",
            value=stale,
        )
    services = []
    for command, decls in by_command.items():
        names = tuple(d.name for d in decls)
        roles = sorted({d.role for d in decls})
        if len(roles) != 1:
            raise ConfigError(
                f"participants {list(names)} run as one service (msk {command}), so they need one role",
                field="role",
                value=roles,
            )
        if command not in deployments:
            raise ConfigError(
                f"participants {list(names)} run as `msk {command}`, which services/sessions/deploy_files.py "
                f"does not deploy: add it to DEPLOYMENTS",
                field="command",
                value=command,
            )
        services.append(GraphService(command, roles[0], names, deployments[command]))
    service_names = [s.deployment.service for s in services]
    clashes = sorted(
        {n for n in service_names if service_names.count(n) > 1} | (set(service_names) & {ROUTER.name, TRIGNO_SIM.name})
    )
    if clashes:
        raise ConfigError("two compose services would have the same name", field="service", value=clashes)
    order = list(deployments)
    return sorted(services, key=lambda s: order.index(s.command))


def role_config(role: str) -> str:
    """The Zenoh config of ``role`` as the secured services see it (``msk certs --pki-path /pki``)."""
    return f"{PKI_CONFIGS}/{role}.json5"


def _command(service: GraphService, network: str) -> tuple[str, ...]:
    first, *rest = service.deployment.args or ("",)
    return (f"{service.command} {first}".rstrip(), *rest, network)


def compose_services() -> list[Service]:
    """The plain file's services: the router, one per graph command, the Trigno simulator."""
    graph = [
        Service(s.deployment.service, merge="msk-node", command=_command(s, PLAIN_NETWORK), fields=s.deployment.fields)
        for s in graph_services()
    ]
    return [ROUTER, *graph, TRIGNO_SIM]


def secure_compose_services() -> list[Service]:
    """The secured override: the router on TLS with the access control, and every graph service with its role's
    config and the certificates mounted (ports, volumes and the rest come from the plain file)."""
    graph = [
        Service(s.deployment.service, merge="pki", command=_command(s, f"--zenoh-config {role_config(s.role)}"))
        for s in graph_services()
    ]
    return [SECURE_ROUTER, *graph]


# --- YAML text --------------------------------------------------------------------------------------------------

_PLAIN = re.compile(r"[A-Za-z./][A-Za-z0-9_./:-]*")


def _scalar(text: str) -> str:
    """``text`` as a YAML scalar: plain when it reads back as itself, double-quoted (JSON) otherwise."""
    if _PLAIN.fullmatch(text) and yaml.safe_load(text) == text:
        return text
    return json.dumps(text)


def _field(field: Field, indent: str) -> list[str]:
    lines = [f"{indent}# {field.comment}"] if field.comment else []
    if isinstance(field.value, str):
        return [*lines, f"{indent}{field.key}: {_scalar(field.value)}"]
    if isinstance(field.value, dict):
        return [*lines, f"{indent}{field.key}:", *(f"{indent}  {k}: {_scalar(v)}" for k, v in field.value.items())]
    if not field.value:
        return [*lines, f"{indent}{field.key}: []"]
    return [*lines, f"{indent}{field.key}:", *(f"{indent}  - {_scalar(v)}" for v in field.value)]


def _command_lines(command: tuple[str, ...], indent: str) -> list[str]:
    for line in command:
        if not line or line != line.strip() or "#" in line or ": " in line:
            raise ConfigError(
                "a command line of a compose service must be folded text without comments", field="command", value=line
            )
    if len(command) == 1:
        return [f"{indent}command: {command[0]}"]
    return [f"{indent}command: >", *(f"{indent}  {line}" for line in command)]


def _service(service: Service) -> list[str]:
    indent = "    "
    lines = [f"  {service.name}:"]
    lines += [f"{indent}<<: *{service.merge}"] if service.merge else []
    lines += _command_lines(service.command, indent) if service.command else []
    for field in service.fields:
        lines += _field(field, indent)
    return lines


def _document(header: str, fragments: dict[str, tuple[Field, ...]], services: list[Service]) -> str:
    lines = [*GENERATED_NOTE.splitlines(), *header.splitlines()]
    for name, fields in fragments.items():
        lines.append(f"x-{name}: &{name}")
        for field in fields:
            lines += _field(field, "  ")
    lines += ["", "services:"]
    for i, service in enumerate(services):
        lines += ([""] if i else []) + _service(service)
    return "\n".join(lines) + "\n"


def compose_text() -> str:
    """``docker-compose.yml``: the session graph on one host, every node a Zenoh client of the router."""
    return _document(COMPOSE_HEADER, {"msk-node": MSK_NODE}, compose_services())


def secure_compose_text() -> str:
    """``docker-compose.secure.yml``: layered on the plain file, TLS and each service's role config."""
    return _document(SECURE_HEADER, {"pki": (Field("volumes", (PKI_MOUNT,)),)}, secure_compose_services())


def generated_files() -> dict[str, str]:
    """File name (in the repository root) -> the text the graph makes."""
    return {COMPOSE_FILE: compose_text(), SECURE_COMPOSE_FILE: secure_compose_text()}


# --- check or write ---------------------------------------------------------------------------------------------


def stale_files(root: Path = REPO_ROOT) -> dict[str, list[str]]:
    """File name -> unified diff (committed -> generated) of every file that is not what the graph makes."""
    stale = {}
    for name, text in generated_files().items():
        path = root / name
        current = path.read_text() if path.is_file() else ""
        if current != text:
            stale[name] = list(
                difflib.unified_diff(
                    current.splitlines(keepends=True),
                    text.splitlines(keepends=True),
                    f"{name} (committed)",
                    f"{name} (from the session graph)",
                )
            )
    return stale


def write_files(root: Path = REPO_ROOT) -> list[Path]:
    """Rewrite the files that differ; the paths written."""
    written = []
    for name, text in generated_files().items():
        path = root / name
        if not path.is_file() or path.read_text() != text:
            path.write_text(text)
            written.append(path)
    return written


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--write", action="store_true", help="rewrite the files (default: only check them)")
    parser.add_argument(
        "--root",
        type=Path,
        default=REPO_ROOT,
        metavar="DIR",
        help="folder holding the compose files (default: the repository)",
    )


def run(args: argparse.Namespace) -> int:
    """Check (exit 1 and the differences when a file is not what the graph makes) or ``--write`` the files."""
    if args.write:
        written = write_files(args.root)
        print(f"wrote {', '.join(str(p) for p in written)}" if written else "compose files already up to date")
        return 0
    stale = stale_files(args.root)
    for diff in stale.values():
        sys.stdout.writelines(diff)
    if stale:
        print(f"{', '.join(stale)}: not what services/transport/session_graph.py generates; run {WRITE_HINT}")
        return 1
    print(f"{COMPOSE_FILE} and {SECURE_COMPOSE_FILE} are what the session graph generates")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m services.sessions.deploy_files",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    add_arguments(parser)
    args = parser.parse_args(argv)
    try:
        return run(args)
    except MskError as error:
        print(f"{parser.prog}: error: {error}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
