"""Secured network mode: a private CA, one certificate per role, and the Zenoh configs that use them.

Every node is a Zenoh *client* of one router (``msk router``). The router listens on TLS only and demands a client
certificate signed by the deployment's CA (mutual TLS); the common name (CN) of that certificate names the client's
role, and the router's ``access_control`` section says what each role may publish and subscribe to. Nothing is
allowed by default. ``msk certs`` writes the CA, the certificates and these configs; docs/deployment.md explains them.

Roles (CN ``msk-<role>``) and what each may publish and read come from the declared session graph
(``services.transport.session_graph``): a role may publish and subscribe to exactly the keys of the nodes that run as it
(driver, kinematics, estimator, recorder, operator = ``msk live`` itself and a second terminal's tools, tablet,
replayer), declare their readiness tokens ``msk/<s>/graph/<node>`` and, when it publishes, watch the other nodes'
tokens. A refused declaration is logged by the router (``RUST_LOG=warn`` shows "denied") and by the node.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import json
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.exceptions import InvalidSignature
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from msk_core.errors import ConfigError
from services.transport import session_graph, topics
from services.transport.zenoh_session import history_selector

CN_PREFIX = "msk-"
ROUTER_ROLE = "router"
DEFAULT_TLS_PORT = 7447


@dataclass(frozen=True)
class RolePolicy:
    """What a role may publish (``put``) and subscribe to (``declare_subscriber``), as Zenoh key expressions, and
    the readiness tokens it declares (``tokens``) or watches (``watch_tokens``)."""

    publish: tuple[str, ...]
    subscribe: tuple[str, ...]
    tokens: tuple[str, ...] = ()
    watch_tokens: tuple[str, ...] = ()


def _policies_from_graph() -> dict[str, RolePolicy]:
    prefix = f"{topics.ROOT}/*/"

    def full(keys: tuple[str, ...]) -> tuple[str, ...]:  # every topic: msk/** as the recorder declares it
        return tuple(topics.ALL_TOPICS if k == session_graph.EVERY_TOPIC else prefix + k for k in keys)

    policies = {}
    for role, keys in session_graph.role_keys().items():
        policies[role] = RolePolicy(
            publish=full(keys.publish),
            subscribe=full(keys.subscribe),
            tokens=tuple(prefix + k for k in keys.tokens),
            watch_tokens=(f"{prefix}{topics.GRAPH_CHUNK}/*",) if keys.watches_tokens else (),
        )
    return policies


ROLE_POLICIES: dict[str, RolePolicy] = _policies_from_graph()


def refused(role: str, action: str, key: str) -> str | None:
    """Why the router refuses ``role`` to ``action`` ("publish" or "subscribe") on ``key``; None when allowed. The
    router itself says so only in its trace log: nodes ask here first, so a refusal is said plainly where it happens."""
    import zenoh

    policy = ROLE_POLICIES.get(role)
    if policy is None:
        return f"role {role!r} is not a role of services/transport/security.py; the router refuses it everything"
    allowed = policy.publish if action == "publish" else policy.subscribe
    if any(zenoh.KeyExpr(a).includes(zenoh.KeyExpr(key)) for a in allowed):
        return None
    return f"role {role!r} may {action} only {list(allowed) or 'nothing'}; the router refuses {key}"


def role_of_config(config_file: Path | str) -> str | None:
    """The role a node joins with: the CN of the client certificate its Zenoh config names (None: not a secured
    config of ``write_configs``)."""
    try:
        document = json.loads(Path(config_file).read_text())
        certificate = Path(document["transport"]["link"]["tls"]["connect_certificate"])
        subject = x509.load_pem_x509_certificate(certificate.read_bytes()).subject
    except (OSError, ValueError, KeyError, TypeError):
        return None
    names = subject.get_attributes_for_oid(NameOID.COMMON_NAME)
    name = str(names[0].value) if names else ""
    return name[len(CN_PREFIX) :] if name.startswith(CN_PREFIX) else None


DASHBOARD = "dashboard"
VALIDITY_DAYS = 825  # browsers' and rustls' comfort limit for leaf certificates


def common_name(role: str) -> str:
    return f"{CN_PREFIX}{role}"


def check_role(role: str) -> str:
    if role != ROUTER_ROLE and role not in ROLE_POLICIES:
        raise ConfigError(f"unknown role; known: {', '.join(ROLE_POLICIES)}", field="role", value=role)
    return role


# --- certificates -----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Pki:
    """Where ``write_pki`` put the files (all PEM)."""

    directory: Path

    @property
    def ca_cert(self) -> Path:
        return self.directory / "ca.pem"

    @property
    def ca_key(self) -> Path:
        return self.directory / "ca.key"

    def cert(self, role: str) -> Path:
        return self.directory / f"{check_role(role)}.pem"

    def key(self, role: str) -> Path:
        return self.directory / f"{check_role(role)}.key"

    @property
    def dashboard_cert(self) -> Path:
        """The HTTPS certificate of ``msk dashboard --pki`` (not a Zenoh role: it serves browsers)."""
        return self.directory / f"{DASHBOARD}.pem"

    @property
    def dashboard_key(self) -> Path:
        return self.directory / f"{DASHBOARD}.key"


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()
    )


def _name(cn: str) -> x509.Name:
    return x509.Name(
        [x509.NameAttribute(NameOID.ORGANIZATION_NAME, "msk-live"), x509.NameAttribute(NameOID.COMMON_NAME, cn)]
    )


def _certificate(
    cn: str, issuer: x509.Name, key: ec.EllipticCurvePrivateKey, *, days: int, ca: bool
) -> x509.CertificateBuilder:
    """A certificate of ``key`` for ``cn`` issued by ``issuer``, valid from 5 minutes ago for ``days``, its basic
    constraints and key usage (critical) those of a CA (signs certificates and CRLs) or of a leaf (signs only)."""
    now = _dt.datetime.now(_dt.UTC)
    return (
        x509.CertificateBuilder()
        .subject_name(_name(cn))
        .issuer_name(issuer)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _dt.timedelta(minutes=5))
        .not_valid_after(now + _dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=ca, path_length=0 if ca else None), critical=True)
        .add_extension(
            x509.KeyUsage(
                digital_signature=True,
                content_commitment=False,
                key_encipherment=False,
                data_encipherment=False,
                key_agreement=False,
                key_cert_sign=ca,
                crl_sign=ca,
                encipher_only=False,
                decipher_only=False,
            ),
            critical=True,
        )
    )


def make_ca(cn: str = "msk-live CA", *, days: int = 3650) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    key = _new_key()
    cert = (
        _certificate(cn, _name(cn), key, days=days, ca=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return key, cert


def make_leaf(
    ca_key: ec.EllipticCurvePrivateKey,
    ca_cert: x509.Certificate,
    cn: str,
    *,
    hosts: tuple[str, ...] = (),
    days: int = VALIDITY_DAYS,
) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    """A certificate for one node. ``hosts`` (DNS names or IP addresses) make it usable by a TLS server."""
    key = _new_key()
    builder = (
        _certificate(cn, ca_cert.subject, key, days=days, ca=False)
        .add_extension(
            x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False
        )
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
    )
    if hosts:
        builder = builder.add_extension(x509.SubjectAlternativeName([_general_name(h) for h in hosts]), critical=False)
    return key, builder.sign(ca_key, hashes.SHA256())


def _general_name(host: str) -> x509.GeneralName:
    try:
        return x509.IPAddress(ipaddress.ip_address(host))
    except ValueError:
        return x509.DNSName(host)


def existing_ca(directory: Path | str) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate] | None:
    """The CA ``msk certs`` made in ``directory`` before (``ca.key`` and ``ca.pem``, checked: readable, the key of
    the certificate, valid now), to issue more certificates under it; None when the folder has neither. One without
    the other is a :class:`ConfigError`: a new CA would silently invalidate every certificate issued under the old."""
    pki = Pki(Path(directory))
    present = [path for path in (pki.ca_cert, pki.ca_key) if path.exists()]
    if not present:
        return None
    if len(present) == 1:
        missing = pki.ca_key if present[0] == pki.ca_cert else pki.ca_cert
        raise ConfigError(
            f"the folder has {present[0].name} but not {missing.name}: a new CA would invalidate every certificate "
            f"issued under the old one; put {missing.name} back, or remove {present[0].name} to start a new deployment",
            path=missing,
        )
    certificate = check_tls_files(pki.ca_cert, pki.ca_key, fields=("CA certificate", "CA key", ""))
    key = serialization.load_pem_private_key(pki.ca_key.read_bytes(), password=None)
    if not isinstance(key, ec.EllipticCurvePrivateKey):
        raise ConfigError("the CA key is not an EC key of msk certs", path=pki.ca_key)
    return key, certificate


def write_pki(
    directory: Path,
    *,
    router_hosts: tuple[str, ...] = ("localhost", "127.0.0.1"),
    roles: tuple[str, ...] = tuple(ROLE_POLICIES),
    ca: tuple[ec.EllipticCurvePrivateKey, x509.Certificate] | None = None,
) -> Pki:
    """A CA (unless given), the router's certificate for ``router_hosts`` and one client certificate per role."""
    if not router_hosts:
        raise ConfigError(
            "the router certificate needs at least one host name or address", field="router_hosts", value=router_hosts
        )
    for role in roles:
        check_role(role)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    pki = Pki(directory)
    ca_key, ca_cert = ca if ca is not None else make_ca()
    _write(pki.ca_key, _key_pem(ca_key), private=True)
    _write(pki.ca_cert, ca_cert.public_bytes(serialization.Encoding.PEM))
    for role, hosts in [(ROUTER_ROLE, tuple(router_hosts))] + [(r, ()) for r in roles]:
        key, cert = make_leaf(ca_key, ca_cert, common_name(role), hosts=hosts)
        _write(pki.key(role), _key_pem(key), private=True)
        _write(pki.cert(role), cert.public_bytes(serialization.Encoding.PEM))
    return pki


