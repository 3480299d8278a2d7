"""The wire schema ``msk.proto`` and the Python code protoc makes of it.

``msk_pb2.py`` and ``msk_pb2.pyi`` are not kept in the repository (protobuf's own advice: "no checked-in protobuf
gencode"): importing this package makes them with the pinned grpcio-tools' protoc when they are missing or older than
``msk.proto``, so the code always matches the schema."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

PROTO = Path(__file__).with_name("msk.proto")
GENERATED = ("msk_pb2.py", "msk_pb2.pyi")


class SchemaGenerationError(RuntimeError):
    """protoc could not make the Python code of ``msk.proto``."""


def is_current(folder: Path, proto: Path = PROTO) -> bool:
    """Whether ``folder`` holds the generated code of ``proto``, made after its last change."""
    made = [folder / name for name in GENERATED]
    return all(p.exists() for p in made) and min(p.stat().st_mtime for p in made) >= proto.stat().st_mtime


def generate(folder: Path, proto: Path = PROTO) -> None:
    """Make ``msk_pb2.py`` and ``msk_pb2.pyi`` of ``proto`` in ``folder``. Each file appears whole (written aside, then
    renamed), so processes that import at the same moment never read half a file."""
    try:
        from grpc_tools import protoc  # noqa: PLC0415 - needed only when the code is (re)made
    except ImportError as exc:
        raise SchemaGenerationError(
            f"{folder / GENERATED[0]} is missing or older than {proto}, and grpcio-tools (its protoc) is not "
            "installed: pip install msk-live's dependencies (python3 dev.py does)"
        ) from exc
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder, prefix=".protoc-") as scratch:
        code = protoc.main(
            ["protoc", f"-I{proto.parent}", f"--python_out={scratch}", f"--pyi_out={scratch}", str(proto)]
        )
        if code != 0:
            raise SchemaGenerationError(f"protoc failed on {proto} (exit code {code}); its message is above")
        for name in GENERATED:
            os.replace(Path(scratch) / name, folder / name)


def _ensure_generated() -> None:
    here = PROTO.parent
    if is_current(here):
        return
    try:
        generate(here)
    except PermissionError as exc:
        raise SchemaGenerationError(
            f"cannot write the code of {PROTO} into {here} ({exc.strerror}): import services.transport.schemas "
            "once as a user who may write there (the Dockerfile does it at build time)"
        ) from exc


_ensure_generated()
