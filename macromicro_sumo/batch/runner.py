"""Batch runs: many scenario variants, each in its own output folder, on local worker
processes or on Ray.

Inputs are scenario files, globs, or a scenario with a ``[sweep]`` table, expanded into
the cartesian product of named variants::

    [sweep]
    seed = [1, 2, 3]
    speed_limits.range_mps = [[10.0, 12.0], [12.0, 14.0]]   # dotted key: table.key
    n_runs = [10, 40]                                       # short key: unique across tables

Sweep keys are those of the file's scenario kind: the ring's tables, or a section's
(``[network] kind = "sumo"``: ``detectors.auto_spacing_m``, ``instrumented.penetration``, ...).
Each stage has a function per kind (``STAGES`` for the ring, ``SECTION_STAGES``).

Layout of a batch folder ``DIR``::

    DIR/batch.json            the expanded spec (variants, their parameters, stages)
    DIR/batch_summary.csv     one row per variant: status, wall time, headline figures
    DIR/batch_macro.csv       every variant's macro statistics, parameters as columns
    DIR/batch_detectors.csv   every variant's per-detector intervals, parameters as columns
    DIR/variants/<name>/      one stage output folder per variant (SUMO's XML under sumo/)
    DIR/logs/<name>.log       what SUMO and the stage wrote to stderr

Faults: a variant runs into a hidden ``.partial-*`` folder that is renamed into place only
when every stage succeeded, so ``variants/<name>/manifest.json`` marks it complete. A failed
variant (bad file, SUMO error, killed worker) becomes a failed row; the others go on. A
re-run skips complete variants whose scenario and stages are unchanged and redoes the rest.

libsumo runs one simulation per process: each local worker slot is its own single-process
pool, so a worker that dies takes down only the variant it was running.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import difflib
import glob
import hashlib
import io
import itertools
import json
import math
import os
import re
import secrets
import shutil
import signal
import socket
import sys
import tarfile
import tempfile
import time
import typing
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from macromicro_sumo.batch import export
from macromicro_sumo.errors import UserError
from macromicro_sumo.files import OUTPUT_MARK, mark_output, prepare_out_dir, write_json, write_text
from macromicro_sumo.scenario.load import load_scenario, read_scenario_toml
from macromicro_sumo.scenario.ring import Scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import scenario_inputs

AnyScenario = Scenario | SectionScenario

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
BACKENDS = ("local", "ray")
EXPORT_FORMATS = export.FORMATS
RAY_INSTALL = "pip install 'macromicro-sumo[ray]'"
MAX_NAME = 120  # characters; longer variant names are shortened with a hash
LOG_LIMIT = 64_000  # characters of a variant's stderr kept


# --------------------------------------------------------------------------- sweeps


def scenario_kind(sc: Any) -> str:
    """``"section"`` for a scenario on the user's SUMO network, else ``"ring"``."""
    return "section" if isinstance(sc, SectionScenario) else "ring"


def stage_table(kind: str) -> dict[str, str]:
    """The stage functions of a scenario kind (``"ring"`` or ``"section"``)."""
    return SECTION_STAGES if kind == "section" else STAGES


def _leaf_keys(cls: type = Scenario, prefix: str = "") -> dict[str, Any]:
    """Every settable scenario key, dotted, mapped to its type hint."""
    out: dict[str, Any] = {}
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name == "source":
            continue
        key = f"{prefix}{f.name}"
        if dataclasses.is_dataclass(hints[f.name]):
            out.update(_leaf_keys(hints[f.name], key + "."))
        elif key != "network.kind":  # the kind picks the tables: one file per kind
            out[key] = hints[f.name]
    return out


# Sweepable keys per scenario kind, with an example for error messages.
LEAF_KEYS: dict[str, dict[str, Any]] = {
    "ring": _leaf_keys(Scenario),
    "section": _leaf_keys(SectionScenario),
}
EXAMPLE_KEY = {"ring": "fleet.n_vehicles", "section": "detectors.auto_spacing_m"}


