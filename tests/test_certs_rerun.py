"""`msk certs --out DIR` on a folder that already holds a deployment keeps its CA: a second run (another role, another
router name) issues under the same ``ca.key``, so every certificate handed out before stays valid. It made a new CA
each time, silently, and every distributed certificate then failed verification (found by QA of the secured
deployment). Configs are written only for the roles whose certificate is in the folder."""

from __future__ import annotations

import pytest

from msk_core.errors import ConfigError
from services.transport import security
from tests.test_security_tls_files import certs


def test_a_second_run_reuses_the_ca_and_says_so(tmp_path):
    pki = tmp_path / "pki"
    first = certs("--out", str(pki), "--router-host", "localhost", "--router-host", "127.0.0.1")
    assert "new CA" in first and "reusing" not in first
    ca, ca_key, driver = ((pki / name).read_bytes() for name in ("ca.pem", "ca.key", "driver.pem"))
    second = certs("--out", str(pki), "--role", "tablet", "--router-host", "gym.local")
    assert f"reusing the CA of {pki / 'ca.pem'}" in second, second
    assert (pki / "ca.pem").read_bytes() == ca and (pki / "ca.key").read_bytes() == ca_key
    assert (pki / "driver.pem").read_bytes() == driver  # not asked: left as it was
    for role in ("driver", "tablet", "router", "dashboard"):  # old and new, all under the one CA
        security.check_tls_files(pki / f"{role}.pem", pki / f"{role}.key", pki / "ca.pem")
    # every role's certificate is in the folder: every role's config is written
    assert {p.stem for p in (pki / "zenoh").glob("*.json5")} == {"router", *security.ROLE_POLICIES}


def test_a_new_folder_with_some_roles_gets_configs_for_those_roles_only(tmp_path):
    pki = tmp_path / "pki"
    certs("--out", str(pki), "--role", "tablet", "--role", "estimator")
    assert {p.stem for p in (pki / "zenoh").glob("*.json5")} == {"router", "tablet", "estimator"}
    assert not (pki / "recorder.pem").exists()


def test_a_ca_certificate_without_its_key_is_refused_rather_than_replaced(tmp_path):
    pki = tmp_path / "pki"
    certs("--out", str(pki))
    ca = (pki / "ca.pem").read_bytes()
    (pki / "ca.key").unlink()
    with pytest.raises(ConfigError, match=r"ca\.key: the folder has ca\.pem but not ca\.key"):
        security.existing_ca(pki)
    from services.cli import main

    assert main(["certs", "--out", str(pki), "--role", "tablet"]) == 2
    assert (pki / "ca.pem").read_bytes() == ca  # untouched
