"""Shared fixtures. Tests that read ../shared skip with a clear reason when it is absent (CI always has it)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

import services  # noqa: F401 - first, before numpy loads: one BLAS thread per process (services/__init__.py)

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("MSK_SHARED_DIR", REPO_ROOT.parent / "shared"))

# Modules whose tests run a whole `msk live` session (real-time simulators, the well-known Zenoh port 7447 when free,
# the machine's calibration cache): under pytest-xdist (`python3 dev.py test` runs two workers) they share one worker,
# one after another, so two sessions never race for the port or the cache, and the other worker runs the rest.
LIVE_SESSION_MODULES = frozenset(
    {
        "test_live",
        "test_live_session",
        "test_live_together",
        "test_live_dashboard",
        "test_sim_clock",
        "test_live_clock_acc",
        "test_live_electrode_quality",
        "test_live_sets",
    }
)


# Wider-than-test fixtures: a module split over the two workers would build them once on each.
_SHARED_SCOPES = frozenset({"module", "class", "package"})


def _uses_a_shared_fixture(item: pytest.Item) -> bool:
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(d.scope in _SHARED_SCOPES for defs in info.name2fixturedefs.values() for d in defs)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """xdist groups (``python3 dev.py test`` runs ``--dist loadgroup``, which otherwise sends each test on its own):
    the live-session modules share one group; a module whose tests share a module- or class-scoped fixture is one
    group, so the fixture is built once (not once per worker, nor again after another module's test came between).
    The live-session group is queued first and the module groups next, so the longest units start first and the
    single tests fill the gaps at the end (xdist queues the groups in the order their first test is collected)."""
    rank: dict[int, int] = {}
    for item in items:
        if item.path.stem in LIVE_SESSION_MODULES:
            item.add_marker(pytest.mark.xdist_group("live-session"))
            rank[id(item)] = 0
        elif _uses_a_shared_fixture(item):
            item.add_marker(pytest.mark.xdist_group(f"module-{item.path.stem}"))
            rank[id(item)] = 1
        else:
            rank[id(item)] = 2
    if config.getoption("dist", "no") == "loadgroup":
        items.sort(key=lambda item: rank[id(item)])  # stable: collection order within each rank


@pytest.fixture(autouse=True, scope="session")
def _own_session_registry(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Each test process announces and finds `msk live` sessions in its own registry (services/discovery.py), so a
    test never attaches to a session of another worker or of the developer's machine."""
    os.environ["MSK_SESSIONS_DIR"] = str(tmp_path_factory.mktemp("sessions"))


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
