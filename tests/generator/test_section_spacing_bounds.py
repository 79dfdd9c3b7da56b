"""The ring's spacing bounds, its A and several completions per scene on the section generator
(issue 16, "Ring as a section: status" item 3).

psi's largest spacing is checked by hand against a real small run of ``ring_paper_section``
(SUMO, two runs of 120 s); the placement cap and the touched A on synthetic ring scenes.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from ring_scenes import N_VEHICLES, S_MIN_M, ring_scenes

from macromicro_sumo.data.section import PSI_FIELDS, SectionSnapshots, psi_table
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_bounds import bounded_gaps
from macromicro_sumo.generator.section_model import SectionGeneratorNet, section_losses
from macromicro_sumo.generator.section_rollout import Scene
from macromicro_sumo.generator.section_sampler import complete_section
from macromicro_sumo.generator.section_scene import Gaps, Psi, Road
from macromicro_sumo.generator.section_stage import run_train_section_generator
from macromicro_sumo.generator.section_train import squared_dispersion
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.section import SectionGeneratorConfig, SectionScenario
from macromicro_sumo.truth.section import load_section_truth

ROOT = Path(__file__).resolve().parents[2]


def with_generator(sc: SectionScenario, **gen: object) -> SectionScenario:
    return dataclasses.replace(sc, generator=dataclasses.replace(sc.generator, **gen))


def by_hand(passages: pd.DataFrame, run: int, begin: float, end: float, s_min: float) -> np.ndarray:
    """The interval's passage spacings: at each loop, consecutive passages' headway x their
    mean speed, dated at the second passage, shorter than s_min / 2 left out."""
    out = []
    for _, g in passages[passages["run"] == run].groupby("detector_id"):
        g = g.sort_values("time_s")
        t, v = g["time_s"].to_numpy(), g["speed_mps"].to_numpy()
        for i in range(1, len(t)):
            d = (t[i] - t[i - 1]) * 0.5 * (v[i] + v[i - 1])
            if begin <= t[i] < end and d >= 0.5 * s_min:
                out.append(d)
    return np.array(out)


def test_psi_spacing_max_from_the_passages_by_hand(ring_section_truth) -> None:
    """spacing_bounds = "passages": psi's shortest and longest spacing are the interval's
    extreme passage spacings (interval), x 0.9 / x 1.1 (margin), widened by range / (n - 1)
    (extended), the shortest never below spacing_min_m; "none" (the default) has no bound.
    The extended bounds hold more of the true spacings around the loop than the
    interval's, and almost all of them."""
    sc, gt = ring_section_truth
    truth = load_section_truth(gt, sc)
    assert SectionGeneratorConfig().spacing_bounds == "none"
    none = psi_table(truth, with_generator(sc, spacing_bounds="none"))
    assert np.isinf(none["spacing_max_m"]).all()

    def table(source: str) -> pd.DataFrame:
        cfg = with_generator(sc, spacing_bounds="passages", bounds_source=source)
        return psi_table(truth, cfg).reset_index(drop=True)

    interval, margin, extended = table("interval"), table("margin"), table("extended")
    assert len(interval) == 4  # two runs x two 60 s intervals
    np.testing.assert_allclose(margin["spacing_max_m"], 1.1 * interval["spacing_max_m"])
    np.testing.assert_allclose(
        margin["spacing_low_m"], np.maximum(0.9 * interval["spacing_low_m"], S_MIN_M)
    )
    assert np.isinf(none["spacing_max_m"]).all()
    np.testing.assert_allclose(none["spacing_low_m"], none["spacing_min_m"])
    passages = pd.read_csv(gt / "detector_passages.csv")
    traj = truth.trajectories
    inside_int = inside_ext = total = 0
    for i, row in interval.iterrows():
        d = by_hand(passages, row["run"], row["begin_s"], row["end_s"], row["spacing_min_m"])
        assert d.size > 10
        assert row["spacing_max_m"] == pytest.approx(d.max())
        assert row["spacing_low_m"] == pytest.approx(max(d.min(), S_MIN_M))
        assert row["spacing_min_m"] == S_MIN_M  # the fleet's 5 m + min_gap_m 2 m, unchanged
        # psi's spacing std is the std of the same sample
        assert row["std_spacing_m"] == pytest.approx(d.std(ddof=1), rel=1e-6)
        widen = (d.max() - d.min()) / (d.size - 1)
        assert extended.loc[i, "spacing_max_m"] == pytest.approx(d.max() + widen)
        assert extended.loc[i, "spacing_low_m"] == pytest.approx(max(d.min() - widen, S_MIN_M))
        w = traj[
            (traj["run"] == row["run"])
            & traj["time_s"].between(row["begin_s"], row["end_s"], inclusive="left")
        ]
        for _, s in w.groupby("time_s"):
            a = np.sort(s["arc_m"].to_numpy())
            gaps = np.append(np.diff(a), a[0] + truth.section.length_m - a[-1])
            total += gaps.size
            low, high = row["spacing_low_m"], row["spacing_max_m"]
            inside_int += int(((gaps >= low) & (gaps <= high)).sum())
            low, high = extended.loc[i, ["spacing_low_m", "spacing_max_m"]]
            inside_ext += int(((gaps >= low) & (gaps <= high)).sum())
    assert inside_ext >= inside_int and inside_ext / total > 0.97


