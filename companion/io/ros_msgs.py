"""ROS 2 sensor messages <-> the companion's samples, under ROS's frame conventions.

A vehicle's recording (rosbag2) carries the autopilot's sensors as ROS messages: ``sensor_msgs/msg/Imu``
(specific force, body rate and, when the autopilot fills it, the attitude), ``sensor_msgs/msg/Range`` (the
downward range finder), ``nav_msgs/msg/Odometry`` (the vehicle's own navigation, the hand-over) and, on a
simulated or surveyed flight, ``geometry_msgs/msg/PoseStamped`` ground truth. The companion works in NED
(world) and FRD (body); ROS in ENU and FLU (REP 103, REP 105: ``map``, ``odom``, ``base_link``). A frame id
ending in ``_ned`` / ``_frd`` (how mavros and PX4's ROS 2 bridge name those frames: ``map_ned``,
``base_link_frd``) is taken as it says and not converted; any other frame id is ENU (world) or FLU (body).
The Imu's orientation is of its body frame in the world of the same convention (FLU in ENU, as mavros's
``imu/data``; FRD in NED).

Pure functions of decoded messages (rosbags' dataclasses); the bag itself is read in ``companion.replay``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from rosbags.typesys import Stores, get_typestore
from scipy.spatial.transform import Rotation

from companion.geometry import rpy_from_rot
from companion.types import AltimeterSample, AttitudeSample, ImuSample, LocalPositionSample

IMU_MSGTYPE: Final = "sensor_msgs/msg/Imu"
RANGE_MSGTYPE: Final = "sensor_msgs/msg/Range"
ODOMETRY_MSGTYPE: Final = "nav_msgs/msg/Odometry"
POSE_MSGTYPE: Final = "geometry_msgs/msg/PoseStamped"
QUATERNION_MSGTYPE: Final = "geometry_msgs/msg/QuaternionStamped"
STRING_MSGTYPE: Final = "std_msgs/msg/String"

TYPESTORE: Final = get_typestore(Stores.ROS2_HUMBLE)
ROSBAG_VERSION: Final = 8
"""rosbag2 metadata version written: 8 is read by ROS 2 Humble and later (9 needs Jazzy)."""

T_FLU_FRD: Final = np.diag([1.0, -1.0, -1.0])
"""v_frd = T v_flu (and back: the matrix is its own inverse)."""
T_ENU_NED: Final = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
"""v_ned = T v_enu (and back)."""


def body_is_frd(frame_id: str) -> bool:
    return str(frame_id).lower().endswith("_frd")


def world_is_ned(frame_id: str) -> bool:
    return str(frame_id).lower().endswith("_ned")


def stamp_us(header: Any) -> int:
    return int(header.stamp.sec) * 1_000_000 + int(header.stamp.nanosec) // 1000


def _vec(v: Any) -> np.ndarray:
    return np.array([float(v.x), float(v.y), float(v.z)])


def _quat(q: Any) -> np.ndarray:
    return np.array([float(q.x), float(q.y), float(q.z), float(q.w)])


def rot_ned_frd(q_xyzw: np.ndarray, ned_frd: bool) -> np.ndarray:
    """R_world_body (NED <- FRD) from a ROS quaternion of the body in the world: FLU in ENU unless
    ``ned_frd`` (FRD in NED). Raises ValueError on a zero or non-finite quaternion."""
    q = np.asarray(q_xyzw, float)
    n = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or n < 1e-6:
        raise ValueError(f"orientation quaternion {q.tolist()} is not a rotation")
    R = Rotation.from_quat(q / n).as_matrix()
    return R if ned_frd else T_ENU_NED @ R @ T_FLU_FRD


def ros_quat(R_ned_frd: np.ndarray, ned_frd: bool) -> np.ndarray:
    """The inverse of ``rot_ned_frd``: (x, y, z, w) of the body in the world of the chosen convention."""
    R = np.asarray(R_ned_frd, float)
    if not ned_frd:
        R = T_ENU_NED @ R @ T_FLU_FRD
    return Rotation.from_matrix(R).as_quat()


@dataclass(frozen=True)
class ImuReading:
    """One Imu message in the companion's frames: the IMU sample and, when the message has one, the attitude."""

    imu: ImuSample
    attitude: AttitudeSample | None