def write_dashboard_certificate(directory: Path, hosts: tuple[str, ...]) -> Pki:
    """The dashboard's HTTPS certificate for ``hosts`` (the names and addresses tablets open), signed by the CA of
    ``directory`` (made by :func:`write_pki`: its ``ca.key`` must be there)."""
    if not hosts:
        raise ConfigError(
            "the dashboard certificate needs at least one host name or address", field="hosts", value=hosts
        )
    pki = Pki(Path(directory))
    try:
        ca_key = serialization.load_pem_private_key(pki.ca_key.read_bytes(), password=None)
        ca_cert = x509.load_pem_x509_certificate(pki.ca_cert.read_bytes())
    except (OSError, ValueError) as error:
        raise ConfigError(
            f"no usable CA to sign with ({error}): make it with `msk certs --out DIR`", path=pki.ca_key
        ) from None
    if not isinstance(ca_key, ec.EllipticCurvePrivateKey):
        raise ConfigError("the CA key is not an EC key of msk certs", path=pki.ca_key)
    key, cert = make_leaf(ca_key, ca_cert, common_name(DASHBOARD), hosts=tuple(hosts))
    _write(pki.dashboard_key, _key_pem(key), private=True)
    _write(pki.dashboard_cert, cert.public_bytes(serialization.Encoding.PEM))
    return pki


