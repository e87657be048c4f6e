"""Project-wide constants: ids, frame names and physical values, one place to look them up."""

from __future__ import annotations

from typing import Final

import numpy as np

MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY: Final = 197
"""Our MAVLink component id (MAV_COMP_ID_VISUAL_INERTIAL_ODOMETRY); the onboard computer is 191."""

MAV_COMP_ID_ONBOARD_COMPUTER: Final = 191
"""Alternative component id a user may pick in the config."""

DEFAULT_COMPANION_SYSID: Final = 1
"""The companion shares the vehicle's system id, as ArduPilot and PX4 expect."""

R_BODY_CAM_NADIR: Final = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
"""Rotation taking nadir-camera vectors into body FRD. Columns are the camera axes in body:
x_cam = body right, y_cam = body backward, z_cam = body down. With heading north the image
top is north and image right is east, like a map."""

PLANET_RADIUS_M: Final = {
    "earth": 6_378_137.0,
    "mars": 3_389_500.0,
    "moon": 1_737_400.0,
    "europa": 1_560_800.0,
}
"""Mean radii used by the local-tangent-plane (NED) approximation around the geodetic origin."""

GRAVITY_MPS2: Final = {"earth": 9.80665, "mars": 3.72076, "moon": 1.625, "europa": 1.315}
"""Surface gravity, for IMU simulation and propagation."""

US_PER_S: Final = 1_000_000
"""Microseconds per second: all timestamps are integer microseconds."""
