"""What keeps the ring-as-a-section generator's spacing spread across training seeds
(docs/design.md, "Ring as a section: status", item 3): the pooled dispersion term
(``generator.dispersion_pool``), two hidden layers (``generator.hidden_layers``), the moving
average's warm-up (``generator.ema_warmup``) and ``generator.min_epochs``. Synthetic closed
one-lane scenes (the paper's ring), no SUMO run.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import torch
from ring_scenes import generator_scenario as scenario
from ring_scenes import ring_scenes

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.errors import UserError
from macromicro_sumo.generator.section_model import SectionGeneratorNet, section_losses
from macromicro_sumo.generator.section_rollout import Scene
from macromicro_sumo.generator.section_scene import Psi, Road
from macromicro_sumo.generator.section_spread import pooled_dispersion, spacing_variance
from macromicro_sumo.generator.section_train import (
    load_section_generator,
    train_section_generator,
)
from macromicro_sumo.generator.training import FitSettings, ema_fn, fit
from macromicro_sumo.road.section import Section
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.scenario.section import (
    SectionGeneratorConfig,
)

ROOT = Path(__file__).resolve().parents[2]


def completed(section: Section, n: int, seed: int) -> tuple[Scene, Psi, Road, SectionSnapshots]:
    """``n`` whole recorded scenes as completed ones: K (1-4) of each in the generated slots."""
    rng = np.random.default_rng(seed + 100)
    snaps = ring_scenes(section, n, seed, lambda r: r.permutation(5)[: r.integers(1, 5)])
    road = Road.of(section)
    scene = Scene.start(snaps, snaps.k_true, road)
    hidden = ~snaps.observed
    for step in range(int(snaps.k_true.max())):
        idx = np.flatnonzero(snaps.k_true > step)
        slot = np.array([np.flatnonzero(hidden[i])[step] for i in idx])
        lane = torch.zeros(len(idx), dtype=torch.int64)
        arc = torch.as_tensor(snaps.arc_m[idx, slot])
        speed = torch.as_tensor(snaps.speed_mps[idx, slot] + rng.normal(0, 0.1, len(idx)))
        scene.place(step, torch.as_tensor(idx), lane, arc, speed)
    return scene, Psi.of(snaps.psi), road, snaps


@pytest.mark.parametrize("touched", [False, True])
def test_spacing_variance_is_the_x_of_the_measured_l_var(ring_loop: Section, touched: bool) -> None:
    """|X - sigma^2| / d^2 is the measured L_var of the same scenes, with either A."""
    scene, psi, road, _ = completed(ring_loop, 40, 1)
    first = scene.n_obs_slots if touched else None
    terms = section_losses(
        scene.lane, scene.arc, scene.speed, scene.present, psi, road, "measured", "scene", first
    )
    x = spacing_variance(scene.lane, scene.arc, scene.present, psi, road, "scene", first)
    torch.testing.assert_close((x - psi.d_std**2).abs() / psi.d_mean**2, terms["L_var"])


def test_pooled_shares_average_to_each_groups_squared_bias(ring_loop: Section) -> None:
    """With one group per hidden count (``bins=1``) the shares average to r_k^2 sigma^2 / d^2
    (r_k the group's summed X - sigma^2 over its summed sigma^2; here sigma and d are one
    per scene); scenes without a spacing std or with nothing to generate get 0; exact sums
    give 0."""
    scene, psi, road, snaps = completed(ring_loop, 60, 2)
    k = snaps.k_true
    x = spacing_variance(scene.lane, scene.arc, scene.present, psi, road, "scene")
    k_t = torch.as_tensor(k)
    share = pooled_dispersion(x, psi, k_t, bins=1)
    s2 = psi.d_std**2
    for kv in np.unique(k):
        g = k_t == int(kv)
        r = float((x[g] - s2[g]).sum() / s2[g].sum())
        want = r * float(((x[g] - s2[g]) / psi.d_mean[g] ** 2).mean())
        assert float(share[g].mean()) == pytest.approx(want, rel=1e-9)
        assert want > 0  # a square, not a cancelling sum
    no_std = snaps.psi.copy()
    no_std[:, 2] = math.nan
    assert (pooled_dispersion(x, Psi.of(no_std), k_t) == 0).all()
    assert (pooled_dispersion(x, psi, torch.zeros_like(k_t)) == 0).all()
    exact = s2.clone()
    assert pooled_dispersion(exact, psi, k_t).abs().max() < 1e-15


def _psi_with_std(std: torch.Tensor) -> Psi:
    n = len(std)
    return Psi.of(
        np.column_stack([np.full(n, 12.0), np.full(n, 125.0), std.numpy()] + [np.ones(n)] * 3)
    )


def test_pooled_groups_by_psis_spread_score_a_variance_that_ignores_it() -> None:
    """Scenes whose variance X is the same whatever psi's sigma, with the right sum: one group
    per hidden count sees no error, groups of sigma do (the low-sigma scenes too wide, the
    high ones too narrow); X = sigma^2 scene by scene is exact either way."""
    std = torch.linspace(15.0, 60.0, 30, dtype=torch.float64)
    psi = _psi_with_std(std)
    k = torch.full((30,), 4)
    flat = torch.full((30,), float((std**2).mean()), dtype=torch.float64)
    assert pooled_dispersion(flat, psi, k, bins=1).abs().max() < 1e-15
    shares = pooled_dispersion(flat, psi, k)
    assert float(shares.mean()) > 0.01
    assert pooled_dispersion(std**2, psi, k).abs().max() < 1e-15


def test_pooled_gradient_makes_the_variance_follow_psis_spread() -> None:
    """Gradient steps on the grouped term move X = a + b sigma^2 from flat (b = 0) to follow
    sigma^2 (b near 1): what a held-out set with wider spread than the training runs needs."""
    std = torch.linspace(15.0, 60.0, 60, dtype=torch.float64)
    psi, k = _psi_with_std(std), torch.full((60,), 2)
    s2 = std**2
    a = torch.tensor(float(s2.mean()), dtype=torch.float64, requires_grad=True)
    b = torch.tensor(0.0, dtype=torch.float64, requires_grad=True)
    opt = torch.optim.Adam([a, b], lr=0.1)
    for _ in range(120):
        x = a + b * (s2 - s2.mean())
        loss = pooled_dispersion(x, psi, k).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert b.item() > 0.8, b.item()


def test_pooled_gradient_moves_the_groups_mean_variance_to_psis() -> None:
    """Gradient steps on the pooled term bring each group's mean X to its mean sigma^2 while
    the scenes' own scatter stays (the per-scene terms alone trade bias for scatter)."""
    n = 12
    psi = Psi.of(
        np.column_stack([np.full(n, 12.0), np.full(n, 125.0), np.full(n, 30.0)] + [np.ones(n)] * 3)
    )
    k = torch.as_tensor([1] * 6 + [3] * 6)
    scale = torch.tensor([0.5, 1.5], dtype=torch.float64, requires_grad=True)
    base = torch.linspace(0.5, 1.5, n, dtype=torch.float64) * 900.0
    opt = torch.optim.SGD([scale], lr=15.0)
    for _ in range(80):
        x = base * torch.where(k == 1, scale[0], scale[1])
        loss = pooled_dispersion(x, psi, k).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    x = (base * torch.where(k == 1, scale[0], scale[1])).detach()
    for kv in (1, 3):
        assert float(x[k == kv].mean()) == pytest.approx(900.0, rel=1e-3)
    assert float(x.std()) > 100.0


