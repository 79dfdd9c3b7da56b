"""Evaluation: roll out a policy on generator-completed held-out scenes and compare the
fleet's macro statistics with the ground truth over the same steps (paper's protocol).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import torch

from macromicro_sumo.env import RingCore


def rollout_policy(
    agent, core: RingCore, horizon: int, seed: int, stochastic: bool = True
) -> pd.DataFrame:
    """Every episode of the core's bank once: speeds and spacings of all vehicles per step."""
    gen = torch.Generator().manual_seed(seed)
    rows = []
    bank = core.bank
    for ep in range(len(bank)):
        o = core.reset(ep)
        k = int(bank.hidden[ep].sum())
        for t in range(horizon):
            with torch.no_grad():
                d = agent.dist(torch.as_tensor(o, dtype=torch.float32))
                a = d.mean + (
                    d.stddev * torch.randn(d.mean.shape, generator=gen) if stochastic else 0.0
                )
            res = core.step(a.numpy()[bank.hidden[ep]])
            o = res.obs
            rows.append(
                {
                    "episode": ep,
                    "K": k,
                    "step": t + 1,
                    "mean_speed_mps": float(o[:, 0].mean()),
                    "speed_std_mps": float(o[:, 0].std()),
                    "spacing_std_m": float(o[:, 2].std()),
                    "gt_mean_speed_mps": float(bank.replay_speed_mps[ep, t + 1].mean()),
                    "collision": res.collision,
                    "error": res.error,
                }
            )
            if res.collision or res.truncated:
                break
    return pd.DataFrame(rows)


def speed_alignment(df: pd.DataFrame) -> pd.DataFrame:
    """Per K: policy fleet mean speed vs ground truth over the same episodes and steps."""
    g = df.groupby("K")
    return pd.DataFrame(
        {
            "mean_speed_mps": g["mean_speed_mps"].mean(),
            "gt_mean_speed_mps": g["gt_mean_speed_mps"].mean(),
            "abs_error_mps": (g["mean_speed_mps"].mean() - g["gt_mean_speed_mps"].mean()).abs(),
            "collisions": g["collision"].sum(),
            "episodes": g["episode"].nunique(),
        }
    ).reset_index()


__all__ = ["rollout_policy", "speed_alignment", "np"]