def test_spacing_bounds_need_the_passages(ring_section_truth, tmp_path: Path) -> None:
    sc, gt = ring_section_truth
    truth = load_section_truth(gt, sc)
    bare = dataclasses.replace(truth, folder=tmp_path)  # a folder without passages
    cfg = with_generator(sc, spacing_bounds="passages", bounds_source="interval")
    with pytest.raises(UserError) as err:
        psi_table(bare, cfg)
    msg = str(err.value)
    assert "\n" not in msg and "detector_passages.csv" in msg and "spacing_bounds" in msg


def scenes_one_hidden(section: Section, n: int, seed: int, d_max: float) -> SectionSnapshots:
    """Five vehicles on the loop, one hidden; psi's largest spacing ``d_max``."""
    return ring_scenes(
        section, n, seed, lambda rng: rng.integers(N_VEHICLES), psi_tail=(d_max, S_MIN_M)
    )


def touched_spacings(section: Section, arc: np.ndarray, generated: np.ndarray) -> np.ndarray:
    """The two spacings around the generated vehicle of one scene."""
    order = np.argsort(arc)
    a, g = arc[order], generated[order]
    gaps = np.append(np.diff(a), a[0] + section.length_m - a[-1])  # gap ahead of each
    j = int(np.flatnonzero(g)[0])
    return np.array([gaps[j], gaps[j - 1]])


def test_the_last_vehicle_keeps_both_spacings_under_psis_largest(ring_loop: Section) -> None:
    """With psi's d_max (the largest true spacing of each scene, so the true place fits), the
    one hidden vehicle is placed with both its spacings <= d_max (Algorithm 3's rejection,
    a few projections); without it (inf) the same untrained generator puts some beyond."""
    torch.manual_seed(0)
    net = SectionGeneratorNet(16, "posterior")
    snaps = scenes_one_hidden(ring_loop, 60, seed=3, d_max=np.inf)
    true_max = np.zeros(len(snaps))
    for i in range(len(snaps)):
        a = np.sort(snaps.arc_m[i])
        true_max[i] = np.append(np.diff(a), a[0] + ring_loop.length_m - a[-1]).max()
    capped = dataclasses.replace(snaps, psi=snaps.psi.copy())
    capped.psi[:, PSI_FIELDS.index("spacing_max_m")] = true_max
    beyond = {}
    for name, s in (("capped", capped), ("free", snaps)):
        comp = complete_section(net, ring_loop, s, s.k_true, 20, seed=1)
        assert comp.projections.sum() <= len(s) // 10  # rejection; the rest projected inside
        touched = np.array(
            [
                touched_spacings(
                    ring_loop, comp.arc_m[i][comp.valid[i]], comp.generated[i][comp.valid[i]]
                )
                for i in range(len(s))
            ]
        )
        beyond[name] = int((touched > true_max[:, None] + 1e-6).sum())
    assert beyond["capped"] == 0 and beyond["free"] > 0