def imu_reading(msg: Any) -> ImuReading:
    """``sensor_msgs/msg/Imu`` -> FRD specific force and rate, and the NED/FRD attitude unless the message says
    it has none (orientation_covariance[0] == -1, ROS's convention). ValueError on non-finite values."""
    t = stamp_us(msg.header)
    frd = body_is_frd(msg.header.frame_id)
    acc, gyr = _vec(msg.linear_acceleration), _vec(msg.angular_velocity)
    if not (np.all(np.isfinite(acc)) and np.all(np.isfinite(gyr))):
        raise ValueError("non-finite acceleration or rate")
    if not frd:
        acc, gyr = T_FLU_FRD @ acc, T_FLU_FRD @ gyr
    att = None
    cov = np.asarray(msg.orientation_covariance, float)
    if not (cov.size and cov[0] == -1.0):
        q = _quat(msg.orientation)
        if np.linalg.norm(q) > 1e-6:  # an all-zero quaternion: a driver that leaves it unset
            r, p, y = rpy_from_rot(rot_ned_frd(q, frd))
            att = AttitudeSample(t, float(r), float(p), float(y))
    return ImuReading(ImuSample(t, acc, gyr), att)


def attitude_sample(msg: Any) -> AttitudeSample:
    """``geometry_msgs/msg/QuaternionStamped`` (the body in the header's world frame: FRD in NED when that
    ends in ``_ned``, else FLU in ENU) -> attitude sample."""
    r, p, y = rpy_from_rot(rot_ned_frd(_quat(msg.quaternion), world_is_ned(msg.header.frame_id)))
    return AttitudeSample(stamp_us(msg.header), float(r), float(p), float(y))


def altimeter_sample(msg: Any) -> AltimeterSample:
    """``sensor_msgs/msg/Range`` -> range (m); outside [min_range, max_range] or infinite (ROS's "no return")
    becomes NaN, which the estimators read as no return. A limit of 0 is taken as not given."""
    r = float(msg.range)
    lo, hi = float(msg.min_range), float(msg.max_range)
    ok = math.isfinite(r) and (lo <= 0 or r >= lo) and (hi <= 0 or r <= hi)
    return AltimeterSample(stamp_us(msg.header), r if ok else float("nan"))


def local_position_sample(msg: Any) -> LocalPositionSample:
    """``nav_msgs/msg/Odometry`` -> NED position and velocity. The twist is in the child frame, per the
    message's definition: the body, whose velocity the pose's orientation turns into the world; or, when the
    child frame is the world frame itself, the world."""
    ned = world_is_ned(msg.header.frame_id)
    p = _vec(msg.pose.pose.position)
    v_world = _vec(msg.twist.twist.linear)
    if msg.child_frame_id != msg.header.frame_id:
        if ned != body_is_frd(msg.child_frame_id):
            raise ValueError(
                f"odometry in {msg.header.frame_id!r} with a {msg.child_frame_id!r} body: mixed conventions"
            )
        R_wb = Rotation.from_quat(_quat(msg.pose.pose.orientation)).as_matrix()  # body in world
        v_world = R_wb @ v_world
    if not ned:
        p, v_world = T_ENU_NED @ p, T_ENU_NED @ v_world
    if not (np.all(np.isfinite(p)) and np.all(np.isfinite(v_world))):
        raise ValueError("non-finite position or velocity")
    return LocalPositionSample(stamp_us(msg.header), p, v_world)


