from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class EmgChunk(_message.Message):
    __slots__ = ("source_id", "channel_labels", "sample_rate_hz", "first_sample_index", "device_time_ns", "host_time_ns", "n_samples", "n_channels", "samples", "units")
    SOURCE_ID_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_LABELS_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    FIRST_SAMPLE_INDEX_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    N_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    N_CHANNELS_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    UNITS_FIELD_NUMBER: _ClassVar[int]
    source_id: str
    channel_labels: _containers.RepeatedScalarFieldContainer[str]
    sample_rate_hz: float
    first_sample_index: int
    device_time_ns: int
    host_time_ns: int
    n_samples: int
    n_channels: int
    samples: _containers.RepeatedScalarFieldContainer[float]
    units: str
    def __init__(self, source_id: _Optional[str] = ..., channel_labels: _Optional[_Iterable[str]] = ..., sample_rate_hz: _Optional[float] = ..., first_sample_index: _Optional[int] = ..., device_time_ns: _Optional[int] = ..., host_time_ns: _Optional[int] = ..., n_samples: _Optional[int] = ..., n_channels: _Optional[int] = ..., samples: _Optional[_Iterable[float]] = ..., units: _Optional[str] = ...) -> None: ...

class AccChunk(_message.Message):
    __slots__ = ("source_id", "sensor_labels", "sample_rate_hz", "first_sample_index", "device_time_ns", "host_time_ns", "n_samples", "n_sensors", "samples", "units")
    SOURCE_ID_FIELD_NUMBER: _ClassVar[int]
    SENSOR_LABELS_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_RATE_HZ_FIELD_NUMBER: _ClassVar[int]
    FIRST_SAMPLE_INDEX_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    N_SAMPLES_FIELD_NUMBER: _ClassVar[int]
    N_SENSORS_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    UNITS_FIELD_NUMBER: _ClassVar[int]
    source_id: str
    sensor_labels: _containers.RepeatedScalarFieldContainer[str]
    sample_rate_hz: float
    first_sample_index: int
    device_time_ns: int
    host_time_ns: int
    n_samples: int
    n_sensors: int
    samples: _containers.RepeatedScalarFieldContainer[float]
    units: str
    def __init__(self, source_id: _Optional[str] = ..., sensor_labels: _Optional[_Iterable[str]] = ..., sample_rate_hz: _Optional[float] = ..., first_sample_index: _Optional[int] = ..., device_time_ns: _Optional[int] = ..., host_time_ns: _Optional[int] = ..., n_samples: _Optional[int] = ..., n_sensors: _Optional[int] = ..., samples: _Optional[_Iterable[float]] = ..., units: _Optional[str] = ...) -> None: ...

