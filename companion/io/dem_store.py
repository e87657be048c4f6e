"""Reading and writing DEM files: our .npz (what sim_bridge writes) and GeoTIFF (what users bring)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from companion.georef.dem import Dem

NPZ_KEYS = ("height_m", "north0_m", "east0_m", "cell_m")


def save_dem_npz(path: str | Path, dem: Dem) -> None:
    """Write ``dem`` losslessly (float32 heights with NaN holes, and the NED placement)."""
    np.savez_compressed(
        Path(path),
        height_m=dem.height_m.astype(np.float32),
        north0_m=dem.north0_m,
        east0_m=dem.east0_m,
        cell_m=dem.cell_m,
    )


def load_dem(
    path: str | Path, origin_en: tuple[float, float] | None = None, origin_alt_m: float = 0.0
) -> Dem:
    """Load a DEM by file type. Raises ValueError naming the file and what was wrong."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"{p}: DEM file not found")
    suffix = p.suffix.lower()
    if suffix == ".npz":
        with np.load(p) as z:
            missing = [k for k in NPZ_KEYS if k not in z]
            if missing:
                raise ValueError(f"{p}: not a DEM .npz (missing {', '.join(missing)})")
            return Dem(
                z["height_m"].astype(np.float32),
                float(z["north0_m"]),
                float(z["east0_m"]),
                float(z["cell_m"]),
            )
    if suffix in (".tif", ".tiff"):
        from companion.io.dem_file import load_geotiff_dem

        return load_geotiff_dem(p, origin_en=origin_en, origin_alt_m=origin_alt_m)
    raise ValueError(f"{p}: unknown DEM format {suffix!r} (expected .tif/.tiff GeoTIFF or .npz)")
