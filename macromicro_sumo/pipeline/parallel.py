"""Stages that do not read each other's outputs, run side by side in worker processes.

The pipeline's policy and its two ablations read only the ground truth and the generator,
and the evaluation and the deployment only those and the policies: each group can run at
once. Every stage seeds its own generators and opens its own SUMO (libsumo runs one per
process), so a stage's outputs are the same whether it runs alone or beside another
(``tests/pipeline/test_parallel.py`` compares them file by file). Workers are spawned
(not forked: torch and libsumo state do not survive a fork) and run one thread each, as
the stages set for themselves when run one after the other.
"""

from __future__ import annotations

import contextlib
import ctypes
import multiprocessing
import os
import pickle
import resource
import signal
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, wait
from pathlib import Path
from typing import Any

import torch

from macromicro_sumo.files import locked_by_caller

MAX_JOBS = 2  # a stage runs one torch thread and SUMO in one process: 2 cores fill with 2


def default_jobs() -> int:
    """Processes ``macromicro run`` uses: up to ``MAX_JOBS`` where the CPUs allow; one
    inside a worker of its own (a batch variant has its slot: no nesting) and where the
    main script is no file a worker could import (read from standard input)."""
    if multiprocessing.parent_process() is not None or unimportable_main():
        return 1
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(MAX_JOBS, cpus))


def unimportable_main() -> str | None:
    """The main script where a spawned worker, which re-imports it, could not (read from
    standard input): every worker would die at start; None where it can."""
    main_file = getattr(sys.modules["__main__"], "__file__", None)
    return main_file if main_file and not Path(main_file).is_file() else None


def worker_setup() -> None:
    """A spawned worker's start. Ctrl-C reaches the whole process group: the driver alone
    handles it and stops the workers, so none prints a traceback. One torch/BLAS thread:
    workers do not oversubscribe the CPUs, and results do not depend on their count. On
    Linux a worker dies with a driver killed by SIGKILL (it would keep writing)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
            if os.getppid() == 1:
                os._exit(1)


def stop_pool(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now, killing a worker that is still running a job."""
    if hasattr(pool, "terminate_workers"):  # Python >= 3.14
        pool.terminate_workers()
        return
    procs = list((getattr(pool, "_processes", None) or {}).values())
    for p in procs:
        with contextlib.suppress(Exception):
            p.terminate()
    pool.shutdown(wait=False, cancel_futures=True)
    for p in procs:
        with contextlib.suppress(Exception):
            p.join(10)


def can_ship(fn: Callable[[], Any]) -> bool:
    """Whether ``fn`` can go to a spawned worker (a module-level function or a partial of
    one with plain arguments; the pipeline's own stages are; a test's closures are not)."""
    try:
        pickle.dumps(fn)
    except Exception:  # pickling raises many kinds: AttributeError, TypeError, PicklingError
        return False
    return True


def cpu_s() -> float:
    """CPU seconds (user + system) of this process and of its children that ended."""
    own = resource.getrusage(resource.RUSAGE_SELF)
    kids = resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + kids.ru_utime + kids.ru_stime


class _LineStream:
    """A worker's stderr, saying it is no terminal: its progress prints one line per stage
    (``progress.tqdm``), where two live bars side by side would overwrite each other."""

    def __init__(self, stream: Any) -> None:
        self._stream = stream

    def isatty(self) -> bool:
        return False

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)


def _worker_init(held: Sequence[str]) -> None:
    worker_setup()
    # The driver holds these folders' locks for the whole run: write into them, as its
    # own stages do, without locking them again.
    locked_by_caller(held)
    sys.stderr = _LineStream(sys.stderr)


def _call(fn: Callable[[], Any]) -> tuple[float, float]:
    """Run one stage in a worker; its wall and CPU seconds (its result stays there)."""
    torch.set_num_threads(1)  # as the stages run one after the other (policy.stage)
    w0, c0 = time.perf_counter(), cpu_s()
    fn()
    return time.perf_counter() - w0, cpu_s() - c0


def run_side_by_side(
    jobs: Sequence[tuple[str, Callable[[], Any]]], held: Sequence[Path], workers: int
) -> dict[str, tuple[float, float]]:
    """Run every ``(name, fn)`` of ``jobs`` in ``workers`` spawned processes (in order, as
    slots free up); returns each one's (wall, CPU) seconds. ``held``: the folders they
    write into, whose locks the caller holds. A failure is raised once every job ended
    (the others' outputs stay, for the next run to reuse)."""
    ctx = multiprocessing.get_context("spawn")
    keys = [str(Path(p).resolve()) for p in held]
    pool = ProcessPoolExecutor(
        min(workers, len(jobs)), mp_context=ctx, initializer=_worker_init, initargs=(keys,)
    )
    try:
        futures: dict[str, Future[tuple[float, float]]] = {
            name: pool.submit(_call, fn) for name, fn in jobs
        }
        wait(futures.values())
    except BaseException:  # Ctrl-C: stop the workers now
        stop_pool(pool)
        raise
    pool.shutdown(wait=True)
    return {name: fut.result() for name, fut in futures.items()}
