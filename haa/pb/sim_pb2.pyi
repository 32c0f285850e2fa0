from google.protobuf.internal import containers as _containers
from google.protobuf.internal import enum_type_wrapper as _enum_type_wrapper
from google.protobuf import descriptor as _descriptor
from google.protobuf import message as _message
from collections.abc import Iterable as _Iterable, Mapping as _Mapping
from typing import ClassVar as _ClassVar, Optional as _Optional, Union as _Union

DESCRIPTOR: _descriptor.FileDescriptor

class ImageEncoding(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    IMAGE_ENCODING_RAW_RGB: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_PNG: _ClassVar[ImageEncoding]
    IMAGE_ENCODING_JPEG: _ClassVar[ImageEncoding]

class ActionStatus(int, metaclass=_enum_type_wrapper.EnumTypeWrapper):
    __slots__ = ()
    ACTION_STATUS_UNSPECIFIED: _ClassVar[ActionStatus]
    ACTION_STATUS_RUNNING: _ClassVar[ActionStatus]
    ACTION_STATUS_SUCCEEDED: _ClassVar[ActionStatus]
    ACTION_STATUS_FAILED: _ClassVar[ActionStatus]
    ACTION_STATUS_CANCELLED: _ClassVar[ActionStatus]
IMAGE_ENCODING_RAW_RGB: ImageEncoding
IMAGE_ENCODING_PNG: ImageEncoding
IMAGE_ENCODING_JPEG: ImageEncoding
ACTION_STATUS_UNSPECIFIED: ActionStatus
ACTION_STATUS_RUNNING: ActionStatus
ACTION_STATUS_SUCCEEDED: ActionStatus
ACTION_STATUS_FAILED: ActionStatus
ACTION_STATUS_CANCELLED: ActionStatus

class Pose(_message.Message):
    __slots__ = ("x", "y", "theta")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    theta: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., theta: _Optional[float] = ...) -> None: ...

class Point(_message.Message):
    __slots__ = ("x", "y")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ...) -> None: ...

class AvatarRef(_message.Message):
    __slots__ = ("avatar_id",)
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    def __init__(self, avatar_id: _Optional[str] = ...) -> None: ...

class CameraInfo(_message.Message):
    __slots__ = ("name", "fov", "max_range", "noise_sigma", "width", "height", "K", "mount")
    NAME_FIELD_NUMBER: _ClassVar[int]
    FOV_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    NOISE_SIGMA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    MOUNT_FIELD_NUMBER: _ClassVar[int]
    name: str
    fov: float
    max_range: float
    noise_sigma: float
    width: int
    height: int
    K: _containers.RepeatedScalarFieldContainer[float]
    mount: Mount
    def __init__(self, name: _Optional[str] = ..., fov: _Optional[float] = ..., max_range: _Optional[float] = ..., noise_sigma: _Optional[float] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., K: _Optional[_Iterable[float]] = ..., mount: _Optional[_Union[Mount, _Mapping]] = ...) -> None: ...

class Mount(_message.Message):
    __slots__ = ("x", "y", "z", "pitch")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    Z_FIELD_NUMBER: _ClassVar[int]
    PITCH_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    z: float
    pitch: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., z: _Optional[float] = ..., pitch: _Optional[float] = ...) -> None: ...

