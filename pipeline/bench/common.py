"""What every benchmark group shares: a result record, a median timer and the scratch project
folder where stages run as a user starts them."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console

from pipeline.workspace import workspace

SHARED_LU = workspace().root.parent / "shared" / "data" / "lu1319381_partial.parquet"
console = Console()

Result = dict[str, Any]  # name, value, unit, target, at_least, ok, note, peer


def result(name: str, value: float, unit: str, target: float | None = None,
            note: str = "", at_least: bool = False, peer: str = "") -> Result:
    """A measurement; `target` is a maximum, or a minimum when `at_least`; `peer` what it is
    compared with (another method's figure; empty: the previous run's figure of the same
    name, filled in by `run_benchmarks`)."""
    ok = None if target is None else bool(value >= target if at_least else value <= target)
    return {"name": name, "value": value, "unit": unit, "target": target, "at_least": at_least,
            "ok": ok, "note": note, "peer": peer}


def target_text(r: Result) -> str:
    if r["target"] is None:
        return r["note"]
    return f"{'>=' if r['at_least'] else '<='} {r['target']:g} {r['unit']}"


def median_ms(fn: Callable[[], Any], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


class Scratch:
    """A scratch project folder (scenarios copied in) where stages run as `python -m pipeline`."""

    def __init__(self) -> None:
        self.dir = Path(tempfile.mkdtemp(prefix="crater-nav-bench-"))
        shutil.copytree(workspace().scenarios_dir, self.dir / "runs" / "scenarios")
        shutil.copy(workspace().root / "pyproject.toml", self.dir / "pyproject.toml")
        shutil.copytree(workspace().catalogue_dir, self.dir / "catalogue",
                        ignore=shutil.ignore_patterns("*.duckdb", "*.rrd", "*.wal", ".tmp*"))

    def cli(self, *args: str) -> float:
        """Wall time (s) of `python -m pipeline <args>` run in the scratch folder."""
        env = {**os.environ, "CRATER_NAV_ROOT": str(self.dir)}
        if env.get("PYTHONPATH"):  # `PYTHONPATH=. just bench`: this checkout, not the scratch's
            env["PYTHONPATH"] = os.pathsep.join(str(Path(p).resolve())
                                                for p in env["PYTHONPATH"].split(os.pathsep) if p)
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "pipeline", *args], cwd=self.dir, check=True,
                       stdout=subprocess.DEVNULL, env=env)
        return time.perf_counter() - t0

    def close(self) -> None:
        shutil.rmtree(self.dir, ignore_errors=True)
