"""Lens distortion removed from camera frames before the estimators see them.

The estimators are pinhole models. A camera calibrated as ROS's camera_info gives it (``K`` and plumb_bob /
OpenCV ``D = k1, k2, p1, p2[, k3[, k4, k5, k6]]``) is undistorted here with OpenCV's maps to the pinhole matrix
``P`` that keeps only valid pixels (``cv2.getOptimalNewCameraMatrix`` with alpha 0: what ROS's
``camera_calibration`` writes as ``P`` and ``image_proc`` rectifies to), so no black border reaches a feature
detector or the phase correlation. The estimators are given ``P``. OpenCV does the work; what is ours is
only the choice of ``P`` and the per-camera maps, built once.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from companion.geometry import CameraIntrinsics
from companion.types import Frame


def _K(intr: CameraIntrinsics) -> np.ndarray:
    return np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])


def rectified_intrinsics(raw: CameraIntrinsics, distortion: np.ndarray) -> CameraIntrinsics:
    """The pinhole matrix of the undistorted image (same size): every pixel of it sees the scene (alpha 0)."""
    size = (raw.width, raw.height)
    P, _roi = cv2.getOptimalNewCameraMatrix(_K(raw), np.asarray(distortion, float), size, 0.0, size)
    return CameraIntrinsics(
        raw.width, raw.height, float(P[0, 0]), float(P[1, 1]), float(P[0, 2]), float(P[1, 2])
    )


@dataclass(frozen=True)
class Undistorter:
    """Maps one camera's raw frames to its pinhole ``rectified`` intrinsics (bilinear; 8- or 16-bit mono)."""

    raw: CameraIntrinsics
    distortion: np.ndarray
    rectified: CameraIntrinsics
    map1: np.ndarray
    map2: np.ndarray

    @classmethod
    def build(cls, raw: CameraIntrinsics, distortion: np.ndarray | list[float]) -> Undistorter:
        d = np.asarray(distortion, float)
        rect = rectified_intrinsics(raw, d)
        m1, m2 = cv2.initUndistortRectifyMap(
            _K(raw), d, None, _K(rect), (raw.width, raw.height), cv2.CV_16SC2
        )
        return cls(raw, d, rect, m1, m2)

    def apply(self, image: np.ndarray) -> np.ndarray:
        """The undistorted image. Raises ValueError on an image of another size than the calibration's."""
        h, w = image.shape[:2]
        if (w, h) != (self.raw.width, self.raw.height):
            raise ValueError(f"image {w}x{h}, calibration {self.raw.width}x{self.raw.height}")
        return cv2.remap(image, self.map1, self.map2, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def distort_points(self, uv_rectified: np.ndarray) -> np.ndarray:
        """Where rectified pixels (N, 2) sit in the raw image (the lens model, for checks and simulation)."""
        uv = np.asarray(uv_rectified, float).reshape(-1, 2)
        P = _K(self.rectified)
        x = np.column_stack([(uv - P[:2, 2]) / np.diag(P)[:2], np.ones(len(uv))])
        out, _ = cv2.projectPoints(x, np.zeros(3), np.zeros(3), _K(self.raw), self.distortion)
        return out.reshape(-1, 2)


class FrameUndistorter:
    """Undistorts the frames of the cameras that have a lens model, on a frame set: what the daemon and the
    replay apply between the hand-off and the estimator (so a record of the inputs keeps the raw frames)."""

    def __init__(self, undistorters: dict[str, Undistorter]) -> None:
        self.undistorters = dict(undistorters)

    def __call__(self, frames: dict[str, Frame]) -> dict[str, Frame]:
        """Raises ValueError when a frame's size is not its calibration's."""
        return {
            cam: f if (u := self.undistorters.get(cam)) is None else replace(f, image=u.apply(f.image))
            for cam, f in frames.items()
        }


def frame_undistorter(cameras: dict[str, Undistorter | None]) -> FrameUndistorter | None:
    """None when no camera has a lens model (nothing to do per frame)."""
    have = {c: u for c, u in cameras.items() if u is not None}
    return FrameUndistorter(have) if have else None
