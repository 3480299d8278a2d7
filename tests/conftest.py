"""Shared fixtures. Tests that read ../shared skip with a clear reason when it is absent (CI always has it)."""

from __future__ import annotations

import functools
import os
import re
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

import services  # noqa: F401 - first, before numpy loads: one BLAS thread per process (services/__init__.py)

REPO_ROOT = Path(__file__).resolve().parents[1]
SHARED_DIR = Path(os.environ.get("MSK_SHARED_DIR", REPO_ROOT.parent / "shared"))
SPECS_DIR = REPO_ROOT / "msk_core" / "model" / "specs"  # the shipped packs' spec files
#: The start of a one-coordinate pack spec (the right knee, one group) that spec tests add their tables to.
KNEE_SPEC = """name = "t"
[coordinates]
knee_angle_r = { range_deg = [0, 120], reference_deg = 0 }
[groups]
VL = ["vaslat140_r"]
"""

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
        # not msk live itself, but as heavy and as timing-bound: beside a live session on the other worker they took
        # 2-3x as long (hosts 31 -> 73 s, bench_sessions 13 -> 42 s in one run)
        "test_hosts",
        "test_bench_sessions",
        "test_mvn",
    }
)
LIVE_SESSION_UNIT = "live-session"
_SHARED_FIXTURE = re.compile(r"""scope\s*=\s*["'](?:module|class|package)["']""")


@functools.cache
def _shares_a_fixture(module_path: str) -> bool:
    """The test module defines a module-, class- or package-scoped fixture (read from its source: the xdist
    controller, which schedules, collects no tests)."""
    path = REPO_ROOT / module_path
    return path.is_file() and bool(_SHARED_FIXTURE.search(path.read_text(encoding="utf-8")))


def work_unit(nodeid: str) -> str:
    """The xdist work unit of a test: the live-session modules are one unit; a module that defines a fixture wider than
    a test is one unit (its fixture built once, not once per worker, nor again after another module's test came
    between); any other test is a unit of its own."""
    module_path = nodeid.split("::", 1)[0]
    if Path(module_path).stem in LIVE_SESSION_MODULES:
        return LIVE_SESSION_UNIT
    return module_path if _shares_a_fixture(module_path) else nodeid


def _rank(nodeid: str) -> int:
    unit = work_unit(nodeid)
    return 0 if unit == LIVE_SESSION_UNIT else 1 if unit != nodeid else 2


@pytest.hookimpl(tryfirst=True)  # before xdist's own hook (firstresult)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist loadgroup`` (``python3 dev.py test``) schedules by :func:`work_unit`. (xdist's own loadgroup reads
    ``xdist_group`` marks into the test ids, which pytest 9 no longer lets it change: every test went alone, the
    live sessions on both workers and a module's shared fixture built on each.)"""
    if config.getvalue("dist") != "loadgroup":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class WorkUnitScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return work_unit(nodeid)

    return WorkUnitScheduling(config, log)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under xdist, the live-session unit first and the module units next: xdist queues units in the order of their
    first test, so the longest start first and the single tests fill the gaps at the end."""
    if getattr(config.option, "loadgroup", False):  # set on the workers by xdist for --dist loadgroup
        items.sort(key=lambda item: _rank(item.nodeid))  # stable: collection order within a rank


@pytest.fixture(autouse=True, scope="session")
def _own_session_registry(tmp_path_factory: pytest.TempPathFactory) -> None:
    """Each test process announces and finds `msk live` sessions in its own registry (services/sessions/discovery.py), so a
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


def committed_trial(folder: str, name: str, shared_dir: Path, tmp_path: Path) -> Path:
    """The committed trial file ``recordings/<folder>/<name>.toml`` (its data under ../shared/data/<folder>), or a copy
    in ``tmp_path`` pointing at ``shared_dir`` when the data are not at ../shared."""
    trials = REPO_ROOT / "recordings" / folder
    path = trials / f"{name}.toml"
    data = (shared_dir / "data" / folder).resolve()
    relative = f"../../../shared/data/{folder}"
    if (trials / relative).resolve() == data:
        return path
    copy = tmp_path / path.name
    copy.write_text(path.read_text().replace(relative, str(data)))
    return copy


def free_tcp_port() -> int:
    """A loopback TCP port nobody listens on right now (for Zenoh endpoints and device simulators)."""
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def wait_until(
    condition: Callable[[], bool], timeout_s: float, what: str, have: Callable[[], object] = lambda: ""
) -> None:
    """Poll ``condition`` every 20 ms until true; after ``timeout_s`` fail saying what it waited for and what there is
    (``have()``): the graph's bounded wait, :func:`services.sessions.graph.wait_for`."""
    from services.sessions.graph import wait_for

    wait_for(what, condition, lambda: str(have()), timeout_s, poll_s=0.02)


def emg_chunk(
    index: int, *, n_samples: int = 27, labels: Sequence[str] = ("c1",), value: float = 0.0, **fields: Any
) -> Any:
    """The ``index``-th EmgChunk of a Trigno at 2 kHz whose chunks start 27 samples apart: ``n_samples`` samples of
    each channel of ``labels``, all ``value``; ``fields``: more of the message's (units, host_time_ns, ...)."""
    from services.transport import messages

    return messages.EmgChunk(
        source_id="trigno",
        channel_labels=list(labels),
        sample_rate_hz=2000.0,
        n_samples=n_samples,
        n_channels=len(labels),
        samples=[value] * (n_samples * len(labels)),
        first_sample_index=27 * index,
        **fields,
    )


@pytest.fixture
def zenoh_endpoint() -> str:
    """A fresh loopback endpoint so tests never join each other's (or a developer's) Zenoh network."""
    from services.transport.zenoh_session import free_loopback_endpoint

    return free_loopback_endpoint()
