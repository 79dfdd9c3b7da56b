"""Build hook: ship the example scenarios and networks inside the package.

``scenarios/`` and ``sumo_nets/`` stay at the repository's top level (the scenarios name
their networks as ``../sumo_nets/...``); a wheel carries both as
``macromicro_sumo/examples/scenarios`` and ``macromicro_sumo/examples/sumo_nets``, where
``macromicro_sumo.env.examples`` finds them. An editable install reads the checkout's own
folders. The sdist carries them through MANIFEST.in.

The compiled parts, optional: ``road/kernels.c`` (``road.physics.safe_speed`` and two more
of a deployment step's arithmetic in one pass each, bit for bit their numpy form) and
``sumo/calls.c`` (a step's per-vehicle libsumo calls and look-ups in one C loop each, the
same calls) and ``sumo/libsumo_cxx.cpp`` (those libsumo calls on libsumo's C++ functions,
not their SWIG wrappers), built where a C (C++) compiler and Python's headers are found; where not, the
install goes on and numpy answers (the same values, more time a deployment step). Everything else is in pyproject.toml.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import Extension, setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent
EXAMPLES = ("scenarios", "sumo_nets")


class BuildPyWithExamples(build_py):
    def run(self) -> None:
        super().run()
        if self.editable_mode:  # the checkout's own folders are read in place
            return
        target = Path(self.build_lib) / "macromicro_sumo" / "examples"
        for name in EXAMPLES:
            shutil.copytree(
                ROOT / name,
                target / name,
                dirs_exist_ok=True,
                ignore=shutil.ignore_patterns("__pycache__", "*.pyc"),
            )


KERNELS = Extension(
    "macromicro_sumo.road.kernels",
    ["macromicro_sumo/road/kernels.c"],
    # No fused multiply-add and no fast math: numpy's roundings, operation by operation.
    extra_compile_args=["-O2", "-ffp-contract=off", "-fno-fast-math"],
    optional=True,
)
CALLS = Extension(
    "macromicro_sumo.sumo.calls",
    ["macromicro_sumo/sumo/calls.c"],
    extra_compile_args=["-O2"],  # no arithmetic: calls and copies
    optional=True,
)

DIRECT = Extension(
    "macromicro_sumo.sumo.libsumo_cxx",
    ["macromicro_sumo/sumo/libsumo_cxx.cpp"],
    extra_compile_args=["-O2"],  # no arithmetic: calls and copies
    language="c++",
    optional=True,
)

setup(cmdclass={"build_py": BuildPyWithExamples}, ext_modules=[KERNELS, CALLS, DIRECT])
