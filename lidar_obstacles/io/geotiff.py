"""GeoTIFF and hillshade export of a DEM (tifffile / Pillow, no GDAL needed).

The GeoTIFF is north-up: the file's first row is the grid's LAST row (largest y), the
tie point maps the upper-left corner of pixel (0, 0) to (origin_x, origin_y + rows*res),
and the pixel scale is (res, res). Unknown cells are NaN and the GDAL_NODATA tag says so.
Files are written under a temporary name in the target folder and renamed into place, so
a reader never sees half a file and a failure leaves nothing behind.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from lidar_obstacles.core.dem import DemGrid
from lidar_obstacles.errors import LidarObstaclesError
from lidar_obstacles.io.atomic import PNG, TIFF, Kind, atomic_write
from lidar_obstacles.io.crs import MODEL_PROJECTED, CrsError, tiff_crs

MODEL_PIXEL_SCALE = 33550
MODEL_TIEPOINT = 33922
GEO_KEY_DIRECTORY = 34735
GEO_ASCII_PARAMS = 34737
GDAL_NODATA = 42113

GT_MODEL_TYPE = 1024  # 1 projected (the only kind a DEM in metres is written in)
GT_RASTER_TYPE = 1025  # 1 PixelIsArea
GT_CITATION = 1026
GEOGRAPHIC_TYPE = 2048
PROJECTED_CS_TYPE = 3072
VERTICAL_CS_TYPE = 4096


class ExportError(LidarObstaclesError):
    """A DEM that cannot be written (empty grid, unwritable path)."""


def _atomic_write(path: str | Path, write: Callable[[str], None], kind: Kind) -> Path:
    """`atomic_write`, with the problems a user can fix as one ExportError line."""
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    try:  # (the check too: a folder one cannot search, or a name too long, raises)
        if not folder.is_dir():
            raise ExportError(f"cannot write {path}: folder {folder} does not exist")
        return atomic_write(path, lambda tmp: write(str(tmp)), kind=kind)
    except OSError as exc:
        raise ExportError(f"cannot write {path}: {exc}") from None


def _geokeys(epsg: int | None, citation: str) -> tuple[list[int], str]:
    """GeoKeyDirectory shorts and GeoAsciiParams text of the CRS of code `epsg`, else of
    the WKT `citation` (:func:`tiff_crs`); the WKT is the citation as well. A CRS with no
    EPSG code (a local one) is in the citation only, as GDAL reads it."""
    keys: list[tuple[int, int, int, int]] = [(GT_RASTER_TYPE, 0, 1, 1)]
    ascii_params = ""
    if epsg is not None or citation:
        try:
            crs = tiff_crs(epsg, citation)
        except CrsError as exc:
            raise ExportError(f"cannot write the DEM's CRS: {exc}") from None
        if crs.projected is not None:
            keys += [(GT_MODEL_TYPE, 0, 1, MODEL_PROJECTED),
                     (PROJECTED_CS_TYPE, 0, 1, crs.projected)]
        if crs.vertical is not None:
            keys.append((VERTICAL_CS_TYPE, 0, 1, crs.vertical))
    if citation:
        ascii_params = citation.replace("|", "/") + "|"
        keys.append((GT_CITATION, GEO_ASCII_PARAMS, len(ascii_params), 0))
    keys.sort()
    flat = [1, 1, 0, len(keys)]
    for key in keys:
        flat.extend(key)
    return flat, ascii_params


def write_geotiff(path: str | Path, grid: DemGrid, *, crs_epsg: int | None,
                  crs_wkt: str = "") -> Path:
    """Write the elevation layer as a float32 GeoTIFF, atomically; return the path.

    crs_epsg: EPSG code of a projected CRS (a compound one's heights go in
    VerticalCSTypeGeoKey) or None; crs_wkt: the CRS as WKT when there is no code, whose
    EPSG match is written as the code would be; stored as the citation too (GDAL reads
    the keys; the WKT documents CRSs without a code). Raises ExportError for an empty
    grid, an unwritable path or a CRS that is not projected (:func:`tiff_crs`).
    """
    import tifffile

    rows, cols = grid.shape
    if rows == 0 or cols == 0:
        raise ExportError(f"cannot write {path}: the DEM is empty ({grid.reason or 'no cells'})")
    res = float(grid.resolution)
    top = float(grid.origin[1]) + rows * res
    geokeys, ascii_params = _geokeys(crs_epsg, crs_wkt.strip())
    tags = [
        (MODEL_PIXEL_SCALE, "d", 3, (res, res, 0.0), True),
        (MODEL_TIEPOINT, "d", 6, (0.0, 0.0, 0.0, float(grid.origin[0]), top, 0.0), True),
        (GEO_KEY_DIRECTORY, "H", len(geokeys), tuple(geokeys), True),
        (GDAL_NODATA, "s", 0, "nan", True),
    ]
    if ascii_params:
        tags.append((GEO_ASCII_PARAMS, "s", 0, ascii_params, True))
    data = np.ascontiguousarray(np.flipud(grid.elevation).astype(np.float32))

    def write(tmp: str) -> None:
        tifffile.imwrite(tmp, data, photometric="minisblack", extratags=tags,
                         metadata=None)

    return _atomic_write(path, write, TIFF)


@dataclass(frozen=True)
class GeoTiffDem:
    """A GeoTIFF read back: elevation (rows, cols) float32 metres in DemGrid row order
    (row 0 = south), origin (2,) x, y of the lower-left corner, metres, resolution: cell
    edge, metres, nodata text, epsg, citation."""

    elevation: np.ndarray
    origin: np.ndarray
    resolution: float
    nodata: str
    epsg: int | None
    citation: str


def read_geotiff(path: str | Path) -> GeoTiffDem:
    """Read a north-up GeoTIFF written by :func:`write_geotiff` (for tests and tools)."""
    import tifffile

    with tifffile.TiffFile(str(path)) as tif:
        page = tif.pages.first
        image = page.asarray().astype(np.float32)
        tags = {tag.code: tag.value for tag in page.tags.values()}
    scale = tags[MODEL_PIXEL_SCALE]
    tie = tags[MODEL_TIEPOINT]
    res = float(scale[0])
    rows = image.shape[0]
    origin = np.array([tie[3] - tie[0] * res, tie[4] + tie[1] * res - rows * res])
    epsg = None
    keys = list(tags.get(GEO_KEY_DIRECTORY, ()))
    for i in range(4, len(keys), 4):
        if keys[i] in (PROJECTED_CS_TYPE, GEOGRAPHIC_TYPE) and keys[i + 1] == 0:
            epsg = int(keys[i + 3])
    nodata = tags.get(GDAL_NODATA, "")
    return GeoTiffDem(elevation=np.flipud(image).copy(), origin=origin, resolution=res,
                      nodata=str(nodata).strip("\x00 "), epsg=epsg,
                      citation=str(tags.get(GEO_ASCII_PARAMS, "")).rstrip("|\x00"))


def hillshade(elevation: np.ndarray, resolution: float, *, azimuth: float = 315.0,
              altitude: float = 45.0) -> np.ndarray:
    """(rows, cols) float64 in [0, 1] shaded relief of a DemGrid-ordered elevation (row 0 =
    south), metres, with cells ``resolution`` metres wide; NaN where the elevation or a
    neighbour is unknown. Light from ``azimuth`` degrees clockwise from north,
    ``altitude`` degrees above the horizon."""
    z = np.asarray(elevation, dtype=np.float64)
    if min(z.shape) < 2:
        return np.full(z.shape, np.nan)
    dzdy, dzdx = np.gradient(z, resolution)  # row index grows northwards
    az, alt = np.radians(azimuth), np.radians(altitude)
    light = np.array([np.sin(az) * np.cos(alt), np.cos(az) * np.cos(alt), np.sin(alt)])
    norm = np.sqrt(dzdx ** 2 + dzdy ** 2 + 1.0)
    shade = (-dzdx * light[0] - dzdy * light[1] + light[2]) / norm
    return np.clip(shade, 0.0, 1.0)


def write_hillshade_png(path: str | Path, grid: DemGrid) -> Path:
    """Write a north-up grey hillshade PNG (unknown cells transparent), atomically."""
    from PIL import Image

    rows, cols = grid.shape
    if rows == 0 or cols == 0:
        raise ExportError(f"cannot write {path}: the DEM is empty ({grid.reason or 'no cells'})")
    shade = np.flipud(hillshade(grid.elevation, grid.resolution))
    known = np.isfinite(shade)
    grey = np.where(known, 40.0 + 215.0 * np.nan_to_num(shade), 0.0).astype(np.uint8)
    rgba = np.dstack([grey, grey, grey, np.where(known, 255, 0).astype(np.uint8)])

    def write(tmp: str) -> None:
        Image.fromarray(rgba, mode="RGBA").save(tmp, format="PNG")

    return _atomic_write(path, write, PNG)
