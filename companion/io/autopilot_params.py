"""Does the autopilot use what we send? The parameters that decide it, read over MAVLink and checked.

The commonest reason an external-vision integration "does nothing" is a parameter: ArduPilot with
VISO_TYPE 0 drops every VISION_POSITION_ESTIMATE without a word, an EKF3 source set still on GPS never
fuses it, a PX4 EKF2_EV_CTRL without its position bit ignores it. The daemon reads these parameters
(PARAM_REQUEST_READ by name) once the autopilot's HEARTBEAT tells which autopilot it is, and reports
what it finds in the log and the status; ``companion check-autopilot`` prints the same as a table.

Values follow the parameter documentation of ArduPilot 4.5 (AP_VisualOdom, AP_NavEKF3 sources) and
PX4 1.14+ (EKF2_EV_CTRL; the older EKF2_AID_MASK is read when EKF2_EV_CTRL is absent). Pure logic:
values in, findings out; the reading is ``companion.io.mavlink.MavlinkLink`` (``MavlinkOptions.read_params``)
and the check at start-up ``companion.io.autopilot.AutopilotLinkAdapter.check_autopilot``.
"""

from __future__ import annotations

import struct
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Final

from pymavlink.dialects.v20 import ardupilotmega as mavlink2

ARDUPILOT: Final = "ardupilot"
PX4: Final = "px4"

OK: Final = "ok"
INFO: Final = "info"
WARNING: Final = "warning"
ERROR: Final = "error"
"""Severities: ERROR = the autopilot will not use our estimates; WARNING = it will, but wrongly."""

OFFSET_TOLERANCE_M = 0.01
"""Camera offsets (autopilot parameter vs config) closer than this agree."""

_EXT_NAV = 6  # EK3_SRCn_* value "ExternalNav"
_PX4_INT_TYPES = (
    mavlink2.MAV_PARAM_TYPE_UINT8,
    mavlink2.MAV_PARAM_TYPE_INT8,
    mavlink2.MAV_PARAM_TYPE_UINT16,
    mavlink2.MAV_PARAM_TYPE_INT16,
    mavlink2.MAV_PARAM_TYPE_UINT32,
    mavlink2.MAV_PARAM_TYPE_INT32,
)

ARDUPILOT_PARAMS: Final = (
    "AHRS_EKF_TYPE",
    "VISO_TYPE",
    "EK3_SRC1_POSXY",
    "EK3_SRC1_VELXY",
    "EK3_SRC1_POSZ",
    "EK3_SRC1_YAW",
    "EK3_SRC2_POSXY",
    "EK3_SRC3_POSXY",
    "VISO_POS_X",
    "VISO_POS_Y",
    "VISO_POS_Z",
    "VISO_DELAY_MS",
)
PX4_PARAMS: Final = (
    "EKF2_EV_CTRL",
    "EKF2_AID_MASK",
    "EKF2_HGT_REF",
    "EKF2_EV_POS_X",
    "EKF2_EV_POS_Y",
    "EKF2_EV_POS_Z",
    "EKF2_EV_DELAY",
)


@dataclass(frozen=True)
class Finding:
    """One checked parameter (or group): its value(s) as read, the severity and what to do."""

    param: str
    value: str
    severity: str
    message: str


def flavour_from_heartbeat(autopilot: int) -> str | None:
    """ARDUPILOT / PX4 from HEARTBEAT.autopilot (MAV_AUTOPILOT_*), None for anything else."""
    if autopilot == mavlink2.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return ARDUPILOT
    if autopilot == mavlink2.MAV_AUTOPILOT_PX4:
        return PX4
    return None


def params_to_read(flavour: str) -> tuple[str, ...]:
    """The parameter names checked for an autopilot flavour."""
    return {ARDUPILOT: ARDUPILOT_PARAMS, PX4: PX4_PARAMS}[flavour]