class AvatarInfo(_message.Message):
    __slots__ = ("avatar_id", "type", "status", "max_speed", "max_turn", "radius", "capacity", "sonars", "linear_drift", "angular_drift", "camera", "start_pose", "joined", "sonar_bearings", "sonar_fov", "sonar_range", "sonar_period")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    MAX_SPEED_FIELD_NUMBER: _ClassVar[int]
    MAX_TURN_FIELD_NUMBER: _ClassVar[int]
    RADIUS_FIELD_NUMBER: _ClassVar[int]
    CAPACITY_FIELD_NUMBER: _ClassVar[int]
    SONARS_FIELD_NUMBER: _ClassVar[int]
    LINEAR_DRIFT_FIELD_NUMBER: _ClassVar[int]
    ANGULAR_DRIFT_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    START_POSE_FIELD_NUMBER: _ClassVar[int]
    JOINED_FIELD_NUMBER: _ClassVar[int]
    SONAR_BEARINGS_FIELD_NUMBER: _ClassVar[int]
    SONAR_FOV_FIELD_NUMBER: _ClassVar[int]
    SONAR_RANGE_FIELD_NUMBER: _ClassVar[int]
    SONAR_PERIOD_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    type: str
    status: str
    max_speed: float
    max_turn: float
    radius: float
    capacity: int
    sonars: int
    linear_drift: float
    angular_drift: float
    camera: CameraInfo
    start_pose: Pose
    joined: float
    sonar_bearings: _containers.RepeatedScalarFieldContainer[float]
    sonar_fov: float
    sonar_range: float
    sonar_period: float
    def __init__(self, avatar_id: _Optional[str] = ..., type: _Optional[str] = ..., status: _Optional[str] = ..., max_speed: _Optional[float] = ..., max_turn: _Optional[float] = ..., radius: _Optional[float] = ..., capacity: _Optional[int] = ..., sonars: _Optional[int] = ..., linear_drift: _Optional[float] = ..., angular_drift: _Optional[float] = ..., camera: _Optional[_Union[CameraInfo, _Mapping]] = ..., start_pose: _Optional[_Union[Pose, _Mapping]] = ..., joined: _Optional[float] = ..., sonar_bearings: _Optional[_Iterable[float]] = ..., sonar_fov: _Optional[float] = ..., sonar_range: _Optional[float] = ..., sonar_period: _Optional[float] = ...) -> None: ...

class RegisterRequest(_message.Message):
    __slots__ = ("type", "avatar_id", "pose", "start_index")
    TYPE_FIELD_NUMBER: _ClassVar[int]
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    START_INDEX_FIELD_NUMBER: _ClassVar[int]
    type: str
    avatar_id: str
    pose: Pose
    start_index: int
    def __init__(self, type: _Optional[str] = ..., avatar_id: _Optional[str] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., start_index: _Optional[int] = ...) -> None: ...

class RegisterReply(_message.Message):
    __slots__ = ("avatar", "attached")
    AVATAR_FIELD_NUMBER: _ClassVar[int]
    ATTACHED_FIELD_NUMBER: _ClassVar[int]
    avatar: AvatarInfo
    attached: bool
    def __init__(self, avatar: _Optional[_Union[AvatarInfo, _Mapping]] = ..., attached: _Optional[bool] = ...) -> None: ...

class Wait(_message.Message):
    __slots__ = ("duration",)
    DURATION_FIELD_NUMBER: _ClassVar[int]
    duration: float
    def __init__(self, duration: _Optional[float] = ...) -> None: ...

class MoveTo(_message.Message):
    __slots__ = ("x", "y", "theta", "speed", "tolerance")
    X_FIELD_NUMBER: _ClassVar[int]
    Y_FIELD_NUMBER: _ClassVar[int]
    THETA_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    TOLERANCE_FIELD_NUMBER: _ClassVar[int]
    x: float
    y: float
    theta: float
    speed: float
    tolerance: float
    def __init__(self, x: _Optional[float] = ..., y: _Optional[float] = ..., theta: _Optional[float] = ..., speed: _Optional[float] = ..., tolerance: _Optional[float] = ...) -> None: ...

class MoveBy(_message.Message):
    __slots__ = ("distance", "speed")
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    distance: float
    speed: float
    def __init__(self, distance: _Optional[float] = ..., speed: _Optional[float] = ...) -> None: ...

class Velocity(_message.Message):
    __slots__ = ("v", "omega", "duration")
    V_FIELD_NUMBER: _ClassVar[int]
    OMEGA_FIELD_NUMBER: _ClassVar[int]
    DURATION_FIELD_NUMBER: _ClassVar[int]
    v: float
    omega: float
    duration: float
    def __init__(self, v: _Optional[float] = ..., omega: _Optional[float] = ..., duration: _Optional[float] = ...) -> None: ...