def test_touched_spacing_set_is_the_rings_a(ring_loop: Section) -> None:
    """spacing_set = "touched": the spacing terms count only the spacings with a generated
    vehicle at either end (the ring's A), deviations from the loop's exact mean spacing."""
    snaps = scenes_one_hidden(ring_loop, 4, seed=8, d_max=np.inf)
    road = Road.of(ring_loop)
    # the first three slots observed, the last two generated
    lane, arc = torch.as_tensor(snaps.lane), torch.as_tensor(snaps.arc_m)
    speed, present = torch.as_tensor(snaps.speed_mps), torch.as_tensor(snaps.valid)
    psi = Psi.of(snaps.psi)
    terms = section_losses(lane, arc, speed, present, psi, road, "measured", "scene", 3)
    every = section_losses(lane, arc, speed, present, psi, road, "measured", "scene")
    for i in range(len(snaps)):
        order = np.argsort(snaps.arc_m[i])
        a = snaps.arc_m[i][order]
        gaps = np.append(np.diff(a), a[0] + ring_loop.length_m - a[-1])
        gen = order >= 3
        in_a = gen | np.roll(gen, -1)  # follower or leader generated
        mu, var = ring_loop.length_m / N_VEHICLES, snaps.psi[i, 2] ** 2
        want = abs(((gaps[in_a] - mu) ** 2).mean() - var) / mu**2
        assert float(terms["L_var"][i]) == pytest.approx(want, rel=1e-9)
        assert float(terms["L_mean"][i]) == pytest.approx((gaps[in_a].mean() / mu - 1) ** 2)
        assert float(every["L_var"][i]) == pytest.approx(abs(gaps.var() - var) / mu**2)


def test_several_completions_per_held_out_scene(ring_section_truth, tmp_path: Path) -> None:
    """eval_completions = 3: generator_metrics.csv holds every held-out snapshot three times
    per method (column completion 0..2), from different draws, and the manifest pools them."""
    sc, gt = ring_section_truth
    sc = with_generator(sc, epochs=2, hidden_size=16, eval_completions=3, hidden_eval=[1, 2])
    man = run_train_section_generator(sc, gt, tmp_path / "gen", progress=False)
    m = pd.read_csv(tmp_path / "gen" / "generator_metrics.csv")
    for _, g in m.groupby("method"):
        counts = g.groupby(["run", "time_s", "k_true"])["completion"].agg(["count", "nunique"])
        assert (counts["count"] == 3).all() and (counts["nunique"] == 3).all()
    gen = m[(m["method"] == "generator") & (m["k_true"] == 2)]
    spread = gen.pivot_table("std_spacing_m", ["run", "time_s"], "completion")
    assert (spread.std(axis=1) > 1e-6).mean() > 0.5  # the completions differ
    assert man["summary"]["generator"]["snapshots"] * 3 == len(m) // 2
    saved = json.loads((tmp_path / "gen" / "generator_manifest.json").read_text())
    assert saved["summary"]["generator_K1"]["snapshots"] * 3 == int(
        ((m["method"] == "generator") & (m["k_true"] == 1)).sum()
    )


