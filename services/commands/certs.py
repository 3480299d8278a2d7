"""``msk certs``: make the deployment's CA, the router's and one client certificate per role, and the Zenoh configs.

    msk certs --out deploy/pki --router-host gym-router.local --router-host 10.0.0.2

writes ``ca.pem``/``ca.key``, ``router.pem``/``router.key``, ``<role>.pem``/``<role>.key`` and, under ``--configs``
(default ``<out>/zenoh``), ``router.json5`` (TLS with mutual authentication + access control) and ``<role>.json5``
(a TLS client of the router presenting that role's certificate). Roles and their rights: services/security.py and
docs/deployment.md. Keep ``ca.key`` off the nodes: it is only needed to issue more certificates.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from msk_core.errors import ConfigError
from services import security


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "certs",
        help="make TLS certificates (CA, router, one per role) and secured Zenoh configs",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--out", type=Path, required=True, metavar="DIR", help="folder for the certificates and keys")
    parser.add_argument(
        "--router-host",
        action="append",
        default=[],
        metavar="NAME_OR_IP",
        help="a name or address the nodes use to reach the router (repeatable; default: localhost and 127.0.0.1)",
    )
    parser.add_argument(
        "--role",
        action="append",
        default=[],
        choices=list(security.ROLE_POLICIES),
        help="client roles to issue (default: all)",
    )
    parser.add_argument(
        "--configs",
        type=Path,
        default=None,
        metavar="DIR",
        help="where to write the Zenoh JSON5 configs (default: OUT/zenoh)",
    )
    parser.add_argument(
        "--pki-path",
        default=None,
        metavar="PATH",
        help="the certificate folder as the nodes see it, written into the configs (default: OUT, absolute; e.g. /pki in containers)",
    )
    parser.add_argument("--port", type=int, default=security.DEFAULT_TLS_PORT, help="router TLS port (default: 7447)")
    parser.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if not 0 < args.port < 65536:
        raise ConfigError("must be a TCP port", field="--port", value=args.port)
    hosts = tuple(args.router_host) or ("localhost", "127.0.0.1")
    roles = tuple(args.role) or tuple(security.ROLE_POLICIES)
    pki = security.write_pki(args.out, router_hosts=hosts, roles=roles)
    pki_path = args.pki_path or str(args.out.resolve())
    configs = security.write_configs(
        args.configs or args.out / "zenoh",
        pki_path,
        router_listen=(f"tls/0.0.0.0:{args.port}",),
        client_connect=(f"tls/{hosts[0]}:{args.port}",),
    )
    print(f"CA {pki.ca_cert}; router certificate for {', '.join(hosts)}; client roles: {', '.join(roles)}")
    for role, path in configs.items():
        print(f"  {role:10s} {path}")
    return 0
