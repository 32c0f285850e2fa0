from google.protobuf.internal import containers as _containers
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class SlamAvatarInfo(_message.Message):
    __slots__ = ("name", "kind", "x", "y", "theta", "drift_linear", "drift_angular", "drift_inflate", "radius")
    NAME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    DRIFT_LINEAR_FIELD_NUMBER: _ClassVar[int]
    DRIFT_ANGULAR_FIELD_NUMBER: _ClassVar[int]
    DRIFT_INFLATE_FIELD_NUMBER: _ClassVar[int]
    RADIUS_FIELD_NUMBER: _ClassVar[int]
    name: str
    kind: str
    x: float
    y: float
    theta: float
    drift_linear: float
    drift_angular: float
    drift_inflate: float
    radius: float
    def __init__(self, name: _Optional[str] = ..., kind: _Optional[str] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., theta: _Optional[float] = ..., drift_linear: _Optional[float] = ..., drift_angular: _Optional[float] = ..., drift_inflate: _Optional[float] = ..., radius: _Optional[float] = ...) -> None: ...

class SlamLandmarkTruth(_message.Message):
    __slots__ = ("id", "x", "y")
    ID_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    id: int
    x: float
    y: float
    def __init__(self, id: _Optional[int] = ..., x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

class SlamRunInfo(_message.Message):
    __slots__ = ("arena", "team", "seed", "x0", "y0", "width", "height", "resolution", "avatars", "landmarks", "duration", "driver", "landmark_range_frac", "landmark_sigma_bearing", "sonar_mount_radius")
    ARENA_FIELD_NUMBER: _ClassVar[int]
    TEAM_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    X0_FIELD_NUMBER: _ClassVar[int]
    Y0_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    AVATARS_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    DURATION_FIELD_NUMBER: _ClassVar[int]
    DRIVER_FIELD_NUMBER: _ClassVar[int]
    LANDMARK_RANGE_FRAC_FIELD_NUMBER: _ClassVar[int]
    LANDMARK_SIGMA_BEARING_FIELD_NUMBER: _ClassVar[int]
    SONAR_MOUNT_RADIUS_FIELD_NUMBER: _ClassVar[int]
    arena: str
    team: str
    seed: int
    x0: float
    y0: float
    width: float
    height: float
    resolution: float
    avatars: _containers.RepeatedCompositeFieldContainer[SlamAvatarInfo]
    landmarks: _containers.RepeatedCompositeFieldContainer[SlamLandmarkTruth]
    duration: float
    driver: str
    landmark_range_frac: float
    landmark_sigma_bearing: float
    sonar_mount_radius: float
    def __init__(self, arena: _Optional[str] = ..., team: _Optional[str] = ..., seed: _Optional[int] = ..., x0: _Optional[float] = ..., y0: _Optional[float] = ..., width: _Optional[float] = ..., height: _Optional[float] = ..., resolution: _Optional[float] = ..., avatars: _Optional[_Iterable[_Union[SlamAvatarInfo, _Mapping]]] = ..., landmarks: _Optional[_Iterable[_Union[SlamLandmarkTruth, _Mapping]]] = ..., duration: _Optional[float] = ..., driver: _Optional[str] = ..., landmark_range_frac: _Optional[float] = ..., landmark_sigma_bearing: _Optional[float] = ..., sonar_mount_radius: _Optional[float] = ...) -> None: ...

class SlamPrediction(_message.Message):
    __slots__ = ("avatar", "t", "vx", "vy", "omega", "sigma_xy", "sigma_theta")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    VX_FIELD_NUMBER: _ClassVar[int]
    VY_FIELD_NUMBER: _ClassVar[int]
    OMEGA_FIELD_NUMBER: _ClassVar[int]
    SIGMA_XY_FIELD_NUMBER: _ClassVar[int]
    SIGMA_THETA_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    vx: float
    vy: float
    omega: float
    sigma_xy: float
    sigma_theta: float
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., vx: _Optional[float] = ..., vy: _Optional[float] = ..., omega: _Optional[float] = ..., sigma_xy: _Optional[float] = ..., sigma_theta: _Optional[float] = ...) -> None: ...

