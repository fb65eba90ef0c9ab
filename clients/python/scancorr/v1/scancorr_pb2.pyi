from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class StreamKind(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    STREAM_KIND_UNSPECIFIED: _ClassVar[StreamKind]
    STREAM_KIND_COMMAND: _ClassVar[StreamKind]
    STREAM_KIND_SCALE: _ClassVar[StreamKind]
    STREAM_KIND_PROBE: _ClassVar[StreamKind]
    STREAM_KIND_TEMPERATURE: _ClassVar[StreamKind]
    STREAM_KIND_DISTANCE: _ClassVar[StreamKind]
    STREAM_KIND_STAGE: _ClassVar[StreamKind]

class Axis(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    AXIS_UNSPECIFIED: _ClassVar[Axis]
    AXIS_X: _ClassVar[Axis]
    AXIS_Y: _ClassVar[Axis]
    AXIS_Z: _ClassVar[Axis]

class AlarmAction(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ALARM_ACTION_UNSPECIFIED: _ClassVar[AlarmAction]
    ALARM_ACTION_FLAG: _ClassVar[AlarmAction]
    ALARM_ACTION_SUSPEND: _ClassVar[AlarmAction]
STREAM_KIND_UNSPECIFIED: StreamKind
STREAM_KIND_COMMAND: StreamKind
STREAM_KIND_SCALE: StreamKind
STREAM_KIND_PROBE: StreamKind
STREAM_KIND_TEMPERATURE: StreamKind
STREAM_KIND_DISTANCE: StreamKind
STREAM_KIND_STAGE: StreamKind
AXIS_UNSPECIFIED: Axis
AXIS_X: Axis
AXIS_Y: Axis
AXIS_Z: Axis
ALARM_ACTION_UNSPECIFIED: AlarmAction
ALARM_ACTION_FLAG: AlarmAction
ALARM_ACTION_SUSPEND: AlarmAction

class Vec3(_message.Message):
    __slots__ = ("x", "y", "z")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class CommandSample(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "x", "y", "z", "arc_cx", "arc_cy", "arc_cz", "arc_radius", "segment_id")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    ARC_CX_FIELD_NUMBER: _ClassVar[int]
    ARC_CY_FIELD_NUMBER: _ClassVar[int]
    ARC_CZ_FIELD_NUMBER: _ClassVar[int]
    ARC_RADIUS_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    x: float
    y: float
    z: float
    arc_cx: float
    arc_cy: float
    arc_cz: float
    arc_radius: float
    segment_id: int
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., arc_cx: _Optional[float] = ..., arc_cy: _Optional[float] = ..., arc_cz: _Optional[float] = ..., arc_radius: _Optional[float] = ..., segment_id: _Optional[int] = ...) -> None: ...

class CommandColumns(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "x", "y", "z", "arc_cx", "arc_cy", "arc_cz", "arc_radius", "segment_id")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    ARC_CX_FIELD_NUMBER: _ClassVar[int]
    ARC_CY_FIELD_NUMBER: _ClassVar[int]
    ARC_CZ_FIELD_NUMBER: _ClassVar[int]
    ARC_RADIUS_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: _containers.RepeatedScalarFieldContainer[int]
    t_ns: _containers.RepeatedScalarFieldContainer[int]
    x: _containers.RepeatedScalarFieldContainer[float]
    y: _containers.RepeatedScalarFieldContainer[float]
    z: _containers.RepeatedScalarFieldContainer[float]
    arc_cx: _containers.RepeatedScalarFieldContainer[float]
    arc_cy: _containers.RepeatedScalarFieldContainer[float]
    arc_cz: _containers.RepeatedScalarFieldContainer[float]
    arc_radius: _containers.RepeatedScalarFieldContainer[float]
    segment_id: _containers.RepeatedScalarFieldContainer[int]
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[_Iterable[int]] = ..., t_ns: _Optional[_Iterable[int]] = ..., x: _Optional[_Iterable[float]] = ..., y: _Optional[_Iterable[float]] = ..., z: _Optional[_Iterable[float]] = ..., arc_cx: _Optional[_Iterable[float]] = ..., arc_cy: _Optional[_Iterable[float]] = ..., arc_cz: _Optional[_Iterable[float]] = ..., arc_radius: _Optional[_Iterable[float]] = ..., segment_id: _Optional[_Iterable[int]] = ...) -> None: ...

class CommandBatch(_message.Message):
    __slots__ = ("samples", "stream", "columns")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    STREAM_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[CommandSample]
    stream: StreamKind
    columns: CommandColumns
    def __init__(self, samples: _Optional[_Iterable[_Union[CommandSample, _Mapping]]] = ..., stream: _Optional[_Union[StreamKind, str]] = ..., columns: _Optional[_Union[CommandColumns, _Mapping]] = ...) -> None: ...

class ScaleSample(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "x", "y", "z")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    x: float
    y: float
    z: float
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ...) -> None: ...