class Rotate(_message.Message):
    __slots__ = ("angle", "absolute", "speed")
    ANGLE_FIELD_NUMBER: _ClassVar[int]
    ABSOLUTE_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    angle: float
    absolute: bool
    speed: float
    def __init__(self, angle: _Optional[float] = ..., absolute: _Optional[bool] = ..., speed: _Optional[float] = ...) -> None: ...

class CaptureAction(_message.Message):
    __slots__ = ("encoding",)
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    encoding: ImageEncoding
    def __init__(self, encoding: _Optional[_Union[ImageEncoding, str]] = ...) -> None: ...

class PickUp(_message.Message):
    __slots__ = ("collectable_id",)
    COLLECTABLE_ID_FIELD_NUMBER: _ClassVar[int]
    collectable_id: str
    def __init__(self, collectable_id: _Optional[str] = ...) -> None: ...

class Drop(_message.Message):
    __slots__ = ("collectable_id",)
    COLLECTABLE_ID_FIELD_NUMBER: _ClassVar[int]
    collectable_id: str
    def __init__(self, collectable_id: _Optional[str] = ...) -> None: ...

class ActionRequest(_message.Message):
    __slots__ = ("avatar_id", "wait", "move_to", "move_by", "velocity", "rotate", "capture", "pick_up", "drop", "progress_period")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    WAIT_FIELD_NUMBER: _ClassVar[int]
    MOVE_TO_FIELD_NUMBER: _ClassVar[int]
    MOVE_BY_FIELD_NUMBER: _ClassVar[int]
    VELOCITY_FIELD_NUMBER: _ClassVar[int]
    ROTATE_FIELD_NUMBER: _ClassVar[int]
    CAPTURE_FIELD_NUMBER: _ClassVar[int]
    PICK_UP_FIELD_NUMBER: _ClassVar[int]
    DROP_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_PERIOD_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    wait: Wait
    move_to: MoveTo
    move_by: MoveBy
    velocity: Velocity
    rotate: Rotate
    capture: CaptureAction
    pick_up: PickUp
    drop: Drop
    progress_period: float
    def __init__(self, avatar_id: _Optional[str] = ..., wait: _Optional[_Union[Wait, _Mapping]] = ..., move_to: _Optional[_Union[MoveTo, _Mapping]] = ..., move_by: _Optional[_Union[MoveBy, _Mapping]] = ..., velocity: _Optional[_Union[Velocity, _Mapping]] = ..., rotate: _Optional[_Union[Rotate, _Mapping]] = ..., capture: _Optional[_Union[CaptureAction, _Mapping]] = ..., pick_up: _Optional[_Union[PickUp, _Mapping]] = ..., drop: _Optional[_Union[Drop, _Mapping]] = ..., progress_period: _Optional[float] = ...) -> None: ...

class ActionUpdate(_message.Message):
    __slots__ = ("avatar_id", "action_id", "kind", "status", "progress", "reason", "time", "odometry", "collectable_id", "region_id", "frame")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    ACTION_ID_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    PROGRESS_FIELD_NUMBER: _ClassVar[int]
    REASON_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    COLLECTABLE_ID_FIELD_NUMBER: _ClassVar[int]
    REGION_ID_FIELD_NUMBER: _ClassVar[int]
    FRAME_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    action_id: int
    kind: str
    status: ActionStatus
    progress: float
    reason: str
    time: float
    odometry: Pose
    collectable_id: str
    region_id: str
    frame: CameraFrame
    def __init__(self, avatar_id: _Optional[str] = ..., action_id: _Optional[int] = ..., kind: _Optional[str] = ..., status: _Optional[_Union[ActionStatus, str]] = ..., progress: _Optional[float] = ..., reason: _Optional[str] = ..., time: _Optional[float] = ..., odometry: _Optional[_Union[Pose, _Mapping]] = ..., collectable_id: _Optional[str] = ..., region_id: _Optional[str] = ..., frame: _Optional[_Union[CameraFrame, _Mapping]] = ...) -> None: ...

class VelocityCommand(_message.Message):
    __slots__ = ("avatar_id", "v", "omega")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    V_FIELD_NUMBER: _ClassVar[int]
    OMEGA_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    v: float
    omega: float
    def __init__(self, avatar_id: _Optional[str] = ..., v: _Optional[float] = ..., omega: _Optional[float] = ...) -> None: ...