class Vector3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class Quaternion(_message.Message):
    __slots__ = ("w", "x", "y", "z")
    W_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    w: float
    x: float
    y: float
    z: float
    def __init__(self, w: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class ImuSample(_message.Message):
    __slots__ = ("tracker_id", "segment", "packet_counter", "sample_time_fine", "orientation", "acceleration", "rate_of_turn", "magnetic_field", "device_time_ns", "host_time_ns", "coordinate_frame")
    TRACKER_ID_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_FIELD_NUMBER: _ClassVar[int]
    PACKET_COUNTER_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_TIME_FINE_FIELD_NUMBER: _ClassVar[int]
    ORIENTATION_FIELD_NUMBER: _ClassVar[int]
    ACCELERATION_FIELD_NUMBER: _ClassVar[int]
    RATE_OF_TURN_FIELD_NUMBER: _ClassVar[int]
    MAGNETIC_FIELD_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    COORDINATE_FRAME_FIELD_NUMBER: _ClassVar[int]
    tracker_id: str
    segment: str
    packet_counter: int
    sample_time_fine: int
    orientation: Quaternion
    acceleration: Vector3
    rate_of_turn: Vector3
    magnetic_field: Vector3
    device_time_ns: int
    host_time_ns: int
    coordinate_frame: str
    def __init__(self, tracker_id: _Optional[str] = ..., segment: _Optional[str] = ..., packet_counter: _Optional[int] = ..., sample_time_fine: _Optional[int] = ..., orientation: _Optional[_Union[Quaternion, _Mapping]] = ..., acceleration: _Optional[_Union[Vector3, _Mapping]] = ..., rate_of_turn: _Optional[_Union[Vector3, _Mapping]] = ..., magnetic_field: _Optional[_Union[Vector3, _Mapping]] = ..., device_time_ns: _Optional[int] = ..., host_time_ns: _Optional[int] = ..., coordinate_frame: _Optional[str] = ...) -> None: ...

class JointAngles(_message.Message):
    __slots__ = ("coordinates", "q", "qd", "qdd", "phase", "device_time_ns", "host_time_ns")
    COORDINATES_FIELD_NUMBER: _ClassVar[int]
    Q_FIELD_NUMBER: _ClassVar[int]
    QD_FIELD_NUMBER: _ClassVar[int]
    QDD_FIELD_NUMBER: _ClassVar[int]
    PHASE_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    coordinates: _containers.RepeatedScalarFieldContainer[str]
    q: _containers.RepeatedScalarFieldContainer[float]
    qd: _containers.RepeatedScalarFieldContainer[float]
    qdd: _containers.RepeatedScalarFieldContainer[float]
    phase: float
    device_time_ns: int
    host_time_ns: int
    def __init__(self, coordinates: _Optional[_Iterable[str]] = ..., q: _Optional[_Iterable[float]] = ..., qd: _Optional[_Iterable[float]] = ..., qdd: _Optional[_Iterable[float]] = ..., phase: _Optional[float] = ..., device_time_ns: _Optional[int] = ..., host_time_ns: _Optional[int] = ...) -> None: ...

class LoadEvent(_message.Message):
    __slots__ = ("barbell_mass_kg", "exercise", "device_time_ns", "host_time_ns", "set_number", "athlete", "names", "set_mark", "set_rest_s", "set_start_s", "set_rep_spans_s", "set_end_s", "set_ended_by", "set_rep_start_s")
    class NamesEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: str
        def __init__(self, key: _Optional[str] = ..., value: _Optional[str] = ...) -> None: ...
    BARBELL_MASS_KG_FIELD_NUMBER: _ClassVar[int]
    EXERCISE_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    SET_NUMBER_FIELD_NUMBER: _ClassVar[int]
    ATHLETE_FIELD_NUMBER: _ClassVar[int]
    NAMES_FIELD_NUMBER: _ClassVar[int]
    SET_MARK_FIELD_NUMBER: _ClassVar[int]
    SET_REST_S_FIELD_NUMBER: _ClassVar[int]
    SET_START_S_FIELD_NUMBER: _ClassVar[int]
    SET_REP_SPANS_S_FIELD_NUMBER: _ClassVar[int]
    SET_END_S_FIELD_NUMBER: _ClassVar[int]
    SET_ENDED_BY_FIELD_NUMBER: _ClassVar[int]
    SET_REP_START_S_FIELD_NUMBER: _ClassVar[int]
    barbell_mass_kg: float
    exercise: str
    device_time_ns: int
    host_time_ns: int
    set_number: int
    athlete: str
    names: _containers.ScalarMap[str, str]
    set_mark: str
    set_rest_s: float
    set_start_s: float
    set_rep_spans_s: _containers.RepeatedScalarFieldContainer[float]
    set_end_s: float
    set_ended_by: str
    set_rep_start_s: float
    def __init__(self, barbell_mass_kg: _Optional[float] = ..., exercise: _Optional[str] = ..., device_time_ns: _Optional[int] = ..., host_time_ns: _Optional[int] = ..., set_number: _Optional[int] = ..., athlete: _Optional[str] = ..., names: _Optional[_Mapping[str, str]] = ..., set_mark: _Optional[str] = ..., set_rest_s: _Optional[float] = ..., set_start_s: _Optional[float] = ..., set_rep_spans_s: _Optional[_Iterable[float]] = ..., set_end_s: _Optional[float] = ..., set_ended_by: _Optional[str] = ..., set_rep_start_s: _Optional[float] = ...) -> None: ...

class CoordinateTorque(_message.Message):
    __slots__ = ("coordinate", "inverse_dynamics_nm", "model_nm", "residual_nm")
    COORDINATE_FIELD_NUMBER: _ClassVar[int]
    INVERSE_DYNAMICS_NM_FIELD_NUMBER: _ClassVar[int]
    MODEL_NM_FIELD_NUMBER: _ClassVar[int]
    RESIDUAL_NM_FIELD_NUMBER: _ClassVar[int]
    coordinate: str
    inverse_dynamics_nm: float
    model_nm: float
    residual_nm: float
    def __init__(self, coordinate: _Optional[str] = ..., inverse_dynamics_nm: _Optional[float] = ..., model_nm: _Optional[float] = ..., residual_nm: _Optional[float] = ...) -> None: ...

class ActivationFrame(_message.Message):
    __slots__ = ("time_s", "method", "groups", "activations", "forces_n", "activation_std", "torques", "solver_status", "iterations", "solve_time_s", "input_arrival_ns", "publish_ns", "flags", "phase", "measured_envelope", "exercise")
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    GROUPS_FIELD_NUMBER: _ClassVar[int]
    ACTIVATIONS_FIELD_NUMBER: _ClassVar[int]
    FORCES_N_FIELD_NUMBER: _ClassVar[int]
    ACTIVATION_STD_FIELD_NUMBER: _ClassVar[int]
    TORQUES_FIELD_NUMBER: _ClassVar[int]
    SOLVER_STATUS_FIELD_NUMBER: _ClassVar[int]
    ITERATIONS_FIELD_NUMBER: _ClassVar[int]
    SOLVE_TIME_S_FIELD_NUMBER: _ClassVar[int]
    INPUT_ARRIVAL_NS_FIELD_NUMBER: _ClassVar[int]
    PUBLISH_NS_FIELD_NUMBER: _ClassVar[int]
    FLAGS_FIELD_NUMBER: _ClassVar[int]
    PHASE_FIELD_NUMBER: _ClassVar[int]
    MEASURED_ENVELOPE_FIELD_NUMBER: _ClassVar[int]
    EXERCISE_FIELD_NUMBER: _ClassVar[int]
    time_s: float
    method: str
    groups: _containers.RepeatedScalarFieldContainer[str]
    activations: _containers.RepeatedScalarFieldContainer[float]
    forces_n: _containers.RepeatedScalarFieldContainer[float]
    activation_std: _containers.RepeatedScalarFieldContainer[float]
    torques: _containers.RepeatedCompositeFieldContainer[CoordinateTorque]
    solver_status: str
    iterations: int
    solve_time_s: float
    input_arrival_ns: int
    publish_ns: int
    flags: _containers.RepeatedScalarFieldContainer[str]
    phase: float
    measured_envelope: _containers.RepeatedScalarFieldContainer[float]
    exercise: str
    def __init__(self, time_s: _Optional[float] = ..., method: _Optional[str] = ..., groups: _Optional[_Iterable[str]] = ..., activations: _Optional[_Iterable[float]] = ..., forces_n: _Optional[_Iterable[float]] = ..., activation_std: _Optional[_Iterable[float]] = ..., torques: _Optional[_Iterable[_Union[CoordinateTorque, _Mapping]]] = ..., solver_status: _Optional[str] = ..., iterations: _Optional[int] = ..., solve_time_s: _Optional[float] = ..., input_arrival_ns: _Optional[int] = ..., publish_ns: _Optional[int] = ..., flags: _Optional[_Iterable[str]] = ..., phase: _Optional[float] = ..., measured_envelope: _Optional[_Iterable[float]] = ..., exercise: _Optional[str] = ...) -> None: ...

class EmgEnvelope(_message.Message):
    __slots__ = ("time_s", "groups", "envelope", "device_time_ns", "host_time_ns", "flags")
    TIME_S_FIELD_NUMBER: _ClassVar[int]
    GROUPS_FIELD_NUMBER: _ClassVar[int]
    ENVELOPE_FIELD_NUMBER: _ClassVar[int]
    DEVICE_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    FLAGS_FIELD_NUMBER: _ClassVar[int]
    time_s: float
    groups: _containers.RepeatedScalarFieldContainer[str]
    envelope: _containers.RepeatedScalarFieldContainer[float]
    device_time_ns: int
    host_time_ns: int
    flags: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, time_s: _Optional[float] = ..., groups: _Optional[_Iterable[str]] = ..., envelope: _Optional[_Iterable[float]] = ..., device_time_ns: _Optional[int] = ..., host_time_ns: _Optional[int] = ..., flags: _Optional[_Iterable[str]] = ...) -> None: ...

