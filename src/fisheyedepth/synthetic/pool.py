"""The processes that render a dataset's frames, and the signals that stop them.

With more than one worker, frames are rendered by spawned worker processes, each building its frame
renderer once; without, in the calling process. SIGTERM while rendering (as SIGINT) stops the workers
and raises :class:`Terminated` (``SystemExit(143)``) in the calling process, so that its cleanup runs;
workers also die with the rendering process on Linux even if it is killed outright (``PR_SET_PDEATHSIG``).
"""

from __future__ import annotations

import ctypes
import os
import signal
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from multiprocessing import get_context

import torch
from tqdm import tqdm

from ..signals import Terminated, sigterm_raises  # noqa: F401  (the renderer's, re-exported)

PR_SET_PDEATHSIG = 1  # linux/prctl.h


_WORKER: Callable | None = None  # a worker process's frame renderer


def _die_with_parent(parent: int) -> None:
    """Linux: the kernel sends this worker SIGTERM when the rendering process dies, even of SIGKILL."""
    if sys.platform.startswith("linux"):
        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):  # best effort: no libc, no prctl
            pass
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(1)


def _init_worker(parent: int, make_worker: Callable, *args) -> None:
    global _WORKER
    _die_with_parent(parent)
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C reaches the whole group: the parent stops us
    torch.set_num_threads(1)
    _WORKER = make_worker(*args)


def _run_job(job) -> None:
    assert _WORKER is not None
    _WORKER(job)


def _stop_pool(pool: ProcessPoolExecutor, timeout: float = 5.0) -> None:
    """Stop the workers now: queued jobs are cancelled, running ones are not waited for."""
    processes = list((pool._processes or {}).values())  # private, but the only handle on the workers
    pool.shutdown(wait=False, cancel_futures=True)
    for process in processes:
        if process.is_alive():
            process.terminate()
    deadline = time.monotonic() + timeout
    for process in processes:
        process.join(max(0.0, deadline - time.monotonic()))
        if process.is_alive():
            process.kill()
            process.join(1.0)


def render_jobs(jobs: list, worker: Callable, workers: int, initargs: tuple, bar: tqdm) -> None:
    """Every job rendered: by ``worker`` in this process (``workers`` 0 or 1), or by ``workers`` spawned
    processes, each running ``initargs[0](*initargs[1:])`` (a picklable equivalent of ``worker``) once.
    ``bar`` counts the jobs done; a failure (or Ctrl-C) stops the workers and is raised."""
    if workers <= 1:
        for job in jobs:
            worker(job)
            bar.update()
        return
    pool = ProcessPoolExecutor(
        workers,
        mp_context=get_context("spawn"),
        initializer=_init_worker,
        initargs=(os.getpid(), *initargs),
    )
    try:
        for future in as_completed([pool.submit(_run_job, job) for job in jobs]):
            future.result()
            bar.update()
    except BaseException:
        _stop_pool(pool)
        raise
    pool.shutdown()
