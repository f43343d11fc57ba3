"""GeoTIFF and hillshade export (lidar_obstacles.io.geotiff)."""
from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from lidar_obstacles.config import DemBuilderConfig, parse_crs, replace
from lidar_obstacles.core.dem import DemGrid, empty_grid
from lidar_obstacles.errors import ConfigError
from lidar_obstacles.io.geotiff import (ExportError, hillshade, read_geotiff,
                                        write_geotiff, write_hillshade_png)


def _grid():
    elevation = np.arange(12, dtype=np.float32).reshape(3, 4)
    elevation[0, 0] = np.nan
    return DemGrid(elevation, np.zeros((3, 4), np.uint8), np.ones((3, 4), np.uint32),
                   np.array([512000.0, 5403000.0]), 2.0)


def test_round_trip_keeps_values_transform_and_crs(tmp_path):
    grid = _grid()
    path = write_geotiff(tmp_path / "dem.tif", grid, crs_epsg=32632)
    back = read_geotiff(path)
    assert np.array_equal(back.elevation, grid.elevation, equal_nan=True)
    assert back.elevation.dtype == np.float32
    assert np.array_equal(back.origin, grid.origin) and back.resolution == 2.0
    assert back.epsg == 32632 and back.nodata == "nan"
    assert [p.name for p in tmp_path.iterdir()] == ["dem.tif"]  # no temp file left
    mask = os.umask(0)
    os.umask(mask)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask  # as open() would make it


def test_file_is_north_up(tmp_path):
    import tifffile

    path = write_geotiff(tmp_path / "dem.tif", _grid(), crs_epsg=None, crs_wkt="")
    raw = tifffile.imread(path)
    assert raw[0].tolist() == [8.0, 9.0, 10.0, 11.0]  # first file row = top = largest y
    with tifffile.TiffFile(path) as tif:
        tags = {t.code: t.value for t in tif.pages[0].tags.values()}
    assert tuple(tags[33922])[3:5] == (512000.0, 5403006.0)  # upper-left corner
    assert tuple(tags[33550])[:2] == (2.0, 2.0)


def test_wkt_citation_is_kept_beside_the_code(tmp_path):
    from pyproj import CRS

    wkt = CRS.from_epsg(28992).to_wkt()
    back = read_geotiff(write_geotiff(tmp_path / "a.tif", _grid(), crs_epsg=28992,
                                      crs_wkt=wkt))
    assert back.epsg == 28992 and back.citation == wkt