def _tables(kind: str) -> list[str]:
    return list(dict.fromkeys(k.split(".")[0] for k in LEAF_KEYS[kind] if "." in k))


def _top_keys(kind: str) -> list[str]:
    return [k for k in LEAF_KEYS[kind] if "." not in k]


def sweep_kind(table: dict[str, Any]) -> str | None:
    """The scenario kind of a raw scenario table (None when its network.kind is not valid)."""
    network = table.get("network")
    kind = network.get("kind", "ring") if isinstance(network, dict) else "ring"
    return {"ring": "ring", "sumo": "section"}.get(kind) if isinstance(kind, str) else None


def _flatten(table: dict[str, Any], prefix: str = "") -> Iterator[tuple[str, Any]]:
    # TOML reads ``fleet.n_vehicles = [...]`` as a nested table: undo that.
    for key, value in table.items():
        if isinstance(value, dict):
            yield from _flatten(value, f"{prefix}{key}.")
        else:
            yield f"{prefix}{key}", value


def resolve_key(key: str, file: str, kind: str = "ring") -> str:
    """The dotted key of a ``kind`` scenario a sweep key names (short keys must be unique
    across tables)."""
    keys = LEAF_KEYS[kind]
    if key in keys:
        return key
    if key == "network.kind":
        raise UserError(
            f"{file}: sweep key 'network.kind' cannot be swept; write one scenario file per kind"
        )
    if key in _tables(kind):
        example = next(k for k in keys if k.startswith(key + "."))
        raise UserError(
            f"{file}: sweep key {key!r} is a table; sweep one of its keys, e.g. {example}"
        )
    matches = [k for k in keys if k.rsplit(".", 1)[-1] == key]
    if len(matches) == 1:
        return matches[0]
    if len(matches) > 1:
        raise UserError(
            f"{file}: sweep key {key!r} is ambiguous; give one of {', '.join(sorted(matches))}"
        )
    close = difflib.get_close_matches(key, list(keys), n=3)
    hint = f"; did you mean {', '.join(close)}?" if close else ""
    what = "a section scenario" if kind == "section" else "a ring scenario"
    top, tables = ", ".join(_top_keys(kind)), ", ".join(_tables(kind))
    raise UserError(
        f"{file}: unknown sweep key {key!r} for {what}; accepted: {top} or a dotted key "
        f"table.key of the tables {tables} (e.g. {EXAMPLE_KEY[kind]}), or a key name unique "
        f"across tables{hint}"
    )


def parse_sweep(sweep: Any, file: str, kind: str = "ring") -> list[tuple[str, str, list[Any]]]:
    """Validate a ``[sweep]`` table of a ``kind`` scenario (``"ring"`` or ``"section"``):
    (key as written, dotted key, values) in file order."""
    if not isinstance(sweep, dict) or not sweep:
        raise UserError(f"{file}: [sweep] must be a table of key = [value, ...] lines")
    out, seen = [], {}
    for key, values in _flatten(sweep):
        dotted = resolve_key(key, file, kind)
        if dotted in seen:
            raise UserError(f"{file}: sweep keys {seen[dotted]!r} and {key!r} both set {dotted}")
        seen[dotted] = key
        if not isinstance(values, list) or not values:
            raise UserError(f"{file}: sweep.{key} = {values!r} must be a non-empty list of values")
        origin = typing.get_origin(LEAF_KEYS[kind][dotted])
        if origin in (tuple, list):
            what = "a pair [low, high]" if origin is tuple else "a list"
            for v in values:
                if not isinstance(v, list):
                    raise UserError(
                        f"{file}: sweep.{key} = {values!r}: each value must be {what}, "
                        f"e.g. [{values!r}] for one variant"
                    )
        out.append((key, dotted, values))
    return out


def _fmt(value: Any) -> str:
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, float):
        return str(int(value)) if value.is_integer() else repr(value)
    if isinstance(value, list | tuple):
        return "_".join(_fmt(v) for v in value)
    return str(value)


