"""scripts/bench_instructions.py: one Bremen run (real SUMO, the policy in the loop) that
switches callgrind's instrumentation on around the run only where valgrind runs it, and
says it counted nothing outside valgrind."""

from __future__ import annotations

import contextlib
import importlib.util
import io
import re
from pathlib import Path

import pytest
from conftest import ROOT

_spec = importlib.util.spec_from_file_location(
    "bench_instructions", ROOT / "scripts" / "bench_instructions.py"
)
script = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(script)


@pytest.mark.parametrize("method", ["policy", "oracle"])
def test_a_short_run_outside_valgrind_drives_and_counts_nothing(
    tmp_path: Path, method: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("LD_PRELOAD", raising=False)
    calls: list[list[str]] = []
    monkeypatch.setattr(script.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    out = io.StringIO()
    args = ["--method", method, "--duration-s", "60", "--checkpoint", str(tmp_path / "no.pt")]
    with contextlib.redirect_stdout(out):
        assert script.main(args) == 0
    got = out.getvalue()
    m = re.search(r"(\d+) steps, ([\d,]+) vehicle-steps, ([\d,]+) driven", got)
    assert m is not None and m[1] == "120", got
    vehicle_steps, driven = int(m[2].replace(",", "")), int(m[3].replace(",", ""))
    assert vehicle_steps > 0, got
    # the oracle drives nobody; the policy most of those on the section
    assert (driven == 0) if method == "oracle" else (0 < driven < vehicle_steps), got
    assert "not counted: not under valgrind" in got
    assert calls == []  # callgrind_control only under valgrind


def test_under_valgrind_the_run_alone_is_instrumented(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("LD_PRELOAD", "/usr/libexec/valgrind/vgpreload_core-amd64-linux.so")
    calls: list[list[str]] = []
    monkeypatch.setattr(script.subprocess, "run", lambda cmd, **kw: calls.append(cmd))
    script.instrument(True)
    script.instrument(False)
    pid = str(script.os.getpid())
    assert calls == [
        ["callgrind_control", "-i", "on", pid],
        ["callgrind_control", "-i", "off", pid],
    ]