def test_gdal_reads_transform_and_nodata(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    path = write_geotiff(tmp_path / "dem.tif", _grid(), crs_epsg=32632)
    with rasterio.open(path) as ds:
        assert tuple(ds.transform)[:6] == (2.0, 0.0, 512000.0, 0.0, -2.0, 5403006.0)
        assert np.isnan(ds.nodata)
        assert ds.crs.to_epsg() == 32632
        band = ds.read(1)
        assert band[2, 1] == 1.0 and np.isnan(band[2, 0])
        # the centre of DemGrid cell (row 0, col 1) maps back to file row 2, col 1
        assert ds.index(512003.0, 5403001.0) == (2, 1)


ESRI_UTM32_ETRS89 = (
    'PROJCS["ETRS_1989_UTM_Zone_32N",GEOGCS["GCS_ETRS_1989",DATUM["D_ETRS_1989",SPHEROID['
    '"GRS_1980",6378137.0,298.257222101]],PRIMEM["Greenwich",0.0],UNIT["Degree",'
    '0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",'
    '500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",9.0],'
    'PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]')


@pytest.mark.parametrize("epsg, wkt, keys", [
    (32632, "", {3072: 32632}),
    # projected, in the 4000s: keyed as geographic by the code's range before
    (4647, "", {3072: 4647}),
    # a projected CRS with its heights: the heights' code in VerticalCSTypeGeoKey
    (7415, "", {3072: 28992, 4096: 5709}),
    # ESRI's WKT (LAS 1.4's usual) names no code: the one it matches; it was a citation only
    (None, ESRI_UTM32_ETRS89, {3072: 25832, 1026: 0}),  # (1026: the citation, at 0)
])
def test_the_crs_goes_in_the_keys_epsg_has_for_it(tmp_path, epsg, wkt, keys):
    """GTModelTypeGeoKey (1024) projected (1), and the code in ProjectedCSTypeGeoKey
    (3072), as EPSG's database says of it, not its range; GDAL reads it back."""
    import tifffile

    path = write_geotiff(tmp_path / "dem.tif", _grid(), crs_epsg=epsg, crs_wkt=wkt)
    with tifffile.TiffFile(path) as tif:
        words = list(tif.pages[0].tags[34735].value)
    assert {words[i]: words[i + 3] for i in range(4, len(words), 4)} == {
        1024: 1, 1025: 1, **keys}  # (1025: PixelIsArea)
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(path) as ds:
        assert ds.crs.is_projected and ds.crs.to_epsg() in (epsg, keys[3072])


@pytest.mark.parametrize("text, message", [
    ("EPSG:4326", r"EPSG:4326 is geographic \(WGS 84\): its x and y are degrees"),
    ("EPSG:7844", "EPSG:7844 is geographic"),  # (GDA2020: keyed as projected before)
    ("EPSG:4978", "EPSG:4978 is a geocentric CRS"),
    ("EPSG:5709", "EPSG:5709 is a vertical CRS"),
    ("EPSG:1234", "EPSG:1234 is not a CRS in the EPSG database"),
    ('GEOGCS["WGS 84"]', "the WKT is no CRS pyproj can read"),
])
def test_a_crs_a_dem_cannot_be_in_is_refused(tmp_path, text, message):
    with pytest.raises(ConfigError, match=message):
        replace(DemBuilderConfig(), {"export.crs": text})
    code = int(text[5:]) if text.startswith("EPSG:") else None
    with pytest.raises(ExportError, match=message):
        write_geotiff(tmp_path / "dem.tif", _grid(), crs_epsg=code,
                      crs_wkt="" if code else text)
    assert list(tmp_path.iterdir()) == []


def test_errors_leave_nothing_behind(tmp_path):
    with pytest.raises(ExportError):
        write_geotiff(tmp_path / "missing" / "dem.tif", _grid(), crs_epsg=None)
    with pytest.raises(ExportError, match="empty"):
        write_geotiff(tmp_path / "dem.tif", empty_grid(1.0, "no ground points"), crs_epsg=None)
    # a folder name the system refuses raised OSError from the check itself, which took
    # `dem_builder` down from its save_dem service (as a folder one may not search does)
    with pytest.raises(ExportError, match="cannot write .*name too long"):
        write_geotiff(tmp_path / ("x" * 300) / "dem.tif", _grid(), crs_epsg=None)
    assert list(tmp_path.iterdir()) == []


def test_parse_crs():
    assert parse_crs("EPSG:32632") == (32632, "")
    assert parse_crs("epsg:28992") == (28992, "")
    assert parse_crs("") == (None, "")
    assert parse_crs(ESRI_UTM32_ETRS89) == (None, ESRI_UTM32_ETRS89)
    with pytest.raises(ConfigError):
        parse_crs("UTM 32")
    # refused when set (a file, -p, set_parameters), not first at save_dem
    assert replace(DemBuilderConfig(), {"export.crs": "epsg:32632"}).export.crs == "epsg:32632"
    with pytest.raises(ConfigError, match="export.crs.*'foo' is neither"):
        replace(DemBuilderConfig(), {"export.crs": "foo"})


@pytest.mark.parametrize("text, message", [
    # a GeoTIFF key is 16 bits: 65536 crashed the writer (struct.error, exit 1)
    ("EPSG:65536", "EPSG code 65536 does not fit a GeoTIFF key"),
    ("EPSG:123456", "EPSG code 123456 does not fit"),
    ("EPSG:0000", "EPSG code 0 does not fit"),
    # a '[' was enough to be written as the CRS's WKT
    ("PROJCS[garbage", "is neither EPSG:<code> nor a CRS WKT"),
    ("hello [world]", "is neither EPSG:<code> nor a CRS WKT"),
    ('GEOGCS["WGS 84"]]', "is neither EPSG:<code> nor a CRS WKT"),
])
def test_a_crs_geotiff_cannot_hold_is_refused_when_set(text, message):
    with pytest.raises(ConfigError, match=message):
        replace(DemBuilderConfig(), {"export.crs": text})


def test_wkt_forms_are_accepted():
    from pyproj import CRS
    from pyproj.enums import WktVersion

    wkt2 = CRS.from_epsg(32632).to_wkt(WktVersion.WKT2_2019)
    assert parse_crs(wkt2) == (None, wkt2)
    compound = "  " + CRS.from_epsg(7415).to_wkt(WktVersion.WKT1_GDAL) + " "
    assert parse_crs(compound)[1].startswith("COMPD_CS")


def test_hillshade_png(tmp_path):
    from PIL import Image

    y, x = np.mgrid[0:30, 0:40].astype(float)
    grid = DemGrid((0.5 * x).astype(np.float32), np.zeros((30, 40), np.uint8),
                   np.ones((30, 40), np.uint32), np.zeros(2), 1.0)
    shade = hillshade(grid.elevation, 1.0)
    flat = hillshade(np.zeros((3, 3)), 1.0)[0, 0]
    # light from the north-west: a slope facing west (rising eastwards) is lit more than
    # flat ground, one facing east less; rows grow northwards, so z = 0.5 row rises to the
    # north, faces south, away from the light
    assert np.allclose(shade, shade[0, 0]) and shade[0, 0] > flat
    assert hillshade(-grid.elevation, 1.0)[0, 0] < flat
    assert hillshade(0.5 * y, 1.0)[0, 0] < flat < hillshade(-0.5 * y, 1.0)[0, 0]
    path = write_hillshade_png(tmp_path / "dem.png", grid)
    with Image.open(path) as img:
        assert img.size == (40, 30) and img.mode == "RGBA"


def test_hillshade_slopes_are_per_metre_not_per_cell():
    # z rising 1 m per 2 m cell eastwards is a slope of 0.5. Light from azimuth 315,
    # altitude 45 degrees: direction (-0.5, 0.5, 0.7071), the surface normal (-s, 0, 1) /
    # sqrt(1 + s^2), so the shade is (0.5 s + 0.7071) / sqrt(1 + s^2) = 0.8561 for s = 0.5
    ramp = np.tile(np.arange(6.0), (5, 1))
    expected = (0.25 + np.sqrt(0.5)) / np.sqrt(1.25)
    np.testing.assert_allclose(hillshade(ramp, 2.0), expected)
    np.testing.assert_allclose(hillshade(0.5 * ramp, 1.0), expected)


@pytest.mark.skipif(not os.path.exists("/proc/self/status"), reason="Linux /proc only")
def test_file_mode_follows_umask_without_changing_it(tmp_path, monkeypatch):
    """The mode is what open() would give under the umask of the moment, and the umask is
    read from /proc, never set: setting it (even back at once) races with other threads."""
    old = os.umask(0o027)
    try:
        real_umask, calls = os.umask, []
        monkeypatch.setattr(os, "umask", lambda mask: calls.append(mask) or real_umask(mask))
        tif = write_geotiff(tmp_path / "dem.tif", _grid(), crs_epsg=None)
        png = write_hillshade_png(tmp_path / "dem.png", _grid())
        monkeypatch.undo()
        assert calls == []
        assert stat.S_IMODE(tif.stat().st_mode) == 0o640  # 0o666 & ~0o027
        assert stat.S_IMODE(png.stat().st_mode) == 0o640
        assert os.umask(0o027) == 0o027  # unchanged afterwards
    finally:
        os.umask(old)


@pytest.mark.parametrize("path", ["", "  ", "out/", ".", "x/.."])
def test_an_export_path_that_names_no_file_is_refused_when_set(path):
    # "" was taken, and `save_dem` then answered "<cwd> exists and is not a TIFF"
    with pytest.raises(ConfigError, match="export.path.*names no file"):
        replace(DemBuilderConfig(), {"export.path": path})
    assert replace(DemBuilderConfig(), {"export.path": "out/dem.tif"}).export.path == \
        "out/dem.tif"
