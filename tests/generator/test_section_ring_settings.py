"""The ring generator's settings on the section generator (issue 16): the same keys, the same
meaning, and defaults that keep a section scenario's results as they were.

Snapshots are synthetic (the paper's ring as a closed one-lane section, five vehicles with
spacings >= the minimum, one or two hidden), so no SUMO run is needed.
"""

from __future__ import annotations

import dataclasses
from functools import partial
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from ring_scenes import FAST, N_VEHICLES, generator_scenario, ring_scenes

from macromicro_sumo.data.section import SectionSnapshots, psi_table
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_metrics import completion_metrics
from macromicro_sumo.generator.section_model import (
    SectionGeneratorNet,
    posterior_log_probs,
    section_losses,
)
from macromicro_sumo.generator.section_rollout import Scene
from macromicro_sumo.generator.section_sampler import complete_section
from macromicro_sumo.generator.section_scene import Psi, Road
from macromicro_sumo.generator.section_train import (
    load_section_generator,
    train_section_generator,
)
from macromicro_sumo.road.section import Section, read_section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import (
    SectionGeneratorConfig,
)
from macromicro_sumo.truth.section import load_section_truth

ROOT = Path(__file__).resolve().parents[2]
# A few more epochs at a higher rate than the other generator tests.
scenario = partial(generator_scenario, base=FAST | {"epochs": 3, "lr": 1e-2})


def ring_snapshots(section: Section, n: int, seed: int) -> SectionSnapshots:
    """Five vehicles on the loop, one or two hidden; psi as the ring's without d_max."""
    return ring_scenes(
        section, n, seed, lambda rng: rng.choice(N_VEHICLES, rng.integers(1, 3), replace=False)
    )


def test_defaults_are_the_sections_former_behaviour() -> None:
    """Defaults: no weight averaging, the measured dispersion, speed bounds widened by 10%,
    the network's gap choice (the section generator before these keys existed)."""
    cfg = SectionGeneratorConfig()
    assert cfg.ema_decay == 0.0
    assert cfg.spacing_dispersion == "measured"
    assert cfg.bounds_source == "margin" and cfg.gap_choice == "network"
    assert cfg.dispersion_center == "psi"


def test_spacing_dispersion_paper_and_measured(ring_loop: Section) -> None:
    """L_var by hand on a completed ring scene: measured = |mean (d - psi mean)^2 - psi
    std^2| / psi mean^2, paper = std(d) / psi mean; measured falls back to the paper's
    where psi has no spacing std."""
    snaps = ring_snapshots(ring_loop, 3, seed=4)
    road = Road.of(ring_loop)
    lane, arc = torch.as_tensor(snaps.lane), torch.as_tensor(snaps.arc_m)
    speed, present = torch.as_tensor(snaps.speed_mps), torch.as_tensor(snaps.valid)
    psi_arr = snaps.psi.copy()
    psi_arr[:, 2] = [10.0, 30.0, np.nan]  # a std below, above and unknown
    psi = Psi.of(psi_arr)
    measured = section_losses(lane, arc, speed, present, psi, road, "measured")["L_var"].numpy()
    paper = section_losses(lane, arc, speed, present, psi, road, "paper")["L_var"].numpy()
    for i in range(3):
        a = np.sort(snaps.arc_m[i])
        d = np.append(np.diff(a), a[0] + ring_loop.length_m - a[-1])
        mu, sigma = psi_arr[i, 1], psi_arr[i, 2]
        own = np.sqrt(d.var() + 1e-8) / mu
        assert paper[i] == pytest.approx(own, rel=1e-9)
        want = abs(((d - mu) ** 2).mean() - sigma**2) / mu**2 if np.isfinite(sigma) else own
        assert measured[i] == pytest.approx(want, rel=1e-9)
    assert measured[0] != pytest.approx(measured[1])  # the target counts


