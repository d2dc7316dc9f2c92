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
