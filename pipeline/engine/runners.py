"""Runners: where a plan's fan-out work runs. In-process, or a local pool of spawned processes
(polars and DuckDB are not fork-safe). A Ray runner will implement the same `map`.

Workers die with their parent: a killed sweep leaves no orphan processes (Linux
PR_SET_PDEATHSIG, and a watchdog thread that exits when the parent is gone).
"""

from __future__ import annotations

import ctypes
import multiprocessing
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Protocol

from pipeline.errors import PipelineError


class Runner(Protocol):
    """Runs `fn(*args)` for each args tuple; yields results in submission order."""

    workers: int

    def map(self, fn: Callable[..., Any], items: Sequence[tuple[Any, ...]], *,
            initializer: Callable[..., None] | None = None,
            initargs: tuple[Any, ...] = ()) -> Iterator[Any]: ...


class InProcessRunner:
    """Everything in this process, one item after the other."""

    workers = 1

    def map(self, fn, items, *, initializer=None, initargs=()):
        if initializer is not None:
            initializer(*initargs)
        for args in items:
            yield fn(*args)


def _die_with_parent(parent_pid: int) -> None:
    """In a worker: exit when the parent process is gone (SIGKILL included)."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass

    def watch() -> None:
        while True:
            if os.getppid() != parent_pid:
                os._exit(1)
            time.sleep(0.5)

    threading.Thread(target=watch, daemon=True).start()


_INIT_ERROR: list[BaseException] = []  # in a worker: why its initializer failed


def _init(parent_pid: int, initializer: Callable[..., None] | None, initargs: tuple) -> None:
    _die_with_parent(parent_pid)
    if initializer is not None:
        try:
            initializer(*initargs)
        except Exception as exc:  # reported by the first task (a raising initializer would
            _INIT_ERROR.append(exc)  # break the pool and lose the message)


def _call(fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    if _INIT_ERROR:
        raise _INIT_ERROR[0]
    return fn(*args)


class ProcessPoolRunner:
    """A pool of `workers` spawned processes on this machine."""

    def __init__(self, workers: int):
        self.workers = workers

    def map(self, fn, items, *, initializer=None, initargs=()):
        ctx = multiprocessing.get_context("spawn")
        pool = ProcessPoolExecutor(self.workers, mp_context=ctx, initializer=_init,
                                   initargs=(os.getpid(), initializer, initargs))
        done = False
        try:
            futures = [pool.submit(_call, fn, args) for args in items]
            for f in futures:
                yield f.result()
            done = True
        except BrokenProcessPool as exc:
            raise PipelineError(f"a worker process died ({exc}); out of memory?") from None
        finally:  # on an error or Ctrl-C: cancel the rest and do not wait (workers die with us)
            pool.shutdown(wait=done, cancel_futures=True)


def runner_for(workers: int) -> Runner:
    """In-process for one worker, else a local process pool."""
    return InProcessRunner() if workers <= 1 else ProcessPoolRunner(workers)