def test_dispersion_center_scene_is_exact_on_a_closed_section(ring_loop: Section) -> None:
    """With psi's mean spacing 6% short (E2 density on the ring), the measured dispersion
    around it reads the scene (mean - psi mean)^2 too wide; centred on the scene's own
    mean it is the spacings' variance against psi's. On an open section both are psi's."""
    snaps = ring_snapshots(ring_loop, 3, seed=9)
    road = Road.of(ring_loop)
    lane, arc = torch.as_tensor(snaps.lane), torch.as_tensor(snaps.arc_m)
    speed, present = torch.as_tensor(snaps.speed_mps), torch.as_tensor(snaps.valid)
    psi_arr = snaps.psi.copy()
    psi_arr[:, 1] *= 0.94
    psi = Psi.of(psi_arr)
    at_psi = section_losses(lane, arc, speed, present, psi, road, "measured", "psi")["L_var"]
    at_scene = section_losses(lane, arc, speed, present, psi, road, "measured", "scene")["L_var"]
    for i in range(3):
        a = np.sort(snaps.arc_m[i])
        d = np.append(np.diff(a), a[0] + ring_loop.length_m - a[-1])
        mu, var = psi_arr[i, 1], psi_arr[i, 2] ** 2
        assert d.mean() == pytest.approx(ring_loop.length_m / N_VEHICLES)
        assert float(at_scene[i]) == pytest.approx(abs(d.var() - var) / mu**2, rel=1e-9)
        assert float(at_psi[i]) == pytest.approx(abs(((d - mu) ** 2).mean() - var) / mu**2)
    bremen = read_section(
        ROOT / "sumo_nets" / "highway_bremen" / "highway.net.xml",
        ["145354574", "189597495", "E0", "191842213"],
        False,
    )
    open_road = Road.of(bremen)
    both = [
        section_losses(lane, arc, speed, present, psi, open_road, "measured", c)["L_var"]
        for c in ("psi", "scene")
    ]
    torch.testing.assert_close(both[0], both[1])


def test_weight_averaging_validates_and_keeps_the_averaged_weights(
    ring_loop: Section, tmp_path: Path
) -> None:
    """generator.ema_decay on a section, as on the ring: training itself is unchanged (same
    seed, same train losses); validation, early stopping and the saved file see the moving
    average; a vanishing decay is the same as none."""
    train, val = ring_snapshots(ring_loop, 32, seed=1), ring_snapshots(ring_loop, 16, seed=2)

    def fit(decay: float) -> tuple:
        sc = scenario(ring_loop, ema_decay=decay)
        out = tmp_path / f"ema{decay}"
        out.mkdir()
        net, log = train_section_generator(sc, ring_loop, train, val, progress=False, out=out)
        saved = load_section_generator(out / "generator.pt", sc).state_dict()
        return log, saved, net.state_dict()

    raw_log, raw, _ = fit(0.0)
    avg_log, avg, avg_net = fit(0.9)
    near_log, near, _ = fit(1e-12)
    train_cols = [c for c in raw_log if c.startswith("train_")]
    for col in train_cols:
        np.testing.assert_array_equal(raw_log[col], avg_log[col])
    assert not np.allclose(raw_log["val_loss"], avg_log["val_loss"])
    assert any(not torch.allclose(raw[k], avg[k]) for k in raw)
    for key, val in avg_net.items():  # the returned net is the saved, averaged one
        torch.testing.assert_close(avg[key], val)
    np.testing.assert_allclose(near_log["val_loss"], raw_log["val_loss"], rtol=1e-5)
    for key in raw:
        torch.testing.assert_close(near[key], raw[key], rtol=1e-5, atol=1e-6)


def test_out_of_range_ema_decay_is_a_one_line_error(tmp_path: Path) -> None:
    text = (ROOT / "scenarios" / "ring_paper_section.toml").read_text()
    bad = tmp_path / "bad.toml"
    bad.write_text(
        text.replace("../sumo_nets/", f"{ROOT}/sumo_nets/").replace(
            "ema_decay = 0.995", "ema_decay = 1.5"
        )
    )
    with pytest.raises(UserError) as err:
        load_scenario(bad)
    msg = str(err.value)
    assert "\n" not in msg and str(bad) in msg and "generator.ema_decay" in msg and "0.9999" in msg


