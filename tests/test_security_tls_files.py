"""The TLS files a Zenoh config names are checked before a session opens or a router listens
(``services.transport.security.check_tls_files``, called by ``services.transport.zenoh_session.open_session``): a
missing, expired, not yet valid, foreign or mismatched file is said in one line naming the file and the config field.
Zenoh said "Unable to connect to any of [tls/...]" for all of them on the client, and nothing about the file on the
router (found by QA of the secured deployment). Certificates from `msk certs`; the bad ones are made here, under its
CA or under a look-alike CA of the same name."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import json
import time
from pathlib import Path

import pytest
from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec

from msk_core.errors import ConfigError
from services.transport import security
from services.transport.zenoh_session import ZenohOptions, open_session
from tests.conftest import free_tcp_port

NOW = dt.datetime.now(dt.UTC)
DAY = dt.timedelta(days=1)


def certs(*argv: str) -> str:
    """`msk certs ARGV` in this process; its output."""
    from services.cli import main

    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["certs", *argv]) == 0
    return out.getvalue()


def leaf(folder: Path, name: str, signer: tuple, *, not_before: dt.datetime, not_after: dt.datetime, cn: str) -> Path:
    """``folder/name.pem`` and ``.key``: a certificate of ``cn`` signed by ``signer`` (CA key, CA certificate) with
    these dates; returns the certificate's path."""
    key = ec.generate_private_key(ec.SECP256R1())
    ca_key, ca_cert = signer
    certificate = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(x509.NameOID.COMMON_NAME, cn)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(not_before)
        .not_valid_after(not_after)
        .sign(ca_key, hashes.SHA256())
    )
    (folder / f"{name}.pem").write_bytes(certificate.public_bytes(serialization.Encoding.PEM))
    (folder / f"{name}.key").write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )
    return folder / f"{name}.pem"


def deployment_ca(pki: Path) -> tuple:
    ca_key = serialization.load_pem_private_key((pki / "ca.key").read_bytes(), password=None)
    return ca_key, x509.load_pem_x509_certificate((pki / "ca.pem").read_bytes())


@pytest.fixture(scope="module")
def pki(tmp_path_factory) -> Path:
    """`msk certs` with its defaults, plus bad certificates in ``bad/``: expired, not yet valid (both signed by the
    deployment's CA), and one signed by a look-alike CA of the same name (``foreign_ca.pem``)."""
    pki = tmp_path_factory.mktemp("tls-files") / "pki"
    certs("--out", str(pki))
    bad = pki / "bad"
    bad.mkdir()
    ca = deployment_ca(pki)
    leaf(bad, "expired", ca, not_before=NOW - 30 * DAY, not_after=NOW - DAY, cn="msk-tablet")
    leaf(bad, "future", ca, not_before=NOW + DAY, not_after=NOW + 30 * DAY, cn="msk-tablet")
    foreign_key, foreign_ca = security.make_ca()  # "msk-live CA", like the deployment's
    (bad / "foreign_ca.pem").write_bytes(foreign_ca.public_bytes(serialization.Encoding.PEM))
    leaf(bad, "foreign", (foreign_key, foreign_ca), not_before=NOW - DAY, not_after=NOW + DAY, cn="msk-tablet")
    return pki


def tablet_config(pki: Path, folder: Path, **tls: str) -> Path:
    """The tablet's config of `msk certs` (a router on a port nobody listens on), with ``tls`` fields replaced."""
    document = security.client_config(pki, "tablet", connect=(f"tls/localhost:{free_tcp_port()}",))
    document["transport"]["link"]["tls"].update(tls)
    path = folder / "tablet.json5"
    path.write_text(json.dumps(document))
    return path


