"""Stage I at a red light: a red or yellow stop line, and the end of a lane that leaves the
section, are standing leaders for the generated vehicles' speeds.

On SUMO's game/cross the generator put a car 1 m before a red stop line at 12 m/s and a car
8 m behind it at 10 m/s: in the env the first stops at the line in one step and the second
runs into it (Stage II evaluation collisions). Hand-built scenes on the cross's section
(west approach 1fi, 1si with three lanes, of which only lane 1 continues onto 2o).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import sumo
import torch

from macromicro_sumo.data.section import SectionSnapshots
from macromicro_sumo.generator.section_model import SectionGeneratorNet
from macromicro_sumo.generator.section_sampler import (
    SectionCompletion,
    complete_section,
    safe_speeds,
)
from macromicro_sumo.generator.section_scene import scene_stops
from macromicro_sumo.road.section import Section, read_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
B = 4.5  # braking bound [m/s^2]
S_MIN = 6.5


@pytest.fixture(scope="module")
def cross() -> Section:
    return read_section(CROSS, ["1fi", "1si", "2o", "2fo"], False)


def stop_line(cross: Section) -> float:
    return float(cross.offsets_m[1] + cross.lengths_m[1])  # 1si's end


def test_a_red_light_is_a_standing_leader_for_generated_speeds(cross: Section) -> None:
    """A generated car 1 m before a red stop line gets a speed it can stop from there, and
    the generated car 8 m behind it one it can stop from behind it; without the red light
    both keep their speeds (nothing stands ahead on the through lane)."""
    line = stop_line(cross)
    comp = SectionCompletion(
        lane=np.array([[1, 1, 1]]),
        arc_m=np.array([[line - 60.0, line - 9.0, line - 1.0]]),
        speed_mps=np.array([[5.0, 10.0, 12.0]]),
        valid=np.ones((1, 3), dtype=bool),
        generated=np.array([[False, True, True]]),
        trials=np.zeros(1),
        projections=np.zeros(1),
    )
    free = dataclasses.replace(comp, speed_mps=comp.speed_mps.copy())
    safe_speeds(free, cross, np.array([S_MIN]), B)
    np.testing.assert_allclose(free.speed_mps[0], [5.0, 10.0, 12.0])
    red = (np.array([[1]]), np.array([[line]]))
    safe_speeds(comp, cross, np.array([S_MIN]), B, stops=red)
    v = comp.speed_mps[0]
    assert v[2] ** 2 <= 2 * B * 1.0 + 1e-9  # stops at the line
    assert v[1] ** 2 <= v[2] ** 2 + 2 * B * (8.0 - S_MIN) + 1e-9  # stops behind it
    assert v[0] == 5.0  # the observed car keeps its record


def test_turning_lanes_end_for_the_sections_route(cross: Section) -> None:
    """1si's lanes 0 and 2 lead off the section (right and left turns): a driver on the
    section's route stops at their end unless it changed lanes, so they end in a standing
    obstacle whatever the signal shows; lane 1 only where the snapshot's light is red."""
    n = 2
    snaps = scenes(cross, n, np.array([[1], [0]]), np.array([[stop_line(cross)], [np.nan]]))
    lane, arc = scene_stops(cross, snaps)
    end = round(stop_line(cross), 6)

    def points(s: int) -> set[tuple[int, float]]:
        at = zip(lane[s], arc[s], strict=True)
        return {(int(a), round(float(b), 6)) for a, b in at if np.isfinite(b)}

    assert points(0) == {(0, end), (1, end), (2, end)}
    assert points(1) == {(0, end), (2, end)}


def scenes(cross: Section, n: int, stop_lane: np.ndarray, stop_arc: np.ndarray) -> SectionSnapshots:
    """``n`` scenes of one observed car far upstream on 1si, 6 vehicles to hide, psi of a
    free road (10-14 m/s), with the given stop lines."""
    psi = np.tile([12.0, 30.0, 0.0, 10.0, 14.0, S_MIN, np.inf, S_MIN], (n, 1))
    return SectionSnapshots(
        run=np.zeros(n, dtype=int),
        time_s=np.arange(n) * 10.0,
        lane=np.ones((n, 1), dtype=np.int64),
        arc_m=np.full((n, 1), 60.0),
        speed_mps=np.full((n, 1), 12.0),
        length_m=np.full((n, 1), 5.0),
        valid=np.ones((n, 1), dtype=bool),
        observed=np.ones((n, 1), dtype=bool),
        psi=psi,
        k_true=np.full(n, 6),
        k_est=np.full(n, 6),
        stop_lane=stop_lane,
        stop_arc_m=stop_arc,
    )


def test_completions_stop_before_red_lights_and_lane_ends(cross: Section) -> None:
    """Generated vehicles on 1si (an untrained generator: anywhere, 10-14 m/s) can all stop
    before the red stop line ahead of them (lane 1) and before the end of the turning lanes
    (0, 2): v^2 + 2 b tau v <= 2 b d. Without stop lines in the snapshot, cars near the
    through lane's end keep speeds they cannot stop from."""
    n, tau = 24, 0.5
    line = stop_line(cross)
    red = scenes(cross, n, np.ones((n, 1), dtype=np.int64), np.full((n, 1), line))
    torch.manual_seed(0)
    net = SectionGeneratorNet(32)
    comp = complete_section(net, cross, red, red.k_true, 20, seed=0, brake_mps2=B, reaction_s=tau)

    def too_fast(c: SectionCompletion, lanes: tuple[int, ...]) -> int:
        g = c.generated & np.isin(c.lane, lanes) & (c.arc_m > cross.offsets_m[1]) & (c.arc_m < line)
        d, v = line - c.arc_m[g], c.speed_mps[g]
        return int((v**2 + 2 * B * tau * v > 2 * B * d + 1e-6).sum())

    assert comp.generated.sum() == 6 * n
    assert too_fast(comp, (0, 1, 2)) == 0
    green = dataclasses.replace(red, stop_lane=None, stop_arc_m=None)
    comp = complete_section(
        net, cross, green, green.k_true, 20, seed=0, brake_mps2=B, reaction_s=tau
    )
    assert too_fast(comp, (0, 2)) == 0  # lane ends hold whatever the light
    assert too_fast(comp, (1,)) > 0