def variant_name(parts: Sequence[tuple[str, Any]], prefix: str = "") -> str:
    """A deterministic, filesystem-safe name: ``seed=1__range_mps=12_14``."""
    words = ([prefix] if prefix else []) + [f"{k}={_fmt(v)}" for k, v in parts]
    name = re.sub(r"[^A-Za-z0-9._=+-]", "_", "__".join(words)).lstrip(".") or "variant"
    if len(name) > MAX_NAME:
        digest = hashlib.sha256(name.encode()).hexdigest()[:10]
        name = f"{name[: MAX_NAME - 11]}-{digest}"
    return name


@dataclass(frozen=True)
class Variant:
    """One scenario to run: a file, the sweep values applied to it, or why it cannot run."""

    name: str
    file: str
    params: dict[str, Any]  # dotted scenario key -> value
    scenario: AnyScenario | None
    error: str = ""

    @property
    def scenario_name(self) -> str:
        return self.scenario.name if self.scenario else ""


def expand_file(path: Path, prefix: str) -> list[Variant]:
    """The variants of one scenario file (one, unless it has a ``[sweep]`` table).

    A file that cannot be read gives one failed variant; a variant whose values fail
    validation is failed on its own. A malformed sweep is an error for the whole batch.
    """
    file = str(path)
    try:
        table, sweep = read_scenario_toml(path)
    except UserError as exc:
        return [Variant(prefix or path.stem, file, {}, None, str(exc))]
    kind = sweep_kind(table)
    if sweep is None or kind is None:  # an unaccepted network.kind fails in load_scenario
        return [_load(prefix or path.stem, path, {})]
    keys = parse_sweep(sweep, file, kind)
    out = []
    for combo in itertools.product(*(values for _, _, values in keys)):
        parts = [(key, v) for (key, _, _), v in zip(keys, combo, strict=True)]
        params = {dotted: v for (_, dotted, _), v in zip(keys, combo, strict=True)}
        out.append(_load(variant_name(parts, prefix), path, params))
    return out


def _load(name: str, path: Path, params: dict[str, Any]) -> Variant:
    try:
        return Variant(name, str(path), params, load_scenario(path, params, allow_sweep=True))
    except UserError as exc:
        return Variant(name, str(path), params, None, str(exc))


def resolve_inputs(inputs: Sequence[str | Path]) -> list[Path]:
    """Scenario files from paths and globs, in the given order, without duplicates."""
    files: list[Path] = []
    for item in inputs:
        s = str(item)
        if Path(s).is_file():
            found = [Path(s)]
        elif glob.has_magic(s):
            found = [Path(p) for p in sorted(glob.glob(s, recursive=True)) if Path(p).is_file()]
            if not found:
                raise UserError(f"{s}: no scenario file matches this pattern")
        elif Path(s).is_dir():
            raise UserError(f"{s}: is a folder; pass scenario files or a glob such as '{s}/*.toml'")
        else:
            raise UserError(f"{s}: scenario file not found")
        for p in found:
            if p.resolve() not in {f.resolve() for f in files}:
                files.append(p)
    return files


def expand(inputs: Sequence[str | Path]) -> list[Variant]:
    """Every variant of every input; names are prefixed by the file stem when several files."""
    files = resolve_inputs(inputs)
    stems: dict[str, Path] = {}
    for f in files:
        if f.stem in stems:
            raise UserError(
                f"{f}: has the same name as {stems[f.stem]}; variant folders are named after "
                "files, so rename one"
            )
        stems[f.stem] = f
    variants = [v for f in files for v in expand_file(f, f.stem if len(files) > 1 else "")]
    names: dict[str, Variant] = {}
    for v in variants:
        if v.name in names:
            raise UserError(
                f"{v.file}: sweep values {names[v.name].params} and {v.params} give the same "
                f"variant name {v.name!r}; make the values distinct"
            )
        names[v.name] = v
    return variants


# --------------------------------------------------------------------------- one variant


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


def _one_line(exc: BaseException) -> str:
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
                error = _one_line(exc) or type(exc).__name__
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


# --------------------------------------------------------------------------- backends

Done = Callable[[Task, Outcome], None]


