"""How Stage II's observed vehicles replay their records on a section (``env.section``).

Observed vehicles drive their recorded speeds and lanes, but the hidden vehicles around
them are generated, not the recorded ones: a recorded speed can run into a generated
vehicle. SUMO's safe speed caps such a command (``SAFE_MODE``); the vehicle is then off
its record, behind it. ``catch_up_speeds`` brings it back: its recorded speed plus a
catch-up term that lands it on its recorded position as soon as its safe speed and its
vType's acceleration allow, never faster than it could shed the extra speed again before
reaching the record (no overshoot). ``safe_places`` says where a recorded lane change can
be applied now. ``vtypes_xml``: the vehicle types of our vehicles; ``junction_lane``: where
a start position inside a junction is inserted.
"""

from __future__ import annotations

import numpy as np

from macromicro_sumo.road.leaders import section_leaders
from macromicro_sumo.road.section import Section

REPLAY_SUFFIX = "_replay"  # observed vehicles' vTypes: no speed-limit cap (``vtypes_xml``)
SAFE_SUFFIX = "_safe"  # hidden vehicles' vTypes under the safety layer: no speed-limit cap
REPLAY_SPEED_FACTOR = 3.0
# Share of the braking bound a catching-up vehicle plans to shed its extra speed with: it
# reaches its record at its recorded speed with braking to spare for what is ahead.
CATCH_UP_BRAKE_SHARE = 0.5


def catch_up_speeds(
    speed_mps: np.ndarray,
    rec_speed_mps: np.ndarray,
    rec_arc_next_m: np.ndarray,
    arc_m: np.ndarray,
    lag_m: np.ndarray,
    dt: float,
    accel_mps2: tuple[float, float],
) -> np.ndarray:
    """Speed commands for vehicles off their record: the recorded speed of the next step
    plus the excess that lands them on their recorded position (Euler: arc' = arc + v' dt),
    bounded by sqrt(2 b |lag|) (b = ``CATCH_UP_BRAKE_SHARE`` x the braking bound: the extra
    speed can be shed before the record is reached) and by the acceleration bounds over
    one step (never beyond the recorded speed itself). ``lag_m``: recorded minus actual
    arc now (positive: behind). SUMO's safe speed still caps the command.
    """
    a_min, a_max = accel_mps2
    excess = (rec_arc_next_m - arc_m) / dt - rec_speed_mps
    bound = np.sqrt(2.0 * CATCH_UP_BRAKE_SHARE * -a_min * np.abs(lag_m))
    cmd = rec_speed_mps + np.clip(excess, -bound, bound)
    cmd = np.minimum(cmd, np.maximum(rec_speed_mps, speed_mps + a_max * dt))
    cmd = np.maximum(cmd, np.minimum(rec_speed_mps, speed_mps + a_min * dt))
    return np.where(np.isfinite(cmd), np.maximum(cmd, 0.0), rec_speed_mps)


def arc_lag(section: Section, rec_arc_m: np.ndarray, arc_m: np.ndarray) -> np.ndarray:
    """Recorded minus actual arc (a loop: the shorter way round)."""
    lag = rec_arc_m - arc_m
    if section.closed:
        half = section.length_m / 2
        lag = np.mod(lag + half, section.length_m) - half
    return lag


def safe_places(
    section: Section,
    lane: np.ndarray,
    arc_m: np.ndarray,
    speed_mps: np.ndarray,
    length_m: np.ndarray,
    fix: np.ndarray,
    fix_lane: np.ndarray,
    fix_arc_m: np.ndarray,
    dt: float,
    a_min: float,
    min_gap_m: float,
) -> np.ndarray:
    """Whether each vehicle ``fix`` (indices into the arrays of the active vehicles, sorted)
    can be put at (``fix_lane``, ``fix_arc_m``) now: its follower there and it can each stop
    behind their leader (braking at ``a_min``, one step to react), bumpers at least
    ``min_gap_m`` apart.

    The moves are judged together, and a refused one stays where it is: the others are
    judged again without it until none is refused. Judged once with every move applied, a
    recorded lane change into the place another vehicle left in the record was applied
    where that vehicle's own move was refused (drawn net 503: an observed car put into the
    side of an observed truck whose recorded lane change waited behind a generated car)."""

    def safe_now(fix: np.ndarray, fix_lane: np.ndarray, fix_arc_m: np.ndarray) -> np.ndarray:
        """The check of the moves ``fix``, every one of them applied."""
        ln, s = lane.copy(), arc_m.copy()
        ln[fix], s[fix] = fix_lane, fix_arc_m
        lead, spacing = section_leaders(section, ln, s)
        v = speed_mps
        has = lead >= 0
        v_l = np.where(has, v[np.maximum(lead, 0)], 0.0)
        l_l = np.where(has, length_m[np.maximum(lead, 0)], 0.0)
        need = min_gap_m + v * dt + np.maximum(0.0, v**2 - v_l**2) / (2 * -a_min)
        safe = np.where(lead == -1, True, spacing - l_l >= need)
        ok = safe[fix].copy()
        # ... and whoever follows it there
        for f in np.flatnonzero(np.isin(lead, fix)):
            ok[np.searchsorted(fix, lead[f])] &= bool(safe[f])
        return ok

    keep = np.ones(len(fix), dtype=bool)
    while True:
        ok = safe_now(fix[keep], fix_lane[keep], fix_arc_m[keep])
        if ok.all():
            return keep
        keep[np.flatnonzero(keep)[~ok]] = False