class DeviceStatus(_message.Message):
    __slots__ = ("device_id", "kind", "connected", "samples_received", "samples_lost", "errors", "last_error", "host_time_ns", "dropped", "clocks", "electrodes", "fatigue", "outages")
    DEVICE_ID_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    CONNECTED_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_RECEIVED_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_LOST_FIELD_NUMBER: _ClassVar[int]
    ERRORS_FIELD_NUMBER: _ClassVar[int]
    LAST_ERROR_FIELD_NUMBER: _ClassVar[int]
    HOST_TIME_NS_FIELD_NUMBER: _ClassVar[int]
    DROPPED_FIELD_NUMBER: _ClassVar[int]
    CLOCKS_FIELD_NUMBER: _ClassVar[int]
    ELECTRODES_FIELD_NUMBER: _ClassVar[int]
    FATIGUE_FIELD_NUMBER: _ClassVar[int]
    OUTAGES_FIELD_NUMBER: _ClassVar[int]
    device_id: str
    kind: str
    connected: bool
    samples_received: int
    samples_lost: int
    errors: int
    last_error: str
    host_time_ns: int
    dropped: _containers.RepeatedCompositeFieldContainer[InputDrop]
    clocks: _containers.RepeatedCompositeFieldContainer[ClockOffset]
    electrodes: _containers.RepeatedCompositeFieldContainer[ElectrodeQuality]
    fatigue: _containers.RepeatedCompositeFieldContainer[ElectrodeFatigue]
    outages: InputOutages
    def __init__(self, device_id: _Optional[str] = ..., kind: _Optional[str] = ..., connected: _Optional[bool] = ..., samples_received: _Optional[int] = ..., samples_lost: _Optional[int] = ..., errors: _Optional[int] = ..., last_error: _Optional[str] = ..., host_time_ns: _Optional[int] = ..., dropped: _Optional[_Iterable[_Union[InputDrop, _Mapping]]] = ..., clocks: _Optional[_Iterable[_Union[ClockOffset, _Mapping]]] = ..., electrodes: _Optional[_Iterable[_Union[ElectrodeQuality, _Mapping]]] = ..., fatigue: _Optional[_Iterable[_Union[ElectrodeFatigue, _Mapping]]] = ..., outages: _Optional[_Union[InputOutages, _Mapping]] = ...) -> None: ...

