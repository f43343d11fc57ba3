"""A survey's CRS as a GeoTIFF's GeoKeys hold it, looked up in EPSG's database (pyproj).

Which key a code goes in, and whether a DEM can be in that CRS at all, is the database's
to say, not the code's range: EPSG:4647 is a projected CRS (ETRS89 / UTM 32N zE-N),
EPSG:7844 a geographic one (GDA2020), EPSG:4978 geocentric and EPSG:7415 a projected CRS
with its heights (Amersfoort / RD New + NAP height).
"""
from __future__ import annotations

from dataclasses import dataclass

MODEL_PROJECTED = 1  # GTModelTypeGeoKey


class CrsError(ValueError):
    """A CRS a DEM's GeoTIFF cannot be in (the message says why)."""


@dataclass(frozen=True)
class TiffCrs:
    """What the GeoKeys say of a CRS. projected: the EPSG code for ProjectedCSTypeGeoKey
    (None: the CRS has none, and only the citation carries it); vertical: the EPSG code of
    its heights for VerticalCSTypeGeoKey, or None."""

    projected: int | None
    vertical: int | None


def tiff_crs(epsg: int | None, wkt: str = "") -> TiffCrs:
    """The GeoKeys of the CRS given by its EPSG code, else by its WKT (1 or 2, ESRI's
    too). Raises CrsError for a code or text that is no CRS, and for a CRS whose x and y
    are not metres on a map: geographic (degrees; the DEM's cells are metres), geocentric
    or vertical alone. A WKT with no EPSG code (a local or custom CRS) has no code here."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    name = f"EPSG:{epsg}" if epsg is not None else "the WKT"
    try:
        crs = CRS.from_epsg(epsg) if epsg is not None else CRS.from_wkt(wkt)
    except CRSError:
        raise CrsError(f"{name} is not a CRS in the EPSG database" if epsg is not None else
                       "the WKT is no CRS pyproj can read") from None
    if crs.is_bound:  # (a WKT with TOWGS84: the CRS it is bound to is the survey's)
        crs = crs.source_crs or crs
    horizontal, vertical = crs, None
    if crs.is_compound:
        horizontal = crs.sub_crs_list[0]
        vertical = next((part for part in crs.sub_crs_list[1:] if part.is_vertical), None)
    if horizontal.is_geographic:
        raise CrsError(f"{name} is geographic ({horizontal.name}): its x and y are degrees, "
                       "the DEM's cells metres; give the projected CRS of the points")
    if horizontal.is_geocentric or horizontal.is_vertical:
        kind = "geocentric" if horizontal.is_geocentric else "vertical"
        raise CrsError(f"{name} is a {kind} CRS ({horizontal.name}): a DEM needs a "
                       "projected one")
    code = epsg if epsg is not None and not crs.is_compound else None
    if horizontal.is_projected and code is None:
        code = horizontal.to_epsg(min_confidence=70)
    return TiffCrs(projected=code if horizontal.is_projected else None,
                   vertical=vertical.to_epsg(min_confidence=70) if vertical is not None
                   else None)


def epsg_of_wkt(wkt: str) -> int | None:
    """The EPSG code a WKT names or matches (ESRI's WKT names none: its UTM 32N on ETRS89
    is EPSG:25832), None when it matches none or is no CRS."""
    from pyproj import CRS
    from pyproj.exceptions import CRSError

    try:
        return CRS.from_wkt(wkt).to_epsg(min_confidence=70)
    except CRSError:
        return None