def pose_ned(msg: Any) -> tuple[int, np.ndarray, np.ndarray]:
    """``geometry_msgs/msg/PoseStamped`` -> (stamp_us, NED position, R_world_body NED <- FRD)."""
    ned = world_is_ned(msg.header.frame_id)
    p = _vec(msg.pose.position)
    return stamp_us(msg.header), (p if ned else T_ENU_NED @ p), rot_ned_frd(_quat(msg.pose.orientation), ned)


# -- writing (the simulator's flight bags) --------------------------------------------------------------

_T = TYPESTORE.types


def _header(t_us: int, frame_id: str) -> Any:
    sec, usec = divmod(int(t_us), 1_000_000)
    return _T["std_msgs/msg/Header"](
        stamp=_T["builtin_interfaces/msg/Time"](sec=int(sec), nanosec=int(usec) * 1000), frame_id=frame_id
    )


def _v3(v: np.ndarray) -> Any:
    return _T["geometry_msgs/msg/Vector3"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def _q(q: np.ndarray) -> Any:
    return _T["geometry_msgs/msg/Quaternion"](x=float(q[0]), y=float(q[1]), z=float(q[2]), w=float(q[3]))


def _pt(v: np.ndarray) -> Any:
    return _T["geometry_msgs/msg/Point"](x=float(v[0]), y=float(v[1]), z=float(v[2]))


def frame_ids(ned_frd: bool) -> tuple[str, str]:
    """(world, body) frame ids written: ("map_ned", "base_link_frd") or ROS's ("map", "base_link")."""
    return ("map_ned", "base_link_frd") if ned_frd else ("map", "base_link")


def imu_cdr(
    t_us: int,
    accel_frd: np.ndarray,
    gyro_frd: np.ndarray,
    R_ned_frd: np.ndarray | None,
    ned_frd: bool,
    accel_var: float = 0.0,
    gyro_var: float = 0.0,
    attitude_var: float = 0.0,
) -> bytes:
    """A CDR ``sensor_msgs/msg/Imu`` (orientation_covariance[0] = -1 when ``R_ned_frd`` is None)."""
    body = frame_ids(ned_frd)[1]
    T = np.eye(3) if ned_frd else T_FLU_FRD
    ocov = np.zeros(9)
    ocov[[0, 4, 8]] = attitude_var
    if R_ned_frd is None:
        ocov[0] = -1.0
    q = np.array([0.0, 0.0, 0.0, 1.0]) if R_ned_frd is None else ros_quat(R_ned_frd, ned_frd)
    msg = _T[IMU_MSGTYPE](
        header=_header(t_us, body),
        orientation=_q(q),
        orientation_covariance=ocov,
        angular_velocity=_v3(T @ gyro_frd),
        angular_velocity_covariance=np.diag([gyro_var] * 3).ravel(),
        linear_acceleration=_v3(T @ accel_frd),
        linear_acceleration_covariance=np.diag([accel_var] * 3).ravel(),
    )
    return bytes(TYPESTORE.serialize_cdr(msg, IMU_MSGTYPE))


def range_cdr(t_us: int, range_m: float, min_m: float, max_m: float, ned_frd: bool) -> bytes:
    """A CDR ``sensor_msgs/msg/Range`` from a downward laser; NaN (no return) is written as +inf."""
    msg = _T[RANGE_MSGTYPE](
        header=_header(t_us, "rangefinder_frd" if ned_frd else "rangefinder"),
        radiation_type=1,  # INFRARED: a laser range finder
        field_of_view=0.01,
        min_range=float(min_m),
        max_range=float(max_m),
        range=float(range_m) if math.isfinite(range_m) else math.inf,
    )
    return bytes(TYPESTORE.serialize_cdr(msg, RANGE_MSGTYPE))


def odometry_cdr(
    t_us: int,
    p_ned: np.ndarray,
    v_ned: np.ndarray,
    R_ned_frd: np.ndarray,
    ned_frd: bool,
    pos_var: float = 0.0,
) -> bytes:
    """A CDR ``nav_msgs/msg/Odometry``: pose in the world frame, twist in the body frame (its definition)."""
    world, body = frame_ids(ned_frd)
    Tw = np.eye(3) if ned_frd else T_ENU_NED
    Tb = np.eye(3) if ned_frd else T_FLU_FRD
    v_body = Tb @ (np.asarray(R_ned_frd).T @ np.asarray(v_ned, float))
    cov = np.zeros(36)
    cov[[0, 7, 14]] = pos_var
    msg = _T[ODOMETRY_MSGTYPE](
        header=_header(t_us, world),
        child_frame_id=body,
        pose=_T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_T["geometry_msgs/msg/Pose"](
                position=_pt(Tw @ p_ned), orientation=_q(ros_quat(R_ned_frd, ned_frd))
            ),
            covariance=cov,
        ),
        twist=_T["geometry_msgs/msg/TwistWithCovariance"](
            twist=_T["geometry_msgs/msg/Twist"](linear=_v3(v_body), angular=_v3(np.zeros(3))),
            covariance=np.zeros(36),
        ),
    )
    return bytes(TYPESTORE.serialize_cdr(msg, ODOMETRY_MSGTYPE))