class InputOutages(_message.Message):
    __slots__ = ("count", "total_s", "longest_s", "last_start_ns", "last_end_ns", "last_keys", "silent_s", "silent_keys", "threshold_s", "missed", "recovered")
    COUNT_FIELD_NUMBER: _ClassVar[int]
    TOTAL_S_FIELD_NUMBER: _ClassVar[int]
    LONGEST_S_FIELD_NUMBER: _ClassVar[int]
    LAST_START_NS_FIELD_NUMBER: _ClassVar[int]
    LAST_END_NS_FIELD_NUMBER: _ClassVar[int]
    LAST_KEYS_FIELD_NUMBER: _ClassVar[int]
    SILENT_S_FIELD_NUMBER: _ClassVar[int]
    SILENT_KEYS_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_S_FIELD_NUMBER: _ClassVar[int]
    MISSED_FIELD_NUMBER: _ClassVar[int]
    RECOVERED_FIELD_NUMBER: _ClassVar[int]
    count: int
    total_s: float
    longest_s: float
    last_start_ns: int
    last_end_ns: int
    last_keys: _containers.RepeatedScalarFieldContainer[str]
    silent_s: float
    silent_keys: _containers.RepeatedScalarFieldContainer[str]
    threshold_s: float
    missed: int
    recovered: int
    def __init__(self, count: _Optional[int] = ..., total_s: _Optional[float] = ..., longest_s: _Optional[float] = ..., last_start_ns: _Optional[int] = ..., last_end_ns: _Optional[int] = ..., last_keys: _Optional[_Iterable[str]] = ..., silent_s: _Optional[float] = ..., silent_keys: _Optional[_Iterable[str]] = ..., threshold_s: _Optional[float] = ..., missed: _Optional[int] = ..., recovered: _Optional[int] = ...) -> None: ...

