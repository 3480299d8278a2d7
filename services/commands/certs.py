"""``msk certs``: make the deployment's CA, the router's and one client certificate per role, and the Zenoh configs.

    msk certs --out deploy/pki --router-host gym-router.local --router-host 10.0.0.2

writes ``ca.pem``/``ca.key``, ``router.pem``/``router.key``, ``<role>.pem``/``<role>.key``, the dashboard's HTTPS
certificate ``dashboard.pem``/``dashboard.key`` (for ``--dashboard-host``, default the router's hosts) and, under
``--configs`` (default ``<out>/zenoh``), ``router.json5`` (TLS with mutual authentication + access control) and
``<role>.json5`` (a TLS client of the router presenting that role's certificate; for the roles whose certificate is
in the folder). A folder that already has ``ca.pem``/``ca.key`` keeps its CA: the run issues the asked certificates
under it, so those issued before stay valid (remove both to start a new deployment). Roles and their rights:
services/transport/security.py and docs/deployment.md. Keep ``ca.key`` off the nodes: it is only needed to issue more
certificates.

Tablets of ``msk dashboard --pki`` (services/surfaces/dashboard/access.py):

    msk certs tablet-token coach-ipad --out deploy/pki    # prints the URL to open once on that tablet
    msk certs revoke-token coach-ipad --out deploy/pki    # that tablet is refused from its next request on
"""

from __future__ import annotations

import argparse
from pathlib import Path

from msk_core.errors import ConfigError
from services.commands import described
from services.transport import security


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = described(
        subparsers.add_parser(
            "certs", help="make TLS certificates (CA, router, one per role) and secured Zenoh configs"
        ),
        __doc__,
    )
    parser.add_argument("--out", type=Path, default=None, metavar="DIR", help="folder for the certificates and keys")
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
    parser.add_argument(
        "--dashboard-host",
        action="append",
        default=[],
        metavar="NAME_OR_IP",
        help="a name or address tablets open the dashboard at (repeatable; default: the --router-host ones)",
    )
    parser.set_defaults(handler=run)
    actions = parser.add_subparsers(dest="action", metavar="ACTION", required=False)
    issue = actions.add_parser("tablet-token", help="issue a tablet's dashboard token; prints the URL to open once")
    issue.add_argument("name", metavar="NAME", help="the tablet's name (letters, digits, - _ .)")
    issue.add_argument(
        "--dashboard-url",
        default=None,
        metavar="URL",
        help="where tablets reach msk dashboard --pki (default: https://<first host of dashboard.pem>:8080)",
    )
    revoke = actions.add_parser("revoke-token", help="revoke a tablet's dashboard token")
    revoke.add_argument("name", metavar="NAME", help="the tablet's name")
    for action in (issue, revoke):
        action.add_argument("--out", type=Path, default=argparse.SUPPRESS, metavar="DIR", help="the certificate folder")
        action.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if args.out is None:
        raise ConfigError("give the certificate folder", field="--out", value=None)
    if getattr(args, "action", None) in ("tablet-token", "revoke-token"):
        return _tokens(args)
    if not 0 < args.port < 65536:
        raise ConfigError("must be a TCP port", field="--port", value=args.port)
    hosts = tuple(args.router_host) or ("localhost", "127.0.0.1")
    roles = tuple(args.role) or tuple(security.ROLE_POLICIES)
    ca = security.existing_ca(args.out)  # a second run issues under the folder's CA: what it issued stays valid
    pki = security.write_pki(args.out, router_hosts=hosts, roles=roles, ca=ca)
    pki_path = args.pki_path or str(args.out.resolve())
    configs = security.write_configs(
        args.configs or args.out / "zenoh",
        pki_path,
        router_listen=(f"tls/0.0.0.0:{args.port}",),
        client_connect=(f"tls/{hosts[0]}:{args.port}",),
        roles=tuple(r for r in security.ROLE_POLICIES if pki.cert(r).is_file()),  # only roles with a certificate
    )
    dashboard_hosts = tuple(args.dashboard_host) or hosts
    security.write_dashboard_certificate(args.out, dashboard_hosts)
    if ca is not None:
        print(
            f"reusing the CA of {pki.ca_cert} (valid until {ca[1].not_valid_after_utc:%Y-%m-%d}): the certificates "
            "issued under it before stay valid; remove ca.pem and ca.key to start a new deployment"
        )
    else:
        print(f"new CA {pki.ca_cert}")
    print(f"router certificate for {', '.join(hosts)}; client roles issued: {', '.join(roles)}")
    print(f"dashboard HTTPS certificate for {', '.join(dashboard_hosts)}: {pki.dashboard_cert}")
    for role, path in configs.items():
        print(f"  {role:10s} {path}")
    return 0


def _tokens(args: argparse.Namespace) -> int:
    from services.surfaces.dashboard.access import LOGIN_PATH, TokenStore

    store = TokenStore(args.out)
    if args.action == "revoke-token":
        store.revoke(args.name)
        print(f"tablet {args.name!r}: token revoked; msk dashboard --pki {args.out} refuses it from its next request")
        return 0
    url = args.dashboard_url or f"https://{_dashboard_host(security.Pki(args.out))}:8080"
    if not url.startswith("https://"):
        raise ConfigError("the dashboard is served over HTTPS only", field="--dashboard-url", value=url)
    token = store.issue(args.name)
    print(f"tablet {args.name!r}: open this URL once on it (it sets a cookie; keep the URL private):")
    print(f"{url.rstrip('/')}{LOGIN_PATH}?token={token}")
    return 0


def _dashboard_host(pki: security.Pki) -> str:
    from cryptography import x509

    if not pki.dashboard_cert.is_file():
        raise ConfigError(
            "no dashboard certificate: make the folder with `msk certs --out DIR`", path=pki.dashboard_cert
        )
    certificate = x509.load_pem_x509_certificate(pki.dashboard_cert.read_bytes())
    names = certificate.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    return str(next(iter(names)).value)