def _worker_init() -> None:
    # Ctrl-C goes to the whole process group: the driver alone handles it and stops the
    # workers, so that no worker prints a traceback.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # One thread per worker for torch/BLAS (as Ray gives a one-CPU task): workers do not
    # oversubscribe the CPUs, and results do not depend on the worker count.
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if sys.platform.startswith("linux"):
        # A worker must not outlive a driver killed with SIGKILL (it would keep writing).
        with contextlib.suppress(Exception):
            import ctypes

            ctypes.CDLL(None).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
            if os.getppid() == 1:
                os._exit(1)


def _failed(task: Task, error: str) -> Outcome:
    return Outcome(task.name, False, error, math.nan, "", "", 0)


class LocalBackend:
    """``workers`` slots, each a one-process pool (spawned: one libsumo simulation each).

    A slot whose worker dies (killed, out of memory, crashed) breaks only its own pool:
    that variant fails and the slot gets a fresh process. A slot whose variant failed also
    gets a fresh process, so nothing of a failed SUMO start leaks into the next variant.
    """

    def __init__(self, workers: int) -> None:
        import multiprocessing

        self.workers = workers
        self._ctx = multiprocessing.get_context("spawn")

    def _pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(1, mp_context=self._ctx, initializer=_worker_init)

    def run(self, tasks: Sequence[Task], done: Done) -> None:
        main_file = getattr(sys.modules["__main__"], "__file__", None)
        if tasks and main_file and not Path(main_file).is_file():
            # Spawned workers re-import the main script; every one would die at start.
            raise UserError(
                f"local workers cannot start from a script read from {main_file}; "
                "run the batch from a file or with the macromicro command"
            )
        queue = list(reversed(tasks))
        pools = [self._pool() for _ in range(min(self.workers, len(tasks)))]
        running: dict[Future[Outcome], tuple[int, Task]] = {}
        try:
            while queue or running:
                busy = {slot for slot, _ in running.values()}
                for slot in range(len(pools)):
                    if slot not in busy and queue:
                        task = queue.pop()
                        running[pools[slot].submit(run_task, task)] = (slot, task)
                finished, _ = wait(running, return_when=FIRST_COMPLETED)
                for fut in finished:
                    slot, task = running.pop(fut)
                    try:
                        outcome = fut.result()
                    except BrokenProcessPool:
                        outcome = _failed(
                            task,
                            "worker process died while running this variant "
                            "(killed, out of memory or crashed)",
                        )
                    except Exception as exc:
                        outcome = _failed(task, _one_line(exc))
                    if not outcome.ok:
                        _stop(pools[slot])
                        pools[slot] = self._pool()
                    done(task, outcome)
        except BaseException:
            for pool in pools:
                _stop(pool)
            raise
        for pool in pools:
            pool.shutdown(wait=True)


def _stop(pool: ProcessPoolExecutor) -> None:
    """Stop a pool now, killing a worker that is still running a variant."""
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


def _pack(folder: Path) -> bytes:
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for item in sorted(folder.iterdir()):
            tar.add(item, arcname=item.name)
    return buf.getvalue()


def _unpack(blob: bytes, folder: Path) -> None:
    folder.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(blob), mode="r") as tar:
        tar.extractall(folder, filter="data")


def _input_key(path: str | Path) -> str:
    """How a shipped input file is named: its absolute path, ``..`` and ``.`` folded."""
    return os.path.normpath(os.path.abspath(path))


def _network_paths(sc: AnyScenario) -> dict[str, str | list[str]]:
    """The scenario's own file keys under ``[network]`` (paths as written, "" when unset)."""
    n = sc.network
    if isinstance(sc, SectionScenario):
        return {
            "sumocfg": n.sumocfg,
            "net_file": n.net_file,
            "route_files": list(n.route_files),
            "additional_files": list(n.additional_files),
        }
    return {"net_file": n.net_file, "routes_file": n.routes_file}


