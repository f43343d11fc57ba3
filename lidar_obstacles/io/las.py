"""LAS/LAZ reading (laspy with the lazrs backend) into plain NumPy.

The survey is returned as one structured array so the rest of the package sees the same
kind of points whether they came from a file, a bag or the simulator.
"""
from __future__ import annotations

import datetime
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lidar_obstacles.errors import LasError
from lidar_obstacles.io.crs import epsg_of_wkt

if TYPE_CHECKING:  # laspy is imported on first use
    from laspy import LasData

# Fields carried from LAS into PointCloud2, with the dtype they get there.
LAS_FIELDS: tuple[tuple[str, str], ...] = (
    ("intensity", "<u2"),
    ("return_number", "u1"),
    ("number_of_returns", "u1"),
    ("classification", "u1"),
    ("gps_time", "<f8"),
    ("point_source_id", "<u2"),  # the flight line (las2bag slices by it without GPS time)
)


@dataclass(frozen=True)
class LasCloud:
    """A whole LAS/LAZ survey.

    points: (N,) structured array with ``x y z`` float64 (metres, file CRS) and the
        ``LAS_FIELDS`` the file has (gps_time only when the point format has it).
    crs_wkt: the file's CRS as WKT, or "" when the file states none.
    epsg: the EPSG code when one can be read from the CRS records, else None.
    has_gps_time: whether the point format records GPS time.
    gps_adjusted: whether the header says that time is adjusted standard GPS time
        (global encoding bit 0), not seconds of the GPS week.
    created: the header's file creation day, or None when it has none.
    """

    points: np.ndarray
    crs_wkt: str
    epsg: int | None
    has_gps_time: bool
    gps_adjusted: bool = False
    created: datetime.date | None = None

    @property
    def xyz(self) -> np.ndarray:
        """(N, 3) float64 coordinates in metres."""
        return np.column_stack([self.points["x"], self.points["y"], self.points["z"]])


def _crs_from_vlrs(header) -> tuple[str, int | None]:
    """WKT and EPSG from the file's CRS records."""
    wkt = ""
    epsg = None
    for vlr in list(header.vlrs) + list(getattr(header, "evlrs", None) or []):
        rid = getattr(vlr, "record_id", None)
        if rid == 2112:  # OGC coordinate system WKT
            raw = getattr(vlr, "string", None) or getattr(vlr, "record_data", b"")
            wkt = raw.decode("utf-8", "replace") if isinstance(raw, bytes) else str(raw)
            wkt = wkt.strip("\x00 ")
        elif rid == 34735:  # GeoKeyDirectory: ProjectedCSTypeGeoKey, else GeographicType
            keys = {key.id: key for key in getattr(vlr, "geo_keys", [])
                    if key.id in (3072, 2048) and key.tiff_tag_location == 0}
            # a user-defined projection (32767) keeps its base GeographicType (4326, say),
            # which is not the CRS of the coordinates
            key = keys.get(3072, keys.get(2048))
            if key is not None and key.value_offset not in (0, 32767):
                epsg = int(key.value_offset)
    if epsg is None and wkt:
        import re

        # the authority of the whole CRS, the last item of its outermost node (WKT1
        # AUTHORITY, WKT2 ID): the last one inside names a part of it (its unit,
        # EPSG:9001, or its base geographic CRS); else the code the CRS matches in EPSG's
        # database (ESRI's WKT, LAS 1.4's usual, names none)
        found = re.search(r'(?:AUTHORITY|ID)\[\s*"EPSG"\s*,\s*"?(\d+)"?\s*\]\s*\]$', wkt)
        epsg = int(found.group(1)) if found else epsg_of_wkt(wkt)
    return wkt, epsg


def _read_laspy(path: Path) -> LasData:
    """``laspy.read(path)``, or LasError "cannot read LAS file <path>: <why>" in one line.

    A file cut short (an interrupted copy or download) is called truncated: of a cut LAS,
    laspy reads the whole records left without a word (and with none left the file "has no
    points"), or says "buffer size must be a multiple of element size"; of a cut LAZ, lazrs
    says "IoError: failed to fill whole buffer". None of that tells what is wrong.
    """
    import laspy

    what = f"cannot read LAS file {path}"
    try:
        with open(path, "rb") as f:  # (a LAZ file's header is a LAS header too)
            head = f.read(26)
    except OSError as exc:
        raise LasError(f"{what}: {exc.strerror or exc}") from None
    if head[:4] == b"LASF" and len(head) == 26 and (head[24] != 1 or head[25] > 4):
        # laspy read a header saying 9.2 as 1.2, and one saying 1.7 failed to "unpack"
        raise LasError(f"{what}: its header says LAS {head[24]}.{head[25]}, none of 1.0-1.4: "
                       "the header is corrupt")
    try:
        with laspy.open(str(path)) as reader:
            header = reader.header
            if header.are_points_compressed:
                try:
                    return reader.read()
                except Exception as exc:  # lazrs/laszip have their own types; the header was read
                    detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                    raise LasError(f"{what}: truncated or corrupt ({detail})") from None
            # LAS: the point records are fixed-size and end where the header says (only
            # extended VLRs may follow), so the file's size tells a cut file
            record = header.point_format.size
            expected = header.offset_to_point_data + header.point_count * record
            size = path.stat().st_size
            if size < expected:
                raise LasError(f"{what}: truncated or corrupt ({size} bytes, but its header says "
                               f"{header.point_count} points of {record} bytes after "
                               f"{header.offset_to_point_data}: {expected} bytes)")
            return reader.read()
    except LasError:
        raise
    except Exception as exc:  # laspy raises many types for corrupt files
        if type(exc).__name__ == "PointFormatNotSupported":  # (its text is the number alone)
            raise LasError(f"{what}: point format {exc} is not one of LAS 1.0-1.4's (0-10): "
                           "the header is corrupt") from None
        raise LasError(f"{what}: {exc}".splitlines()[0]) from None