def decode_param_value(value: float, param_type: int, flavour: str) -> float:
    """PARAM_VALUE.param_value as a number. ArduPilot sends every type as a float (cast); PX4 puts an
    integer's bytes in the float field (MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE)."""
    if flavour == PX4 and param_type in _PX4_INT_TYPES:
        raw = struct.pack("<f", value)
        signed = param_type in (
            mavlink2.MAV_PARAM_TYPE_INT8,
            mavlink2.MAV_PARAM_TYPE_INT16,
            mavlink2.MAV_PARAM_TYPE_INT32,
        )
        return float(struct.unpack("<i" if signed else "<I", raw)[0])
    return float(value)


def _fmt(v: float | None) -> str:
    if v is None:
        return "unanswered"
    return str(int(v)) if float(v).is_integer() else f"{v:g}"


def _offset(
    values: Mapping[str, float], names: Sequence[str], camera_offset_m: Sequence[float]
) -> Finding | None:
    got = [values.get(n) for n in names]
    label = "/".join(names)
    if any(v is None for v in got):
        return None
    diff = max(abs(float(g) - float(c)) for g, c in zip(got, camera_offset_m))  # type: ignore[arg-type]
    shown = ", ".join(_fmt(v) for v in got)
    want = ", ".join(f"{c:g}" for c in camera_offset_m)
    if diff > OFFSET_TOLERANCE_M:
        return Finding(
            label,
            shown,
            WARNING,
            f"camera offset differs from the config's position_in_body_m ({want} m): the autopilot moves "
            "our camera position to its body origin with these; set them to where the camera is",
        )
    return Finding(label, shown, OK, "camera offset matches the config")


def check_ardupilot(
    values: Mapping[str, float], camera_offset_m: Sequence[float], message: str
) -> list[Finding]:
    """Findings for an ArduPilot vehicle (EKF3 with external navigation)."""
    out: list[Finding] = []
    v = values.get
    ekf = v("AHRS_EKF_TYPE")
    if ekf is not None:
        ok = int(ekf) == 3
        out.append(
            Finding(
                "AHRS_EKF_TYPE",
                _fmt(ekf),
                OK if ok else ERROR,
                "EKF3" if ok else "external navigation needs EKF3: set AHRS_EKF_TYPE 3",
            )
        )
    viso = v("VISO_TYPE")
    if viso is None:
        out.append(
            Finding(
                "VISO_TYPE",
                "unanswered",
                ERROR,
                "the autopilot has no VISO_TYPE parameter: firmware built without visual odometry?",
            )
        )
    else:
        ok = int(viso) != 0
        out.append(
            Finding(
                "VISO_TYPE",
                _fmt(viso),
                OK if ok else ERROR,
                "visual odometry enabled"
                if ok
                else "0 = none: VISION_POSITION_ESTIMATE is dropped; set VISO_TYPE 1 (MAVLink) and reboot",
            )
        )
    srcs = {n: v(f"EK3_SRC{n}_POSXY") for n in (1, 2, 3)}
    s1 = srcs[1]
    if s1 is not None:
        if int(s1) == _EXT_NAV:
            out.append(Finding("EK3_SRC1_POSXY", _fmt(s1), OK, "horizontal position from ExternalNav"))
        else:
            other = [n for n in (2, 3) if srcs[n] is not None and int(srcs[n]) == _EXT_NAV]  # type: ignore[arg-type]
            if other:
                out.append(
                    Finding(
                        "EK3_SRC1_POSXY",
                        _fmt(s1),
                        INFO,
                        f"ExternalNav is source set {other[0]}: used only after switching to it "
                        "(EK3_SRC_OPTIONS / RC aux function 90)",
                    )
                )
            else:
                out.append(
                    Finding(
                        "EK3_SRC1_POSXY",
                        _fmt(s1),
                        ERROR,
                        "no EKF3 source set takes horizontal position from ExternalNav: set EK3_SRC1_POSXY 6",
                    )
                )
    velxy = v("EK3_SRC1_VELXY")
    if velxy is not None:
        if int(velxy) == _EXT_NAV and message == "vision_position_estimate":
            out.append(
                Finding(
                    "EK3_SRC1_VELXY",
                    _fmt(velxy),
                    WARNING,
                    "EKF3 waits for external-nav velocity, which VISION_POSITION_ESTIMATE does not carry: "
                    'set EK3_SRC1_VELXY 0, or mavlink.message = "odometry"',
                )
            )
        else:
            out.append(Finding("EK3_SRC1_VELXY", _fmt(velxy), OK, "velocity source consistent"))
    for name, what in (("EK3_SRC1_POSZ", "height"), ("EK3_SRC1_YAW", "yaw")):
        val = v(name)
        if val is not None:
            src = "ExternalNav (ours)" if int(val) == _EXT_NAV else "another source"
            out.append(Finding(name, _fmt(val), INFO, f"{what} from {src}"))
    off = _offset(values, ("VISO_POS_X", "VISO_POS_Y", "VISO_POS_Z"), camera_offset_m)
    if off is not None:
        out.append(off)
    delay = v("VISO_DELAY_MS")
    if delay is not None:
        out.append(
            Finding(
                "VISO_DELAY_MS",
                _fmt(delay),
                INFO,
                "set it near the companion's capture-to-send latency (status line 'lat p50')",
            )
        )
    return out