def input_files(sc: AnyScenario) -> list[Path]:
    """Every file besides the scenario that a variant reads: the ring's net and routes, or a
    section's SUMO files (the .sumocfg and every file it names, and the explicit ones)."""
    if isinstance(sc, SectionScenario):
        i = scenario_inputs(sc)
        files = [*([i.sumocfg] if i.sumocfg else []), i.net_file, *i.route_files]
        files += i.additional_files
    else:
        files = [sc.resolve(sc.network.net_file), sc.resolve(sc.network.routes_file)]
    return list(dict.fromkeys(Path(f) for f in files))


def shipment(sc: AnyScenario) -> dict[str, bytes]:
    """What a node without the scenario's input files needs: their bytes by absolute path."""
    return {_input_key(p): p.read_bytes() for p in input_files(sc)}


def _localise(sc: AnyScenario, inputs: dict[str, bytes], tmp: Path) -> AnyScenario:
    """On a node without the scenario's input files, use the copies the driver sent.

    The copies keep their layout relative to each other under ``tmp/inputs`` (a .sumocfg
    names its files relative to itself), and the scenario's ``[network]`` paths point at them.
    """
    if not inputs or all(os.path.isfile(k) for k in inputs):
        return sc
    root = os.path.commonpath([os.path.dirname(k) for k in inputs])
    base = tmp / "inputs"

    def local(path: str) -> str:
        key = _input_key(sc.resolve(path))
        if key not in inputs:  # not shipped: leave it (the stage names what is missing)
            return path
        return str(base / os.path.relpath(key, root))

    for key, data in inputs.items():
        copy = base / os.path.relpath(key, root)
        copy.parent.mkdir(parents=True, exist_ok=True)
        copy.write_bytes(data)
    changes: dict[str, Any] = {}
    for field, value in _network_paths(sc).items():
        if isinstance(value, list):
            changes[field] = [local(v) for v in value]
        elif value:
            changes[field] = local(value)
    return dataclasses.replace(sc, network=dataclasses.replace(sc.network, **changes))


def run_shipped(task: Task, inputs: dict[str, bytes]) -> tuple[Outcome, bytes]:
    """Run a variant on a node that shares no disk with the driver: input files come in
    ``inputs`` (``shipment``: path -> bytes), the variant's folder goes back as an
    uncompressed tar."""
    with tempfile.TemporaryDirectory(prefix="macromicro-") as tmp:
        sc = _localise(task.scenario, inputs, Path(tmp))
        local = dataclasses.replace(task, scenario=sc, out=str(Path(tmp) / "out"))
        outcome = run_task(local)
        return outcome, _pack(Path(local.out)) if outcome.ok else b""


def ray_task(task: Task, inputs: dict[str, bytes], driver_node: str) -> tuple[Outcome, bytes]:
    """A Ray task: on the driver's node, straight into the batch folder; elsewhere shipped."""
    import ray

    if ray.get_runtime_context().get_node_id() == driver_node:
        return run_task(task), b""
    return run_shipped(task, inputs)


def require_ray() -> Any:
    try:
        import ray
    except ImportError:
        raise UserError(f"--backend ray needs Ray, which is not installed: {RAY_INSTALL}") from None
    return ray


