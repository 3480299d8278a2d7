"""Readers and writers of the file formats msk-live meets: OpenSim storage, .anc, C3D analogs, Delsys CSV exports,
and the alignment of signals recorded at different rates."""

from msk_core.io.align import AlignedTrial, align_to_kinematics, resample_linear, window_mean
from msk_core.io.analog import AnalogRecording, read_anc, read_c3d_analogs
from msk_core.io.delsys import (
    DelsysChannel,
    DelsysExport,
    read_delsys_csv,
    read_emgworks_csv,
    read_trigno_discover_csv,
)
from msk_core.io.storage import Storage, read_sto, write_sto

__all__ = [
    "AlignedTrial",
    "AnalogRecording",
    "DelsysChannel",
    "DelsysExport",
    "Storage",
    "align_to_kinematics",
    "read_anc",
    "read_c3d_analogs",
    "read_delsys_csv",
    "read_emgworks_csv",
    "read_sto",
    "read_trigno_discover_csv",
    "resample_linear",
    "window_mean",
    "write_sto",
]