# (fields replaced in the tablet's config, pki-relative) -> (the file named, its field, what is said)
CLIENT_CASES = {
    "expired": (
        {"connect_certificate": "bad/expired.pem", "connect_private_key": "bad/expired.key"},
        ("bad/expired.pem", "connect_certificate", f"certificate expired {(NOW - DAY):%Y-%m-%d}"),
    ),
    "not yet valid": (
        {"connect_certificate": "bad/future.pem", "connect_private_key": "bad/future.key"},
        ("bad/future.pem", "connect_certificate", f"certificate not valid before {(NOW + DAY):%Y-%m-%d}"),
    ),
    "signed by a look-alike CA": (
        {"connect_certificate": "bad/foreign.pem", "connect_private_key": "bad/foreign.key"},
        ("bad/foreign.pem", "connect_certificate", "not signed by the CA of"),
    ),
    "wrong root CA": (
        {"root_ca_certificate": "bad/foreign_ca.pem"},
        ("tablet.pem", "connect_certificate", "not signed by the CA of"),
    ),
    "missing key": (
        {"connect_private_key": "nosuch.key"},
        ("nosuch.key", "connect_private_key", "cannot read it (No such file or directory)"),
    ),
    "missing certificate": (
        {"connect_certificate": "nosuch.pem"},
        ("nosuch.pem", "connect_certificate", "cannot read it (No such file or directory)"),
    ),
    "missing CA": (
        {"root_ca_certificate": "nosuch_ca.pem"},
        ("nosuch_ca.pem", "root_ca_certificate", "cannot read it (No such file or directory)"),
    ),
    "key of another role": (
        {"connect_private_key": "driver.key"},
        ("driver.key", "connect_private_key", "not the key of"),
    ),
    "not a certificate": (
        {"connect_certificate": "tablet.key"},
        ("tablet.key", "connect_certificate", "not a PEM certificate"),
    ),
}


@pytest.mark.parametrize("case", list(CLIENT_CASES))
def test_a_client_with_an_unusable_tls_file_is_told_which_file_and_field(pki, tmp_path, case):
    replaced, (named, field, said) = CLIENT_CASES[case]
    config = tablet_config(pki, tmp_path, **{k: str(pki / v) for k, v in replaced.items()})
    started = time.perf_counter()
    with pytest.raises(ConfigError) as raised:
        open_session(ZenohOptions(mode=None, config_file=config))
    message = str(raised.value)
    assert message.startswith(f"{pki / named}, field '{field}': {said}"), message
    assert f"named by {config}" in message and "\n" not in message
    assert time.perf_counter() - started < 1.0  # said before Zenoh tries to connect


def test_the_check_passes_the_files_of_msk_certs_and_costs_milliseconds(pki):
    """Every config `msk certs` wrote passes; the check runs at every tool's start, so it must stay cheap."""
    from services.transport.zenoh_session import check_tls

    configs = sorted((pki / "zenoh").glob("*.json5"))
    assert len(configs) == len(security.ROLE_POLICIES) + 1
    for path in configs:
        check_tls(ZenohOptions(mode=None, config_file=path).to_config(), path)
    config = ZenohOptions(mode=None, config_file=pki / "zenoh" / "tablet.json5").to_config()
    started = time.perf_counter()
    for _ in range(20):
        check_tls(config)
    assert (time.perf_counter() - started) / 20 < 0.02  # measured about 2 ms on the 2-core machine


def test_msk_certs_reissues_an_expired_certificate_under_the_same_ca(pki, tmp_path):
    """The expired message says `msk certs --out DIR` renews it: the renewed tablet certificate passes, under the
    CA the router already trusts."""
    import shutil

    copy = tmp_path / "pki"
    shutil.copytree(pki, copy)
    for suffix in ("pem", "key"):
        shutil.copy(copy / "bad" / f"expired.{suffix}", copy / f"tablet.{suffix}")
    config = tablet_config(copy, tmp_path)
    with pytest.raises(ConfigError, match="certificate expired"):
        open_session(ZenohOptions(mode=None, config_file=config))
    ca_before = (copy / "ca.pem").read_bytes()
    certs("--out", str(copy), "--role", "tablet")
    assert (copy / "ca.pem").read_bytes() == ca_before
    security.check_tls_files(copy / "tablet.pem", copy / "tablet.key", copy / "ca.pem")