class CommandReply(_message.Message):
    __slots__ = ("time",)
    TIME_FIELD_NUMBER: _ClassVar[int]
    time: float
    def __init__(self, time: _Optional[float] = ...) -> None: ...

class StreamRequest(_message.Message):
    __slots__ = ("avatar_id", "period")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    PERIOD_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    period: float
    def __init__(self, avatar_id: _Optional[str] = ..., period: _Optional[float] = ...) -> None: ...

class OdometryReading(_message.Message):
    __slots__ = ("avatar_id", "time", "pose", "distance", "rotation", "bumps", "bumper")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    DISTANCE_FIELD_NUMBER: _ClassVar[int]
    ROTATION_FIELD_NUMBER: _ClassVar[int]
    BUMPS_FIELD_NUMBER: _ClassVar[int]
    BUMPER_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    time: float
    pose: Pose
    distance: float
    rotation: float
    bumps: int
    bumper: bool
    def __init__(self, avatar_id: _Optional[str] = ..., time: _Optional[float] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., distance: _Optional[float] = ..., rotation: _Optional[float] = ..., bumps: _Optional[int] = ..., bumper: _Optional[bool] = ...) -> None: ...

class SonarReading(_message.Message):
    __slots__ = ("bearing", "echo", "range", "fov", "max_range")
    BEARING_FIELD_NUMBER: _ClassVar[int]
    ECHO_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    FOV_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    bearing: float
    echo: bool
    range: float
    fov: float
    max_range: float
    def __init__(self, bearing: _Optional[float] = ..., echo: _Optional[bool] = ..., range: _Optional[float] = ..., fov: _Optional[float] = ..., max_range: _Optional[float] = ...) -> None: ...

class SonarScan(_message.Message):
    __slots__ = ("avatar_id", "time", "readings")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    READINGS_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    time: float
    readings: _containers.RepeatedCompositeFieldContainer[SonarReading]
    def __init__(self, avatar_id: _Optional[str] = ..., time: _Optional[float] = ..., readings: _Optional[_Iterable[_Union[SonarReading, _Mapping]]] = ...) -> None: ...

class CaptureRequest(_message.Message):
    __slots__ = ("avatar_id", "encoding")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    encoding: ImageEncoding
    def __init__(self, avatar_id: _Optional[str] = ..., encoding: _Optional[_Union[ImageEncoding, str]] = ...) -> None: ...

class CameraFrame(_message.Message):
    __slots__ = ("avatar_id", "time", "camera", "width", "height", "encoding", "data", "K", "mount", "fov", "max_range", "odometry", "floor_homography")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    CAMERA_FIELD_NUMBER: _ClassVar[int]
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    ENCODING_FIELD_NUMBER: _ClassVar[int]
    DATA_FIELD_NUMBER: _ClassVar[int]
    K_FIELD_NUMBER: _ClassVar[int]
    MOUNT_FIELD_NUMBER: _ClassVar[int]
    FOV_FIELD_NUMBER: _ClassVar[int]
    MAX_RANGE_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    FLOOR_HOMOGRAPHY_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    time: float
    camera: str
    width: int
    height: int
    encoding: ImageEncoding
    data: bytes
    K: _containers.RepeatedScalarFieldContainer[float]
    mount: Mount
    fov: float
    max_range: float
    odometry: Pose
    floor_homography: _containers.RepeatedScalarFieldContainer[float]
    def __init__(self, avatar_id: _Optional[str] = ..., time: _Optional[float] = ..., camera: _Optional[str] = ..., width: _Optional[int] = ..., height: _Optional[int] = ..., encoding: _Optional[_Union[ImageEncoding, str]] = ..., data: _Optional[bytes] = ..., K: _Optional[_Iterable[float]] = ..., mount: _Optional[_Union[Mount, _Mapping]] = ..., fov: _Optional[float] = ..., max_range: _Optional[float] = ..., odometry: _Optional[_Union[Pose, _Mapping]] = ..., floor_homography: _Optional[_Iterable[float]] = ...) -> None: ...