def test_ring_paper_section_sets_the_rings_settings() -> None:
    """The experimental ring-as-a-section scenario turns the ring's settings on."""
    sc = load_scenario(ROOT / "scenarios" / "ring_paper_section.toml")
    g = sc.generator
    assert (g.ema_decay, g.spacing_dispersion, g.bounds_source, g.gap_choice) == (
        0.995,
        "measured",
        "extended",
        "posterior",
    )
    assert g.dispersion_center == "scene"
    # item 3: the ring's batch and epochs, mean-matched variance, 4 completions per scene
    assert (g.batch_size, g.epochs, g.dispersion_error, g.eval_completions) == (
        256,
        900,
        "squared",
        4,
    )
    assert (g.spacing_bounds, g.spacing_set) == ("none", "touched")  # touched: K = 1's spread


def one_hidden(section: Section, n: int, seed: int) -> SectionSnapshots:
    """``ring_snapshots`` with exactly one hidden vehicle per scene."""
    s = ring_snapshots(section, n, seed)
    observed = np.ones_like(s.observed)
    observed[np.arange(n), np.random.default_rng(seed).integers(0, N_VEHICLES, n)] = False
    ones = np.ones(n, dtype=int)
    return dataclasses.replace(s, observed=observed, k_true=ones, k_est=ones)


def test_posterior_gap_choice_is_calibrated_on_one_lane(ring_loop: Section) -> None:
    """With one hidden vehicle the posterior's probability of the largest observed gap
    matches how often the hidden vehicle lies in it (i.i.d.-like Dirichlet spacings)."""
    snaps = one_hidden(ring_loop, 400, seed=5)
    road = Road.of(ring_loop)
    scene = Scene.start(snaps, snaps.k_true, road)
    psi = Psi.of(snaps.psi)
    obs = scene.observe(0, torch.arange(len(snaps)), psi, road, torch.Generator().manual_seed(0))
    log_p, known = posterior_log_probs(obs, psi)
    assert bool(known.all())
    p = log_p.exp().numpy()
    np.testing.assert_allclose(np.where(obs.gaps.valid.numpy(), p, 0.0).sum(axis=1), 1.0)
    length = np.where(obs.gaps.valid.numpy(), obs.gaps.length.numpy(), -1.0)
    largest = length.argmax(axis=1)
    start = obs.gaps.start.numpy()[np.arange(len(snaps)), largest]
    hidden_arc = snaps.arc_m[~snaps.observed]
    inside = np.mod(hidden_arc - start, ring_loop.length_m) < length[np.arange(len(snaps)), largest]
    assert abs(p[np.arange(len(snaps)), largest].mean() - inside.mean()) < 0.03
    assert p[np.arange(len(snaps)), largest].mean() < 0.9999  # a draw, not an argmax


def test_posterior_gap_choice_does_not_depend_on_the_network(ring_loop: Section) -> None:
    """Two differently initialised networks with the same seed put the hidden vehicle into
    the same gap (the posterior chooses; the network only says where in it and how fast),
    and every completion is feasible."""
    snaps = one_hidden(ring_loop, 40, seed=6)
    sc = scenario(ring_loop, gap_choice="posterior")
    gaps = []
    for init in (0, 1):
        torch.manual_seed(init)
        net = SectionGeneratorNet(16, "posterior")
        comp = complete_section(net, ring_loop, snaps, snaps.k_true, 20, seed=3)
        assert completion_metrics(ring_loop, snaps, comp, snaps.k_true)["feasible"].all()
        arc = comp.arc_m[comp.generated]
        behind = np.array(  # the observed vehicle the new one follows
            [
                np.mod(arc[i] - snaps.arc_m[i][snaps.observed[i]], ring_loop.length_m).argmin()
                for i in range(40)
            ]
        )
        gaps.append(behind)
    np.testing.assert_array_equal(gaps[0], gaps[1])
    assert sc.generator.gap_choice == "posterior"


