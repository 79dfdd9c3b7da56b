"""Stage I on a road section: the scenes being completed and the training rollout.

``Scene`` holds a batch of scenes, the observed vehicles in the first slots and the
generated ones after them, as the generator completes them one vehicle per step: the
training ``rollout`` here (one proposal per step, no rejection), Algorithm 3 in
``section_sampler``. What a step sees and proposes is ``section_model``'s (``observe``,
``propose``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.generator.section_model import (
    Observation,
    SectionGeneratorNet,
    observe,
    propose,
)
from macromicro_sumo.generator.section_scene import Psi, Road, extra_lengths


@dataclass
class Scene:
    """Observed vehicles in the first N slots, the generated ones after (B, N + K_max)."""

    lane: torch.Tensor
    arc: torch.Tensor
    speed: torch.Tensor
    present: torch.Tensor
    n_obs_slots: int
    k: torch.Tensor  # (B,) vehicles to generate
    total: torch.Tensor  # (B,) vehicles of the completed scene
    extra: torch.Tensor | None = None  # (B, N + K_max) length beyond the shortest [m]
    new_extra: float = 0.0  # a generated one's (``complete_section``: ``generated_extra``)

    @classmethod
    def start(cls, snaps: SectionSnapshots, k: np.ndarray, road: Road) -> Scene:
        """The observed vehicles packed to the front (a snapshot's hidden slots are never
        present: packing shrinks every per-step array), K_max empty slots after them."""
        obs = np.asarray(snaps.valid & snaps.observed, dtype=bool)
        k_t = torch.as_tensor(np.maximum(np.asarray(k, dtype=np.int64), 0))
        k_max = int(k_t.max()) if len(k_t) else 0
        b = len(obs)
        n = max(int(obs.sum(axis=1).max()) if b else 0, 1)
        slot = np.argsort(~obs, axis=1, kind="stable")[:, :n]
        rows = np.arange(b)[:, None]
        packed = obs[rows, slot]
        pad = np.zeros((b, k_max))
        arc = np.where(packed, snaps.arc_m[rows, slot], 0.0)
        if road.closed:
            arc = np.mod(arc, road.length_m)
        # the generator's lane numbers, along the connections (``section_lanes``)
        lane = np.where(packed, np.maximum(road.lane_numbers(snaps.lane[rows, slot], arc), 0), 0)
        speed = np.where(packed, snaps.speed_mps[rows, slot], 0.0)
        extra = np.where(packed, extra_lengths(snaps)[rows, slot], 0.0)
        return cls(
            lane=torch.as_tensor(np.concatenate([lane, pad], 1).astype(np.int64)),
            arc=torch.as_tensor(np.concatenate([arc, pad], 1)),
            speed=torch.as_tensor(np.concatenate([speed, pad], 1)),
            present=torch.as_tensor(np.concatenate([packed, pad.astype(bool)], 1)),
            n_obs_slots=n,
            k=k_t,
            total=torch.as_tensor(obs.sum(axis=1)) + k_t,
            extra=torch.as_tensor(np.concatenate([extra, pad], 1)),
        )

    def observe(
        self, step: int, idx: torch.Tensor, psi: Psi, road: Road, gen: torch.Generator
    ) -> Observation:
        """What step ``step`` sees in rows ``idx`` (those with a vehicle still to place);
        only the slots that can be filled by now (observed + ``step`` generated) enter."""
        m = self.n_obs_slots + step
        return observe(
            self.lane[idx, :m],
            self.arc[idx, :m],
            self.speed[idx, :m],
            self.present[idx, :m],
            self.k[idx] - step,
            self.total[idx],
            psi,
            road,
            _anchor(len(idx), road, gen),
            None if self.extra is None else self.extra[idx, :m],
            self.new_extra,
        )

    def place(
        self,
        step: int,
        idx: torch.Tensor,
        lane: torch.Tensor,
        arc: torch.Tensor,
        v: torch.Tensor,
        present: torch.Tensor | None = None,
    ) -> None:
        """Put the step's vehicle of rows ``idx`` into its slot (out of place: the training
        graph keeps every earlier step's values); ``present`` False leaves a row's slot
        empty (a vehicle that fits nowhere)."""
        j = self.n_obs_slots + step
        if present is None:
            present = torch.ones_like(idx, dtype=torch.bool)

        def put(x: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
            col = x[:, j].index_put((idx,), new)
            return torch.cat([x[:, :j], col[:, None], x[:, j + 1 :]], dim=1)

        self.lane = put(self.lane, lane)
        self.arc = put(self.arc, arc)
        self.speed = put(self.speed, v)
        self.present = put(self.present, present)


def _anchor(b: int, road: Road, gen: torch.Generator) -> torch.Tensor:
    return torch.rand(b, road.max_lanes, generator=gen, dtype=torch.float64) * road.length_m


def rollout(
    net: SectionGeneratorNet,
    road: Road,
    snaps: SectionSnapshots,
    k: np.ndarray,
    gen: torch.Generator,
) -> tuple[Scene, torch.Tensor]:
    """Training rollout (one sample per step, no rejection): the completed scenes and the
    summed log-probability of each scene's gap choices (B,)."""
    scene = Scene.start(snaps, k, road)
    psi = Psi.of(snaps.psi)
    b = len(snaps)
    log_p = torch.zeros(b, dtype=torch.float64)
    for step in range(int(scene.k.max()) if b else 0):
        idx = torch.nonzero(scene.k > step).flatten()
        sub = psi.take(idx)
        t = propose(net, scene.observe(step, idx, sub, road, gen), sub, road, 1, gen)
        log_p = log_p.index_add(0, idx, t.log_p[:, 0])
        scene.place(step, idx, t.lane[:, 0], t.arc[:, 0], t.speed[:, 0])
    return scene, log_p