def _write(path: Path, data: bytes, *, private: bool = False) -> None:
    path.write_bytes(data)
    if private:
        path.chmod(0o600)


# --- Zenoh configs ----------------------------------------------------------------------------------------------


def access_control(roles: dict[str, RolePolicy] = ROLE_POLICIES) -> dict:
    """The router's ``access_control`` section: deny by default; per role, allow exactly its flows.

    The router applies it on each client's link: ``ingress`` is what the client sends, ``egress`` what it gets.
    A subscriber needs its ``declare_subscriber`` let in and the matching ``put`` let out; a publisher needs its
    ``put`` let in and the subscribers' declarations let out (a Zenoh publisher only sends what someone wants).
    """
    rules, subjects, policies = [], [], []
    for role, policy in roles.items():
        subjects.append({"id": role, "cert_common_names": [common_name(role)]})
        role_rules = _role_rules(role, policy)
        rules.extend(role_rules)
        policies.append({"id": role, "rules": [r["id"] for r in role_rules], "subjects": [role]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects, "policies": policies}


def _allow(rule_id: str, flow: str, messages: list[str], key_exprs: list[str]) -> dict:
    """One ``allow`` rule of the router's access control."""
    return {"id": rule_id, "permission": "allow", "flows": [flow], "messages": messages, "key_exprs": key_exprs}


def _role_rules(role: str, policy: RolePolicy) -> list[dict]:
    """The rules of one role, in the order: publish, subscribe, history (serve, fetch), ready tokens."""
    rules = []
    if policy.publish:
        rules.append(_allow(f"{role}-publish", "ingress", ["put", "delete"], list(policy.publish)))
        # Subscribers declare broad expressions (the recorder's msk/**): the publisher must see them to send.
        rules.append(_allow(f"{role}-publish-interest", "egress", ["declare_subscriber"], ["msk/**"]))
    if policy.subscribe:
        rules.append(_allow(f"{role}-subscribe", "ingress", ["declare_subscriber"], list(policy.subscribe)))
        rules.append(_allow(f"{role}-receive", "egress", ["put", "delete"], list(policy.subscribe)))
    # History (a restarted recorder fetching what device publishers kept, services.transport.zenoh_session
    # .declare_history_publisher): the publisher's cache is a queryable announced by a liveliness token under
    # <key>/@adv/**, a verbatim chunk that msk/** does not cover.
    serve = ["declare_queryable", "reply", "liveliness_token"]
    ask = ["query", "declare_liveliness_subscriber", "liveliness_query"]
    if policy.publish:
        history_keys = _with_history(policy.publish)
        rules.append(_allow(f"{role}-history-serve", "ingress", serve, history_keys))
        rules.append(_allow(f"{role}-history-asked", "egress", ask, history_keys))
    if policy.subscribe:
        history_keys = _with_history(policy.subscribe)
        rules.append(_allow(f"{role}-history-fetch", "ingress", ask, history_keys))
        rules.append(
            _allow(
                f"{role}-history-receive", "egress", ["reply", "liveliness_token", "declare_queryable"], history_keys
            )
        )
    if policy.tokens:  # "I am ready": services.nodes.readiness.declare_ready
        rules.append(_allow(f"{role}-ready", "ingress", ["liveliness_token"], list(policy.tokens)))
    if policy.watch_tokens:  # wait for the readers: services.nodes.readiness.wait_for_nodes
        watch = list(policy.watch_tokens)
        rules.append(
            _allow(f"{role}-watch-ready", "ingress", ["declare_liveliness_subscriber", "liveliness_query"], watch)
        )
        rules.append(_allow(f"{role}-see-ready", "egress", ["liveliness_token", "reply"], watch))
    return rules


def _with_history(keys: tuple[str, ...]) -> list[str]:
    return [*keys, *(history_selector(key) for key in keys)]


def router_config(
    pki_dir: Path | str, *, listen: tuple[str, ...] = (f"tls/0.0.0.0:{DEFAULT_TLS_PORT}",), acl: bool = True
) -> dict:
    """The router's Zenoh config: TLS listener(s) demanding a CA-signed client certificate, and the ACL."""
    config = _tls_config(
        Pki(Path(pki_dir)), ROUTER_ROLE, "listen", listen, "a secured router listens on tls/ endpoints only"
    )
    if acl:
        config["access_control"] = access_control()
    return config


def client_config(pki_dir: Path | str, role: str, *, connect: tuple[str, ...]) -> dict:
    """A node's Zenoh config: client of the router over TLS, presenting the certificate of ``role``."""
    check_role(role)
    return _tls_config(Pki(Path(pki_dir)), role, "connect", connect, "a secured node connects over tls/ only")


def _tls_config(pki: Pki, role: str, side: str, endpoints: tuple[str, ...], not_tls: str) -> dict:
    """A Zenoh config over mutual TLS only, no scouting: ``side`` "listen" (the router) or "connect" (a client node,
    which also checks the router's name) on ``endpoints`` with the certificate of ``role``; an endpoint that is not
    ``tls/`` is a ConfigError saying ``not_tls``."""
    for endpoint in endpoints:
        if not endpoint.startswith("tls/"):
            raise ConfigError(not_tls, field=side, value=endpoint)
    tls = {
        "root_ca_certificate": str(pki.ca_cert),
        f"{side}_certificate": str(pki.cert(role)),
        f"{side}_private_key": str(pki.key(role)),
        "enable_mtls": True,
    }
    if side == "connect":
        tls["verify_name_on_connect"] = True
    return {
        "mode": "router" if side == "listen" else "client",
        side: {"endpoints": list(endpoints)},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": {"tls": tls}},
    }


def write_configs(
    out_dir: Path,
    pki_dir_as_seen_by_nodes: Path | str,
    *,
    router_listen: tuple[str, ...],
    client_connect: tuple[str, ...],
    roles: tuple[str, ...] = tuple(ROLE_POLICIES),
) -> dict[str, Path]:
    """``router.json5`` and ``<role>.json5`` for each of ``roles`` (default every role), referencing the PKI by
    ``pki_dir_as_seen_by_nodes``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = {}
    documents = {ROUTER_ROLE: router_config(pki_dir_as_seen_by_nodes, listen=router_listen)}
    for role in roles:
        documents[role] = client_config(pki_dir_as_seen_by_nodes, role, connect=client_connect)
    for role, document in documents.items():
        path = out_dir / f"{role}.json5"
        path.write_text(json.dumps(document, indent=2) + "\n")
        written[role] = path
    return written


# --- checks before use ------------------------------------------------------------------------------------------


def _pem_file(path: Path, field: str, origin: str) -> bytes:
    try:
        return path.read_bytes()
    except OSError as error:
        raise ConfigError(f"cannot read it ({error.strerror or error}){origin}", path=path, field=field) from None


def _certificates(path: Path, field: str, origin: str, now: _dt.datetime) -> list[x509.Certificate]:
    """The PEM certificates of ``path``, each valid at ``now``."""
    try:
        certificates = x509.load_pem_x509_certificates(_pem_file(path, field, origin))
    except ValueError:
        raise ConfigError(f"not a PEM certificate{origin}", path=path, field=field) from None
    for certificate in certificates:
        if certificate.not_valid_after_utc < now:
            renew = (
                "a new deployment: remove ca.pem and ca.key, then `msk certs --out DIR` issues every certificate anew"
                if _is_ca(certificate)
                else "issue a new one with `msk certs --out DIR` (it keeps the folder's CA)"
            )
            raise ConfigError(
                f"certificate expired {certificate.not_valid_after_utc:%Y-%m-%d %H:%M} UTC{origin}; {renew}",
                path=path,
                field=field,
            )
        if certificate.not_valid_before_utc > now:
            raise ConfigError(
                f"certificate not valid before {certificate.not_valid_before_utc:%Y-%m-%d %H:%M} UTC (this machine's "
                f"clock says {now:%Y-%m-%d %H:%M} UTC){origin}",
                path=path,
                field=field,
            )
    return certificates


def _is_ca(certificate: x509.Certificate) -> bool:
    try:
        return bool(certificate.extensions.get_extension_for_class(x509.BasicConstraints).value.ca)
    except x509.ExtensionNotFound:
        return False


def check_tls_files(
    certificate: Path | str,
    key: Path | str,
    ca: Path | str | None = None,
    *,
    fields: tuple[str, str, str] = ("certificate", "private_key", "root_ca_certificate"),
    named_by: Path | str | None = None,
) -> x509.Certificate:
    """Check a TLS identity before a server listens or a client connects with it: ``certificate`` and ``key`` (and
    ``ca`` when given) readable PEM files, the certificate (and the CA) valid now, ``key`` the certificate's private key
    and the certificate signed by ``ca``. Raises a :class:`ConfigError` naming the file and its field (``fields``:
    the certificate's, the key's, the CA's; ``named_by``: the config file that names them); returns the certificate.
    TLS libraries refuse the same files later with a generic handshake error; this costs about a millisecond."""
    cert_field, key_field, ca_field = fields
    origin = f" (named by {named_by})" if named_by is not None else ""
    now = _dt.datetime.now(_dt.UTC)
    cert_path, key_path = Path(certificate), Path(key)
    leaf = _certificates(cert_path, cert_field, origin, now)[0]
    try:
        private = serialization.load_pem_private_key(_pem_file(key_path, key_field, origin), password=None)
    except (ValueError, TypeError):
        raise ConfigError(f"not an unencrypted PEM private key{origin}", path=key_path, field=key_field) from None
    spki = (serialization.Encoding.DER, serialization.PublicFormat.SubjectPublicKeyInfo)
    if private.public_key().public_bytes(*spki) != leaf.public_key().public_bytes(*spki):
        raise ConfigError(
            f"not the key of {cert_path} (the key of another certificate, role or msk certs run){origin}",
            path=key_path,
            field=key_field,
        )
    if ca is not None:
        authorities = _certificates(Path(ca), ca_field, origin, now)
        if not any(_issued_by(leaf, authority) for authority in authorities):
            raise ConfigError(
                f"not signed by the CA of {ca} (a certificate of another deployment's CA? issue it with "
                f"`msk certs --out DIR` from the CA the others use){origin}",
                path=cert_path,
                field=cert_field,
            )
    return leaf


def _issued_by(certificate: x509.Certificate, authority: x509.Certificate) -> bool:
    try:
        certificate.verify_directly_issued_by(authority)
    except (ValueError, TypeError, InvalidSignature):
        return False
    return True


def check_zenoh_tls(tls: dict, named_by: Path | str | None = None) -> None:
    """:func:`check_tls_files` on the files a Zenoh config's ``transport/link/tls`` section names (``tls``): the
    listener's and the client's certificate and key, and ``root_ca_certificate``."""
    ca = tls.get("root_ca_certificate")
    checked = False
    for side in ("listen", "connect"):
        certificate, key = tls.get(f"{side}_certificate"), tls.get(f"{side}_private_key")
        if not certificate and not key:
            continue
        if not certificate or not key:
            missing = f"{side}_certificate" if not certificate else f"{side}_private_key"
            raise ConfigError(
                f"a TLS identity needs both {side}_certificate and {side}_private_key; {missing} is not set",
                path=named_by,
                field=missing,
            )
        fields = (f"{side}_certificate", f"{side}_private_key", "root_ca_certificate")
        check_tls_files(certificate, key, ca, fields=fields, named_by=named_by)
        checked = True
    if ca and not checked:
        origin = f" (named by {named_by})" if named_by is not None else ""
        _certificates(Path(ca), "root_ca_certificate", origin, _dt.datetime.now(_dt.UTC))