class LandmarkObservation(_message.Message):
    __slots__ = ("landmark_id", "range", "bearing")
    LANDMARK_ID_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    BEARING_FIELD_NUMBER: _ClassVar[int]
    landmark_id: int
    range: float
    bearing: float
    def __init__(self, landmark_id: _Optional[int] = ..., range: _Optional[float] = ..., bearing: _Optional[float] = ...) -> None: ...

class CollectableObservation(_message.Message):
    __slots__ = ("collectable_id", "range", "bearing")
    COLLECTABLE_ID_FIELD_NUMBER: _ClassVar[int]
    RANGE_FIELD_NUMBER: _ClassVar[int]
    BEARING_FIELD_NUMBER: _ClassVar[int]
    collectable_id: str
    range: float
    bearing: float
    def __init__(self, collectable_id: _Optional[str] = ..., range: _Optional[float] = ..., bearing: _Optional[float] = ...) -> None: ...

class Detections(_message.Message):
    __slots__ = ("avatar_id", "time", "landmarks", "collectables")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    COLLECTABLES_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    time: float
    landmarks: _containers.RepeatedCompositeFieldContainer[LandmarkObservation]
    collectables: _containers.RepeatedCompositeFieldContainer[CollectableObservation]
    def __init__(self, avatar_id: _Optional[str] = ..., time: _Optional[float] = ..., landmarks: _Optional[_Iterable[_Union[LandmarkObservation, _Mapping]]] = ..., collectables: _Optional[_Iterable[_Union[CollectableObservation, _Mapping]]] = ...) -> None: ...

class EventsRequest(_message.Message):
    __slots__ = ("replay",)
    REPLAY_FIELD_NUMBER: _ClassVar[int]
    replay: bool
    def __init__(self, replay: _Optional[bool] = ...) -> None: ...

class SimEvent(_message.Message):
    __slots__ = ("time", "kind", "avatar_id", "type", "pose", "collectable_id", "region_id", "detail")
    TIME_FIELD_NUMBER: _ClassVar[int]
    KIND_FIELD_NUMBER: _ClassVar[int]
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    COLLECTABLE_ID_FIELD_NUMBER: _ClassVar[int]
    REGION_ID_FIELD_NUMBER: _ClassVar[int]
    DETAIL_FIELD_NUMBER: _ClassVar[int]
    time: float
    kind: str
    avatar_id: str
    type: str
    pose: Pose
    collectable_id: str
    region_id: str
    detail: str
    def __init__(self, time: _Optional[float] = ..., kind: _Optional[str] = ..., avatar_id: _Optional[str] = ..., type: _Optional[str] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., collectable_id: _Optional[str] = ..., region_id: _Optional[str] = ..., detail: _Optional[str] = ...) -> None: ...

class InfoRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class SimInfo(_message.Message):
    __slots__ = ("arena", "arena_yaml", "seed", "time", "mode", "speed", "achieved_speed", "tick", "avatar_types", "truth_calls")
    class TruthCallsEntry(_message.Message):
        __slots__ = ("key", "value")
        KEY_FIELD_NUMBER: _ClassVar[int]
        VALUE_FIELD_NUMBER: _ClassVar[int]
        key: str
        value: int
        def __init__(self, key: _Optional[str] = ..., value: _Optional[int] = ...) -> None: ...
    ARENA_FIELD_NUMBER: _ClassVar[int]
    ARENA_YAML_FIELD_NUMBER: _ClassVar[int]
    SEED_FIELD_NUMBER: _ClassVar[int]
    TIME_FIELD_NUMBER: _ClassVar[int]
    MODE_FIELD_NUMBER: _ClassVar[int]
    SPEED_FIELD_NUMBER: _ClassVar[int]
    ACHIEVED_SPEED_FIELD_NUMBER: _ClassVar[int]
    TICK_FIELD_NUMBER: _ClassVar[int]
    AVATAR_TYPES_FIELD_NUMBER: _ClassVar[int]
    TRUTH_CALLS_FIELD_NUMBER: _ClassVar[int]
    arena: str
    arena_yaml: str
    seed: int
    time: float
    mode: str
    speed: float
    achieved_speed: float
    tick: float
    avatar_types: _containers.RepeatedScalarFieldContainer[str]
    truth_calls: _containers.ScalarMap[str, int]
    def __init__(self, arena: _Optional[str] = ..., arena_yaml: _Optional[str] = ..., seed: _Optional[int] = ..., time: _Optional[float] = ..., mode: _Optional[str] = ..., speed: _Optional[float] = ..., achieved_speed: _Optional[float] = ..., tick: _Optional[float] = ..., avatar_types: _Optional[_Iterable[str]] = ..., truth_calls: _Optional[_Mapping[str, int]] = ...) -> None: ...