class RayBackend:
    """Variants as Ray tasks (one CPU each): a local Ray instance with ``workers`` CPUs,
    or the cluster at ``address``. Tasks on the driver's node write into the batch folder;
    elsewhere the scenario's input files (``shipment``: the ring's net and routes, a
    section's SUMO files) travel with the task and the variant's folder comes back, so
    other nodes need macromicro-sumo installed but no shared disk. Each distinct set of
    input files is put into Ray's object store once, however many variants share it."""

    def __init__(self, workers: int, address: str | None) -> None:
        self.ray = require_ray()
        self.workers = workers
        self.address = address

    def run(self, tasks: Sequence[Task], done: Done) -> None:
        ray = self.ray
        started = not ray.is_initialized()
        if started:
            kwargs: dict[str, Any] = {"address": self.address}
            if not self.address:
                kwargs["num_cpus"] = self.workers
            try:
                ray.init(**kwargs, include_dashboard=False, logging_level="ERROR")
            except Exception as exc:  # Ray raises ConnectionError, RuntimeError, ... here
                where = f"--address {self.address}" if self.address else "a local Ray instance"
                raise UserError(f"{where}: Ray did not start ({_one_line(exc)[:300]})") from None
        remote = ray.remote(num_cpus=1, max_retries=0)(ray_task)
        node = ray.get_runtime_context().get_node_id()
        refs: dict[Any, Task] = {}
        shipped: dict[tuple[str, ...], Any] = {}  # input paths -> their bytes in the store
        try:
            for task in tasks:
                try:
                    files = tuple(_input_key(p) for p in input_files(task.scenario))
                    if files not in shipped:
                        shipped[files] = ray.put(shipment(task.scenario))
                except (UserError, OSError) as exc:  # an input vanished since loading
                    done(task, _failed(task, _one_line(exc)))
                    continue
                refs[remote.remote(task, shipped[files], node)] = task
            while refs:
                ready, _ = ray.wait(list(refs), num_returns=1)
                for ref in ready:
                    task = refs.pop(ref)
                    try:
                        outcome, blob = ray.get(ref)
                        if outcome.ok and blob:
                            _unpack(blob, Path(task.out))
                    except ray.exceptions.RayError as exc:
                        outcome = _failed(task, _ray_error(exc))
                    done(task, outcome)
        except BaseException:
            for ref in refs:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
            raise
        finally:
            if started:
                ray.shutdown()


def _ray_error(exc: Exception) -> str:
    name = type(exc).__name__
    if "WorkerCrashed" in name or "NodeDied" in name:
        return f"worker process died while running this variant ({name})"
    return (_one_line(exc) or name)[:500]


# --------------------------------------------------------------------------- the batch


@dataclass
class BatchResult:
    out: Path
    summary: Any  # pandas DataFrame, one row per variant
    counts: dict[str, int]


def is_complete(folder: Path, variant: Variant, stages: Sequence[str]) -> bool:
    """Complete: renamed into place with its manifest, for the same scenario and stages."""
    if not (folder / "manifest.json").is_file() or not (folder / export.VARIANT_FILE).is_file():
        return False
    try:
        info = json.loads((folder / export.VARIANT_FILE).read_text())
    except (OSError, json.JSONDecodeError):
        return False
    return (
        variant.scenario is not None
        and info.get("scenario_sha256") == variant.scenario.digest()
        and info.get("stages") == list(stages)
        and not export.damaged(folder)  # an output lost or cut short: redo the variant
    )


def _discard(partial: Path) -> None:
    """Remove an unfinished variant's folder and the stderr log beside it."""
    shutil.rmtree(partial, ignore_errors=True)
    partial.with_name(partial.name + ".log").unlink(missing_ok=True)


@contextlib.contextmanager
def _lock(out: Path) -> Iterator[None]:
    """One batch per folder at a time (the lock dies with its process, even on SIGKILL)."""
    import fcntl

    with open(out / ".batch.lock", "w") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            raise UserError(f"{out}: another batch is running in this folder") from None
        yield


