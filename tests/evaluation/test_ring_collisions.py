"""No collisions the ground truth does not have, on a dense ring (ring_sugiyama's regime).

On 230 m with 22 vehicles every method, the oracle ``idm_true`` included, collided in a
third to a half of the evaluation's episodes: the generator put vehicles on top of each
other and slow ones just ahead of fast ones, and observed vehicles replayed their recorded
speeds into generated leaders placed closer or slower than the true ones. These tests run
real SUMO on that ring.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from conftest import dump_toml

from macromicro_sumo.data.ring import load_ground_truth
from macromicro_sumo.env.ring import EpisodeBank, RingCore, build_bank, generator_completion
from macromicro_sumo.env.rollout import rollout
from macromicro_sumo.errors import UserError
from macromicro_sumo.evaluation.ring import idm_action, true_idm_params
from macromicro_sumo.generator.ring_model import GeneratorNet
from macromicro_sumo.scenario.load import load_scenario
from macromicro_sumo.truth.ring import simulate

ROOT = Path(__file__).resolve().parents[2]
SUGIYAMA = ROOT / "scenarios" / "ring_sugiyama.toml"
H = 10


def sugiyama(folder: Path, runs: int, duration_s: float) -> Path:
    """ring_sugiyama.toml with ``runs`` runs of ``duration_s`` (absolute network paths)."""
    table = tomllib.loads(SUGIYAMA.read_text())
    for key in ("net_file", "routes_file"):
        table["network"][key] = str((SUGIYAMA.parent / table["network"][key]).resolve())
    table["simulation"].update(n_runs=runs, duration_s=duration_s)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "scenario.toml"
    path.write_text(dump_toml(table))
    return path


@pytest.fixture(scope="module")
def dense(tmp_path_factory):
    """Two 180 s runs of ring_sugiyama's ground truth."""
    folder = tmp_path_factory.mktemp("sugiyama")
    sc = load_scenario(sugiyama(folder, 2, 180.0))
    return sc, load_ground_truth(simulate(sc, folder / "gt", progress=False), sc)


def one_episode_bank(sc, arc, speed, hidden, replay) -> EpisodeBank:
    n = len(arc)
    replay = np.tile(np.asarray(replay, float), (H + 1, 1))[None]
    return EpisodeBank(
        arc0_m=np.array([arc], float),
        speed0_mps=np.array([speed], float),
        hidden=np.array([hidden], bool),
        psi=np.array([[3.4, 10.45, 6.0, 20.0, 0.0, 10.0]]),
        limits_mps=np.full((1, sc.network.n_edges), 9.0),
        replay_speed_mps=replay,
        gt_accel_mps2=np.zeros((1, H, n)),
        true_arc0_m=np.array([arc], float),
        run=np.zeros(1, dtype=np.int64),
        time_s=np.zeros(1),
    )


def test_a_replayed_follower_brakes_behind_a_stopped_generated_leader():
    """An observed vehicle recorded at a steady 6 m/s, 8 m behind a generated vehicle that
    stands still: replayed as recorded it runs into it in the second step; it leaves its
    record, stops short of it and is counted."""
    sc = load_scenario(SUGIYAMA)
    bank = one_episode_bank(
        sc, [0.0, 8.0, 120.0], [6.0, 0.0, 6.0], [False, True, False], [6.0, 0.0, 6.0]
    )
    core = RingCore(sc, bank, seed=0)
    try:
        ro = rollout(core, lambda c, o, r: np.zeros(1), H, 0)
        assert ro.collisions == 0 and ro.errors == 0
        assert core.replay_overrides > 0 and core.overridden_episodes == {0}
        gap = ro.spacing_m[0, :, 0] - sc.fleet.length_m
        assert gap.min() >= 0.5 * sc.fleet.min_gap_m[0] - 1e-6
        assert ro.speed_mps[0, -1, 0] == pytest.approx(0.0, abs=1e-6)
        # The free vehicle ahead replays its record untouched.
        np.testing.assert_allclose(ro.speed_mps[0, :, 2], 6.0, atol=1e-6)
    finally:
        core.close()


def test_the_recording_replays_unchanged_on_a_dense_ring(dense):
    """Every vehicle observed (K = 0): the recorded fleet replays exactly, never braked."""
    sc, gt = dense
    bank = build_bank(sc, gt, gt.runs, lambda s: (s.arc_m, s.speed_mps), 0, 1, horizon=H)
    core = RingCore(sc, bank, seed=0)
    try:
        ro = rollout(core, lambda c, o, r: np.zeros(0), H, 0)
    finally:
        core.close()
    assert ro.collisions == 0 and core.replay_overrides == 0
    np.testing.assert_allclose(ro.speed_mps, bank.replay_speed_mps[:, 1:], atol=1e-6)