class ScaleColumns(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "x", "y", "z")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: _containers.RepeatedScalarFieldContainer[int]
    t_ns: _containers.RepeatedScalarFieldContainer[int]
    x: _containers.RepeatedScalarFieldContainer[float]
    y: _containers.RepeatedScalarFieldContainer[float]
    z: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[_Iterable[int]] = ..., t_ns: _Optional[_Iterable[int]] = ..., x: _Optional[_Iterable[float]] = ..., y: _Optional[_Iterable[float]] = ..., z: _Optional[_Iterable[float]] = ...) -> None: ...

class ScaleBatch(_message.Message):
    __slots__ = ("samples", "stream", "columns")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    STREAM_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[ScaleSample]
    stream: StreamKind
    columns: ScaleColumns
    def __init__(self, samples: _Optional[_Iterable[_Union[ScaleSample, _Mapping]]] = ..., stream: _Optional[_Union[StreamKind, str]] = ..., columns: _Optional[_Union[ScaleColumns, _Mapping]] = ...) -> None: ...

class ProbeSample(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "u", "v", "w", "tip_id", "head_a1_deg", "head_a2_deg", "force_n")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    U_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    W_FIELD_NUMBER: _ClassVar[int]
    TIP_ID_FIELD_NUMBER: _ClassVar[int]
    HEAD_A1_DEG_FIELD_NUMBER: _ClassVar[int]
    HEAD_A2_DEG_FIELD_NUMBER: _ClassVar[int]
    FORCE_N_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    u: float
    v: float
    w: float
    tip_id: int
    head_a1_deg: float
    head_a2_deg: float
    force_n: float
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., u: _Optional[float] = ..., v: _Optional[float] = ..., w: _Optional[float] = ..., tip_id: _Optional[int] = ..., head_a1_deg: _Optional[float] = ..., head_a2_deg: _Optional[float] = ..., force_n: _Optional[float] = ...) -> None: ...

class ProbeColumns(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "u", "v", "w", "tip_id", "head_a1_deg", "head_a2_deg", "force_n")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    U_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    W_FIELD_NUMBER: _ClassVar[int]
    TIP_ID_FIELD_NUMBER: _ClassVar[int]
    HEAD_A1_DEG_FIELD_NUMBER: _ClassVar[int]
    HEAD_A2_DEG_FIELD_NUMBER: _ClassVar[int]
    FORCE_N_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: _containers.RepeatedScalarFieldContainer[int]
    t_ns: _containers.RepeatedScalarFieldContainer[int]
    u: _containers.RepeatedScalarFieldContainer[float]
    v: _containers.RepeatedScalarFieldContainer[float]
    w: _containers.RepeatedScalarFieldContainer[float]
    tip_id: _containers.RepeatedScalarFieldContainer[int]
    head_a1_deg: _containers.RepeatedScalarFieldContainer[float]
    head_a2_deg: _containers.RepeatedScalarFieldContainer[float]
    force_n: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[_Iterable[int]] = ..., t_ns: _Optional[_Iterable[int]] = ..., u: _Optional[_Iterable[float]] = ..., v: _Optional[_Iterable[float]] = ..., w: _Optional[_Iterable[float]] = ..., tip_id: _Optional[_Iterable[int]] = ..., head_a1_deg: _Optional[_Iterable[float]] = ..., head_a2_deg: _Optional[_Iterable[float]] = ..., force_n: _Optional[_Iterable[float]] = ...) -> None: ...