def test_posterior_gap_choice_refuses_other_sections(ring_loop: Section) -> None:
    """Open or multi-lane sections and the paper's dispersion: one-line errors naming the
    field and what is accepted; a checkpoint is only valid for its gap choice."""
    bremen = read_section(
        ROOT / "sumo_nets" / "highway_bremen" / "highway.net.xml",
        ["145354574", "189597495", "E0", "191842213"],
        False,
    )
    snaps = ring_snapshots(ring_loop, 4, seed=7)
    for section, extra, accepted in (
        (bremen, {}, "closed one-lane section"),
        (ring_loop, {"spacing_dispersion": "paper"}, 'accepted "measured"'),
    ):
        sc = scenario(section, gap_choice="posterior", **extra)
        with pytest.raises(UserError) as err:
            train_section_generator(sc, section, snaps, snaps, progress=False)
        msg = str(err.value)
        assert "\n" not in msg and "generator.gap_choice" in msg and accepted in msg


def test_posterior_checkpoint_round_trip(ring_loop: Section, tmp_path: Path) -> None:
    train = ring_snapshots(ring_loop, 16, seed=8)
    sc = scenario(ring_loop, gap_choice="posterior", epochs=2)
    net, log = train_section_generator(sc, ring_loop, train, train, progress=False, out=tmp_path)
    back = load_section_generator(tmp_path / "generator.pt", sc)
    assert back.gap_choice == "posterior" and np.isfinite(log["val_loss"]).all()
    other = scenario(ring_loop, epochs=2)
    with pytest.raises(UserError, match="generator.gap_choice"):
        load_section_generator(tmp_path / "generator.pt", other)


def test_bounds_source_margin_interval_extended(ring_section_truth) -> None:
    """psi's speed bounds: margin = the passages' extremes x 0.9 / x 1.1 (the section's
    former bounds), interval = the extremes, extended = widened by range / (n - 1) with n
    the interval's passages counted here from detector_passages.csv; the extended bounds
    hold more of the recorded speeds than the interval's."""
    sc, gt = ring_section_truth
    truth = load_section_truth(gt, sc)

    def table(source: str) -> pd.DataFrame:
        cfg = dataclasses.replace(sc.generator, bounds_source=source)
        return psi_table(truth, dataclasses.replace(sc, generator=cfg)).reset_index(drop=True)

    margin, interval, extended = table("margin"), table("interval"), table("extended")
    assert len(interval) == 4  # two runs x two 60 s intervals
    np.testing.assert_allclose(margin["speed_min_mps"], 0.9 * interval["speed_min_mps"])
    np.testing.assert_allclose(margin["speed_max_mps"], 1.1 * interval["speed_max_mps"])
    passages = pd.read_csv(gt / "detector_passages.csv")
    inside_int = inside_ext = 0
    traj = truth.trajectories
    for i, row in interval.iterrows():
        at = (passages["run"] == row["run"]) & passages["time_s"].between(
            row["begin_s"], row["end_s"], inclusive="left"
        )
        speeds = passages.loc[at, "speed_mps"]
        assert speeds.min() == pytest.approx(row["speed_min_mps"])
        widen = (speeds.max() - speeds.min()) / (at.sum() - 1)
        assert extended.loc[i, "speed_min_mps"] == pytest.approx(row["speed_min_mps"] - widen)
        assert extended.loc[i, "speed_max_mps"] == pytest.approx(row["speed_max_mps"] + widen)
        w = traj[
            (traj["run"] == row["run"])
            & traj["time_s"].between(row["begin_s"], row["end_s"], inclusive="left")
        ]
        v = w["speed_mps"]
        inside_int += int(v.between(row["speed_min_mps"], row["speed_max_mps"]).sum())
        lo, hi = extended.loc[i, ["speed_min_mps", "speed_max_mps"]]
        inside_ext += int(v.between(lo, hi).sum())
    assert inside_ext > inside_int


def test_extended_bounds_need_the_passages(ring_section_truth, tmp_path: Path) -> None:
    sc, gt = ring_section_truth
    truth = load_section_truth(gt, sc)
    cfg = dataclasses.replace(sc.generator, bounds_source="extended")
    bare = dataclasses.replace(truth, folder=tmp_path)  # a folder without passages
    with pytest.raises(UserError) as err:
        psi_table(bare, dataclasses.replace(sc, generator=cfg))
    msg = str(err.value)
    assert "\n" not in msg and "detector_passages.csv" in msg and "bounds_source" in msg
