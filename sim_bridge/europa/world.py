"""The simulated Europa landing site: terrain, albedo, illumination and surface temperature.

Everything that does not depend on where the camera is gets computed once here (the Sun is fixed during a
descent): the DEM, the albedo map, cast-shadow maps of the Sun and Jupiter and the temperature map.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from companion.georef.dem import Dem
from sim_bridge.europa.terrain import AlbedoOptions, TerrainOptions, europa_albedo, europa_heights
from sim_bridge.europa.thermal import Illumination, ThermalOptions, lit_fraction, surface_temperature


@dataclass(frozen=True)
class Reflectance:
    """Quasi-Phong BRDF of paper 2 eq. 9 for a regolith-ice mixture (the paper gives no numbers).

    E = rho_a + alpha rho_d (N.L) + (1 - alpha) rho_s (R.V)^k, with rho_a = rho_d = the albedo map (the
    paper: "for the most part, we set rho_a = rho_d") and alpha = 1 - phase / pi (1 when the Sun is
    behind the viewer, 0 when the light and view vectors oppose).

    specular_fraction: share of the incident light reflected in the specular lobe. 0.1 is the order of
    ice's Fresnel reflectance averaged over incidence angles (2 % at normal incidence, rising at grazing)
    plus smooth-facet glints. rho_s is derived from it for an energy-normalised Phong lobe in the units of
    the diffuse term: rho_s = specular_fraction (k + 2) / 2.
    sharpness_k: Phong exponent; 20 gives a lobe ~15 deg wide (half maximum), a fairly glossy ice crust.
    """

    specular_fraction: float = 0.1
    sharpness_k: float = 20.0

    @property
    def rho_s(self) -> float:
        return self.specular_fraction * (self.sharpness_k + 2.0) / 2.0


@dataclass(frozen=True)
class EuropaOptions:
    """All knobs of the world; defaults documented in each options class."""

    terrain: TerrainOptions = field(default_factory=TerrainOptions)
    albedo: AlbedoOptions = field(default_factory=AlbedoOptions)
    illumination: Illumination = field(default_factory=Illumination)
    thermal: ThermalOptions = field(default_factory=ThermalOptions)
    reflectance: Reflectance = field(default_factory=Reflectance)


@dataclass(frozen=True, eq=False)
class EuropaWorld:
    """A Europa landing site on a north-up grid centred on the world origin (NED (0, 0) is the centre).

    dem: elevations (m, up positive; NED z of the ground = -height). albedo: (rows, cols) float32,
    rho_a = rho_d of eq. 9. temperature_k: (rows, cols) float32 surface temperature.
    sun_lit, jupiter_lit: (rows, cols) float32, 1 where the source is not hidden by terrain.
    """

    dem: Dem
    albedo: np.ndarray
    temperature_k: np.ndarray
    sun_lit: np.ndarray
    jupiter_lit: np.ndarray
    illumination: Illumination
    thermal: ThermalOptions
    reflectance: Reflectance
    seed: int

    @property
    def sun_dir_enu(self) -> np.ndarray:
        """(3,) unit vector towards the Sun (east, north, up)."""
        return self.illumination.sun.direction_enu

    @property
    def jupiter_dir_enu(self) -> np.ndarray:
        """(3,) unit vector towards Jupiter's disc centre (east, north, up)."""
        return self.illumination.jupiter.direction_enu


def make_europa(
    seed: int = 0, size_m: float = 400.0, cell_m: float = 0.25, options: EuropaOptions | None = None
) -> EuropaWorld:
    """Generate the site: ``size_m`` square (paper: 400 m), ``cell_m`` grid (0.25 m: 5 cm/pixel at 30 m
    above ground with the default camera resolves texture down to ~5 px per cell). Deterministic by seed."""
    opts = EuropaOptions() if options is None else options
    n = int(round(size_m / cell_m))
    shape = (n, n)
    heights = europa_heights(np.random.default_rng([seed, 0]), shape, cell_m, opts.terrain)
    albedo = europa_albedo(np.random.default_rng([seed, 1]), shape, cell_m, opts.albedo)
    half = 0.5 * (n - 1) * cell_m
    dem = Dem(heights, north0_m=half, east0_m=-half, cell_m=cell_m)
    illum = opts.illumination
    sun_lit = lit_fraction(heights, cell_m, illum.sun)
    jup_lit = lit_fraction(heights, cell_m, illum.jupiter)
    temperature = surface_temperature(heights, cell_m, illum, opts.thermal, sun_lit=sun_lit, albedo=albedo)
    return EuropaWorld(
        dem, albedo, temperature, sun_lit, jup_lit, illum, opts.thermal, opts.reflectance, seed
    )
