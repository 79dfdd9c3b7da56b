"""The consistency term L_rec of joint refinement (paper, Algorithm 1's outer iterations).

L_gen = L_macro + lambda_rec L_rec, where L_rec compares the generator's completion of a
scene at t + 1 with the hidden vehicles the policy drove there from t. Vehicles are
unlabelled, so each generated vehicle is matched to a target one by the assignment with
the least total error (``scipy.optimize.linear_sum_assignment`` on detached values); the
error is then differentiable in the generated positions and speeds (reparameterised),
and the lane, discrete, enters the cost and the score-function term of the gap choice.

Units: a position error in psi's mean spacing (on the paper's ring 125.7 m; the ring
generator's angle in rad measured it in R = 100 m), a speed error in psi's half speed
range (``Psi.v_scale``, the generator's speed unit), a lane that differs costs 1.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.optimize import linear_sum_assignment

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.generator.section_model import SectionGeneratorNet
from macromicro_sumo.generator.section_rollout import Scene, rollout
from macromicro_sumo.generator.section_scene import Psi, Road


def reconstruction_loss(scene: Scene, snaps: SectionSnapshots, road: Road) -> torch.Tensor:
    """L_rec of each scene (B,): the mean over matched pairs of (da / d)^2 + (dv / v_s)^2 +
    [lanes differ] between the scene's generated vehicles and ``snaps``' hidden ones (the
    targets; d psi's mean spacing, v_s its speed scale, da wrapped on a loop). A scene
    with no generated or no target vehicle has 0; with different counts, the matched
    pairs (min of the two) count."""
    n0 = scene.n_obs_slots
    b = len(snaps)
    gen_on = scene.present[:, n0:]
    if b == 0 or gen_on.shape[1] == 0:
        return torch.zeros(b, dtype=torch.float64)
    psi = Psi.of(snaps.psi)
    # Targets packed to the front of (B, T) arrays, as the generated ones are.
    tgt = np.asarray(snaps.valid & snaps.hidden, dtype=bool)
    t_n = max(int(tgt.sum(axis=1).max()), 1)
    slot = np.argsort(~tgt, axis=1, kind="stable")[:, :t_n]
    rows = np.arange(b)[:, None]
    t_on = torch.as_tensor(tgt[rows, slot])
    t_arc = torch.as_tensor(np.where(tgt[rows, slot], snaps.arc_m[rows, slot], 0.0))
    t_v = torch.as_tensor(np.where(tgt[rows, slot], snaps.speed_mps[rows, slot], 0.0))
    t_lane = road.lane_numbers(snaps.lane[rows, slot], snaps.arc_m[rows, slot])
    t_lane = torch.as_tensor(np.where(tgt[rows, slot], t_lane, 0))
    g_arc, g_v, g_lane = scene.arc[:, n0:], scene.speed[:, n0:], scene.lane[:, n0:]
    da = g_arc[:, :, None] - t_arc[:, None, :]
    if road.closed:  # the shorter way round
        half = road.length_m / 2
        da = torch.remainder(da + half, road.length_m) - half
    dv = g_v[:, :, None] - t_v[:, None, :]
    cost = (
        (da / psi.d_mean.clamp(min=1e-6)[:, None, None]) ** 2
        + (dv / psi.v_scale[:, None, None]) ** 2
        + (g_lane[:, :, None] != t_lane[:, None, :]).to(da.dtype)
    )
    pair = gen_on[:, :, None] & t_on[:, None, :]
    detached = cost.detach().numpy()
    picks = []
    for i in range(b):
        gi, ti = np.flatnonzero(gen_on[i].numpy()), np.flatnonzero(t_on[i].numpy())
        if gi.size and ti.size:
            r, c = linear_sum_assignment(detached[i][np.ix_(gi, ti)])
            picks += [(i, int(gi[x]), int(ti[y])) for x, y in zip(r, c, strict=True)]
    if not picks:
        return torch.zeros(b, dtype=cost.dtype)
    bi, gj, tj = (torch.as_tensor(x) for x in zip(*picks, strict=True))
    assert bool(pair[bi, gj, tj].all())  # matched slots hold vehicles on both sides
    sums = torch.zeros(b, dtype=cost.dtype).index_add(0, bi, cost[bi, gj, tj])
    counts = torch.zeros(b, dtype=cost.dtype).index_add(0, bi, torch.ones_like(sums[bi]))
    return sums / counts.clamp(min=1.0)


@torch.no_grad()
def mean_reconstruction(
    net: SectionGeneratorNet, road: Road, snaps: SectionSnapshots, k: np.ndarray, seed: int
) -> float:
    """Mean L_rec of ``net``'s training rollout on ``snaps`` with a fixed seed: the same
    draws for two networks, so that their figures compare (before and after a fine-tune)."""
    if len(snaps) == 0:
        return float("nan")
    scene, _ = rollout(net, road, snaps, k, torch.Generator().manual_seed(seed))
    return float(reconstruction_loss(scene, snaps, road).mean())
