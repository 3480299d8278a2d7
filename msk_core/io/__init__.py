"""Readers and writers of the file formats msk-live meets: OpenSim storage, .anc, C3D analogs, Delsys CSV exports."""

from msk_core.io.analog import AnalogRecording, read_anc, read_c3d_analogs
from msk_core.io.storage import Storage, read_sto, write_sto

__all__ = ["AnalogRecording", "Storage", "read_anc", "read_c3d_analogs", "read_sto", "write_sto"]
