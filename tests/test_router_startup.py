"""`msk router` at start: it says where it listens, and with a TLS config it checks the files the config names before
listening (``services.transport.security.check_tls_files``). An expired router certificate started "router ... up" and
every client then failed with a generic line; a missing CA said "Cannot create a new TLS listener ... No such file or
directory" without the file (found by QA of the secured deployment)."""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import shutil

import pytest

from tests.conftest import free_tcp_port
from tests.test_security_tls_files import certs, deployment_ca, leaf


def _router(*argv: str) -> tuple[int, str]:
    """`msk router ARGV` in this process: exit code and what it printed on stderr."""
    from services.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = main(["router", *argv])
    return code, err.getvalue()


def test_the_router_says_the_endpoints_it_listens_on():
    endpoint = f"tcp/127.0.0.1:{free_tcp_port()}"
    code, said = _router("--listen", endpoint, "--duration", "0.2")
    assert code == 0
    assert f"up, listening on {endpoint}" in said, said


def test_the_secured_router_says_its_tls_endpoint(tmp_path):
    pki = tmp_path / "pki"
    certs("--out", str(pki), "--port", str(free_tcp_port()))
    port = free_tcp_port()
    code, said = _router(
        "--zenoh-config", str(pki / "zenoh" / "router.json5"), "--listen", f"tls/127.0.0.1:{port}", "--duration", "0.2"
    )
    assert code == 0 and f"listening on tls/127.0.0.1:{port}" in said, said


@pytest.mark.parametrize("case", ["expired certificate", "missing CA", "key of another role"])
def test_a_router_with_an_unusable_tls_file_refuses_to_start_naming_it(tmp_path, case):
    pki = tmp_path / "pki"
    certs("--out", str(pki))
    now = dt.datetime.now(dt.UTC)
    if case == "expired certificate":
        expired = leaf(
            tmp_path, "router", deployment_ca(pki), not_before=now - dt.timedelta(days=9),
            not_after=now - dt.timedelta(days=1), cn="msk-router",
        )  # fmt: skip
        shutil.copy(expired, pki / "router.pem")
        shutil.copy(tmp_path / "router.key", pki / "router.key")
        expected = f"{pki / 'router.pem'}, field 'listen_certificate': certificate expired"
    elif case == "missing CA":
        (pki / "ca.pem").unlink()
        expected = f"{pki / 'ca.pem'}, field 'root_ca_certificate': cannot read it (No such file or directory)"
    else:
        shutil.copy(pki / "tablet.key", pki / "router.key")
        expected = f"{pki / 'router.key'}, field 'listen_private_key': not the key of {pki / 'router.pem'}"
    code, said = _router(
        "--zenoh-config", str(pki / "zenoh" / "router.json5"), "--listen", f"tls/127.0.0.1:{free_tcp_port()}",
        "--duration", "3",
    )  # fmt: skip
    assert code == 2, said
    assert said.startswith(f"msk router: error: {expected}"), said
    assert said.count("\n") == 1 and " up" not in said, said
