"""Where variants run: ``LocalBackend`` (one single-process pool per worker slot) or
``RayBackend`` (Ray tasks, on this machine or a cluster), and the shipping of a scenario's
input files to a node that shares no disk with the driver.

libsumo runs one simulation per process: each local worker slot is its own single-process
pool, so a worker that dies takes down only the variant it was running.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import math
import multiprocessing
import os
import tarfile
import tempfile
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

from macromicro_sumo.batch.sweep import AnyScenario
from macromicro_sumo.batch.tasks import Outcome, Task, one_line, run_task
from macromicro_sumo.errors import UserError
from macromicro_sumo.pipeline.parallel import stop_pool, unimportable_main, worker_setup
from macromicro_sumo.sumo.inputs import input_files

RAY_INSTALL = "pip install 'macromicro-sumo[ray]'"

Done = Callable[[Task, Outcome], None]


def _failed(task: Task, error: str) -> Outcome:
    return Outcome(task.name, False, error, math.nan, "", "")


class LocalBackend:
    """``workers`` slots, each a one-process pool (spawned: one libsumo simulation each).

    A slot whose worker dies (killed, out of memory, crashed) breaks only its own pool:
    that variant fails and the slot gets a fresh process. A slot whose variant failed also
    gets a fresh process, so nothing of a failed SUMO start leaks into the next variant.
    """

    def __init__(self, workers: int) -> None:
        self.workers = workers
        self._ctx = multiprocessing.get_context("spawn")

    def _pool(self) -> ProcessPoolExecutor:
        return ProcessPoolExecutor(1, mp_context=self._ctx, initializer=worker_setup)

    def run(self, tasks: Sequence[Task], done: Done) -> None:
        main_file = unimportable_main()
        if tasks and main_file:
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
                        outcome = _failed(task, one_line(exc))
                    if not outcome.ok:
                        stop_pool(pools[slot])
                        pools[slot] = self._pool()
                    done(task, outcome)
        except BaseException:
            for pool in pools:
                stop_pool(pool)
            raise
        for pool in pools:
            pool.shutdown(wait=True)


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
    return {
        "sumocfg": n.sumocfg,
        "net_file": n.net_file,
        "route_files": list(n.route_files),
        "additional_files": list(n.additional_files),
    }


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
    elsewhere the scenario's input files (``shipment``: its SUMO files) travel with the task and the variant's folder comes back, so
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
                raise UserError(f"{where}: Ray did not start ({one_line(exc)[:300]})") from None
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
                    done(task, _failed(task, one_line(exc)))
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
    return (one_line(exc) or name)[:500]