class SlamPose(_message.Message):
    __slots__ = ("avatar", "t", "x", "y", "theta")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    x: float
    y: float
    theta: float
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., x: _Optional[float] = ..., y: _Optional[float] = ..., theta: _Optional[float] = ...) -> None: ...

class SlamEcho(_message.Message):
    __slots__ = ("bearing", "range")
    BEARING_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    bearing: float
    range: float
    def __init__(self, bearing: _Optional[float] = ..., range: _Optional[float] = ...) -> None: ...

class SlamSonar(_message.Message):
    __slots__ = ("avatar", "t", "echoes", "fov", "max_range")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    ECHOES_FIELD_NUMBER: _ClassVar[int]
    FOV_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    echoes: _containers.RepeatedCompositeFieldContainer[SlamEcho]
    fov: float
    max_range: float
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., echoes: _Optional[_Iterable[_Union[SlamEcho, _Mapping]]] = ..., fov: _Optional[float] = ..., max_range: _Optional[float] = ...) -> None: ...

class SlamSighting(_message.Message):
    __slots__ = ("landmark_id", "range", "bearing")
    LANDMARK_ID_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    BEARING_FIELD_NUMBER: _ClassVar[int]
    landmark_id: int
    range: float
    bearing: float
    def __init__(self, landmark_id: _Optional[int] = ..., range: _Optional[float] = ..., bearing: _Optional[float] = ...) -> None: ...

class SlamLandmark(_message.Message):
    __slots__ = ("avatar", "t", "sightings")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    SIGHTINGS_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    sightings: _containers.RepeatedCompositeFieldContainer[SlamSighting]
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., sightings: _Optional[_Iterable[_Union[SlamSighting, _Mapping]]] = ...) -> None: ...

class SlamRangeBearing(_message.Message):
    __slots__ = ("range", "bearing")
    RANGE_FIELD_NUMBER: _ClassVar[int]
    BEARING_FIELD_NUMBER: _ClassVar[int]
    range: float
    bearing: float
    def __init__(self, range: _Optional[float] = ..., bearing: _Optional[float] = ...) -> None: ...

class SlamCollectables(_message.Message):
    __slots__ = ("avatar", "t", "sightings")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    SIGHTINGS_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    sightings: _containers.RepeatedCompositeFieldContainer[SlamRangeBearing]
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., sightings: _Optional[_Iterable[_Union[SlamRangeBearing, _Mapping]]] = ...) -> None: ...

class SlamCooccupancy(_message.Message):
    __slots__ = ("avatar", "t", "radius")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    RADIUS_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    radius: float
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., radius: _Optional[float] = ...) -> None: ...

class SlamFloor(_message.Message):
    __slots__ = ("avatar", "t", "xs", "ys", "occupied")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T_FIELD_NUMBER: _ClassVar[int]
    XS_FIELD_NUMBER: _ClassVar[int]
    YS_FIELD_NUMBER: _ClassVar[int]
    OCCUPIED_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    t: float
    xs: _containers.RepeatedScalarFieldContainer[float]
    ys: _containers.RepeatedScalarFieldContainer[float]
    occupied: _containers.RepeatedScalarFieldContainer[bool]
    def __init__(self, avatar: _Optional[str] = ..., t: _Optional[float] = ..., xs: _Optional[_Iterable[float]] = ..., ys: _Optional[_Iterable[float]] = ..., occupied: _Optional[_Iterable[bool]] = ...) -> None: ...

