"""The wire schema ``msk.proto`` and the Python code protoc makes of it.

``msk_pb2.py`` and ``msk_pb2.pyi`` are not kept in the repository (protobuf's own advice: "no checked-in protobuf
gencode"): importing this package makes them with the pinned grpcio-tools' protoc when they are missing or were made
from another ``msk.proto`` than the one beside them (its SHA-256, kept in ``msk_pb2.proto-sha256`` next to the code:
file times say nothing once pip or git has copied the files), so the code always matches the schema."""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

PROTO = Path(__file__).with_name("msk.proto")
GENERATED = ("msk_pb2.py", "msk_pb2.pyi")
#: the SHA-256 of the msk.proto the code beside it was made from (written last)
STAMP = "msk_pb2.proto-sha256"


class SchemaGenerationError(RuntimeError):
    """protoc could not make the Python code of ``msk.proto``."""


def _digest(proto: Path) -> str:
    return hashlib.sha256(proto.read_bytes()).hexdigest()


def is_current(folder: Path, proto: Path = PROTO) -> bool:
    """Whether ``folder`` holds the generated code of ``proto`` as it is now."""
    try:
        made_from = (folder / STAMP).read_text().strip()
    except OSError:
        return False
    return made_from == _digest(proto) and all((folder / name).exists() for name in GENERATED)


def generate(folder: Path, proto: Path = PROTO) -> None:
    """Make ``msk_pb2.py`` and ``msk_pb2.pyi`` of ``proto`` in ``folder``. Each file appears whole (written aside, then
    renamed), so processes that import at the same moment never read half a file."""
    try:
        from grpc_tools import protoc  # noqa: PLC0415 - needed only when the code is (re)made
    except ImportError as exc:
        raise SchemaGenerationError(
            f"{folder / GENERATED[0]} is missing or not made from {proto} as it is, and grpcio-tools (its protoc) is not "
            "installed: pip install msk-live's dependencies (python3 dev.py does)"
        ) from exc
    folder.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=folder, prefix=".protoc-") as scratch:
        code = protoc.main(
            ["protoc", f"-I{proto.parent}", f"--python_out={scratch}", f"--pyi_out={scratch}", str(proto)]
        )
        if code != 0:
            raise SchemaGenerationError(f"protoc failed on {proto} (exit code {code}); its message is above")
        (Path(scratch) / STAMP).write_text(_digest(proto) + "\n")
        for name in (*GENERATED, STAMP):  # the stamp last: it vouches for the code already in place
            os.replace(Path(scratch) / name, folder / name)


def _ensure_generated() -> None:
    here = PROTO.parent
    if is_current(here):
        return
    try:
        generate(here)
    except OSError as exc:  # not ours to write (another user's install, a read-only file system)
        raise SchemaGenerationError(
            f"cannot write the code of {PROTO} into {here} ({exc.strerror or exc}): import services.transport.schemas "
            "once as a user who may write there (the Dockerfile does it at build time)"
        ) from exc


_ensure_generated()