class ElectrodeFatigue(_message.Message):
    __slots__ = ("source", "channel", "group", "set_number", "median_hz", "mean_hz", "rep_end_s", "median_slope_hz_per_rep", "median_slope_se_hz_per_rep", "median_slope_pct_per_rep", "median_change_pct", "mean_slope_pct_per_rep", "mean_change_pct")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    SET_NUMBER_FIELD_NUMBER: _ClassVar[int]
    MEDIAN_HZ_FIELD_NUMBER: _ClassVar[int]
    MEAN_HZ_FIELD_NUMBER: _ClassVar[int]
    REP_END_S_FIELD_NUMBER: _ClassVar[int]
    MEDIAN_SLOPE_HZ_PER_REP_FIELD_NUMBER: _ClassVar[int]
    MEDIAN_SLOPE_SE_HZ_PER_REP_FIELD_NUMBER: _ClassVar[int]
    MEDIAN_SLOPE_PCT_PER_REP_FIELD_NUMBER: _ClassVar[int]
    MEDIAN_CHANGE_PCT_FIELD_NUMBER: _ClassVar[int]
    MEAN_SLOPE_PCT_PER_REP_FIELD_NUMBER: _ClassVar[int]
    MEAN_CHANGE_PCT_FIELD_NUMBER: _ClassVar[int]
    source: str
    channel: str
    group: str
    set_number: int
    median_hz: _containers.RepeatedScalarFieldContainer[float]
    mean_hz: _containers.RepeatedScalarFieldContainer[float]
    rep_end_s: _containers.RepeatedScalarFieldContainer[float]
    median_slope_hz_per_rep: float
    median_slope_se_hz_per_rep: float
    median_slope_pct_per_rep: float
    median_change_pct: float
    mean_slope_pct_per_rep: float
    mean_change_pct: float
    def __init__(self, source: _Optional[str] = ..., channel: _Optional[str] = ..., group: _Optional[str] = ..., set_number: _Optional[int] = ..., median_hz: _Optional[_Iterable[float]] = ..., mean_hz: _Optional[_Iterable[float]] = ..., rep_end_s: _Optional[_Iterable[float]] = ..., median_slope_hz_per_rep: _Optional[float] = ..., median_slope_se_hz_per_rep: _Optional[float] = ..., median_slope_pct_per_rep: _Optional[float] = ..., median_change_pct: _Optional[float] = ..., mean_slope_pct_per_rep: _Optional[float] = ..., mean_change_pct: _Optional[float] = ...) -> None: ...

class ElectrodeQuality(_message.Message):
    __slots__ = ("source", "channel", "group", "state", "reasons", "detail", "since_s", "check_s", "bad_s", "episodes", "episode_reasons", "recent")
    class EpisodeReasonsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    CHANNEL_FIELD_NUMBER: _ClassVar[int]
    GROUP_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    REASONS_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    SINCE_S_FIELD_NUMBER: _ClassVar[int]
    CHECK_S_FIELD_NUMBER: _ClassVar[int]
    BAD_S_FIELD_NUMBER: _ClassVar[int]
    EPISODES_FIELD_NUMBER: _ClassVar[int]
    EPISODE_REASONS_FIELD_NUMBER: _ClassVar[int]
    RECENT_FIELD_NUMBER: _ClassVar[int]
    source: str
    channel: str
    group: str
    state: str
    reasons: _containers.RepeatedScalarFieldContainer[str]
    detail: str
    since_s: float
    check_s: float
    bad_s: float
    episodes: int
    episode_reasons: _containers.ScalarMap[str, int]
    recent: _containers.RepeatedCompositeFieldContainer[FaultEpisode]
    def __init__(self, source: _Optional[str] = ..., channel: _Optional[str] = ..., group: _Optional[str] = ..., state: _Optional[str] = ..., reasons: _Optional[_Iterable[str]] = ..., detail: _Optional[str] = ..., since_s: _Optional[float] = ..., check_s: _Optional[float] = ..., bad_s: _Optional[float] = ..., episodes: _Optional[int] = ..., episode_reasons: _Optional[_Mapping[str, int]] = ..., recent: _Optional[_Iterable[_Union[FaultEpisode, _Mapping]]] = ...) -> None: ...

