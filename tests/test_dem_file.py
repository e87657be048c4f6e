"""GeoTIFF DEM loading (real SRTM file and written test rasters), and DEM crops at edges and holes."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import tifffile

from companion.georef.dem import Dem
from companion.io.dem_file import load_geotiff_dem
from sim_bridge.terrain import degrade_dem, make_scene

# the real SRTM raster lives in shared/ beside the checkout (as CI lays it out), not in this repository
_SRTM_NAME = "shared/data/srtm_bigtujunga30m_utm11.tif"
SRTM = next(
    (p for p in (Path(__file__).resolve().parents[2] / _SRTM_NAME, Path("/work") / _SRTM_NAME) if p.exists()),
    Path(__file__).resolve().parents[2] / _SRTM_NAME,
)
needs_srtm = pytest.mark.skipif(not SRTM.exists(), reason="shared SRTM test raster not present")

# GeoKeyDirectory: version 1.1.0, 3 keys: GTModelType = projected, GTRasterType (1 area / 2 point),
# ProjectedCSType = 32611 (UTM 11N)
_GEOKEYS_AREA = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 1, 3072, 0, 1, 32611)
_GEOKEYS_POINT = (1, 1, 0, 3, 1024, 0, 1, 1, 1025, 0, 1, 2, 3072, 0, 1, 32611)
_GEOKEYS_GEOGRAPHIC = (1, 1, 0, 2, 1024, 0, 1, 2, 2048, 0, 1, 4326)


def _write(
    path,
    data,
    scale=(2.0, 2.0),
    tie=(0, 0, 500000.0, 4000000.0),
    geokeys=_GEOKEYS_AREA,
    nodata=None,
    transform=None,
):
    tags = [(34735, "H", len(geokeys), geokeys, True)]
    if transform is not None:
        tags.append((34264, "d", 16, tuple(float(v) for v in transform), True))
    else:
        tags.append((33550, "d", 3, (float(scale[0]), float(scale[1]), 0.0), True))
        tags.append((33922, "d", 6, (float(tie[0]), float(tie[1]), 0.0, tie[2], tie[3], 0.0), True))
    if nodata is not None:
        tags.append((42113, "s", 0, str(nodata), True))
    tifffile.imwrite(path, data, extratags=tags)
    return path


@needs_srtm
def test_real_srtm_geotiff_loads_with_shape_cell_nodata_and_range():
    dem = load_geotiff_dem(SRTM)
    raw = tifffile.imread(SRTM)
    assert dem.shape == (643, 1197) == raw.shape
    assert dem.cell_m == pytest.approx(30.0)
    assert dem.height_m.dtype == np.float32
    assert int(np.isnan(dem.height_m).sum()) == int((raw == 32767).sum())
    assert np.nanmin(dem.height_m) == pytest.approx(315.0)
    assert np.nanmax(dem.height_m) == pytest.approx(2295.0)
    # default origin: the raster centre, so the extent is symmetric about N = E = 0
    n0, n1, e0, e1 = dem.extent_ne
    assert n0 == pytest.approx(-n1) and e0 == pytest.approx(-e1)
    assert n1 - n0 == pytest.approx(642 * 30.0) and e1 - e0 == pytest.approx(1196 * 30.0)
    # row 0 is the north edge: the raster's first row is at the top of the map
    np.testing.assert_array_equal(dem.height_m[0], raw[0].astype(np.float32))


@needs_srtm
def test_real_srtm_geotransform_agrees_with_rasterio():
    rasterio = pytest.importorskip("rasterio")
    origin = (380000.0, 3800000.0)
    dem = load_geotiff_dem(SRTM, origin_en=origin, origin_alt_m=1000.0)
    with rasterio.open(SRTM) as ds:
        for row, col in ((0, 0), (642, 1196), (100, 700)):
            x, y = ds.xy(row, col)  # cell centre in UTM metres
            n, e = dem.ne_from_rc(row, col)
            assert float(n) == pytest.approx(y - origin[1], abs=1e-6)
            assert float(e) == pytest.approx(x - origin[0], abs=1e-6)
        band = ds.read(1)
    assert dem.height_m[100, 700] == pytest.approx(float(band[100, 700]) - 1000.0)


def test_written_float_geotiff_nodata_becomes_nan(tmp_path):
    rng = np.random.default_rng(0)
    data = rng.uniform(-4000.0, -3000.0, (50, 80)).astype(np.float32)  # Mars-like elevations
    data[10:14, 20:25] = -9999.0
    data[0, :] = -9999.0
    path = _write(tmp_path / "mars.tif", data, scale=(1.0, 1.0), nodata=-9999)
    dem = load_geotiff_dem(path, origin_alt_m=-3500.0)
    holes = np.isnan(dem.height_m)
    assert holes.sum() == (data == -9999.0).sum() == 4 * 5 + 80
    ok = ~holes
    np.testing.assert_allclose(dem.height_m[ok], data[ok] + 3500.0, rtol=0, atol=1e-3)
    assert dem.cell_m == 1.0


def test_pixel_is_area_and_pixel_is_point_place_cell_centres(tmp_path):
    data = np.zeros((10, 20), np.int16)
    tie = (0, 0, 1000.0, 2000.0)
    area = load_geotiff_dem(_write(tmp_path / "a.tif", data, tie=tie), origin_en=(1000.0, 2000.0))
    point = load_geotiff_dem(
        _write(tmp_path / "p.tif", data, tie=tie, geokeys=_GEOKEYS_POINT), origin_en=(1000.0, 2000.0)
    )
    # pixel-is-area: the tie point is the outer corner, the first centre is half a cell (1 m) in
    assert (area.north0_m, area.east0_m) == pytest.approx((-1.0, 1.0))
    assert (point.north0_m, point.east0_m) == pytest.approx((0.0, 0.0))


def test_model_transformation_tag_is_read(tmp_path):
    data = np.arange(12, dtype=np.float32).reshape(3, 4)
    m = [5.0, 0, 0, 300.0, 0, -5.0, 0, 900.0, 0, 0, 0, 0, 0, 0, 0, 1]
    dem = load_geotiff_dem(_write(tmp_path / "t.tif", data, transform=m), origin_en=(300.0, 900.0))
    assert dem.cell_m == 5.0
    assert (dem.north0_m, dem.east0_m) == pytest.approx((-2.5, 2.5))


def test_bad_files_are_refused_with_the_file_and_the_tag(tmp_path):
    not_tiff = tmp_path / "dem.tif"
    not_tiff.write_bytes(b"this is not a tiff at all")
    with pytest.raises(ValueError, match="not a TIFF"):
        load_geotiff_dem(not_tiff)
    plain = tmp_path / "plain.tif"
    tifffile.imwrite(plain, np.zeros((5, 5), np.float32))
    with pytest.raises(ValueError, match="ModelPixelScaleTag") as e:
        load_geotiff_dem(plain)
    assert "plain.tif" in str(e.value)
    rotated = [5.0, 1.0, 0, 300.0, 1.0, -5.0, 0, 900.0, 0, 0, 0, 0, 0, 0, 0, 1]
    with pytest.raises(ValueError, match="ModelTransformationTag.*rotation"):
        load_geotiff_dem(_write(tmp_path / "rot.tif", np.zeros((5, 5), np.float32), transform=rotated))
    with pytest.raises(ValueError, match="geographic"):
        load_geotiff_dem(
            _write(tmp_path / "geo.tif", np.zeros((5, 5), np.float32), geokeys=_GEOKEYS_GEOGRAPHIC)
        )
    with pytest.raises(ValueError, match="non-square"):
        load_geotiff_dem(_write(tmp_path / "rect.tif", np.zeros((5, 5), np.float32), scale=(2.0, 3.0)))
    with pytest.raises(ValueError, match="single elevation band"):
        load_geotiff_dem(_write(tmp_path / "rgb.tif", np.zeros((5, 5, 3), np.uint8)))
    with pytest.raises(ValueError, match="GDAL_NODATA"):
        load_geotiff_dem(_write(tmp_path / "nd.tif", np.zeros((5, 5), np.float32), nodata="none"))


# ----------------------------------------------------------------------------------------------------------
# crops at the raster edge and near holes (companion.georef.dem.Dem on loaded and degraded DEMs)


@needs_srtm
def test_crop_at_the_raster_edge_is_clipped_and_keeps_georeferencing():
    dem = load_geotiff_dem(SRTM)
    n0, n1, e0, e1 = dem.extent_ne
    corner = dem.crop(n1, e0, 300.0)  # north-west corner, 10 cells each way
    assert corner.shape == (11, 11)
    assert (corner.north0_m, corner.east0_m) == pytest.approx((n1, e0))
    np.testing.assert_array_equal(corner.height_m, dem.height_m[:11, :11])
    inner = dem.crop(0.0, 0.0, 300.0)
    assert inner.shape == (21, 21)
    # heights agree in world coordinates, and off the raster is NaN
    assert float(corner.height_at(n1 - 45.0, e0 + 75.0)[0]) == pytest.approx(
        float(dem.height_at(n1 - 45.0, e0 + 75.0)[0])
    )
    assert np.isnan(dem.height_at(n1 + 1.0, 0.0)[0]) and np.isnan(corner.height_at(n1 - 330.0, e0)[0])
    with pytest.raises(ValueError, match="off the DEM"):
        dem.crop(n1 + 1000.0, 0.0, 300.0)


def test_crop_near_holes_keeps_them_and_filled_removes_them():
    truth = make_scene("01", seed=0, cell_m=0.5, size_m=100.0).dem
    deg, info = degrade_dem(truth, factor=4, hole_fraction=0.05, seed=3)
    holes = np.argwhere(np.isnan(deg.height_m))
    r, c = holes[len(holes) // 2]
    n, e = deg.ne_from_rc(r, c)
    crop = deg.crop(float(n), float(e), 6.0)
    assert np.isnan(crop.height_m).any()
    # bilinear lookups next to a hole are NaN; the filled DEM has no holes and keeps valid cells
    assert np.isnan(deg.height_at(float(n), float(e))[0])
    filled = crop.filled()
    assert not np.isnan(filled.height_m).any()
    ok = ~np.isnan(crop.height_m)
    np.testing.assert_array_equal(filled.height_m[ok], crop.height_m[ok])
    assert (filled.north0_m, filled.east0_m, filled.cell_m) == (crop.north0_m, crop.east0_m, crop.cell_m)
    assert info.cell_m == pytest.approx(2.0)


def test_crop_of_an_edge_with_holes():
    h = np.arange(100, dtype=np.float32).reshape(10, 10)
    h[0, :3] = np.nan
    dem = Dem(h, 45.0, -45.0, 10.0)
    crop = dem.crop(45.0, -45.0, 15.0)
    assert crop.shape == (3, 3)
    assert np.isnan(crop.height_m[0, :3]).all()
    assert crop.filled().hole_fraction() == 0.0