class ProbeBatch(_message.Message):
    __slots__ = ("samples", "stream", "columns")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    STREAM_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[ProbeSample]
    stream: StreamKind
    columns: ProbeColumns
    def __init__(self, samples: _Optional[_Iterable[_Union[ProbeSample, _Mapping]]] = ..., stream: _Optional[_Union[StreamKind, str]] = ..., columns: _Optional[_Union[ProbeColumns, _Mapping]] = ...) -> None: ...

class TemperatureSample(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "sensor", "celsius")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    SENSOR_FIELD_NUMBER: _ClassVar[int]
    CELSIUS_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    sensor: str
    celsius: float
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., sensor: _Optional[str] = ..., celsius: _Optional[float] = ...) -> None: ...

class TemperatureColumns(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "sensor", "celsius")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    SENSOR_FIELD_NUMBER: _ClassVar[int]
    CELSIUS_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: _containers.RepeatedScalarFieldContainer[int]
    t_ns: _containers.RepeatedScalarFieldContainer[int]
    sensor: _containers.RepeatedScalarFieldContainer[str]
    celsius: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[_Iterable[int]] = ..., t_ns: _Optional[_Iterable[int]] = ..., sensor: _Optional[_Iterable[str]] = ..., celsius: _Optional[_Iterable[float]] = ...) -> None: ...

class TemperatureBatch(_message.Message):
    __slots__ = ("samples", "stream", "columns")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    STREAM_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[TemperatureSample]
    stream: StreamKind
    columns: TemperatureColumns
    def __init__(self, samples: _Optional[_Iterable[_Union[TemperatureSample, _Mapping]]] = ..., stream: _Optional[_Union[StreamKind, str]] = ..., columns: _Optional[_Union[TemperatureColumns, _Mapping]] = ...) -> None: ...

class DistanceSample(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "probe_id", "distance_mm", "spacing_mm")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    PROBE_ID_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_MM_FIELD_NUMBER: _ClassVar[int]
    SPACING_MM_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    probe_id: int
    distance_mm: float
    spacing_mm: float
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., probe_id: _Optional[int] = ..., distance_mm: _Optional[float] = ..., spacing_mm: _Optional[float] = ...) -> None: ...

class DistanceBatch(_message.Message):
    __slots__ = ("samples", "stream")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    STREAM_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[DistanceSample]
    stream: StreamKind
    def __init__(self, samples: _Optional[_Iterable[_Union[DistanceSample, _Mapping]]] = ..., stream: _Optional[_Union[StreamKind, str]] = ...) -> None: ...

class StageSample(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "commanded_mm", "sensor_mm", "probe_id")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    COMMANDED_MM_FIELD_NUMBER: _ClassVar[int]
    SENSOR_MM_FIELD_NUMBER: _ClassVar[int]
    PROBE_ID_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    commanded_mm: float
    sensor_mm: float
    probe_id: int
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., commanded_mm: _Optional[float] = ..., sensor_mm: _Optional[float] = ..., probe_id: _Optional[int] = ...) -> None: ...

class StageBatch(_message.Message):
    __slots__ = ("samples", "stream")
    SAMPLES_FIELD_NUMBER: _ClassVar[int]
    STREAM_FIELD_NUMBER: _ClassVar[int]
    samples: _containers.RepeatedCompositeFieldContainer[StageSample]
    stream: StreamKind
    def __init__(self, samples: _Optional[_Iterable[_Union[StageSample, _Mapping]]] = ..., stream: _Optional[_Union[StreamKind, str]] = ...) -> None: ...

class Correction(_message.Message):
    __slots__ = ("effect", "dx", "dy", "dz")
    EFFECT_FIELD_NUMBER: _ClassVar[int]
    DX_FIELD_NUMBER: _ClassVar[int]
    DY_FIELD_NUMBER: _ClassVar[int]
    DZ_FIELD_NUMBER: _ClassVar[int]
    effect: str
    dx: float
    dy: float
    dz: float
    def __init__(self, effect: _Optional[str] = ..., dx: _Optional[float] = ..., dy: _Optional[float] = ..., dz: _Optional[float] = ...) -> None: ...

