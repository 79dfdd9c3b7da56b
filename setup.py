"""Build hook: ship the example scenarios and networks inside the package.

``scenarios/`` and ``sumo_nets/`` stay at the repository's top level (the scenarios name
their networks as ``../sumo_nets/...``); a wheel carries both as
``macromicro_sumo/examples/scenarios`` and ``macromicro_sumo/examples/sumo_nets``, where
``macromicro_sumo.env.examples`` finds them. An editable install reads the checkout's own
folders. The sdist carries them through MANIFEST.in. Everything else is in pyproject.toml.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
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


setup(cmdclass={"build_py": BuildPyWithExamples})
