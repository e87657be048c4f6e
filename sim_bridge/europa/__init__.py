"""Simulated Europa for paper 2 (visible + thermal EKF-SLAM): terrain, eq. 9 visible and thermal
renderers, co-registered downward cameras, the ten trajectories, a ranging altimeter."""

from sim_bridge.europa.render import (
    EuropaCameras,
    HeightfieldTracer,
    ThermalNoise,
    VisibleNoise,
    default_intrinsics,
    ground_points,
)
from sim_bridge.europa.thermal import Illumination, ThermalOptions
from sim_bridge.europa.world import EuropaOptions, EuropaWorld, Reflectance, make_europa

__all__ = [
    "EuropaCameras",
    "EuropaOptions",
    "EuropaWorld",
    "HeightfieldTracer",
    "Illumination",
    "Reflectance",
    "ThermalNoise",
    "ThermalOptions",
    "VisibleNoise",
    "default_intrinsics",
    "ground_points",
    "make_europa",
]