def odometry_world_twist_cdr(t_us: int, p_ned: np.ndarray, v_ned: np.ndarray) -> bytes:
    """A CDR ``nav_msgs/msg/Odometry`` of a position and velocity without attitude (LOCAL_POSITION_NED): the
    child frame is the world (``map_ned``), so the twist is the NED velocity; orientation identity."""
    msg = _T[ODOMETRY_MSGTYPE](
        header=_header(t_us, "map_ned"),
        child_frame_id="map_ned",
        pose=_T["geometry_msgs/msg/PoseWithCovariance"](
            pose=_T["geometry_msgs/msg/Pose"](
                position=_pt(p_ned), orientation=_q(np.array([0.0, 0.0, 0.0, 1.0]))
            ),
            covariance=np.zeros(36),
        ),
        twist=_T["geometry_msgs/msg/TwistWithCovariance"](
            twist=_T["geometry_msgs/msg/Twist"](linear=_v3(v_ned), angular=_v3(np.zeros(3))),
            covariance=np.zeros(36),
        ),
    )
    return bytes(TYPESTORE.serialize_cdr(msg, ODOMETRY_MSGTYPE))


def quaternion_cdr(t_us: int, R_ned_frd: np.ndarray) -> bytes:
    """A CDR ``geometry_msgs/msg/QuaternionStamped``: the FRD body in NED (``map_ned``)."""
    msg = _T[QUATERNION_MSGTYPE](header=_header(t_us, "map_ned"), quaternion=_q(ros_quat(R_ned_frd, True)))
    return bytes(TYPESTORE.serialize_cdr(msg, QUATERNION_MSGTYPE))


def string_cdr(text: str) -> bytes:
    """A CDR ``std_msgs/msg/String``."""
    return bytes(TYPESTORE.serialize_cdr(_T[STRING_MSGTYPE](data=text), STRING_MSGTYPE))


def pose_cdr(t_us: int, p_ned: np.ndarray, R_ned_frd: np.ndarray, ned_frd: bool) -> bytes:
    """A CDR ``geometry_msgs/msg/PoseStamped`` (ground truth)."""
    world = frame_ids(ned_frd)[0]
    Tw = np.eye(3) if ned_frd else T_ENU_NED
    msg = _T[POSE_MSGTYPE](
        header=_header(t_us, world),
        pose=_T["geometry_msgs/msg/Pose"](
            position=_pt(Tw @ p_ned), orientation=_q(ros_quat(R_ned_frd, ned_frd))
        ),
    )
    return bytes(TYPESTORE.serialize_cdr(msg, POSE_MSGTYPE))
