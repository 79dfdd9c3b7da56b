"""How the ring generator's completions compare with Psi and with the true hidden vehicles.

Per snapshot (``completion_metrics``): whether a completion within Psi's bounds exists at
all, whether this one is within them (with and without projected vehicles), the macro
errors and every loss term, and the errors of the hidden vehicles matched to the true
ones; per method and K (``summarise_metrics``): generator_metrics.csv.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch
from scipy.optimize import linear_sum_assignment

from macromicro_sumo.data.ring import Snapshots
from macromicro_sumo.generator.ring_gaps import PsiTensors
from macromicro_sumo.generator.ring_model import LOSS_TERMS, macro_losses
from macromicro_sumo.generator.ring_sampler import Completion

# --------------------------------------------------------------------------- metrics


def feasible_exists(snaps: Snapshots) -> np.ndarray:
    """(B,) whether any completion puts every touched gap and speed within Psi's bounds."""
    out = np.zeros(len(snaps), dtype=bool)
    for i in range(len(snaps)):
        d_min, d_max, v_min, v_max = snaps.psi[i, 2:6]
        k = int(snaps.hidden[i].sum())
        if v_min > v_max or d_min > d_max:
            continue
        obs = np.sort(snaps.arc_m[i, ~snaps.hidden[i]])
        if k == 0:
            out[i] = True
            continue
        if len(obs) == 0:
            out[i] = k * d_min <= snaps.length_m <= k * d_max
            continue
        arcs = np.mod(np.roll(obs, -1) - obs, snaps.length_m)
        if len(obs) == 1:
            arcs = np.array([snaps.length_m])
        reachable = {0}
        for ln in arcs:
            options = [0] + [c for c in range(1, k + 1) if (c + 1) * d_min <= ln <= (c + 1) * d_max]
            reachable = {r + c for r in reachable for c in options if r + c <= k}
        out[i] = k in reachable
    return out


def _ring_spacing_std(arc_m: np.ndarray, length_m: float) -> np.ndarray:
    """Std of all spacings of each completed ring, (B,)."""
    s = np.sort(np.mod(arc_m, length_m), axis=1)
    gaps = np.diff(np.concatenate([s, s[:, :1] + length_m], axis=1), axis=1)
    return gaps.std(axis=1)


def completion_metrics(snaps: Snapshots, comp: Completion) -> pd.DataFrame:
    """Per snapshot: feasibility, macro errors, each L term, matched hidden-state errors."""
    terms = macro_losses(
        torch.as_tensor(comp.arc_m, dtype=torch.float64),
        torch.as_tensor(comp.speed_mps, dtype=torch.float64),
        torch.as_tensor(snaps.hidden),
        PsiTensors.of(snaps, dtype=torch.float64),
        snaps.length_m,
    )
    length = snaps.length_m
    b = len(snaps)
    in_bounds = np.zeros(b, dtype=bool)
    pos_err = np.full(b, np.nan)
    spd_err = np.full(b, np.nan)
    mean_spacing = np.full(b, length / snaps.arc_m.shape[1])
    for i in range(b):
        hid = snaps.hidden[i]
        s = np.mod(comp.arc_m[i], length)
        order = np.argsort(s)
        gaps = np.mod(np.roll(s[order], -1) - s[order], length)
        gaps[gaps == 0] = length if len(s) == 1 else 0.0
        touched = hid[order] | np.roll(hid[order], -1)
        d_min, d_max, v_min, v_max = snaps.psi[i, 2:6]
        g_ok = np.all((gaps[touched] >= d_min - 1e-6) & (gaps[touched] <= d_max + 1e-6))
        v = comp.speed_mps[i, hid]
        in_bounds[i] = g_ok and np.all((v >= v_min - 1e-6) & (v <= v_max + 1e-6))
        idx = np.flatnonzero(hid)
        if len(idx):
            da = np.abs(
                np.mod(
                    comp.arc_m[i, idx][:, None] - snaps.arc_m[i, idx][None, :] + length / 2, length
                )
                - length / 2
            )
            dv = np.abs(comp.speed_mps[i, idx][:, None] - snaps.speed_mps[i, idx][None, :])
            r, c = linear_sum_assignment(
                da / snaps.psi[i, 1] + dv / max(snaps.psi[i, 5] - snaps.psi[i, 4], 0.1)
            )
            pos_err[i], spd_err[i] = da[r, c].mean(), dv[r, c].mean()
    return pd.DataFrame(
        {
            "run": snaps.run,
            "time_s": snaps.time_s,
            "K": snaps.k,
            "feasible_exists": feasible_exists(snaps),
            "projected": comp.projected,
            # Algorithm 3 without projection met the bounds (the strict measure) ...
            "feasible": in_bounds & (comp.projected == 0),
            # ... and the completion meets them, projected vehicles included.
            "in_bounds": in_bounds,
            "speed_rel_err": np.abs(comp.speed_mps.mean(axis=1) - snaps.psi[:, 0])
            / snaps.psi[:, 0],
            "spacing_rel_err": np.abs(mean_spacing - snaps.psi[:, 1]) / snaps.psi[:, 1],
            "spacing_std_m": _ring_spacing_std(comp.arc_m, snaps.length_m),
            "true_spacing_std_m": _ring_spacing_std(snaps.arc_m, snaps.length_m),
            **{k: v.numpy() for k, v in terms.items()},
            "pos_err_m": pos_err,
            "speed_err_mps": spd_err,
        }
    )


def summarise_metrics(per_snapshot: pd.DataFrame) -> pd.DataFrame:
    """generator_metrics.csv: one row per method and K."""
    rows = []
    for (method, k), g in per_snapshot.groupby(["method", "K"], sort=True):
        fe = g["feasible_exists"]
        rows.append(
            {
                "method": method,
                "K": k,
                "n_snapshots": len(g),
                "n_feasible_exists": int(fe.sum()),
                "n_no_feasible": int((~fe).sum()),
                "feasibility_rate": float(g.loc[fe, "feasible"].mean()) if fe.any() else np.nan,
                "in_bounds_rate": float(g.loc[fe, "in_bounds"].mean()) if fe.any() else np.nan,
                "projected_vehicles": int(g["projected"].sum()),
                "speed_rel_err": g["speed_rel_err"].mean(),
                "spacing_rel_err": g["spacing_rel_err"].mean(),
                "spacing_std_m": np.sqrt((g["spacing_std_m"] ** 2).mean()),
                "true_spacing_std_m": np.sqrt((g["true_spacing_std_m"] ** 2).mean()),
                **{t: g[t].mean() for t in LOSS_TERMS},
                "pos_err_m": g["pos_err_m"].mean(),
                "speed_err_mps": g["speed_err_mps"].mean(),
            }
        )
    return pd.DataFrame(rows)