class CorrectedPoint(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "sample_seq", "surface", "tip_center", "normal", "corrections", "calibration_version", "estimator_valid", "segment_id", "tip_id")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_SEQ_FIELD_NUMBER: _ClassVar[int]
    SURFACE_FIELD_NUMBER: _ClassVar[int]
    TIP_CENTER_FIELD_NUMBER: _ClassVar[int]
    NORMAL_FIELD_NUMBER: _ClassVar[int]
    CORRECTIONS_FIELD_NUMBER: _ClassVar[int]
    CALIBRATION_VERSION_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_VALID_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    TIP_ID_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    sample_seq: int
    surface: Vec3
    tip_center: Vec3
    normal: Vec3
    corrections: _containers.RepeatedCompositeFieldContainer[Correction]
    calibration_version: int
    estimator_valid: bool
    segment_id: int
    tip_id: int
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., sample_seq: _Optional[int] = ..., surface: _Optional[_Union[Vec3, _Mapping]] = ..., tip_center: _Optional[_Union[Vec3, _Mapping]] = ..., normal: _Optional[_Union[Vec3, _Mapping]] = ..., corrections: _Optional[_Iterable[_Union[Correction, _Mapping]]] = ..., calibration_version: _Optional[int] = ..., estimator_valid: _Optional[bool] = ..., segment_id: _Optional[int] = ..., tip_id: _Optional[int] = ...) -> None: ...

class CorrectedPointColumns(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "sample_seq", "calibration_version", "estimator_valid", "segment_id", "tip_id", "surface_x", "surface_y", "surface_z", "tip_center_x", "tip_center_y", "tip_center_z", "normal_x", "normal_y", "normal_z", "effects", "correction_dx", "correction_dy", "correction_dz")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    SAMPLE_SEQ_FIELD_NUMBER: _ClassVar[int]
    CALIBRATION_VERSION_FIELD_NUMBER: _ClassVar[int]
    ESTIMATOR_VALID_FIELD_NUMBER: _ClassVar[int]
    SEGMENT_ID_FIELD_NUMBER: _ClassVar[int]
    TIP_ID_FIELD_NUMBER: _ClassVar[int]
    SURFACE_X_FIELD_NUMBER: _ClassVar[int]
    SURFACE_Y_FIELD_NUMBER: _ClassVar[int]
    SURFACE_Z_FIELD_NUMBER: _ClassVar[int]
    TIP_CENTER_X_FIELD_NUMBER: _ClassVar[int]
    TIP_CENTER_Y_FIELD_NUMBER: _ClassVar[int]
    TIP_CENTER_Z_FIELD_NUMBER: _ClassVar[int]
    NORMAL_X_FIELD_NUMBER: _ClassVar[int]
    NORMAL_Y_FIELD_NUMBER: _ClassVar[int]
    NORMAL_Z_FIELD_NUMBER: _ClassVar[int]
    EFFECTS_FIELD_NUMBER: _ClassVar[int]
    CORRECTION_DX_FIELD_NUMBER: _ClassVar[int]
    CORRECTION_DY_FIELD_NUMBER: _ClassVar[int]
    CORRECTION_DZ_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: _containers.RepeatedScalarFieldContainer[int]
    t_ns: _containers.RepeatedScalarFieldContainer[int]
    sample_seq: _containers.RepeatedScalarFieldContainer[int]
    calibration_version: _containers.RepeatedScalarFieldContainer[int]
    estimator_valid: _containers.RepeatedScalarFieldContainer[bool]
    segment_id: _containers.RepeatedScalarFieldContainer[int]
    tip_id: _containers.RepeatedScalarFieldContainer[int]
    surface_x: _containers.RepeatedScalarFieldContainer[float]
    surface_y: _containers.RepeatedScalarFieldContainer[float]
    surface_z: _containers.RepeatedScalarFieldContainer[float]
    tip_center_x: _containers.RepeatedScalarFieldContainer[float]
    tip_center_y: _containers.RepeatedScalarFieldContainer[float]
    tip_center_z: _containers.RepeatedScalarFieldContainer[float]
    normal_x: _containers.RepeatedScalarFieldContainer[float]
    normal_y: _containers.RepeatedScalarFieldContainer[float]
    normal_z: _containers.RepeatedScalarFieldContainer[float]
    effects: _containers.RepeatedScalarFieldContainer[str]
    correction_dx: _containers.RepeatedScalarFieldContainer[float]
    correction_dy: _containers.RepeatedScalarFieldContainer[float]
    correction_dz: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[_Iterable[int]] = ..., t_ns: _Optional[_Iterable[int]] = ..., sample_seq: _Optional[_Iterable[int]] = ..., calibration_version: _Optional[_Iterable[int]] = ..., estimator_valid: _Optional[_Iterable[bool]] = ..., segment_id: _Optional[_Iterable[int]] = ..., tip_id: _Optional[_Iterable[int]] = ..., surface_x: _Optional[_Iterable[float]] = ..., surface_y: _Optional[_Iterable[float]] = ..., surface_z: _Optional[_Iterable[float]] = ..., tip_center_x: _Optional[_Iterable[float]] = ..., tip_center_y: _Optional[_Iterable[float]] = ..., tip_center_z: _Optional[_Iterable[float]] = ..., normal_x: _Optional[_Iterable[float]] = ..., normal_y: _Optional[_Iterable[float]] = ..., normal_z: _Optional[_Iterable[float]] = ..., effects: _Optional[_Iterable[str]] = ..., correction_dx: _Optional[_Iterable[float]] = ..., correction_dy: _Optional[_Iterable[float]] = ..., correction_dz: _Optional[_Iterable[float]] = ...) -> None: ...