Via = dict[tuple[int, int], tuple[str, float, float]]


def junction_vias(section: Section) -> Via:
    """(edge index, lane index entered) -> (internal lane, its arc start, arc per metre)."""
    via: Via = {}
    for lane_id, (e, idx, start, scale) in section.lanes.items():
        if lane_id.startswith(":"):
            via.setdefault((e, idx), (lane_id, start, scale))
    return via


def junction_lane(
    section: Section, via: Via, lane: int, arc_m: float
) -> tuple[int, str, float, int] | None:
    """(edge before, internal lane ID, position on it, lane index) of a position inside
    a junction of the section, or None."""
    sec = section
    s = float(np.mod(arc_m, sec.length_m)) if sec.closed else float(arc_m)
    e = int(sec.edge_index(np.array([s]))[0])
    if s - float(sec.offsets_m[e]) <= sec.lengths_m[e]:
        return None
    hit = via.get((e, int(lane)))
    if hit is None:
        return None
    via_id, start, scale = hit
    depth = (s - start) / scale if scale > 0 else 0.0
    return e, via_id, max(0.0, depth), int(lane)


def vtypes_xml(
    types: dict[float, str],
    accel_mps2: tuple[float, float],
    min_gap_m: float,
    vclass: str = "passenger",
    tau_s: float = 1.0,
    replay_min_gap_m: float | None = None,
) -> str:
    """Our vehicle types, one per length: speed-commanded, SUMO's lane changing.

    speedFactor 1 (SUMO's lane-change model sees the lane limit as the desired speed),
    maxSpeed high (commands above the limit apply in speed mode 0), collisions only on
    bumper overlap (collisionMinGapFactor 0), accel/decel = the action bounds.
    Each length has two more types with speedFactor ``REPLAY_SPEED_FACTOR`` (the safe-speed
    check, ``SAFE_MODE``, also caps at limit x speedFactor; commands above the limit are
    the policy's or the record's): id + ``SAFE_SUFFIX`` for hidden vehicles under the
    safety layer, id + ``REPLAY_SUFFIX`` for observed vehicles, whose minGap is
    ``replay_min_gap_m`` where smaller (the recorded vehicles' own: a recorded follower
    closer than our minimum gap is what the truth drove, not a danger).
    """
    a_min, a_max = accel_mps2
    replay_gap = min_gap_m if replay_min_gap_m is None else min(min_gap_m, replay_min_gap_m)
    rows = ["<additional>"]
    for length, tid in types.items():
        for suffix, factor, gap in (
            ("", 1.0, min_gap_m),
            (SAFE_SUFFIX, REPLAY_SPEED_FACTOR, min_gap_m),
            (REPLAY_SUFFIX, REPLAY_SPEED_FACTOR, replay_gap),
        ):
            rows.append(
                f'    <vType id="{tid}{suffix}" length="{length:g}" minGap="{gap:g}" '
                f'maxSpeed="100" speedFactor="{factor:g}" speedDev="0" accel="{a_max:g}" '
                f'decel="{-a_min:g}" emergencyDecel="{max(9.0, -a_min):g}" '
                f'collisionMinGapFactor="0" vClass="{vclass}" tau="{tau_s:g}"/>'
            )
    rows.append("</additional>")
    return "\n".join(rows) + "\n"