def test_a_touched_gap_beyond_d_max_draws_the_last_vehicle(ring_loop: Section) -> None:
    """Two hidden vehicles (slots 0 and 2, not neighbours): with both still to place every
    gap up to 3 d_max has an accepted part (Algorithm 3's, ``bounded_gaps``). The first is
    then put 8 m ahead of the observed vehicle with the longest gap ahead, which leaves a
    touched gap longer than d_max: the last vehicle is accepted only there, at a point that
    leaves both pieces within d_max."""
    n = 8
    snaps = scenes_one_hidden(ring_loop, n, seed=11, d_max=np.inf)
    hidden = np.zeros_like(snaps.observed)
    hidden[:, [0, 2]] = True
    d_max = 1.4 * ring_loop.length_m / N_VEHICLES
    psi_arr = snaps.psi.copy()
    psi_arr[:, PSI_FIELDS.index("spacing_max_m")] = d_max
    snaps = dataclasses.replace(snaps, observed=~hidden, psi=psi_arr, k_true=np.full(n, 2))
    road = Road.of(ring_loop)
    scene = Scene.start(snaps, snaps.k_true, road)
    psi = Psi.of(snaps.psi)
    idx = torch.arange(n)
    gen = torch.Generator().manual_seed(0)

    def bounded(step: int) -> Gaps:
        m = scene.n_obs_slots + step
        obs = scene.observe(step, idx, psi, road, gen)
        arrays = (scene.lane[:, :m], scene.arc[:, :m], scene.present[:, :m])
        out = bounded_gaps(obs.gaps, *arrays, scene.k - step, psi, road, scene.n_obs_slots)
        assert out is not None
        return out

    first = bounded(0)
    short = first.valid & (first.length <= 3 * d_max) & (first.length > 2 * S_MIN_M)
    assert bool(short.any()) and bool((first.room[short] > 0).all())
    # the longest observed gap and the vehicle behind it
    a = np.sort(snaps.arc_m[:, [1, 3, 4]], axis=1)
    ahead = np.concatenate([np.diff(a, axis=1), a[:, :1] + ring_loop.length_m - a[:, -1:]], axis=1)
    j = ahead.argmax(axis=1)
    new_arc = torch.as_tensor(np.mod(a[np.arange(n), j] + 8.0, ring_loop.length_m))
    left = ahead[np.arange(n), j] - 8.0
    scene.place(
        0,
        idx,
        torch.zeros(n, dtype=torch.int64),
        new_arc,
        torch.full((n,), 12.0, dtype=torch.float64),
    )
    g = bounded(1)
    fits = (left > d_max) & (left <= 2 * d_max)
    assert fits.sum() >= n // 2
    target = g.valid & ((g.start - new_arc[:, None]).abs() < 1e-9)
    for i in np.flatnonzero(fits):
        assert bool(((g.room[i] > 0) & g.valid[i] == target[i]).all())
        t = int(torch.nonzero(target[i])[0])
        assert float(g.hi[i, t]) <= d_max + 1e-9  # the piece behind the last vehicle
        assert float(g.length[i, t] - g.lo[i, t]) <= d_max + 1e-9  # the piece ahead
        assert float(g.room[i, t]) > 0


def test_squared_dispersion_error_by_hand(ring_loop: Section) -> None:
    """dispersion_error = "squared": L_var = (X - sigma^2)^2 / (d^2 sigma^2) with X the
    scene's spacing variance around the loop's exact mean (dispersion_center = "scene"),
    sigma and d psi's spacing std and mean spacing (here 6% short, as E2's on the ring)."""
    snaps = scenes_one_hidden(ring_loop, 5, seed=2, d_max=np.inf)
    psi_arr = snaps.psi.copy()
    psi_arr[:, 1] *= 0.94
    psi_arr[:, 2] = [10.0, 20.0, 30.0, 40.0, 50.0]
    psi = Psi.of(psi_arr)
    road = Road.of(ring_loop)
    lane, arc = torch.as_tensor(snaps.lane), torch.as_tensor(snaps.arc_m)
    speed, present = torch.as_tensor(snaps.speed_mps), torch.as_tensor(snaps.valid)
    l_var = section_losses(lane, arc, speed, present, psi, road, "measured", "scene")["L_var"]
    sq = squared_dispersion(l_var, psi)
    signs = []
    for i in range(len(snaps)):
        a = np.sort(snaps.arc_m[i])
        x = np.append(np.diff(a), a[0] + ring_loop.length_m - a[-1]).var()
        d, var = psi_arr[i, 1], psi_arr[i, 2] ** 2
        assert float(sq[i]) == pytest.approx((x - var) ** 2 / (d * d * var), rel=1e-9)
        signs.append(np.sign(x - var))
    assert min(signs) < 0 < max(signs)  # both sides of psi's variance
    assert SectionGeneratorConfig().dispersion_error == "absolute"