def test_ema_warmup_lets_go_of_the_initial_weights() -> None:
    """After n updates towards 1 from 0 the plain average holds decay^n of the start; with
    the warm-up the decay is min(decay, (1 + i) / (10 + i)) at update i, so far less."""
    plain, warm = ema_fn(0.995, False), ema_fn(0.995, True)
    a = b = torch.zeros(1)
    for i in range(200):
        a, b = plain(a, torch.ones(1), i), warm(b, torch.ones(1), i)
    start_share = math.prod(min(0.995, (1 + i) / (10 + i)) for i in range(200))
    assert 1 - float(a) == pytest.approx(0.995**200, rel=1e-4)
    assert 1 - float(b) == pytest.approx(start_share, rel=1e-4)
    assert start_share < 0.01 < 0.995**200
    # once (1 + i) / (10 + i) passes the decay, the two are the same update
    assert float(warm(torch.zeros(1), torch.ones(1), 10_000)) == pytest.approx(0.005)


def test_min_epochs_holds_off_early_stopping() -> None:
    """A validation loss that never improves ends training after ``patience`` epochs, or at
    ``min_epochs`` where that is later; never past ``epochs``."""
    net = torch.nn.Linear(1, 1)

    def batches(epoch: int):
        return [(lambda m: ((m(torch.ones(1, 1)) ** 2).sum(), {"loss": 0.0}), 1)]

    def run(min_epochs: int, epochs: int = 50) -> pd.DataFrame:
        s = FitSettings(epochs, 3, 1e-3, 0.9, "test", True, min_epochs)
        return fit(net, s, batches, lambda m: {"loss": 1.0}, progress=False)

    assert len(run(0)) == 4 and len(run(20)) == 20 and len(run(80)) == 50


def test_two_hidden_layers_train_save_and_are_remembered(
    ring_loop: Section, tmp_path: Path
) -> None:
    """Default one hidden layer (the network as before: no deep weights); two train with the
    pooled term and the warm-up, load back, and a checkpoint of one
    depth is refused for a scenario of the other, naming the key."""
    assert SectionGeneratorConfig().hidden_layers == 1
    assert not any(name.startswith("deep") for name in SectionGeneratorNet(16).state_dict())
    snaps = ring_scenes(ring_loop, 24, 5, lambda r: r.permutation(5)[: r.integers(0, 5)])
    sc = scenario(
        ring_loop,
        gap_choice="posterior",
        hidden_layers=2,
        dispersion_pool=1.0,
        ema_decay=0.99,
        ema_warmup=True,
    )
    net, log = train_section_generator(sc, ring_loop, snaps, snaps, progress=False, out=tmp_path)
    assert len(net.deep) == 2 and np.isfinite(log["val_loss"]).all()
    back = load_section_generator(tmp_path / "generator.pt", sc)
    for a, b in zip(back.parameters(), net.parameters(), strict=True):
        torch.testing.assert_close(a, b)
    with pytest.raises(UserError, match="generator.hidden_layers"):
        load_section_generator(
            tmp_path / "generator.pt", scenario(ring_loop, gap_choice="posterior")
        )


def test_ring_paper_section_uses_them() -> None:
    g = load_scenario(ROOT / "scenarios" / "ring_paper_section.toml").generator
    assert (g.dispersion_pool, g.hidden_layers, g.ema_warmup) == (1.0, 2, True)
    assert g.min_epochs > g.patience