def run_batch(
    inputs: Sequence[str | Path],
    out: Path | str,
    stages: Sequence[str] = ("simulate",),
    workers: int = 1,
    backend: str = "local",
    address: str | None = None,
    progress: bool = True,
    command: str = "",
) -> BatchResult:
    """Run every variant of ``inputs`` into ``out``; re-runs skip complete variants."""
    from tqdm import tqdm

    if workers < 1:
        raise UserError(f"--workers {workers}: accepted >= 1")
    if backend not in BACKENDS:
        raise UserError(f"--backend {backend!r} is not accepted; accepted: {', '.join(BACKENDS)}")
    if address and backend != "ray":
        raise UserError("--address is for --backend ray")
    for stage in stages:
        if stage not in STAGES or stage not in SECTION_STAGES:
            raise UserError(f"unknown stage {stage!r}; accepted: {', '.join(STAGES)}")
    engine = LocalBackend(workers) if backend == "local" else RayBackend(workers, address)
    variants = expand(inputs)
    out = prepare_out_dir(out, [v.file for v in variants if v.file])
    vdir = out / "variants"
    vdir.mkdir(exist_ok=True)
    with _lock(out):
        for leftover in itertools.chain(vdir.glob(".partial-*"), vdir.glob(".trash-*")):
            if leftover.is_dir():
                shutil.rmtree(leftover, ignore_errors=True)
            else:
                leftover.unlink(missing_ok=True)
        spec = [
            {"name": v.name, "scenario": v.scenario_name, "file": v.file, "params": v.params}
            for v in variants
        ]
        # Parameters as [key, value] pairs: JSON objects are written with sorted keys, and the
        # sweep's own order is the order of the parameter columns.
        stored = [{**row, "params": list(row["params"].items())} for row in spec]
        write_json(
            {"stages": list(stages), "command": command, "variants": stored}, out / "batch.json"
        )

        statuses: dict[str, dict[str, Any]] = {}
        tasks, by_name = [], {v.name: v for v in variants}
        missing = {
            kind: "; ".join(filter(None, (stage_problem(s, kind) for s in stages)))
            for kind in KINDS
        }
        for v in variants:
            cannot = missing[scenario_kind(v.scenario)]
            if v.error or (cannot and not is_complete(vdir / v.name, v, stages)):
                statuses[v.name] = {"status": "failed", "error": v.error or cannot}
            elif is_complete(vdir / v.name, v, stages):
                info = json.loads((vdir / v.name / export.VARIANT_FILE).read_text())
                statuses[v.name] = {"status": "complete", "reused": True, "wall_s": info["wall_s"]}
            else:
                assert v.scenario is not None
                partial = vdir / f".partial-{v.name}.{secrets.token_hex(4)}"
                tasks.append(
                    Task(v.name, v.scenario, tuple(stages), str(partial), f"{command} [{v.name}]")
                )
        n_reused = sum(s["status"] == "complete" for s in statuses.values())
        n_invalid = sum(s["status"] == "failed" for s in statuses.values())
        bar = tqdm(
            total=len(variants),
            initial=n_reused + n_invalid,
            desc="batch",
            unit="variant",
            disable=not progress,
            dynamic_ncols=True,
        )

        def say(line: str) -> None:
            if progress:
                bar.write(line)

        say(
            f"batch: {len(variants)} variants, {n_reused} already complete, {n_invalid} invalid, "
            f"{len(tasks)} to run on {backend} with {workers} worker(s)"
        )
        for name, st in statuses.items():
            if st["status"] == "failed":
                say(f"  failed    {name}: {st['error']}")
                if not progress:
                    print(f"failed: {name}: {st['error']}", file=sys.stderr)

        headlines: dict[str, dict[str, Any]] = {}  # complete variants' figures, read once

        def write_tables(which: tuple[str, ...] = ("summary",)) -> None:
            tables = export.gather(spec, statuses, vdir, which, headlines)
            export.write_tables(tables, out, "batch", "csv")

        def done(task: Task, outcome: Outcome) -> None:
            partial, final = Path(task.out), vdir / task.name
            write_text(outcome.log, out / "logs" / f"{task.name}.log")
            if outcome.ok and final.exists() and not (final / OUTPUT_MARK).is_file():
                outcome = dataclasses.replace(
                    outcome,
                    ok=False,
                    error=f"{final}: exists and was not written by macromicro-sumo; move it away",
                )
            if outcome.ok:
                v = by_name[task.name]
                assert v.scenario is not None
                info = {
                    "variant": v.name,
                    "scenario_file": v.file,
                    "params": list(v.params.items()),
                    "stages": list(task.stages),
                    "scenario_sha256": v.scenario.digest(),
                    "wall_s": outcome.wall_s,
                    "backend": backend,
                    "host": outcome.host,
                }
                write_json(info, partial / export.VARIANT_FILE)
                mark_output(partial)
                if final.exists():  # stale: another scenario or other stages under this name
                    trash = vdir / f".trash-{task.name}.{secrets.token_hex(4)}"
                    os.replace(final, trash)
                    os.replace(partial, final)
                    shutil.rmtree(trash, ignore_errors=True)
                else:
                    os.replace(partial, final)
                statuses[task.name] = {"status": "complete", "wall_s": outcome.wall_s}
                say(f"  complete  {task.name}  ({outcome.wall_s:.1f} s)")
            else:
                _discard(partial)
                statuses[task.name] = {
                    "status": "failed",
                    "wall_s": outcome.wall_s,
                    "error": outcome.error,
                }
                say(f"  failed    {task.name}: {outcome.error}")
                if not progress:
                    print(f"failed: {task.name}: {outcome.error}", file=sys.stderr)
            bar.update(1)
            write_tables()

        try:
            engine.run(tasks, done)
        except BaseException:
            bar.close()
            for t in tasks:
                _discard(Path(t.out))
                if t.name not in statuses:  # it may have been renamed into place just now
                    final = vdir / t.name
                    done_now = is_complete(final, by_name[t.name], stages)
                    statuses[t.name] = {"status": "complete" if done_now else "interrupted"}
            with contextlib.suppress(Exception):
                write_tables(export.TABLES)
            raise
        bar.close()
        write_tables(export.TABLES)
    summary = export.gather(spec, statuses, vdir, ("summary",), headlines)["summary"]
    counts = summary["status"].value_counts().to_dict()
    counts["reused"] = n_reused
    return BatchResult(out, summary, counts)