# No survey's coordinates are larger (m): a UTM northing is ~1e7, ECEF ~6.4e6. Beyond it the
# header's scale or offset is wrong, and the points would overflow whatever grids them (the
# detector's limit, core.ground.MAX_COORDINATE, is the same: a file read is a file it takes).
MAX_COORDINATE = 1e8


def read_las(path: str | Path, *, allow_empty: bool = False) -> LasCloud:
    """Read a LAS or LAZ file into a :class:`LasCloud`.

    Raises LasError (one line naming the file and the problem) for a missing or unreadable
    file, a header whose scales and offsets give no coordinates (not finite, beyond
    MAX_COORDINATE), and a file without points unless `allow_empty`. A LAS file of 0 points is valid
    (`features` writes one when no point is a feature), but most callers can do nothing
    with it and say so in that line; those that can (a filter of the points: 0 in, 0 out)
    ask for it.
    """
    path = Path(path)
    if not path.is_file():
        raise LasError(f"not a LAS file, a folder: {path}" if path.is_dir()
                       else f"LAS file not found: {path}")
    las = _read_laspy(path)
    n = len(las.points)
    if n == 0 and not allow_empty:
        raise LasError(f"LAS file has no points: {path}")
    scales, offsets = np.asarray(las.header.scales), np.asarray(las.header.offsets)
    if not (np.isfinite(scales).all() and np.isfinite(offsets).all() and scales.all()):
        raise LasError(f"{path}: its header's scales {scales.tolist()} / offsets "
                       f"{offsets.tolist()} cannot give coordinates (not finite, or a zero "
                       "scale): the header is corrupt")
    names = set(las.point_format.dimension_names)
    dtype = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    dtype += [(name, dt) for name, dt in LAS_FIELDS if name in names]
    points = np.empty(n, dtype=dtype)
    with np.errstate(over="ignore", invalid="ignore"):  # (said below, in one line)
        points["x"] = np.asarray(las.x, dtype=np.float64)
        points["y"] = np.asarray(las.y, dtype=np.float64)
        points["z"] = np.asarray(las.z, dtype=np.float64)
    reach = max((float(np.abs(points[a]).max()) for a in "xyz"), default=0.0) if n else 0.0
    if not reach <= MAX_COORDINATE:  # (NaN fails too)
        raise LasError(f"{path}: its coordinates reach {reach:.3g} m, beyond "
                       f"{MAX_COORDINATE:.0e} m of any survey: its header's scales "
                       f"{scales.tolist()} or offsets {offsets.tolist()} are wrong")
    for name, _ in dtype[3:]:
        points[name] = np.asarray(las[name])
    wkt, epsg = _crs_from_vlrs(las.header)
    created = las.header.creation_date  # (None when the header's day and year are 0)
    return LasCloud(points=points, crs_wkt=wkt, epsg=epsg, has_gps_time="gps_time" in names,
                    gps_adjusted=bool(int(las.header.global_encoding.gps_time_type)),
                    created=created if created is None or created.year >= 1990 else None)


def write_las_subset(src: str | Path, keep: np.ndarray, out: str | Path) -> int:
    """Write the points of LAS/LAZ file `src` where (N,) bool `keep` holds to `out`, every
    dimension, the header's scales, offsets and CRS records kept; LAZ when `out` ends in
    .laz. Atomic: written beside `out` and renamed, so a failure leaves no half file.
    Returns the number of points written. Raises LasError for an unreadable `src`, a
    `keep` of the wrong length, or an output folder that does not exist."""
    import laspy

    from lidar_obstacles.io.atomic import LAS, atomic_write

    src, out = Path(src), Path(out)
    if not out.parent.is_dir():
        raise LasError(f"output folder does not exist: {out.parent}")
    las = _read_laspy(src)
    keep = np.asarray(keep, dtype=bool)
    if keep.shape != (len(las.points),):
        raise LasError(f"{src}: keep mask has {keep.shape} entries for {len(las.points)} points")
    sub = laspy.LasData(las.header)
    sub.points = las.points[keep]
    atomic_write(out, lambda tmp: sub.write(str(tmp)), kind=LAS)  # (LAZ by the suffix)
    return int(keep.sum())