class SlamGrid(_message.Message):
    __slots__ = ("rows", "cols", "resolution", "x0", "y0", "p", "region")
    ROWS_FIELD_NUMBER: _ClassVar[int]
    COLS_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    X0_FIELD_NUMBER: _ClassVar[int]
    Y0_FIELD_NUMBER: _ClassVar[int]
    P_FIELD_NUMBER: _ClassVar[int]
    REGION_FIELD_NUMBER: _ClassVar[int]
    rows: int
    cols: int
    resolution: float
    x0: float
    y0: float
    p: _containers.RepeatedScalarFieldContainer[float]
    region: _containers.RepeatedScalarFieldContainer[bool]
    def __init__(self, rows: _Optional[int] = ..., cols: _Optional[int] = ..., resolution: _Optional[float] = ..., x0: _Optional[float] = ..., y0: _Optional[float] = ..., p: _Optional[_Iterable[float]] = ..., region: _Optional[_Iterable[bool]] = ...) -> None: ...

class SlamAddAvatar(_message.Message):
    __slots__ = ("avatar", "t0")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    T0_FIELD_NUMBER: _ClassVar[int]
    avatar: SlamAvatarInfo
    t0: float
    def __init__(self, avatar: _Optional[_Union[SlamAvatarInfo, _Mapping]] = ..., t0: _Optional[float] = ...) -> None: ...

class SlamObserve(_message.Message):
    __slots__ = ("sonar", "landmark", "cooccupancy", "floor", "collectables", "processor")
    SONAR_FIELD_NUMBER: _ClassVar[int]
    LANDMARK_FIELD_NUMBER: _ClassVar[int]
    COOCCUPANCY_FIELD_NUMBER: _ClassVar[int]
    FLOOR_FIELD_NUMBER: _ClassVar[int]
    COLLECTABLES_FIELD_NUMBER: _ClassVar[int]
    PROCESSOR_FIELD_NUMBER: _ClassVar[int]
    sonar: SlamSonar
    landmark: SlamLandmark
    cooccupancy: SlamCooccupancy
    floor: SlamFloor
    collectables: SlamCollectables
    processor: str
    def __init__(self, sonar: _Optional[_Union[SlamSonar, _Mapping]] = ..., landmark: _Optional[_Union[SlamLandmark, _Mapping]] = ..., cooccupancy: _Optional[_Union[SlamCooccupancy, _Mapping]] = ..., floor: _Optional[_Union[SlamFloor, _Mapping]] = ..., collectables: _Optional[_Union[SlamCollectables, _Mapping]] = ..., processor: _Optional[str] = ...) -> None: ...

class SlamRequest(_message.Message):
    __slots__ = ("avatar",)
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    avatar: str
    def __init__(self, avatar: _Optional[str] = ...) -> None: ...

class SlamRemoveAvatar(_message.Message):
    __slots__ = ("name",)
    NAME_FIELD_NUMBER: _ClassVar[int]
    name: str
    def __init__(self, name: _Optional[str] = ...) -> None: ...

class SlamEvent(_message.Message):
    __slots__ = ("add_avatar", "predict", "observe", "request", "remove_avatar")
    ADD_AVATAR_FIELD_NUMBER: _ClassVar[int]
    PREDICT_FIELD_NUMBER: _ClassVar[int]
    OBSERVE_FIELD_NUMBER: _ClassVar[int]
    REQUEST_FIELD_NUMBER: _ClassVar[int]
    REMOVE_AVATAR_FIELD_NUMBER: _ClassVar[int]
    add_avatar: SlamAddAvatar
    predict: SlamPrediction
    observe: SlamObserve
    request: SlamRequest
    remove_avatar: SlamRemoveAvatar
    def __init__(self, add_avatar: _Optional[_Union[SlamAddAvatar, _Mapping]] = ..., predict: _Optional[_Union[SlamPrediction, _Mapping]] = ..., observe: _Optional[_Union[SlamObserve, _Mapping]] = ..., request: _Optional[_Union[SlamRequest, _Mapping]] = ..., remove_avatar: _Optional[_Union[SlamRemoveAvatar, _Mapping]] = ...) -> None: ...