class CorrectedPointBatch(_message.Message):
    __slots__ = ("points", "columns")
    POINTS_FIELD_NUMBER: _ClassVar[int]
    COLUMNS_FIELD_NUMBER: _ClassVar[int]
    points: _containers.RepeatedCompositeFieldContainer[CorrectedPoint]
    columns: _containers.RepeatedCompositeFieldContainer[CorrectedPointColumns]
    def __init__(self, points: _Optional[_Iterable[_Union[CorrectedPoint, _Mapping]]] = ..., columns: _Optional[_Iterable[_Union[CorrectedPointColumns, _Mapping]]] = ...) -> None: ...

class EstimatorAlarm(_message.Message):
    __slots__ = ("machine_id", "seq", "t_ns", "raised", "axis", "estimated_accel", "measured_accel", "difference", "threshold", "action", "calibration_version")
    MACHINE_ID_FIELD_NUMBER: _ClassVar[int]
    SEQ_FIELD_NUMBER: _ClassVar[int]
    T_NS_FIELD_NUMBER: _ClassVar[int]
    RAISED_FIELD_NUMBER: _ClassVar[int]
    AXIS_FIELD_NUMBER: _ClassVar[int]
    ESTIMATED_ACCEL_FIELD_NUMBER: _ClassVar[int]
    MEASURED_ACCEL_FIELD_NUMBER: _ClassVar[int]
    DIFFERENCE_FIELD_NUMBER: _ClassVar[int]
    THRESHOLD_FIELD_NUMBER: _ClassVar[int]
    ACTION_FIELD_NUMBER: _ClassVar[int]
    CALIBRATION_VERSION_FIELD_NUMBER: _ClassVar[int]
    machine_id: str
    seq: int
    t_ns: int
    raised: bool
    axis: Axis
    estimated_accel: float
    measured_accel: float
    difference: float
    threshold: float
    action: AlarmAction
    calibration_version: int
    def __init__(self, machine_id: _Optional[str] = ..., seq: _Optional[int] = ..., t_ns: _Optional[int] = ..., raised: _Optional[bool] = ..., axis: _Optional[_Union[Axis, str]] = ..., estimated_accel: _Optional[float] = ..., measured_accel: _Optional[float] = ..., difference: _Optional[float] = ..., threshold: _Optional[float] = ..., action: _Optional[_Union[AlarmAction, str]] = ..., calibration_version: _Optional[int] = ...) -> None: ...
