"""Shared fixtures. Tests that read ../shared skip with a clear reason when it is absent (CI always has it)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("MSK_SHARED_DIR", REPO_ROOT.parent / "shared"))


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    if not SHARED_DIR.is_dir():
        pytest.skip(f"reference material not found at {SHARED_DIR} (set MSK_SHARED_DIR or put shared/ beside the repo)")
    return SHARED_DIR


@pytest.fixture(scope="session")
def repo_root() -> Path:
    return REPO_ROOT


def free_tcp_port() -> int:
    """A loopback TCP port nobody listens on right now (for Zenoh endpoints and device simulators)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def zenoh_endpoint() -> str:
    """A fresh loopback endpoint so tests never join each other's (or a developer's) Zenoh network."""
    from services.zenoh_session import free_loopback_endpoint

    return free_loopback_endpoint()
