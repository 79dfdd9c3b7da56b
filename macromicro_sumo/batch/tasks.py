"""One variant's run: the stage table (every stage serves every scenario kind), a stage
looked up by name, and a worker running a ``Task``'s stages into a fresh folder with its
stderr captured (SUMO writes its real errors there) into an ``Outcome``."""

from __future__ import annotations

import contextlib
import os
import socket
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from macromicro_sumo.batch.sweep import AnyScenario
from macromicro_sumo.errors import UserError
from macromicro_sumo.pipeline import stages as pipeline

# A stage is a function (scenario, out folder, command=..., progress=...) of
# ``pipeline.stages``: one for every scenario kind, which picks the kind's implementation.
STAGES: dict[str, Callable[..., Any]] = {"simulate": pipeline.simulate, "run": pipeline.run}
LOG_LIMIT = 64_000  # characters of a variant's stderr kept


def resolve_stage(name: str) -> Callable[..., Any]:
    """The stage function registered under ``name``."""
    if name not in STAGES:
        raise UserError(f"unknown stage {name!r}; accepted: {', '.join(STAGES)}")
    return STAGES[name]


@dataclass(frozen=True)
class Task:
    """What a worker needs to run one variant into a fresh folder ``out``."""

    name: str
    scenario: AnyScenario
    stages: tuple[str, ...]
    out: str
    command: str


@dataclass(frozen=True)
class Outcome:
    """How one variant went; ``error`` is one line, ``log`` what went to stderr."""

    name: str
    ok: bool
    error: str
    wall_s: float
    log: str
    host: str


@contextlib.contextmanager
def _stderr_to(path: Path) -> Iterator[None]:
    """Send file descriptor 2 to ``path``: SUMO (C++) writes its real errors there."""
    sys.stderr.flush()
    saved = os.dup(2)
    with open(path, "wb") as f:
        os.dup2(f.fileno(), 2)
    try:
        yield
    finally:
        sys.stderr.flush()
        os.dup2(saved, 2)
        os.close(saved)


def one_line(exc: BaseException) -> str:
    """An exception as one line: a ``UserError``'s message, else its type and message."""
    text = str(exc) if isinstance(exc, UserError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split())


def run_task(task: Task) -> Outcome:
    """Run one variant's stages into ``task.out`` (a worker process owns the simulation)."""
    t0 = time.perf_counter()
    out = Path(task.out)
    log_path = out.with_name(out.name + ".log")
    error = ""
    try:
        with _stderr_to(log_path):
            try:
                out.mkdir(parents=True)
                for stage in task.stages:
                    run = resolve_stage(stage)
                    run(task.scenario, out, command=task.command, progress=False)
            except Exception as exc:
                error = one_line(exc) or type(exc).__name__
        log = log_path.read_text(errors="replace")[-LOG_LIMIT:]
    finally:
        log_path.unlink(missing_ok=True)
    if error:
        sumo_errors = [ln.strip() for ln in log.splitlines() if ln.startswith("Error:")]
        if sumo_errors and sumo_errors[0] not in error:
            error += f" [SUMO: {sumo_errors[0]}]"
    return Outcome(
        task.name,
        not error,
        error,
        round(time.perf_counter() - t0, 3),
        log,
        socket.gethostname(),
    )
