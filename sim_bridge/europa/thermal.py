"""Europa's light sources and surface temperature (paper 2 section 4.3). Pure numpy/OpenCV.

Temperature per terrain cell: absorbed irradiance from the Sun and Jupiter (paper's figures: 50 W/m^2,
0.0897 W/m^2 and 0.0001 W/m^2 for sunlight reflected by Jupiter) on the facet's normal, cast shadows
from the DEM, times (1 - bolometric Bond albedo 0.68); then Stefan-Boltzmann for a grey body with
emissivity 0.94, then a few smoothing passes standing for lateral heat diffusion at first order.

One addition to the paper's instantaneous model, on by default and documented at ``ThermalOptions``:
a constant conducted/re-radiated flux that holds unlit ice near Europa's observed night-side
temperature instead of the ~27 K that Jupiter alone would give. Setting it to 0 gives the paper's model.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from companion.georef.shading import Sun, cast_shadow_mask, slopes

STEFAN_BOLTZMANN_W_M2_K4 = 5.670374419e-8
"""Stefan-Boltzmann constant sigma (W m^-2 K^-4)."""


@dataclass(frozen=True)
class Illumination:
    """Sky of a site on Europa's equator, angles in degrees (azimuth clockwise from north).

    Defaults: local solar time 09:00 (hour angle -45 deg; Europa's obliquity is ~0.1 deg, so the Sun is
    45 deg up due east), at a site 40 deg of longitude east of the sub-Jovian point, so Jupiter (fixed
    in the sky of a tidally locked moon) stands 50 deg up due west. Irradiances and apparent sizes are
    the paper's (section 4.3).
    """

    sun_azimuth_deg: float = 90.0
    sun_elevation_deg: float = 45.0
    sun_irradiance_w_m2: float = 50.0
    sun_apparent_diameter_arcmin: float = 6.14  # point source: penumbra < 1 cm for 30 m relief
    jupiter_azimuth_deg: float = 270.0
    jupiter_elevation_deg: float = 50.0
    jupiter_irradiance_w_m2: float = 0.0897  # Jupiter's own (thermal) emission at Europa
    jupiter_reflected_w_m2: float = 0.0001  # sunlight reflected by Jupiter (the only visible-band part)
    jupiter_apparent_diameter_arcmin: float = 717.55  # treated as a point at the disc centre

    @property
    def sun(self) -> Sun:
        return Sun.from_degrees(self.sun_irradiance_w_m2, self.sun_azimuth_deg, self.sun_elevation_deg)

    @property
    def jupiter(self) -> Sun:
        return Sun.from_degrees(
            self.jupiter_irradiance_w_m2 + self.jupiter_reflected_w_m2,
            self.jupiter_azimuth_deg,
            self.jupiter_elevation_deg,
        )


@dataclass(frozen=True)
class ThermalOptions:
    """Surface energy balance (paper 2 section 4.3)."""

    bond_albedo: float = 0.68  # bolometric Bond albedo (paper)
    emissivity: float = 0.94  # grey-body emissivity (paper)
    smoothing_passes: int = 4  # 3x3 box passes on the temperature ("several smoothing passes");
    # 4 passes spread heat over ~1.6 cells rms (0.4 m at 0.25 m cells)
    albedo_coupling: float = 0.0  # local Bond albedo = bond_albedo * (1 + c (albedo / mean - 1)): 0 keeps
    # the paper's single 0.68; 1 makes the darker splotches and striae of the albedo map absorb
    # proportionally more (physically expected, e.g. Europa's darker terrains are warmer)
    night_temperature_k: float = 80.0  # adds the flux eps*sigma*T^4 that keeps unlit ice at this
    # temperature (Galileo PPR night-side ~80-95 K): stands for thermal inertia and re-radiation from
    # neighbouring terrain, which the paper's instantaneous model leaves out. 0 = the paper's model.


def facet_cosines(height_m: np.ndarray, cell_m: float, direction_enu: np.ndarray) -> np.ndarray:
    """(rows, cols) float32 max(n . d, 0) for the unit facet normal n and a unit direction (E, N, U)."""
    dh_de, dh_dn = slopes(height_m, cell_m)
    d_e, d_n, d_u = (float(x) for x in direction_enu)
    ndots = (-dh_de * d_e - dh_dn * d_n + d_u) / np.sqrt(1.0 + dh_de * dh_de + dh_dn * dh_dn)
    return np.maximum(ndots, 0.0).astype(np.float32)


def lit_fraction(height_m: np.ndarray, cell_m: float, source: Sun) -> np.ndarray:
    """(rows, cols) float32, 1 where ``source`` is visible from the cell, 0 in cast shadow."""
    return (~cast_shadow_mask(height_m, cell_m, source)).astype(np.float32)


def absorbed_flux(
    height_m: np.ndarray,
    cell_m: float,
    illum: Illumination,
    opts: ThermalOptions,
    sun_lit: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
) -> np.ndarray:
    """(rows, cols) float32 absorbed flux (W/m^2) incl. the night-side term of ``opts``.

    sun_lit: optional precomputed ``lit_fraction`` for the Sun (it is also used by the visible renderer).
    albedo: the (visible) albedo map, used only when ``opts.albedo_coupling`` is not 0."""
    sun, jup = illum.sun, illum.jupiter
    lit_s = lit_fraction(height_m, cell_m, sun) if sun_lit is None else sun_lit
    lit_j = lit_fraction(height_m, cell_m, jup)
    incident = sun.intensity * facet_cosines(height_m, cell_m, sun.direction_enu) * lit_s
    incident += jup.intensity * facet_cosines(height_m, cell_m, jup.direction_enu) * lit_j
    floor = opts.emissivity * STEFAN_BOLTZMANN_W_M2_K4 * opts.night_temperature_k**4
    bond: float | np.ndarray = opts.bond_albedo
    if opts.albedo_coupling and albedo is not None:
        rel = albedo / float(np.mean(albedo)) - 1.0
        bond = np.clip(opts.bond_albedo * (1.0 + opts.albedo_coupling * rel), 0.0, 0.99)
    return ((1.0 - bond) * incident + floor).astype(np.float32)


def equilibrium_temperature(absorbed_w_m2: np.ndarray, emissivity: float) -> np.ndarray:
    """Grey-body radiative equilibrium T = (E_abs / (eps sigma))^(1/4), K, same shape, float32."""
    return np.power(np.maximum(absorbed_w_m2, 0.0) / (emissivity * STEFAN_BOLTZMANN_W_M2_K4), 0.25).astype(
        np.float32
    )


def surface_temperature(
    height_m: np.ndarray,
    cell_m: float,
    illum: Illumination,
    opts: ThermalOptions,
    sun_lit: np.ndarray | None = None,
    albedo: np.ndarray | None = None,
) -> np.ndarray:
    """(rows, cols) float32 surface temperature (K): equilibrium, then ``opts.smoothing_passes`` 3x3 passes."""
    flux = absorbed_flux(height_m, cell_m, illum, opts, sun_lit, albedo)
    t = equilibrium_temperature(flux, opts.emissivity)
    for _ in range(opts.smoothing_passes):
        t = cv2.blur(t, (3, 3), borderType=cv2.BORDER_REPLICATE)
    return t
