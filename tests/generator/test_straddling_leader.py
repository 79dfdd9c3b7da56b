"""Stage I's pair check and safe speeds behind a vehicle standing across a red line.

The envs' observation and the deployment order a red line against the tails of the
vehicles past it (``road.leaders.section_ahead`` with lengths, stop 49); Stage I's
``safe_speeds`` and ``drop_unsafe_pairs`` ordered by fronts: a generated follower behind a
12 m truck whose front stood 3 m past the line was checked against the line, 9 m nearer the
truck's tail. On game/cross's through lane (1si lane 1 into 2o lane 0), by hand and on
random scenes checked against every vehicle ahead by its tail and the line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import sumo

from macromicro_sumo.generator.section_pairs import (
    SectionCompletion,
    drop_unsafe_pairs,
    pair_leaders,
    safe_speeds,
)
from macromicro_sumo.road.section import STOP, Section, read_section

CROSS = Path(sumo.__file__).resolve().parent / "tools" / "game" / "cross" / "cross.net.xml"
B = 4.5  # braking bound [m/s^2]
TAU = 0.5  # reaction [s]
SHORTEST = 4.5  # the snapshots' shortest vehicle [m]
S_MIN = 6.5  # psi's standstill spacing: the shortest vehicle plus a 2 m minimum gap
TOL = 1e-6


@pytest.fixture(scope="module")
def cross() -> Section:
    return read_section(CROSS, ["1fi", "1si", "2o", "2fo"], False)


def line_of(cross: Section) -> float:
    return float(cross.offsets_m[1] + cross.lengths_m[1])  # 1si's end: its stop line


def scene(line: float, arc, speed, length, generated) -> tuple[SectionCompletion, np.ndarray]:
    """One scene on the through lane (1si lane 1 before the line, 2o lane 0 past it) and its
    extra lengths (beyond the shortest)."""
    arc = np.asarray(arc, dtype=float)
    n = len(arc)
    comp = SectionCompletion(
        lane=np.where(arc < line, 1, 0)[None, :].astype(np.int64),
        arc_m=arc[None, :],
        speed_mps=np.asarray(speed, dtype=float)[None, :],
        valid=np.ones((1, n), dtype=bool),
        generated=np.asarray(generated, dtype=bool)[None, :],
        trials=np.zeros(1),
        projections=np.zeros(1),
    )
    return comp, (np.asarray(length, dtype=float) - SHORTEST)[None, :]


def line_stop(line: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([1]), np.array([line])  # one scene's (``pair_leaders``)


def red(line: float) -> tuple[np.ndarray, np.ndarray]:
    return np.array([[1]]), np.array([[line]])


def test_a_truck_across_the_line_leads_its_generated_follower(cross: Section) -> None:
    """A 12 m truck standing with its front 3 m past the red line; a generated car 12 m
    before the line at 6 m/s. By fronts it could stop at the line (5.5 m of room: 7.0 m/s);
    behind the truck's tail it has 1.0 m (3.0 m/s) and gets a speed it can stop from there.
    A generated car 5 m before the line, standing, overlaps the truck (its front 4 m inside
    the truck's tail) and is dropped; by fronts the line led and it stayed."""
    line = line_of(cross)
    comp, ex = scene(line, [line - 12.0, line + 3.0], [6.0, 0.0], [4.5, 12.0], [True, False])
    lead, spacing, hidden = pair_leaders(
        cross, comp.lane[0], comp.arc_m[0], ex[0], *line_stop(line)
    )
    assert lead.tolist() == [1, -1] and spacing[0] == pytest.approx(15.0)
    assert hidden[0] == pytest.approx(12.0) and np.isinf(hidden[1])  # the line holds too
    safe_speeds(comp, cross, np.array([S_MIN]), B, TAU, ex, red(line))
    v = comp.speed_mps[0, 0]
    free = 15.0 - 12.0 - (S_MIN - SHORTEST)  # the bumper gap less the minimum gap
    assert v * v + 2 * B * TAU * v <= 2 * B * free + 1e-9
    assert v < 3.0
    stand, _ = scene(line, [line - 5.0, line + 3.0], [0.0, 0.0], [4.5, 12.0], [True, False])
    args = (cross, np.array([S_MIN]), B, TAU, ex, red(line))
    assert drop_unsafe_pairs(stand, *args).tolist() == [1]
    assert stand.valid[0].tolist() == [False, True]
    # A car (the shortest) past the line by 1 m: the line is nearer and leads, as by fronts.
    car, ex_c = scene(line, [line - 12.0, line + 1.0], [6.0, 0.0], [4.5, 4.5], [True, False])
    lead, spacing, hidden = pair_leaders(
        cross, car.lane[0], car.arc_m[0], ex_c[0], *line_stop(line)
    )
    assert lead[0] == STOP and spacing[0] == pytest.approx(12.0) and np.isinf(hidden[0])


def test_a_moving_truck_across_a_yellow_line_leaves_the_line_standing(cross: Section) -> None:
    """A truck crossing the line at 10 m/s leads the observation, but SUMO's follower still
    stops at the line: the generated follower's speed is the line's cap, not the truck's."""
    line = line_of(cross)
    comp, ex = scene(line, [line - 12.0, line + 3.0], [9.0, 10.0], [4.5, 12.0], [True, False])
    safe_speeds(comp, cross, np.array([S_MIN]), B, TAU, ex, red(line))
    v = comp.speed_mps[0, 0]
    room = 2 * B * (12.0 - S_MIN)
    assert v * v + 2 * B * TAU * v <= room + 1e-9
    assert v == pytest.approx(np.sqrt((B * TAU) ** 2 + room) - B * TAU)


def random_scene(rng: np.random.Generator, line: float) -> tuple[SectionCompletion, np.ndarray]:
    """Up to 8 vehicles (cars 4.5-5 m, trucks 12 m) packed upstream from one whose front is
    0-10 m past the line, bumper gaps 0.3-15 m, speeds 0-12 m/s, half generated."""
    n = int(rng.integers(2, 9))
    length = rng.choice([4.5, 5.0, 12.0], n, p=[0.4, 0.2, 0.4])
    arc = np.empty(n)
    arc[0] = line + rng.uniform(0.0, 10.0)
    for i in range(1, n):
        arc[i] = arc[i - 1] - length[i - 1] - rng.uniform(0.3, 15.0)
    speed = rng.uniform(0.0, 12.0, n) * (rng.random(n) < 0.7)
    gen = rng.random(n) < 0.5
    return scene(line, arc, speed, length, gen)


def test_random_scenes_keep_the_tails_and_the_line(cross: Section) -> None:
    """On 400 random scenes with a red line, after ``safe_speeds`` and the pair check, every
    pair with a generated vehicle in it keeps at least the minimum gap to the leader's
    physical tail (a standing follower a generated leader's extra length less) and its
    follower can stop behind it; a generated follower can stop at the line ahead of it."""
    line = line_of(cross)
    rng = np.random.default_rng(49)
    straddling = dropped = 0
    for _ in range(400):
        comp, ex = random_scene(rng, line)
        straddling += int(((comp.arc_m > line) & (comp.arc_m - ex - SHORTEST < line)).sum())
        safe_speeds(comp, cross, np.array([S_MIN]), B, TAU, ex, red(line))
        dropped += int(drop_unsafe_pairs(comp, cross, np.array([S_MIN]), B, TAU, ex, red(line))[0])
        on = np.flatnonzero(comp.valid[0])
        arc, v, gen = comp.arc_m[0, on], comp.speed_mps[0, on], comp.generated[0, on]
        length = ex[0, on] + SHORTEST
        order = np.argsort(-arc)  # front first: each one's leader is the one before it
        ahead = dict(zip(order[1:].tolist(), order[:-1].tolist(), strict=True))
        for a in order.tolist():
            reach = v[a] ** 2 + 2 * B * TAU * v[a]
            b = ahead.get(a)
            if gen[a] and arc[a] < line and (b is None or arc[b] > line):
                assert reach <= 2 * B * max(line - arc[a] - S_MIN, 0.0) * (1 + TOL) + TOL
            if b is None or not (gen[a] or gen[b]):
                continue
            free = arc[b] - length[b] - arc[a] - (S_MIN - SHORTEST)  # to the physical tail
            stand_ok = v[a] <= 0.0 and gen[b]
            assert free >= -TOL or (stand_ok and free + length[b] - SHORTEST >= -TOL)
            # Where the line is nearer than the leader's tail (the line leads), a generated
            # follower stops at the line (above); an observed one keeps its record.
            line_leads = arc[a] < line < arc[b] - (length[b] - SHORTEST)
            if not line_leads:
                assert reach <= v[b] ** 2 + 2 * B * max(free, 0.0) * (1 + TOL) + TOL
    assert straddling > 50 and dropped > 0  # the scenes test what they are for
