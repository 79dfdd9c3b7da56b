"""Progress when the output is not a terminal: one line per stage, not every bar refresh."""

from __future__ import annotations

import subprocess
import sys

from macromicro_sumo.progress import tqdm


def test_one_summary_line_per_stage_off_a_terminal(capsys):
    for _ in tqdm(range(3), desc="simulate", unit="run"):
        pass
    bar = tqdm(total=5, desc="train-policy", unit="update")
    for i in range(5):
        bar.update(1)
        bar.set_postfix(r_macro=f"{0.5 + i / 10:.1f}")
    bar.close()
    bar.close()  # closing twice prints nothing more
    with tqdm(total=2, desc="quiet", disable=True) as off:
        off.update(2)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 2
    assert lines[0].startswith("simulate: 3/3 run in ")
    assert lines[1].startswith("train-policy: 5/5 update in ") and lines[1].endswith(
        "(r_macro=0.9)"
    )


def test_simulate_logs_one_line_to_a_file(make_scenario, tmp_path):
    log = tmp_path / "log.txt"
    with open(log, "w") as f:
        small = make_scenario({"simulation.n_runs": 2, "simulation.duration_s": 60.0})
        cmd = [sys.executable, "-m", "macromicro_sumo.cli", "simulate", str(small)]
        subprocess.run([*cmd, "--out", str(tmp_path / "out")], stderr=f, check=True)
    text = log.read_text()
    assert "\r" not in text
    assert [line for line in text.splitlines() if line.startswith("simulate:")] == [
        line for line in text.splitlines() if "simulate" in line
    ]
    assert sum(line.startswith("simulate: ") for line in text.splitlines()) == 1