class PosesRequest(_message.Message):
    __slots__ = ()
    def __init__(self) -> None: ...

class TrueAvatar(_message.Message):
    __slots__ = ("avatar_id", "type", "status", "pose", "odometry", "carrying", "joined", "left", "radius", "bumps")
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    TYPE_FIELD_NUMBER: _ClassVar[int]
    STATUS_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    ODOMETRY_FIELD_NUMBER: _ClassVar[int]
    CARRYING_FIELD_NUMBER: _ClassVar[int]
    JOINED_FIELD_NUMBER: _ClassVar[int]
    LEFT_FIELD_NUMBER: _ClassVar[int]
    RADIUS_FIELD_NUMBER: _ClassVar[int]
    BUMPS_FIELD_NUMBER: _ClassVar[int]
    avatar_id: str
    type: str
    status: str
    pose: Pose
    odometry: Pose
    carrying: _containers.RepeatedScalarFieldContainer[str]
    joined: float
    left: float
    radius: float
    bumps: int
    def __init__(self, avatar_id: _Optional[str] = ..., type: _Optional[str] = ..., status: _Optional[str] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., odometry: _Optional[_Union[Pose, _Mapping]] = ..., carrying: _Optional[_Iterable[str]] = ..., joined: _Optional[float] = ..., left: _Optional[float] = ..., radius: _Optional[float] = ..., bumps: _Optional[int] = ...) -> None: ...

class PosesReply(_message.Message):
    __slots__ = ("time", "avatars")
    TIME_FIELD_NUMBER: _ClassVar[int]
    AVATARS_FIELD_NUMBER: _ClassVar[int]
    time: float
    avatars: _containers.RepeatedCompositeFieldContainer[TrueAvatar]
    def __init__(self, time: _Optional[float] = ..., avatars: _Optional[_Iterable[_Union[TrueAvatar, _Mapping]]] = ...) -> None: ...

class GridRequest(_message.Message):
    __slots__ = ("resolution",)
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    resolution: float
    def __init__(self, resolution: _Optional[float] = ...) -> None: ...

class GridReply(_message.Message):
    __slots__ = ("width", "height", "resolution", "origin", "cells", "explorable", "explorable_area", "surface")
    WIDTH_FIELD_NUMBER: _ClassVar[int]
    HEIGHT_FIELD_NUMBER: _ClassVar[int]
    RESOLUTION_FIELD_NUMBER: _ClassVar[int]
    ORIGIN_FIELD_NUMBER: _ClassVar[int]
    CELLS_FIELD_NUMBER: _ClassVar[int]
    EXPLORABLE_FIELD_NUMBER: _ClassVar[int]
    EXPLORABLE_AREA_FIELD_NUMBER: _ClassVar[int]
    SURFACE_FIELD_NUMBER: _ClassVar[int]
    width: int
    height: int
    resolution: float
    origin: Point
    cells: bytes
    explorable: bytes
    explorable_area: float
    surface: bytes
    def __init__(self, width: _Optional[int] = ..., height: _Optional[int] = ..., resolution: _Optional[float] = ..., origin: _Optional[_Union[Point, _Mapping]] = ..., cells: _Optional[bytes] = ..., explorable: _Optional[bytes] = ..., explorable_area: _Optional[float] = ..., surface: _Optional[bytes] = ...) -> None: ...

