"""The Rerun viewer for a run: which files to open, the command line, and headless screenshots.

A run's stage recordings share one recording id and open as one recording. The catalogue's craters
live once beside the catalogue database (`catalogue/<db stem>.rrd`, see
`recording.log_catalogue`) and are attached with `--asset`: static data shared by the recordings
opened with it (the viewer shows them in the run's recording, under /world/moon/craters).

Screenshots: a headless viewer (`rerun --headless`, Debian's `mesa-vulkan-drivers libvulkan1` for
a software Vulkan driver) in its own process group, driven over gRPC with
`rr.experimental.ViewerClient`: wait until the recording has loaded, go to a frame, pause, shoot,
then kill the process group.
"""

from __future__ import annotations

import ctypes.util
import glob
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from pipeline.errors import PipelineError
from pipeline.io.files import verified_file

WINDOW_SIZE = (1600, 1000)
LOAD_TIMEOUT_S = 60.0
SETTLE_S = 0.5  # after moving the time cursor, before the first shot
STABLE_POLL_S = 0.3  # between shots while waiting for two equal ones


def rerun_executable() -> str:
    """The `rerun` CLI of this environment (the wheel's, beside the interpreter, first)."""
    beside = Path(sys.executable).parent / "rerun"
    return str(beside) if beside.is_file() else (shutil.which("rerun") or "rerun")


def has_display() -> bool:
    """True when a window can be opened ($DISPLAY or $WAYLAND_DISPLAY set)."""
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def vulkan_available() -> bool:
    """True when a Vulkan loader and at least one driver (ICD) are installed: what the headless
    viewer needs (Debian: `apt-get install mesa-vulkan-drivers libvulkan1`)."""
    if ctypes.util.find_library("vulkan") is None and not glob.glob("/usr/lib/*/libvulkan.so.1"):
        return False
    icds = [p for d in ("/usr/share/vulkan/icd.d", "/etc/vulkan/icd.d")
            for p in glob.glob(f"{d}/*.json")]
    return bool(icds or os.environ.get("VK_ICD_FILENAMES") or os.environ.get("VK_DRIVER_FILES"))


def run_recordings(run: str, root: Path | None = None) -> tuple[Path, list[Path], Path | None]:
    """The run folder, its committed recordings and the catalogue recording to attach (the one
    beside the database the run's ingest stage used; None when there is none). A campaign's
    folder (no stages of its own): its recordings (campaign.rrd, a sweep's sweep.rrd)."""
    from pipeline.io.catalogue import recorded_catalogue_db, recorded_facts
    from pipeline.io.store import RunStore

    store = RunStore(run, root)
    if not store.manifest_path.is_file() and (store.run_dir / "campaign.parquet").is_file():
        # only what campaign.json records, each as recorded (size, sha256, not a link)
        try:
            names = json.loads((store.run_dir / "campaign.json").read_text())["outputs"]
            files = [verified_file(store.run_dir, n, "campaign.json") for n in sorted(names)
                     if n.endswith(".rrd")]
        except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError) as exc:
            raise PipelineError(f"view {run}: {exc}") from None
        return store.run_dir, files, None
    committed = store.verified()  # the whole run as committed, not only what is shown
    facts_path = committed.get("catalogue.json")
    catalogue = None
    if facts_path is not None:
        recorded_catalogue_db(facts_path)  # still the run's catalogue, else a clear error
        catalogue = Path(recorded_facts(facts_path)["recording"])
        if not catalogue.is_file():
            catalogue = None
    return store.run_dir, sorted(p for n, p in committed.items() if n.endswith(".rrd")), catalogue


def viewer_args(files: list[Path], catalogue: Path | None = None) -> list[str]:
    """Arguments after `rerun` that open the run's recordings with the catalogue attached."""
    asset = ["--asset", str(catalogue)] if catalogue is not None else []
    return [*asset, *(str(f) for f in files)]


@dataclass
class Shot:
    """What a screenshot did: the PNG, the frame shown, the run's frames, seconds to start the
    viewer, to load the recordings and in all, and the shots taken until two were equal."""

    path: Path
    frame: int
    frames: tuple[int, int]
    start_s: float
    load_s: float
    total_s: float
    shots: int = 1


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _kill_group(proc: subprocess.Popen) -> None:
    """Terminate the viewer's process group (it was started in a session of its own)."""
    if proc.poll() is not None:
        return
    try:
        pgid = os.getpgid(proc.pid)
    except ProcessLookupError:
        return
    for sig, wait_s in ((signal.SIGTERM, 5.0), (signal.SIGKILL, 5.0)):
        try:
            os.killpg(pgid, sig)
        except ProcessLookupError:
            return
        try:
            proc.wait(wait_s)
            return
        except subprocess.TimeoutExpired:
            continue


