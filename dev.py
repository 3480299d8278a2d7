#!/usr/bin/env python3
"""Set-up and entry point needing nothing but Python >= 3.11 and pip.

    python3 dev.py demo   # create .venv (first time), install msk-live, run the demo on the embedded default
    python3 dev.py test   # same install, then the whole test suite
    python3 dev.py bench  # the benchmarks (`msk bench`)
    python3 dev.py lint   # ruff (lint and format check) and mypy, as CI runs them

Extra arguments after the command go to the tool (e.g. ``python3 dev.py test -k emg``).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PYTHON = BIN / "python"


def _install() -> None:
    if sys.version_info < (3, 11):  # noqa: UP036 - dev.py runs under whatever python3 the machine has
        sys.exit(f"msk-live needs Python >= 3.11; this is {sys.version.split()[0]}")
    digest = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()[:16]
    stamp = VENV / f".installed-{digest}"
    if stamp.exists():
        return
    if not PYTHON.exists():
        print(f"creating {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    print("installing msk-live and its dependencies into .venv (first run takes a few minutes)", flush=True)
    subprocess.check_call([str(PYTHON), "-m", "pip", "install", "--quiet", "--upgrade", "pip"])
    subprocess.check_call([str(PYTHON), "-m", "pip", "install", "--quiet", "-e", f"{ROOT}[test]"])
    for old in VENV.glob(".installed-*"):
        old.unlink()
    stamp.touch()


def _parallel(args: list[str]) -> list[str]:
    """pytest-xdist options: one worker per core, the tests that run whole live sessions kept on one worker and each
    module's tests that share a module-scoped fixture on one worker, these groups queued first (tests/conftest.py);
    none when the caller chose (``-n``, ``-p no:xdist``)."""
    if any(a.startswith(("-n", "--numprocesses", "--dist")) or a == "no:xdist" for a in args):
        return []
    return ["-n", "auto", "--dist", "loadgroup"]


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in ("demo", "test", "bench", "lint"):
        print(__doc__)
        return 2
    command, rest = argv[0], argv[1:]
    _install()
    os.chdir(ROOT)
    if command == "lint":
        # mypy reads msk_pb2.pyi, which the schema package makes from msk.proto on import
        subprocess.check_call([str(PYTHON), "-c", "import services.transport.schemas"])
        checks = [["ruff", "check", "."], ["ruff", "format", "--check", "."], ["mypy"]]
        failed = [" ".join(c) for c in checks if subprocess.call([str(BIN / c[0]), *c[1:]]) != 0]
        if failed:
            print(f"lint: failed: {', '.join(failed)}", file=sys.stderr)
        return 1 if failed else 0
    if command == "test":
        return subprocess.call([str(PYTHON), "-m", "pytest", *_parallel(rest), *rest])
    return subprocess.call([str(BIN / "msk"), command, *rest])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
