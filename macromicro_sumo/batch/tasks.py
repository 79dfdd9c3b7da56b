"""One variant's run: the stage tables of each scenario kind, a stage looked up by name,
and a worker running a ``Task``'s stages into a fresh folder with its stderr captured
(SUMO writes its real errors there) into an ``Outcome``."""

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
from macromicro_sumo.scenario.section import SectionScenario

# A stage is a function (scenario, out folder, command=..., progress=...) -> out folder,
# named as "module:function" and imported only when a variant runs it; one table per
# scenario kind, with the same stage names.
STAGES: dict[str, str] = {
    "simulate": "macromicro_sumo.truth.ring:simulate",
    "run": "macromicro_sumo.pipeline.ring:run",
}
SECTION_STAGES: dict[str, str] = {
    "simulate": "macromicro_sumo.truth.section:simulate_section",
    "run": "macromicro_sumo.pipeline.section:run_section",
}
KINDS = ("ring", "section")
LOG_LIMIT = 64_000  # characters of a variant's stderr kept


def scenario_kind(sc: Any) -> str:
    """``"section"`` for a scenario on the user's SUMO network, else ``"ring"``."""
    return "section" if isinstance(sc, SectionScenario) else "ring"


def stage_table(kind: str) -> dict[str, str]:
    """The stage functions of a scenario kind (``"ring"`` or ``"section"``)."""
    return SECTION_STAGES if kind == "section" else STAGES


def _unavailable(name: str, module: str) -> str:
    return (
        f"stage {name!r} is not available in this version of macromicro-sumo "
        f"(module {module} is missing); run --stage simulate"
    )


def stage_problem(name: str, kind: str = "ring") -> str:
    """Why stage ``name`` cannot run here for a ``kind`` scenario ('' when it can), checked
    without importing it."""
    import importlib.util

    table = stage_table(kind)
    if name not in table:
        return f"unknown stage {name!r}; accepted: {', '.join(table)}"
    module = table[name].split(":")[0]
    return "" if importlib.util.find_spec(module) else _unavailable(name, module)


def resolve_stage(name: str, kind: str = "ring") -> Callable[..., Any]:
    """The stage function registered under ``name`` for a ``kind`` scenario (imported only
    when a variant needs it)."""
    import importlib

    table = stage_table(kind)
    if name not in table:
        raise UserError(f"unknown stage {name!r}; accepted: {', '.join(table)}")
    module, func = table[name].split(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module:
            raise
        raise UserError(_unavailable(name, module)) from None
    if not hasattr(mod, func):
        raise UserError(f"stage {name!r} is not available: {module} has no {func}()")
    return getattr(mod, func)


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
    pid: int


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
                kind = scenario_kind(task.scenario)
                for stage in task.stages:
                    run = resolve_stage(stage, kind)
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
        os.getpid(),
    )
