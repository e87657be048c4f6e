"""Load a user's DEM from a GeoTIFF (HiRISE DTMs, SRTM tiles, ...) into a ``Dem`` in the local NED frame.

Read with tifffile (no GDAL needed): the elevation band, the affine geotransform from ModelPixelScaleTag +
ModelTiepointTag (or ModelTransformationTag), GDAL_NODATA, and GTRasterTypeGeoKey (pixel-is-area: the
tie point is the outer corner of the first pixel; pixel-is-point: its centre). Projected rasters only
(metres east / north, e.g. UTM or a Mars equirectangular DTM); the local frame is a plane tangent at the
chosen origin: north = Y - Y0, east = X - X0, height = elevation - origin_alt_m.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import tifffile

from companion.georef.dem import Dem

_TAG_PIXEL_SCALE = 33550
_TAG_TIEPOINT = 33922
_TAG_TRANSFORMATION = 34264
_TAG_GEOKEYS = 34735
_TAG_GDAL_NODATA = 42113
_KEY_RASTER_TYPE = 1025  # GTRasterTypeGeoKey: 1 = PixelIsArea, 2 = PixelIsPoint
_KEY_GEOGRAPHIC_TYPE = 2048
_KEY_MODEL_TYPE = 1024  # GTModelTypeGeoKey: 1 = projected, 2 = geographic


def _geokeys(page: tifffile.TiffPage) -> dict[int, int]:
    tag = page.tags.get(_TAG_GEOKEYS)
    if tag is None:
        return {}
    v = [int(x) for x in tag.value]
    keys = {}
    for i in range(v[3]):
        key_id, loc, _count, value = v[4 + 4 * i : 8 + 4 * i]
        if loc == 0:  # value stored inline (SHORT); other locations hold doubles / ASCII we do not need
            keys[key_id] = value
    return keys


def _nodata(page: tifffile.TiffPage, path: Path) -> float | None:
    tag = page.tags.get(_TAG_GDAL_NODATA)
    if tag is None:
        return None
    raw = tag.value
    text = raw.decode("ascii", "replace") if isinstance(raw, bytes) else str(raw)
    text = text.strip().strip("\x00").strip()
    if text == "":
        return None
    try:
        return float(text)
    except ValueError as exc:
        raise ValueError(f"{path}: GDAL_NODATA tag is {text!r}, expected a number") from exc


def load_geotiff_dem(
    path: str | Path,
    origin_en: tuple[float, float] | None = None,
    origin_alt_m: float = 0.0,
) -> Dem:
    """Read a single-band elevation GeoTIFF into a north-up ``Dem`` (float32 heights, nodata -> NaN).

    origin_en: projected (X easting, Y northing) of the local NED origin; None = the raster centre.
    origin_alt_m: elevation of the origin (heights are elevation - origin_alt_m).
    Raises ValueError naming the file, the tag and what was expected for anything it cannot honour
    (not a TIFF, no georeferencing, rotated or south-up transform, several bands, geographic degrees).
    """
    path = Path(path)
    # tifffile logs a warning when GDAL_NODATA does not fit the sample type (SRTM int16 tiles say 32767):
    # we parse that tag ourselves, so silence tifffile's warnings while it parses the page
    tf_log = logging.getLogger("tifffile")
    level = tf_log.level
    tf_log.setLevel(logging.ERROR)
    try:
        return _load(path, origin_en, origin_alt_m)
    finally:
        tf_log.setLevel(level)


def _load(path: Path, origin_en: tuple[float, float] | None, origin_alt_m: float) -> Dem:
    try:
        tif = tifffile.TiffFile(path)
    except (tifffile.TiffFileError, ValueError) as exc:
        raise ValueError(f"{path}: not a TIFF file ({exc})") from exc
    with tif:
        page = tif.pages.first
        keys = _geokeys(page)
        if keys.get(_KEY_MODEL_TYPE) == 2 or (_KEY_GEOGRAPHIC_TYPE in keys and _KEY_MODEL_TYPE not in keys):
            raise ValueError(
                f"{path}: GTModelTypeGeoKey says geographic (degrees); expected a projected raster in "
                "metres (reproject it, e.g. gdalwarp -t_srs to UTM or a local projection)"
            )
        scale_tag = page.tags.get(_TAG_PIXEL_SCALE)
        tie_tag = page.tags.get(_TAG_TIEPOINT)
        trans_tag = page.tags.get(_TAG_TRANSFORMATION)
        if trans_tag is not None:
            m = np.asarray(trans_tag.value, float).reshape(4, 4)
            if abs(m[0, 1]) > 1e-9 * abs(m[0, 0]) or abs(m[1, 0]) > 1e-9 * abs(m[1, 1]):
                raise ValueError(
                    f"{path}: ModelTransformationTag has rotation/shear terms ({m[0, 1]}, {m[1, 0]}); "
                    "expected a north-up raster (warp it to north-up first)"
                )
            sx, sy = m[0, 0], -m[1, 1]
            x_corner, y_corner = m[0, 3], m[1, 3]  # model coords of raster point (0, 0)
        elif scale_tag is not None and tie_tag is not None:
            sc = [float(v) for v in scale_tag.value]
            tp = [float(v) for v in tie_tag.value]
            if len(tp) != 6:
                raise ValueError(
                    f"{path}: ModelTiepointTag has {len(tp) // 6} tie points; expected exactly 1 "
                    "(rasters georeferenced by several control points need warping first)"
                )
            sx, sy = sc[0], sc[1]
            i0, j0, x0, y0 = tp[0], tp[1], tp[3], tp[4]
            x_corner, y_corner = x0 - i0 * sx, y0 + j0 * sy
        else:
            raise ValueError(
                f"{path}: no ModelPixelScaleTag + ModelTiepointTag or ModelTransformationTag; "
                "expected a GeoTIFF with an affine geotransform"
            )
        if not (sx > 0 and sy > 0):
            raise ValueError(
                f"{path}: pixel scale ({sx}, {sy}) must be positive with rows going south; "
                "expected a north-up raster"
            )
        if abs(sx - sy) > 1e-6 * max(sx, sy):
            raise ValueError(
                f"{path}: ModelPixelScaleTag gives non-square cells ({sx} x {sy} m); expected square cells "
                "(resample it first)"
            )
        data = page.asarray()
        nodata = _nodata(page, path)
    if data.ndim == 3 and 1 in (data.shape[0], data.shape[-1]):
        data = data.squeeze()
    if data.ndim != 2:
        raise ValueError(f"{path}: raster has shape {data.shape}; expected a single elevation band")
    if not (np.issubdtype(data.dtype, np.integer) or np.issubdtype(data.dtype, np.floating)):
        raise ValueError(
            f"{path}: SampleFormat gives dtype {data.dtype}; expected integer or float elevations"
        )
    h = data.astype(np.float32)
    invalid = ~np.isfinite(h)
    if nodata is not None:
        invalid |= data == nodata if np.issubdtype(data.dtype, np.integer) else np.isclose(h, nodata)
    h[invalid] = np.nan
    h -= np.float32(origin_alt_m)

    # pixel-is-area: (x_corner, y_corner) is the outer corner of cell (0, 0); its centre is half a cell in
    if keys.get(_KEY_RASTER_TYPE, 1) == 2:
        x_c, y_c = x_corner, y_corner
    else:
        x_c, y_c = x_corner + 0.5 * sx, y_corner - 0.5 * sy
    rows, cols = h.shape
    if origin_en is None:
        origin_en = (x_c + (cols - 1) / 2.0 * sx, y_c - (rows - 1) / 2.0 * sy)
    east0 = x_c - float(origin_en[0])
    north0 = y_c - float(origin_en[1])
    return Dem(h, float(north0), float(east0), float(sx))