class Landmark(_message.Message):
    __slots__ = ("id", "position", "normal", "congregation")
    ID_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    NORMAL_FIELD_NUMBER: _ClassVar[int]
    CONGREGATION_FIELD_NUMBER: _ClassVar[int]
    id: int
    position: Point
    normal: Point
    congregation: bool
    def __init__(self, id: _Optional[int] = ..., position: _Optional[_Union[Point, _Mapping]] = ..., normal: _Optional[_Union[Point, _Mapping]] = ..., congregation: _Optional[bool] = ...) -> None: ...

class LandmarksReply(_message.Message):
    __slots__ = ("landmarks", "marker_size", "marker_height", "dictionary")
    LANDMARKS_FIELD_NUMBER: _ClassVar[int]
    MARKER_SIZE_FIELD_NUMBER: _ClassVar[int]
    MARKER_HEIGHT_FIELD_NUMBER: _ClassVar[int]
    DICTIONARY_FIELD_NUMBER: _ClassVar[int]
    landmarks: _containers.RepeatedCompositeFieldContainer[Landmark]
    marker_size: float
    marker_height: float
    dictionary: str
    def __init__(self, landmarks: _Optional[_Iterable[_Union[Landmark, _Mapping]]] = ..., marker_size: _Optional[float] = ..., marker_height: _Optional[float] = ..., dictionary: _Optional[str] = ...) -> None: ...

class Collectable(_message.Message):
    __slots__ = ("id", "position", "state", "carrier", "region")
    ID_FIELD_NUMBER: _ClassVar[int]
    POSITION_FIELD_NUMBER: _ClassVar[int]
    STATE_FIELD_NUMBER: _ClassVar[int]
    CARRIER_FIELD_NUMBER: _ClassVar[int]
    REGION_FIELD_NUMBER: _ClassVar[int]
    id: str
    position: Point
    state: str
    carrier: str
    region: str
    def __init__(self, id: _Optional[str] = ..., position: _Optional[_Union[Point, _Mapping]] = ..., state: _Optional[str] = ..., carrier: _Optional[str] = ..., region: _Optional[str] = ...) -> None: ...

class Region(_message.Message):
    __slots__ = ("id", "polygon")
    ID_FIELD_NUMBER: _ClassVar[int]
    POLYGON_FIELD_NUMBER: _ClassVar[int]
    id: str
    polygon: _containers.RepeatedCompositeFieldContainer[Point]
    def __init__(self, id: _Optional[str] = ..., polygon: _Optional[_Iterable[_Union[Point, _Mapping]]] = ...) -> None: ...

class CollectablesReply(_message.Message):
    __slots__ = ("time", "collectables", "regions")
    TIME_FIELD_NUMBER: _ClassVar[int]
    COLLECTABLES_FIELD_NUMBER: _ClassVar[int]
    REGIONS_FIELD_NUMBER: _ClassVar[int]
    time: float
    collectables: _containers.RepeatedCompositeFieldContainer[Collectable]
    regions: _containers.RepeatedCompositeFieldContainer[Region]
    def __init__(self, time: _Optional[float] = ..., collectables: _Optional[_Iterable[_Union[Collectable, _Mapping]]] = ..., regions: _Optional[_Iterable[_Union[Region, _Mapping]]] = ...) -> None: ...

class StepRequest(_message.Message):
    __slots__ = ("dt",)
    DT_FIELD_NUMBER: _ClassVar[int]
    dt: float
    def __init__(self, dt: _Optional[float] = ...) -> None: ...

class StepReply(_message.Message):
    __slots__ = ("time",)
    TIME_FIELD_NUMBER: _ClassVar[int]
    time: float
    def __init__(self, time: _Optional[float] = ...) -> None: ...

class JoinRequest(_message.Message):
    __slots__ = ("type", "avatar_id", "pose", "start_index")
    TYPE_FIELD_NUMBER: _ClassVar[int]
    AVATAR_ID_FIELD_NUMBER: _ClassVar[int]
    POSE_FIELD_NUMBER: _ClassVar[int]
    START_INDEX_FIELD_NUMBER: _ClassVar[int]
    type: str
    avatar_id: str
    pose: Pose
    start_index: int
    def __init__(self, type: _Optional[str] = ..., avatar_id: _Optional[str] = ..., pose: _Optional[_Union[Pose, _Mapping]] = ..., start_index: _Optional[int] = ...) -> None: ...