class FaultEpisode(_message.Message):
    __slots__ = ("start_s", "end_s", "worst", "reasons")
    START_S_FIELD_NUMBER: _ClassVar[int]
    END_S_FIELD_NUMBER: _ClassVar[int]
    WORST_FIELD_NUMBER: _ClassVar[int]
    REASONS_FIELD_NUMBER: _ClassVar[int]
    start_s: float
    end_s: float
    worst: str
    reasons: _containers.RepeatedScalarFieldContainer[str]
    def __init__(self, start_s: _Optional[float] = ..., end_s: _Optional[float] = ..., worst: _Optional[str] = ..., reasons: _Optional[_Iterable[str]] = ...) -> None: ...

class ClockOffset(_message.Message):
    __slots__ = ("source", "offset_ms", "spread_ms", "latency_ms", "method", "samples", "arrival_offset_ms", "reason", "alignments")
    SOURCE_FIELD_NUMBER: _ClassVar[int]
    OFFSET_MS_FIELD_NUMBER: _ClassVar[int]
    SPREAD_MS_FIELD_NUMBER: _ClassVar[int]
    LATENCY_MS_FIELD_NUMBER: _ClassVar[int]
    METHOD_FIELD_NUMBER: _ClassVar[int]
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    ARRIVAL_OFFSET_MS_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    ALIGNMENTS_FIELD_NUMBER: _ClassVar[int]
    source: str
    offset_ms: float
    spread_ms: float
    latency_ms: float
    method: str
    samples: int
    arrival_offset_ms: float
    reason: str
    alignments: _containers.RepeatedCompositeFieldContainer[ClockAlignment]
    def __init__(self, source: _Optional[str] = ..., offset_ms: _Optional[float] = ..., spread_ms: _Optional[float] = ..., latency_ms: _Optional[float] = ..., method: _Optional[str] = ..., samples: _Optional[int] = ..., arrival_offset_ms: _Optional[float] = ..., reason: _Optional[str] = ..., alignments: _Optional[_Iterable[_Union[ClockAlignment, _Mapping]]] = ...) -> None: ...

class ClockAlignment(_message.Message):
    __slots__ = ("reference", "status", "reason", "device_offset_ms", "spread_ms", "drift_ppm", "peak_correlation", "sensor", "windows", "host_offset_ms")
    REFERENCE_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    DEVICE_OFFSET_MS_FIELD_NUMBER: _ClassVar[int]
    SPREAD_MS_FIELD_NUMBER: _ClassVar[int]
    DRIFT_PPM_FIELD_NUMBER: _ClassVar[int]
    PEAK_CORRELATION_FIELD_NUMBER: _ClassVar[int]
    SENSOR_FIELD_NUMBER: _ClassVar[int]
    WINDOWS_FIELD_NUMBER: _ClassVar[int]
    HOST_OFFSET_MS_FIELD_NUMBER: _ClassVar[int]
    reference: str
    status: str
    reason: str
    device_offset_ms: float
    spread_ms: float
    drift_ppm: float
    peak_correlation: float
    sensor: str
    windows: int
    host_offset_ms: float
    def __init__(self, reference: _Optional[str] = ..., status: _Optional[str] = ..., reason: _Optional[str] = ..., device_offset_ms: _Optional[float] = ..., spread_ms: _Optional[float] = ..., drift_ppm: _Optional[float] = ..., peak_correlation: _Optional[float] = ..., sensor: _Optional[str] = ..., windows: _Optional[int] = ..., host_offset_ms: _Optional[float] = ...) -> None: ...

class InputDrop(_message.Message):
    __slots__ = ("key", "reason", "count")
    KEY_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    COUNT_FIELD_NUMBER: _ClassVar[int]
    key: str
    reason: str
    count: int
    def __init__(self, key: _Optional[str] = ..., reason: _Optional[str] = ..., count: _Optional[int] = ...) -> None: ...
