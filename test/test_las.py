"""LAS/LAZ reading: a file cut short is called truncated, whatever laspy says of it; the
CRS's EPSG code is that of the whole CRS, never of a part of it."""
from __future__ import annotations

import re

import laspy
import numpy as np
import pytest

from conftest import data_file
from lidar_obstacles.errors import LasError
from lidar_obstacles.io.las import read_las

SAMPLE = "isprs/samp11-utm.laz"


def test_a_truncated_laz_file_is_named_as_such(tmp_path):
    full = data_file(SAMPLE).read_bytes()
    cut = tmp_path / "trunc.laz"
    cut.write_bytes(full[:len(full) // 2])  # (lazrs: "IoError: failed to fill whole buffer")
    with pytest.raises(LasError, match=rf"^cannot read LAS file {re.escape(str(cut))}: "
                                       r"truncated or corrupt \(.+\)$"):
        read_las(cut)


@pytest.mark.parametrize("records_left", [1000, 1000.5, 0, 38009])  # (38009: the last one)
def test_a_truncated_las_file_is_named_as_such(tmp_path, records_left):
    """Cut inside a record laspy failed with "buffer size must be a multiple of element
    size"; cut between records it read the points left without a word (none: "no points")."""
    full = tmp_path / "full.las"
    laspy.read(str(data_file(SAMPLE))).write(str(full))
    with laspy.open(str(full)) as reader:
        header = reader.header
    cut = tmp_path / "trunc.las"
    cut.write_bytes(full.read_bytes()[:header.offset_to_point_data
                                      + int(records_left * header.point_format.size)])
    with pytest.raises(LasError, match=rf"^cannot read LAS file {re.escape(str(cut))}: "
                                       r"truncated or corrupt \(\d+ bytes, but its header "
                                       r"says 38010 points"):
        read_las(cut)
    assert len(read_las(full).points) == 38010  # (the whole file is read as before)


@pytest.mark.parametrize("major, minor, ok", [(1, 2, True), (1, 0, True), (9, 2, False),
                                              (1, 7, False), (0, 2, False)])
def test_a_las_version_of_none_of_1_0_to_1_4_is_a_corrupt_header(tmp_path, major, minor, ok):
    # laspy read a file whose header said LAS 9.2 without a word
    las = laspy.LasData(laspy.LasHeader(point_format=1, version="1.2"))
    las.x, las.y, las.z = np.arange(5.0), np.arange(5.0), np.zeros(5)
    path = tmp_path / "v.las"
    las.write(str(path))
    raw = bytearray(path.read_bytes())
    raw[24:26] = bytes([major, minor])  # the header's version major, minor
    path.write_bytes(bytes(raw))
    if ok:
        assert len(read_las(path).points) == 5
    else:
        said = (f"cannot read LAS file {path}: its header says LAS {major}.{minor}, none of "
                "1.0-1.4: the header is corrupt")
        with pytest.raises(LasError, match=f"^{re.escape(said)}$"):
            read_las(path)


UTM32 = ('PROJCS["WGS 84 / UTM zone 32N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
         '6378137,298.257223563,AUTHORITY["EPSG","7030"]],AUTHORITY["EPSG","6326"]],'
         'PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433],AUTHORITY["EPSG","4326"]],'
         'PROJECTION["Transverse_Mercator"],PARAMETER["central_meridian",9],'
         'UNIT["metre",1,AUTHORITY["EPSG","9001"]]{}]')


def _las_with(tmp_path, vlr) -> laspy.LasData:
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.vlrs.append(vlr)
    las = laspy.LasData(header)
    las.x, las.y, las.z = [0.0, 1.0], [0.0, 1.0], [0.0, 1.0]
    las.write(str(tmp_path / "crs.las"))
    return read_las(tmp_path / "crs.las")


@pytest.mark.parametrize("wkt, epsg", [
    (UTM32.format(',AUTHORITY["EPSG","32632"]'), 32632),
    # a custom projection: the last authority inside was taken, the unit's (EPSG:9001)
    (UTM32.format(""), None),
    ('PROJCRS["UTM 32N",BASEGEOGCRS["WGS 84",DATUM["WGS84",ELLIPSOID["WGS 84",6378137,'
     '298.257223563]],ID["EPSG",4326]],CS[Cartesian,2],ID["EPSG",32632]]', 32632),  # WKT2
    ('PROJCRS["custom",BASEGEOGCRS["WGS 84",DATUM["WGS84",ELLIPSOID["WGS 84",6378137,'
     '298.257223563]],ID["EPSG",4326]],CS[Cartesian,2]]', None),  # not its base's 4326
    # ESRI's WKT names no code (LAS 1.4's usual): the one it matches in EPSG's database;
    # it was None, and the GeoTIFF had the CRS as a citation only
    ('PROJCS["ETRS_1989_UTM_Zone_32N",GEOGCS["GCS_ETRS_1989",DATUM["D_ETRS_1989",SPHEROID['
     '"GRS_1980",6378137.0,298.257222101]],PRIMEM["Greenwich",0.0],UNIT["Degree",'
     '0.0174532925199433]],PROJECTION["Transverse_Mercator"],PARAMETER["False_Easting",'
     '500000.0],PARAMETER["False_Northing",0.0],PARAMETER["Central_Meridian",9.0],'
     'PARAMETER["Scale_Factor",0.9996],PARAMETER["Latitude_Of_Origin",0.0],UNIT["Meter",1.0]]',
     25832),
])
def test_the_epsg_code_of_a_wkt_is_that_of_the_whole_crs(tmp_path, wkt, epsg):
    from laspy.vlrs.known import WktCoordinateSystemVlr

    las = _las_with(tmp_path, WktCoordinateSystemVlr(wkt))
    assert (las.crs_wkt, las.epsg) == (wkt, epsg)


@pytest.mark.parametrize("keys, epsg", [
    ({1024: 1, 3072: 32632}, 32632),
    ({1024: 2, 2048: 4326}, 4326),
    # a user-defined projection on WGS 84 was taken for WGS 84 itself
    ({1024: 1, 2048: 4326, 3072: 32767}, None),
])
def test_the_epsg_code_of_geokeys_is_the_projected_one(tmp_path, keys, epsg):
    import struct

    from laspy.vlrs.known import GeoKeyDirectoryVlr

    vlr = GeoKeyDirectoryVlr()
    words = [1, 1, 0, len(keys)] + [v for k in sorted(keys) for v in (k, 0, 1, keys[k])]
    vlr.parse_record_data(struct.pack(f"<{len(words)}H", *words))
    assert _las_with(tmp_path, vlr).epsg == epsg


def test_coordinates_are_metres_by_the_files_scales_and_offsets(tmp_path):
    """A LAS file stores integers; x = X * scale + offset. Raw integers, or a scale or
    offset of the wrong axis, are kilometres off. The classification is the class alone,
    without the flag bits that share its byte in point formats 0-5."""
    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales = [0.01, 0.02, 0.001]
    header.offsets = [500000.0, 5400000.0, -10.0]
    las = laspy.LasData(header)
    las.X, las.Y, las.Z = [12, 150], [0, 7], [10500, 0]
    las.classification = [2, 6]
    las.withheld = [False, True]  # (bit 7 of the same byte)
    las.intensity = [7, 65535]
    las.gps_time = [1.5, 2.25]
    las.write(str(tmp_path / "scaled.las"))
    cloud = read_las(tmp_path / "scaled.las")
    np.testing.assert_allclose(cloud.xyz, [[500000.12, 5400000.0, 0.5],
                                           [500001.5, 5400000.14, -10.0]], rtol=0, atol=1e-9)
    assert cloud.points["classification"].tolist() == [2, 6]
    assert cloud.points["intensity"].tolist() == [7, 65535]
    assert cloud.has_gps_time and cloud.points["gps_time"].tolist() == [1.5, 2.25]


@pytest.mark.parametrize("scale, offset, message", [
    (float("nan"), 0.0, r"scales \[nan, nan, nan\] / offsets .* the header is corrupt"),
    (0.0, 0.0, r"cannot give coordinates \(not finite, or a zero scale\)"),
    (0.01, float("inf"), r"the header is corrupt"),
    # finite, but no survey lies there: overflowed into inf downstream, or a crash in
    # `simplify` (cKDTree: "data must be finite")
    (1e300, 0.0, r"its coordinates reach 1\.2e\+303 m, beyond 1e\+08 m of any survey"),
])
def test_a_header_whose_scales_or_offsets_give_no_survey_is_refused(tmp_path, scale, offset,
                                                                    message):
    """Scales and offsets are written into the header's bytes (laspy will not write
    them): LAS 1.2 keeps them as six float64 from byte 131."""
    import struct

    header = laspy.LasHeader(point_format=1, version="1.2")
    header.scales, header.offsets = [1.0] * 3, [0.0] * 3
    las = laspy.LasData(header)
    las.X, las.Y, las.Z = [1200, 5], [0, 7], [3, 0]
    path = tmp_path / "bad.las"
    las.write(str(path))
    data = bytearray(path.read_bytes())
    data[131:179] = struct.pack("<6d", *([scale] * 3 + [offset] * 3))
    path.write_bytes(bytes(data))
    with pytest.raises(LasError, match=message):
        read_las(path)


def test_an_unknown_point_format_is_named(tmp_path):
    # laspy's error is the number alone: "cannot read LAS file bad.las: 42"
    header = laspy.LasHeader(point_format=1, version="1.2")
    las = laspy.LasData(header)
    las.X, las.Y, las.Z = [1, 2], [3, 4], [5, 6]
    path = tmp_path / "bad.las"
    las.write(str(path))
    data = bytearray(path.read_bytes())
    data[104] = 42  # LAS 1.2: the point data format id
    path.write_bytes(bytes(data))
    with pytest.raises(LasError, match=r"point format 42 is not one of LAS 1\.0-1\.4's"):
        read_las(path)


def test_a_missing_source_of_a_subset_is_a_las_error(tmp_path):
    from lidar_obstacles.io.las import write_las_subset

    with pytest.raises(LasError, match="cannot read LAS file .*nope.las: No such file"):
        write_las_subset(tmp_path / "nope.las", np.ones(3, bool), tmp_path / "out.las")
