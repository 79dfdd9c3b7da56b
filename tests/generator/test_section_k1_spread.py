"""``generator.dispersion_feature``: the section generator's position head sees how much of
psi's spacing variance the rest of the scene leaves to its gap.

The cause it fixes (docs/design.md, "Ring as a section: status", item 3): every input of
the position head described the chosen gap and psi, none the spacings elsewhere, so the
last vehicle of a K = 1 scene (observed spacings around it) and of a K = 4 scene (earlier
generated ones) looked alike and went equally far from their gap's middle; K = 1's spread
came out 3.9% short. Synthetic closed one-lane scenes (the paper's ring), no SUMO run.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
from ring_scenes import N_VEHICLES, S_MIN_M, loop_snapshots
from ring_scenes import generator_scenario as scenario

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_model import N_GAP_FEATURES, SectionGeneratorNet, gap_input
from macromicro_sumo.generator.section_rollout import Scene
from macromicro_sumo.generator.section_scene import Psi, Road
from macromicro_sumo.generator.section_train import (
    load_section_generator,
    train_section_generator,
)
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import (
    SectionGeneratorConfig,
)

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def ring(ring_loop: Section) -> Section:
    return ring_loop


def scenes(section: Section, spacings_m: np.ndarray, sigma_m: np.ndarray) -> SectionSnapshots:
    """Five vehicles per scene with the given spacings (S, 5) from arc 0, the second one
    hidden (it splits the gap from the first to the third), all at 12 m/s; psi's mean
    spacing L / 5, its spacing std ``sigma_m`` (NaN: none)."""
    n = len(spacings_m)
    arc = np.concatenate([np.zeros((n, 1)), np.cumsum(spacings_m[:, :-1], axis=1)], axis=1)
    observed = np.ones((n, N_VEHICLES), bool)
    observed[:, 1] = False
    psi = np.column_stack(
        [
            np.full(n, 12.0),
            np.full(n, section.length_m / N_VEHICLES),
            sigma_m,
            np.full(n, 10.0),
            np.full(n, 14.0),
            np.full(n, S_MIN_M),
        ]
    )
    return loop_snapshots(arc, np.full((n, N_VEHICLES), 12.0), observed, psi)


def two_scenes(section: Section) -> SectionSnapshots:
    """The same hidden vehicle's gap (200 m from the first vehicle to the third), the same
    psi; the three observed spacings elsewhere nearly equal in one, spread in the other."""
    rest = section.length_m - 200.0
    even = [100.0, 100.0, rest / 3, rest / 3, rest / 3]
    spread = [100.0, 100.0, rest / 3 - 60.0, rest / 3, rest / 3 + 60.0]
    return scenes(section, np.array([even, spread]), np.array([40.0, 40.0]))


def observe(section: Section, snaps: SectionSnapshots):
    road = Road.of(section)
    scene = Scene.start(snaps, snaps.k_true, road)
    psi = Psi.of(snaps.psi)
    gen = torch.Generator().manual_seed(0)
    return scene.observe(0, torch.arange(len(snaps)), psi, road, gen), psi, road


def test_dispersion_budget_by_hand(ring: Section) -> None:
    """Each gap's budget is 1 - S / (5 sigma^2), S the squared deviations of the spacings
    from L / 5 with that gap halved; clamped to [-5, 1]; 0 where psi has no spacing std."""
    rng = np.random.default_rng(3)
    sp = 60.0 + rng.dirichlet(np.full(N_VEHICLES, 7.0), 6) * (ring.length_m - 300.0)
    sigma = np.array([20.0, 30.0, 40.0, 5.0, np.nan, 35.0])
    obs, _, _ = observe(ring, scenes(ring, sp, sigma))
    g = obs.gaps
    center = ring.length_m / N_VEHICLES
    for i in range(len(sp)):
        observed = np.delete(sp[i], 1)
        observed[0] = sp[i, 0] + sp[i, 1]  # the hidden vehicle's two spacings merged
        for j in np.flatnonzero(g.valid[i].numpy()):
            length = float(g.length[i, j])
            k = int(np.argmin(np.abs(observed - length)))
            halved = np.concatenate([np.delete(observed, k), [length / 2, length / 2]])
            s = ((halved - center) ** 2).sum()
            want = np.clip(1.0 - s / (N_VEHICLES * sigma[i] ** 2), -5.0, 1.0)
            want = 0.0 if np.isnan(sigma[i]) else want
            assert float(obs.budget[i, j]) == pytest.approx(want, rel=1e-9, abs=1e-12)
        assert (obs.budget[i][~g.valid[i]] == 0).all()
    assert float(obs.budget[3].min()) == -5.0  # a tiny sigma: clamped


def test_the_position_head_sees_the_rest_of_the_scene(ring: Section) -> None:
    """The cause of the K = 1 deficit: without the feature the hidden vehicle's gap gets the
    same position output whatever the spacings elsewhere (so it cannot go further from the
    middle where they are even); with it the output differs, and the budgets say the even
    scene lacks more spread than the spread one."""
    snaps = two_scenes(ring)
    obs, psi, road = observe(ring, snaps)
    length = obs.gaps.length.numpy()
    gap = [int(np.flatnonzero(np.isclose(length[i], 200.0))[0]) for i in range(2)]
    assert obs.budget[0, gap[0]] > obs.budget[1, gap[1]] + 0.1
    for feature in (False, True):
        torch.manual_seed(1)
        net = SectionGeneratorNet(16, "posterior", dispersion_feature=feature)
        with torch.no_grad():
            out = net(gap_input(net, obs), obs.glob)
        # the position head (mean and log-std of the place in the gap)
        head = [out[i, gap[i], 1:3] for i in range(2)]
        assert (not torch.allclose(head[0], head[1], atol=1e-6)) == feature


def test_off_by_default_and_checkpoints_remember_it(ring: Section, tmp_path: Path) -> None:
    """Default off (the network as before: N_GAP_FEATURES inputs per gap); on, one more; a
    checkpoint trained with it is refused for a scenario without it, naming the key."""
    assert SectionGeneratorConfig().dispersion_feature is False
    assert SectionGeneratorNet(16).gap_in.in_features == N_GAP_FEATURES
    rng = np.random.default_rng(4)
    sp = 60.0 + rng.dirichlet(np.full(N_VEHICLES, 7.0), 16) * (ring.length_m - 300.0)
    train = scenes(ring, sp, sp.std(axis=1))
    train = dataclasses.replace(train, speed_mps=rng.uniform(11.0, 13.0, train.speed_mps.shape))
    sc = scenario(ring, gap_choice="posterior", dispersion_feature=True)
    net, log = train_section_generator(sc, ring, train, train, progress=False, out=tmp_path)
    assert net.gap_in.in_features == N_GAP_FEATURES + 1 and np.isfinite(log["val_loss"]).all()
    back = load_section_generator(tmp_path / "generator.pt", sc)
    for a, b in zip(back.parameters(), net.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    with pytest.raises(UserError, match="generator.dispersion_feature"):
        load_section_generator(tmp_path / "generator.pt", scenario(ring, gap_choice="posterior"))


def test_ring_paper_section_reads_the_budget_beside_the_rings_a() -> None:
    g = load_scenario(ROOT / "scenarios" / "ring_paper_section.toml").generator
    assert g.dispersion_feature and g.spacing_set == "touched"