@pytest.mark.parametrize("k", [1, 4])
def test_generated_scenes_of_a_dense_ring_drive_without_collisions(dense, k):
    """The evaluation's idm_true method (each hidden vehicle's true IDM parameters) on
    completions of an untrained generator, 4 draws per scene: 0 collisions, as in the
    ground truth."""
    sc, gt = dense
    net = GeneratorNet(sc.generator.hidden_size, sc.generator.gap_choice).eval()
    banks = [
        build_bank(sc, gt, gt.runs, generator_completion(net, sc, seed), k, 7, horizon=H)
        for seed in range(4)
    ]
    bank = EpisodeBank.concat(banks)
    core = RingCore(sc, bank, seed=0)
    try:
        act = idm_action(true_idm_params(sc, gt, bank), sc.fleet.length_m)
        ro = rollout(core, act, H, 0)
    finally:
        core.close()
    assert len(bank) >= 200
    assert ro.collisions == 0 and ro.errors == 0
    assert np.nanmin(ro.spacing_m) > sc.fleet.length_m


@pytest.mark.parametrize("safety", ["sumo", "none"])
def test_the_safety_layer_stops_a_hidden_vehicle_behind_a_braking_observed_leader(safety):
    """A hidden vehicle at 6 m/s whose action holds its speed, 12 m behind an observed
    vehicle that brakes from 6 m/s to a stop at 3 m/s^2 as recorded: with the safety layer
    its commands are capped (counted, per step in ``step_capped``) and it stops behind its
    leader, keeping the bumper gap; without it, it runs into the leader."""
    sc = load_scenario(SUGIYAMA)
    lead = np.maximum(6.0 - 3.0 * sc.simulation.step_length_s * np.arange(H + 1), 0.0)
    bank = one_episode_bank(
        sc, [0.0, 12.0, 120.0], [6.0, 6.0, 6.0], [True, False, False], [6.0] * 3
    )
    bank.replay_speed_mps[0, :, 1] = lead
    core = RingCore(sc, bank, seed=0, safety=safety)
    try:
        ro = rollout(core, lambda c, o, r: np.zeros(1), H, 0)
    finally:
        core.close()
    if safety == "none":  # the collision ends the episode
        assert ro.collisions == 1 and core.safety_capped == 0 and core.hidden_steps < H
        return
    assert ro.collisions == 0 and ro.errors == 0 and core.hidden_steps == H
    assert 0 < core.safety_capped <= H and core.capped_episodes == {0}
    gap = ro.spacing_m[0, :, 0] - sc.fleet.length_m
    assert gap.min() >= 0.5 * sc.fleet.min_gap_m[0] - 1e-6
    assert ro.speed_mps[0, -1, 0] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_allclose(ro.speed_mps[0, :, 1], lead[1:], atol=1e-6)  # on record


def test_the_safety_layer_leaves_the_recorded_drivers_alone_on_a_dense_ring(dense):
    """True scenes with 4 hidden vehicles applying their recorded actions under the safety
    layer: it never acts, and the recording replays exactly (its leader assumption, |a_min|,
    is no stricter than the fleet's own driving)."""
    sc, gt = dense
    bank = build_bank(sc, gt, gt.runs, lambda s: (s.arc_m, s.speed_mps), 4, 1, horizon=H)
    core = RingCore(sc, bank, seed=0, safety="sumo")
    try:
        ro = rollout(core, lambda c, o, r: c.bank.gt_accel_mps2[c.episode, c.t][c.hidden], H, 0)
    finally:
        core.close()
    assert len(bank) >= 60 and core.hidden_steps == 4 * H * len(bank)
    assert core.safety_capped == 0 and core.replay_overrides == 0 and ro.collisions == 0
    np.testing.assert_allclose(ro.speed_mps, bank.replay_speed_mps[:, 1:], atol=1e-6)


def test_an_unknown_safety_layer_is_refused():
    sc = load_scenario(SUGIYAMA)
    bank = one_episode_bank(sc, [0.0, 50.0], [5.0, 5.0], [True, False], [5.0, 5.0])
    with pytest.raises(UserError, match="safety = 'gipps'"):
        RingCore(sc, bank, seed=0, safety="gipps")
