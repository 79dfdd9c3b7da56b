"""Joint refinement's consistency term L_rec (generator/reconstruction.py), without SUMO."""

from __future__ import annotations

import numpy as np
import torch

from macromicro_sumo.data.section import PSI_FIELDS, SectionSnapshots
from macromicro_sumo.generator.reconstruction import reconstruction_loss
from macromicro_sumo.generator.section_rollout import Scene
from macromicro_sumo.generator.section_scene import Road

MEAN_SPACING_M, V_MIN, V_MAX = 125.0, 10.0, 14.0  # v_scale = 2 m/s


def _snaps(arc: np.ndarray, speed: np.ndarray, lane: np.ndarray, hidden: np.ndarray):
    """Scenes (B, N) with the given hidden (target) vehicles; psi with the constants above."""
    b, n = arc.shape
    psi = np.zeros((b, len(PSI_FIELDS)))
    psi[:, PSI_FIELDS.index("mean_speed_mps")] = 12.0
    psi[:, PSI_FIELDS.index("mean_spacing_m")] = MEAN_SPACING_M
    psi[:, PSI_FIELDS.index("std_spacing_m")] = np.nan
    psi[:, PSI_FIELDS.index("speed_min_mps")] = V_MIN
    psi[:, PSI_FIELDS.index("speed_max_mps")] = V_MAX
    psi[:, PSI_FIELDS.index("spacing_min_m")] = 7.0
    psi[:, PSI_FIELDS.index("spacing_max_m")] = np.inf
    psi[:, PSI_FIELDS.index("spacing_low_m")] = 7.0
    valid = np.ones((b, n), dtype=bool)
    return SectionSnapshots(
        run=np.zeros(b, dtype=int),
        time_s=np.zeros(b),
        lane=lane.astype(np.int64),
        arc_m=arc.astype(float),
        speed_mps=speed.astype(float),
        length_m=np.full((b, n), 5.0),
        valid=valid,
        observed=valid & ~hidden,
        psi=psi,
        k_true=hidden.sum(axis=1),
        k_est=hidden.sum(axis=1),
    )


def _generated(snaps: SectionSnapshots, road: Road, arc, speed, lane) -> Scene:
    """The scene with its generated slots set to (arc, speed, lane) (B, K), all present."""
    k = np.asarray(arc).shape[1]
    scene = Scene.start(snaps, np.full(len(snaps), k), road)
    for j in range(k):
        idx = torch.arange(len(snaps))
        scene.place(
            j,
            idx,
            torch.as_tensor(np.asarray(lane)[:, j], dtype=torch.int64),
            torch.as_tensor(np.asarray(arc, dtype=float)[:, j]),
            torch.as_tensor(np.asarray(speed, dtype=float)[:, j]),
        )
    return scene


def test_l_rec_matches_unlabelled_vehicles_and_measures_in_spacing_and_speed_units(ring_loop):
    road = Road.of(ring_loop)
    arc = np.array([[10.0, 200.0, 350.0, 500.0]])
    speed = np.array([[11.0, 12.0, 13.0, 12.5]])
    lane = np.zeros((1, 4))
    hidden = np.array([[False, True, True, True]])
    snaps = _snaps(arc, speed, lane, hidden)
    # The three targets in another order: a perfect match once matched.
    same = _generated(snaps, road, [[500.0, 200.0, 350.0]], [[12.5, 12.0, 13.0]], [[0, 0, 0]])
    assert float(reconstruction_loss(same, snaps, road)[0]) < 1e-12
    # One of them 12.5 m ahead and 1 m/s faster: 0.1^2 + 0.5^2 over 3 pairs.
    off = _generated(snaps, road, [[512.5, 200.0, 350.0]], [[13.5, 12.0, 13.0]], [[0, 0, 0]])
    want = ((12.5 / MEAN_SPACING_M) ** 2 + (1.0 / 2.0) ** 2) / 3
    np.testing.assert_allclose(float(reconstruction_loss(off, snaps, road)[0]), want, rtol=1e-9)


def test_l_rec_takes_the_shorter_way_round_a_loop_and_has_a_gradient(ring_loop):
    road = Road.of(ring_loop)
    snaps = _snaps(np.array([[300.0, 2.0]]), np.array([[12.0, 12.0]]), np.zeros((1, 2)),
                   np.array([[False, True]]))  # fmt: skip
    scene = _generated(snaps, road, [[road.length_m - 3.0]], [[12.0]], [[0]])
    scene.arc = scene.arc.clone().requires_grad_(True)
    loss = reconstruction_loss(scene, snaps, road)
    np.testing.assert_allclose(float(loss[0].detach()), (5.0 / MEAN_SPACING_M) ** 2, rtol=1e-9)
    loss.sum().backward()
    # Moving the generated vehicle forward (across the loop's end, towards 2 m) lowers it.
    assert float(scene.arc.grad[0, -1]) < 0


def test_l_rec_counts_lanes_and_ignores_scenes_without_targets(ring_loop):
    road = Road.of(ring_loop)
    hidden = np.array([[False, True], [False, False]])
    snaps = _snaps(np.array([[0.0, 100.0], [0.0, 100.0]]), np.full((2, 2), 12.0),
                   np.zeros((2, 2)), hidden)  # fmt: skip
    scene = _generated(snaps, road, [[100.0], [100.0]], [[12.0], [12.0]], [[1], [0]])
    loss = reconstruction_loss(scene, snaps, road)
    assert float(loss[0]) == 1.0  # same place and speed, another lane
    assert float(loss[1]) == 0.0  # nothing hidden: nothing to reconstruct
