"""The seeded split of the ground-truth runs into train / val / held_out (``data.section.split_runs``)."""

from __future__ import annotations

import numpy as np
import pytest

from macromicro_sumo.data.section import split_runs
from macromicro_sumo.errors import UserError


@pytest.mark.parametrize("n_runs", [2, 3, 4, 7, 20, 40])
@pytest.mark.parametrize("seed", [0, 2024])
def test_split_runs_is_a_disjoint_cover(n_runs, seed):
    runs = np.arange(n_runs) + 100  # ids need not start at 0
    parts = split_runs(runs, 0.25, seed)
    assert set(parts) == {"train", "val", "held_out"}
    all_ids = np.concatenate(list(parts.values()))
    assert len(all_ids) == n_runs and set(all_ids) == set(runs.tolist())  # disjoint and covering
    assert len(parts["held_out"]) >= 1 and len(parts["train"]) >= 1
    assert len(parts["held_out"]) == max(1, round(0.25 * n_runs))
    assert len(parts["val"]) == (0 if n_runs < 3 else max(1, round(0.15 * n_runs)))
    for ids in parts.values():
        assert list(ids) == sorted(ids)


def test_split_runs_is_seeded():
    runs = np.arange(40)
    a = split_runs(runs, 0.25, 1)
    assert all(np.array_equal(a[k], split_runs(runs, 0.25, 1)[k]) for k in a)
    # Another seed -> another held-out set (10 of 40: equal sets are astronomically rare).
    assert not np.array_equal(a["held_out"], split_runs(runs, 0.25, 2)["held_out"])
    assert len(a["held_out"]) == 10 and len(a["val"]) == 6 and len(a["train"]) == 24


def test_split_runs_needs_two_runs():
    with pytest.raises(UserError, match="at least 2 ground-truth runs"):
        split_runs(np.array([0]), 0.25, 0)
