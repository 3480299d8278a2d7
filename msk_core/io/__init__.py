"""Readers and writers of the file formats msk-live meets: OpenSim storage, .anc, C3D analogs, Delsys CSV exports."""

from msk_core.io.storage import Storage, read_sto, write_sto

__all__ = ["Storage", "read_sto", "write_sto"]