# --------------------------------------------------------------------------- command line


def _cmd_batch(args: argparse.Namespace) -> int:
    t0 = time.perf_counter()
    res = run_batch(
        args.scenarios,
        args.out,
        stages=args.stage or ["simulate"],
        workers=args.workers,
        backend=args.backend,
        address=args.address,
        progress=not args.quiet,
        command=args.command_line,
    )
    c = res.counts
    print(
        f"batch: {c.get('complete', 0)} complete ({c['reused']} reused), {c.get('failed', 0)} "
        f"failed in {time.perf_counter() - t0:.1f} s; see {res.out / 'batch_summary.csv'}"
    )
    return 1 if c.get("failed", 0) else 0


def _cmd_export(args: argparse.Namespace) -> int:
    for path in export.export(args.folder, args.format):
        print(f"wrote {path}")
    return 0


def register(sub: Any) -> None:
    """Add the ``batch`` and ``export`` subcommands to the CLI's subparsers."""
    p = sub.add_parser(
        "batch",
        help="run many scenario variants (files, globs or a [sweep]) in parallel",
        description="Run many scenario variants, each in its own folder under OUT/variants/, "
        "and gather their macro statistics in OUT/batch_macro.csv. Re-running skips "
        "complete variants. Exit code 1 when a variant failed.",
    )
    p.set_defaults(func=_cmd_batch)
    p.add_argument("scenarios", nargs="+", help="scenario TOML files or globs ('runs/*.toml')")
    p.add_argument("--out", type=Path, required=True, help="batch output folder")
    p.add_argument(
        "--stage",
        action="append",
        choices=list(STAGES),
        help="stage to run per variant, repeatable, in order (default: simulate)",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1,
        help="parallel worker processes (local) or CPUs of the local Ray instance "
        "(default: CPUs available)",
    )
    p.add_argument("--backend", choices=BACKENDS, default="local", help="where variants run")
    p.add_argument("--address", help=f"Ray cluster address for --backend ray ({RAY_INSTALL})")
    p.add_argument("--quiet", action="store_true", help="no progress bar or status lines")

    p = sub.add_parser(
        "export",
        help="re-export a finished run or batch as CSV or Parquet tables",
        description="Write the macro, detector and summary tables of a finished batch "
        "(batch_*.FORMAT) or run (export_*.FORMAT) into its folder.",
    )
    p.set_defaults(func=_cmd_export)
    p.add_argument("folder", type=Path, help="output folder of `macromicro batch` or `simulate`")
    p.add_argument("--format", choices=EXPORT_FORMATS, default="csv", help="table format")
    p.add_argument("--quiet", action="store_true", help="accepted for symmetry; prints paths")
