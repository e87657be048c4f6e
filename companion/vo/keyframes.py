"""Key-frame selection (paper 1 section 4.2, after ORB-SLAM): a frame becomes a key frame when
1) more than ``min_frames_between`` frames have passed since the last key frame,
2) it tracks more than ``min_features`` map points, and
3) it tracks less than ``max_tracked_ratio`` of the points the reference (last) key frame observed.
As in ORB-SLAM, weak tracking also forces a key frame (so that new points are triangulated before the
map runs out), once ``min_frames_force`` frames have passed.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class KeyframeOptions:
    min_frames_between: int = 20  # criterion 1
    min_features: int = 50  # criterion 2: map points tracked in the current frame
    max_tracked_ratio: float = 0.9  # criterion 3: fraction of the reference key frame's points still tracked
    force_below_features: int = 80  # fewer tracked map points than this forces a key frame ...
    min_frames_force: int = 3  # ... once this many frames have passed


def is_keyframe(
    frames_since_kf: int, n_map_points_tracked: int, n_ref_tracked: int, n_ref: int, options: KeyframeOptions
) -> bool:
    """The paper's three criteria (all must hold), or weak tracking.

    n_ref_tracked / n_ref: points of the reference key frame still tracked / observed by it.
    """
    ratio = n_ref_tracked / n_ref if n_ref > 0 else 0.0
    paper = (
        frames_since_kf >= options.min_frames_between
        and n_map_points_tracked > options.min_features
        and ratio < options.max_tracked_ratio
    )
    weak = frames_since_kf >= options.min_frames_force and n_map_points_tracked < options.force_below_features
    return paper or weak