def check_px4(values: Mapping[str, float], camera_offset_m: Sequence[float], message: str) -> list[Finding]:
    """Findings for a PX4 vehicle (EKF2 external vision)."""
    out: list[Finding] = []
    ctrl = values.get("EKF2_EV_CTRL")
    if ctrl is not None:
        bits = int(ctrl)
        if not bits & 1:
            out.append(
                Finding(
                    "EKF2_EV_CTRL",
                    _fmt(ctrl),
                    ERROR,
                    "bit 0 (horizontal position) clear: EKF2 ignores our position; set EKF2_EV_CTRL 15 or 11",
                )
            )
        elif bits & 4 and message == "vision_position_estimate":
            out.append(
                Finding(
                    "EKF2_EV_CTRL",
                    _fmt(ctrl),
                    WARNING,
                    "bit 2 (velocity) set but VISION_POSITION_ESTIMATE carries none: clear it or send odometry",
                )
            )
        else:
            out.append(Finding("EKF2_EV_CTRL", _fmt(ctrl), OK, "external-vision position fused"))
    else:
        mask = values.get("EKF2_AID_MASK")
        if mask is None:
            out.append(
                Finding(
                    "EKF2_EV_CTRL",
                    "unanswered",
                    ERROR,
                    "neither EKF2_EV_CTRL nor EKF2_AID_MASK answered: is this PX4 with EKF2?",
                )
            )
        else:
            ok = bool(int(mask) & 8)
            out.append(
                Finding(
                    "EKF2_AID_MASK",
                    _fmt(mask),
                    OK if ok else ERROR,
                    "vision position fused (bit 3)"
                    if ok
                    else "bit 3 (vision position) clear: EKF2 ignores our position",
                )
            )
    hgt = values.get("EKF2_HGT_REF")
    if hgt is not None:
        src = "vision (ours)" if int(hgt) == 3 else "another source"
        out.append(Finding("EKF2_HGT_REF", _fmt(hgt), INFO, f"height reference: {src}"))
    off = _offset(values, ("EKF2_EV_POS_X", "EKF2_EV_POS_Y", "EKF2_EV_POS_Z"), camera_offset_m)
    if off is not None:
        out.append(off)
    delay = values.get("EKF2_EV_DELAY")
    if delay is not None:
        out.append(
            Finding(
                "EKF2_EV_DELAY",
                _fmt(delay),
                INFO,
                "set it near the companion's capture-to-send latency (status line 'lat p50')",
            )
        )
    return out


def check_params(
    flavour: str, values: Mapping[str, float], camera_offset_m: Sequence[float], message: str
) -> list[Finding]:
    """Every finding for ``flavour`` given the parameter ``values`` read (missing = unanswered)."""
    if flavour == ARDUPILOT:
        return check_ardupilot(values, camera_offset_m, message)
    if flavour == PX4:
        return check_px4(values, camera_offset_m, message)
    raise ValueError(f"unknown autopilot flavour {flavour!r}")


def worst(findings: Sequence[Finding]) -> str:
    """The most severe severity among ``findings`` (OK when empty)."""
    order = (OK, INFO, WARNING, ERROR)
    return max((f.severity for f in findings), key=order.index, default=OK)
