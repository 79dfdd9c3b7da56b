"""The example scenarios and networks shipped with the package, and the demo that lets
``gymnasium.make("macromicro/RingHidden-v0")`` run with no arguments.

Where the examples are: in an installed wheel, ``scenarios/`` and ``sumo_nets/`` lie in
``macromicro_sumo/examples/`` (``setup.py``'s build hook copies them there); in a checkout
or an editable install they are the repository's own folders. A scenario names its network
relative to itself (``../sumo_nets/...``), which holds in both layouts.

The demo: the shipped ``ring_paper`` scenario with a small budget (``DEMO_OVERRIDES``),
simulated and its generator trained once, seeded, into a per-user cache folder
(``$MACROMICRO_CACHE``, else ``$XDG_CACHE_HOME/macromicro-sumo``, else
``~/.cache/macromicro-sumo``), and reused afterwards. What it does is said on stderr.
"""

from __future__ import annotations

import contextlib
import hashlib
import importlib.resources
import os
import shutil
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import torch

from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_stage import run_train_section_generator
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import SectionScenario
from macromicro_sumo.truth.section import simulate_section

try:  # POSIX: one process builds the demo while the others wait (vector envs' workers)
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None

EXAMPLES = ("scenarios", "sumo_nets")  # the folders shipped as package data

DEMO_EXAMPLE = "ring_paper"
# 20 runs of 180 s (about 400 training episodes) and a generator of 200 epochs at most:
# 25 s on one core through the section stages (measured 26 Nov 2026, loaded machine).
DEMO_OVERRIDES = {
    "simulation.n_runs": 20,
    "simulation.duration_s": 180.0,
    "generator.epochs": 200,
}
DEMO_FORMAT = 2  # bump when what the demo folder holds changes (2: the section stages)
_DONE = "demo_complete"  # written last: a folder without it is rebuilt


def examples_root() -> Path:
    """The folder that holds ``scenarios/`` and ``sumo_nets/``."""
    shipped = Path(str(importlib.resources.files("macromicro_sumo") / "examples"))
    checkout = Path(__file__).resolve().parents[2]
    for root in (shipped, checkout):
        if all((root / name).is_dir() for name in EXAMPLES):
            return root
    raise UserError(
        f"the example scenarios are not installed (looked in {shipped} and {checkout}); "
        "reinstall macromicro-sumo"
    )


def example_names() -> list[str]:
    """The shipped scenarios, by name (``ring_paper``, ...); none if they are missing."""
    try:
        root = examples_root()
    except UserError:
        return []
    return sorted(p.stem for p in (root / "scenarios").glob("*.toml"))


def example_scenario(name: str) -> Path:
    """The TOML file of the shipped scenario ``name``."""
    path = examples_root() / "scenarios" / f"{name}.toml"
    if not path.is_file():
        raise UserError(
            f"no example scenario {name!r}; accepted: one of {', '.join(example_names())}"
        )
    return path


def sumo_nets_dir() -> Path:
    """The shipped SUMO networks."""
    return examples_root() / "sumo_nets"


def cache_root() -> Path:
    """The per-user folder for built demos."""
    if os.environ.get("MACROMICRO_CACHE"):
        return Path(os.environ["MACROMICRO_CACHE"]).expanduser()
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base).expanduser() / "macromicro-sumo"


@dataclass(frozen=True)
class Demo:
    """A built demo: the scenario (with ``DEMO_OVERRIDES``), its ground truth and generator."""

    scenario: SectionScenario
    data: Path
    generator: Path
    folder: Path


def _package_version() -> str:
    try:
        return version("macromicro-sumo")
    except PackageNotFoundError:
        return "unknown"


@contextlib.contextmanager
def _locked(path: Path) -> Iterator[None]:
    with open(path, "a") as handle:
        if fcntl is not None:
            fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            if fcntl is not None:
                fcntl.flock(handle, fcntl.LOCK_UN)


def demo() -> Demo:
    """The demo's ground truth and generator, built into the cache on first use (what it
    does then is said on stderr)."""
    sc = load_scenario(example_scenario(DEMO_EXAMPLE), DEMO_OVERRIDES)
    key = hashlib.sha256(f"{sc.digest()} {_package_version()} {DEMO_FORMAT}".encode())
    folder = cache_root() / f"demo-{DEMO_EXAMPLE}-{key.hexdigest()[:12]}"
    built = Demo(sc, folder / "ground_truth", folder / "generator" / "generator.pt", folder)
    if (folder / _DONE).is_file():
        return built
    try:
        folder.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(
            f"{folder.parent}: cannot create the demo's cache folder ({exc.strerror}); "
            "set MACROMICRO_CACHE to a folder you can write"
        ) from None
    with _locked(folder.parent / f"{folder.name}.lock"):
        if (folder / _DONE).is_file():  # another process built it while this one waited
            return built
        print(
            f"macromicro: first use of the demo: simulating {sc.simulation.n_runs} runs of the "
            f"example scenario {DEMO_EXAMPLE!r} and training its generator into {folder} "
            "(once; later uses read it from there)",
            file=sys.stderr,
        )
        t0 = time.perf_counter()
        shutil.rmtree(folder, ignore_errors=True)  # an unfinished build's leftovers
        threads = torch.get_num_threads()  # the generator stage sets one thread
        try:
            simulate_section(sc, built.data, command="macromicro demo", progress=False)
            run_train_section_generator(
                sc, built.data, built.generator.parent, "macromicro demo", progress=False
            )
        finally:
            torch.set_num_threads(threads)
        (folder / _DONE).write_text(f"built in {time.perf_counter() - t0:.1f} s\n")
        print(f"macromicro: demo built in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    return built
