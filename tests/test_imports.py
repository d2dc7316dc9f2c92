"""Imports paid only by the commands that need them: the command line and config loading (what
every command does first) leave the heavy libraries unimported (issue 26)."""

from __future__ import annotations

import subprocess
import sys

HEAVY = ("scipy.stats", "scipy.optimize", "scipy.integrate", "scipy.signal", "scipy.spatial",
         "rerun", "matplotlib", "healpy", "ray", "skyfield", "onnxruntime")


def test_cli_and_config_loading_import_no_heavy_library():
    code = ("import sys, pipeline.cli\n"
            "from pipeline.config import load_config\n"
            "load_config('default'); load_config('camera'); load_config('identify')\n"
            f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == ""


def test_the_stage_registry_leaves_the_plotting_and_sky_libraries_to_the_stages_that_use_them():
    """Every stage command loads all the stages' declarations (the DAG decides what is stale):
    healpy (~2 s with the matplotlib and astropy it brings), matplotlib and scipy.stats/signal
    (~1 s each) come only with a tile query or a figure, or not at all."""
    late = ("healpy", "astropy", "matplotlib", "scipy.stats", "scipy.signal", "ray", "skyfield",
            "onnxruntime", "rerun")
    code = ("import sys, pipeline.cli, pipeline.stages\n"
            f"print(','.join(m for m in {late!r} if m in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert out.stdout.strip() == "rerun"  # every stage draws its recording