def _log_tail(path: Path, lines: int = 5) -> str:
    try:
        text = path.read_text(errors="replace").strip().splitlines()
    except OSError:
        return ""
    return " | ".join(line.strip() for line in text[-lines:])


def _frame_timeline(state):
    for rec in state.recordings:
        for tl in rec.timelines:
            if tl.name == "frame":
                return rec, tl
    return None, None


def screenshot(files: list[Path], out: Path, catalogue: Path | None = None,
               frame: int | None = None, window_size: tuple[int, int] = WINDOW_SIZE,
               timeout_s: float = LOAD_TIMEOUT_S, settle_s: float = SETTLE_S) -> Shot:
    """Render the run headless to the PNG `out` at `frame` (default: the middle of the run's
    frames). Raises PipelineError (with the viewer's last log lines) when the viewer cannot start
    or the recording does not load within `timeout_s`."""
    import rerun as rr

    if not vulkan_available():
        raise PipelineError("no Vulkan driver for the headless viewer: install Debian's "
                            "`mesa-vulkan-drivers libvulkan1`")
    out = Path(out).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    port = free_port()
    log = out.with_name(f".{out.stem}-viewer.log")
    args = [rerun_executable(), "--headless", "--bind", "127.0.0.1", "--port", str(port),
            "--hide-welcome-screen", "--window-size", f"{window_size[0]}x{window_size[1]}",
            *viewer_args([Path(f).resolve() for f in files],
                         None if catalogue is None else Path(catalogue).resolve())]
    t0 = time.perf_counter()
    deadline = t0 + timeout_s
    with open(log, "w") as log_file:
        proc = subprocess.Popen(args, stdin=subprocess.DEVNULL, stdout=log_file,
                                stderr=subprocess.STDOUT, start_new_session=True)
    try:
        client = None
        while client is None:
            if proc.poll() is not None:
                raise PipelineError(f"the headless viewer exited ({proc.returncode}): "
                                    f"{_log_tail(log)}")
            try:
                client = rr.experimental.ViewerClient.connect(
                    f"rerun+http://127.0.0.1:{port}/proxy")
                client.get_state()
            except Exception:
                client = None
                if time.perf_counter() > deadline:
                    raise PipelineError(f"the headless viewer did not answer on port {port} "
                                        f"within {timeout_s:g} s: {_log_tail(log)}") from None
                time.sleep(0.1)
        t_start = time.perf_counter() - t0

        # Loaded: the recording is there with its frame timeline, nothing is loading (the files
        # are registered: their chunk index is read, chunks come on demand), and neither the
        # timeline's range nor the entities change between two polls.
        last = None
        while True:
            state = client.get_state()
            rec, tl = _frame_timeline(state)
            current = None
            if tl is not None and not state.loading:
                schema = client.get_recording_schema(rec.store_id, paths_only=True)
                current = (tl.start, tl.end, len(state.views), len(schema.entities or []))
            if current is not None and not state.loading and current == last:
                break
            if time.perf_counter() > deadline:
                raise PipelineError(f"the run's recordings did not load within {timeout_s:g} s "
                                    f"(viewer state: {state})")
            last = current
            time.sleep(0.25)
        if state.active_recording != rec.store_id:
            client.set_location(rec.location)
        t_load = time.perf_counter() - t0

        lo, hi = int(tl.start), int(tl.end)
        shown = (lo + hi) // 2 if frame is None else int(frame)
        if not lo <= shown <= hi:
            raise PipelineError(f"--frame {shown}: the run's frames are {lo}-{hi}")
        client.set_time("frame", sequence=shown, play_state="paused")
        # Painted: the views fetch the frame's chunks on demand, so shoot until two shots in a
        # row are the same picture (or the time is up; then the last one).
        time.sleep(settle_s)
        png, shots = client.take_screenshot(), 1
        while time.perf_counter() < deadline:
            time.sleep(STABLE_POLL_S)
            again = client.take_screenshot()
            shots += 1
            if again == png:
                break
            png = again
        out.write_bytes(png)
        return Shot(out, shown, (lo, hi), t_start, t_load, time.perf_counter() - t0, shots)
    finally:
        _kill_group(proc)
        log.unlink(missing_ok=True)
