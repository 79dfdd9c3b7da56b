"""Stage II: the shared policy's agent (actor and value baseline) and how it acts.

* The policy is a Gaussian over the acceleration with a state-independent std; the env
  clips the sample to [a_min, a_max]. One policy drives every hidden vehicle
  (``policy_action``).
* Observations are normalised with fixed ring constants on the ring
  (``env.observation.shift_scale``) and with the mean/std of the bank's initial
  observations on a section (``env.observation.bank_shift_scale``); both are buffers of the agent,
  so they travel in the checkpoint's state_dict.
* ``prior`` (``policy.prior``): "none", the mean is the actor's output; "idm" or "gipps",
  the mean is a fixed, fitted car-following model's acceleration on the raw observation
  plus the actor's output (a residual; ``policy.prior``), the model's parameters a buffer
  too (``idm_prior``, ``gipps_prior``). The residual is bounded,
  B tanh(out / B) with B = ``policy.residual_bound_mps2`` (a buffer; checkpoints from before
  it have none and load unbounded, as they were trained): unbounded, it learned to cancel
  the IDM (Bremen, 40 m/s: IDM -9, residual +8.5 m/s^2), so the policy lost the IDM's
  spacing response it was meant to keep. ``mean_action`` is that mean; everything that
  acts or scores goes through it (``dist``).
* ``driver_tau`` (``policy.driver_follow``): the observed drivers' Krauss tau quantiles
  (``evaluation.driver_follow``), a buffer; with it the observation may carry each row's
  own tau as a trailing column (``env.driver_tau.with_tau``): the actor and the critic read
  the first D columns, the prior takes its tau from the last. Without the column (or
  without the buffer: checkpoints from before it) the prior has its one fitted tau.

Training is ``policy.ppo``, checkpoints ``policy.checkpoint``.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from macromicro_sumo.env.observation import shift_scale as fixed_shift_scale
from macromicro_sumo.env.rollout import ActionFn
from macromicro_sumo.env.section import SectionCore
from macromicro_sumo.errors import UserError
from macromicro_sumo.policy.prior import PRIOR_ACCEL, PRIOR_KEYS, PRIORS
from macromicro_sumo.road.physics import OBSERVATION_FEATURES

# Fixed observation scaling per feature: env.observation.FEATURES (the envs' normalize too).


class Agent(nn.Module):
    def __init__(
        self,
        hidden_size: int = 64,
        init_log_std: float = -1.0,
        observation: str = "paper",
        shift_scale: tuple[np.ndarray, np.ndarray] | None = None,
        prior: str = "none",
        prior_params: Mapping[str, float] | None = None,
        residual_bound_mps2: float = float("inf"),
        driver_speed: np.ndarray | None = None,
        driver_tau: np.ndarray | None = None,
    ) -> None:
        """``shift_scale``: the observation normalisation (None: the features' fixed
        ``env.observation.shift_scale``).
        ``prior_params`` (``policy.prior.PRIOR_KEYS``) for a ``prior`` other than "none"; None
        leaves them NaN, for a checkpoint's state_dict to fill. ``residual_bound_mps2``:
        the largest correction [m/s^2] the actor adds to the prior (inf: unbounded; 0: the
        prior alone). ``driver_speed``: the drivers' desired-speed factor quantiles
        (``policy.driver_speed = "drawn"``, ``env.driver_speed.ratio_quantiles``; a buffer,
        for the deployment to draw from); None: no buffer. ``driver_tau``: the drivers' tau
        quantiles (``policy.driver_follow``; a buffer, as ``driver_speed``)."""
        super().__init__()
        if prior not in PRIORS:
            raise UserError(f"policy.prior = {prior!r}: expected one of {', '.join(PRIORS)}")
        features = OBSERVATION_FEATURES[observation]
        obs_dim = len(features)
        self.obs_dim = obs_dim  # the features' columns; a tau column may follow
        self.observation = observation
        if shift_scale is None:
            shift_scale = fixed_shift_scale(observation)
        shift = torch.as_tensor(np.asarray(shift_scale[0]), dtype=torch.float32)
        scale = torch.as_tensor(np.asarray(shift_scale[1]), dtype=torch.float32)
        self.register_buffer("shift", shift)
        self.register_buffer("scale", scale)
        self.actor = nn.Sequential(
            nn.Linear(obs_dim, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, 1),
        )
        self.critic = nn.Sequential(
            nn.Linear(obs_dim + 1, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, hidden_size),
            nn.Tanh(),
            nn.Linear(hidden_size, 1),
        )
        self.log_std = nn.Parameter(torch.full((1,), float(init_log_std)))
        self.hidden_size = hidden_size
        self.prior = prior
        q = None if driver_speed is None else torch.as_tensor(np.asarray(driver_speed))
        self.register_buffer("driver_speed", None if q is None else q.to(torch.float32))
        t = None if driver_tau is None else torch.as_tensor(np.asarray(driver_tau))
        self.register_buffer("driver_tau", None if t is None else t.to(torch.float32))
        if prior != "none":
            keys = PRIOR_KEYS[prior]
            values = [float("nan")] * len(keys)
            if prior_params is not None:
                values = [float(prior_params[k]) for k in keys]
            self.register_buffer(f"{prior}_prior", torch.tensor(values, dtype=torch.float32))
            self.register_buffer(
                "residual_bound", torch.tensor(float(residual_bound_mps2), dtype=torch.float32)
            )
            # The residual starts at 0: training starts from the calibrated model, and the
            # likelihood moves it only where the observed pairs disagree with it.
            last = self.actor[-1]
            assert isinstance(last, nn.Linear)
            nn.init.zeros_(last.weight)
            nn.init.zeros_(last.bias)

    def residual(self, obs: torch.Tensor) -> torch.Tensor:
        """The actor's part of the mean action [m/s^2] for raw observations (..., D): its
        output, bounded with a ``prior`` (0 with a bound of 0)."""
        out = _mlp(self.actor, (self.features(obs) - self.shift) / self.scale).squeeze(-1)
        if self.prior != "none":
            bound = self.residual_bound
            if bound <= 0.0:  # the fitted prior alone (an ablation)
                out = torch.zeros_like(out)
            elif torch.isfinite(bound):
                # Slope 1 at 0: the zero-initialised residual learns as an unbounded one would.
                out = bound * torch.tanh(out / bound)
        return out

    def features(self, obs: torch.Tensor) -> torch.Tensor:
        """The observation's feature columns: all of them, or the first D where a tau
        column may follow (``driver_tau``)."""
        return obs if self.driver_tau is None else obs[..., : self.obs_dim]

    def row_tau(self, obs: torch.Tensor) -> torch.Tensor | None:
        """Each row's own tau [s] (the trailing column, ``policy.driver_follow``); None
        without the buffer or the column (the prior's one tau)."""
        if self.driver_tau is None or obs.shape[-1] <= self.obs_dim:
            return None
        return obs[..., self.obs_dim]

    def prior_accel(self, obs: torch.Tensor) -> torch.Tensor:
        """The fixed prior's acceleration [m/s^2] (0 without a ``prior``), with each row's
        own tau where the observation carries one (``row_tau``)."""
        if self.prior == "none":
            return torch.zeros(obs.shape[:-1], dtype=obs.dtype)
        buffer = getattr(self, f"{self.prior}_prior")
        p = dict(zip(PRIOR_KEYS[self.prior], buffer.unbind(), strict=True))
        if (tau := self.row_tau(obs)) is not None:
            p["tau_s"] = tau
        return PRIOR_ACCEL[self.prior](obs, p)

    def mean_action(self, obs: torch.Tensor) -> torch.Tensor:
        """The policy's deterministic action [m/s^2] for raw observations (..., D): the
        actor's output, plus the prior's acceleration with a ``prior``."""
        mean = self.residual(obs)
        if self.prior != "none":
            mean = mean + self.prior_accel(obs)
        return mean

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs) -> None:
        # Residual policies trained before the bound had none: they load unbounded.
        key = prefix + "residual_bound"
        if self.prior != "none" and key not in state_dict:
            state_dict[key] = torch.tensor(float("inf"))
        # A checkpoint with drivers' taus (policy.driver_follow) loads them into an agent
        # made without (``policy.checkpoint.load_policy`` makes it from the scenario).
        tau = state_dict.get(prefix + "driver_tau")
        if tau is not None and self.driver_tau is None:
            self.driver_tau = torch.empty_like(tau)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def dist(self, obs: torch.Tensor) -> torch.distributions.Normal:
        mean = self.mean_action(obs)
        # No argument checks: they cost ~5% of a run (every env step builds one), and a
        # NaN observation is caught where it is made, not here.
        return torch.distributions.Normal(
            mean, self.log_std.exp().expand_as(mean), validate_args=False
        )

    def value(self, obs: torch.Tensor, t_frac: torch.Tensor) -> torch.Tensor:
        x = torch.cat([(self.features(obs) - self.shift) / self.scale, t_frac[..., None]], dim=-1)
        return _mlp(self.critic, x).squeeze(-1)


def _mlp(net: nn.Sequential, x: torch.Tensor) -> torch.Tensor:
    """``net(x)`` for a stack of ``Linear`` and ``Tanh`` layers, the same operations
    without nn.Module's call machinery: the policy acts on a handful of vehicles per env
    step, where that machinery cost more than the arithmetic."""
    for layer in net:
        if isinstance(layer, nn.Linear):
            x = F.linear(x, layer.weight, layer.bias)
        elif isinstance(layer, nn.Tanh):
            x = torch.tanh(x)
        else:
            x = layer(x)
    return x


def policy_action(agent, stochastic: bool = True) -> ActionFn:
    def act(core: SectionCore, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        with torch.no_grad():
            d = agent.dist(torch.as_tensor(obs[core.hidden], dtype=torch.float32))
        mean, std = d.mean.numpy(), d.stddev.numpy()
        return mean + std * rng.standard_normal(mean.shape) if stochastic else mean

    return act


def mean_logp(agent: Agent, obs: torch.Tensor, actions: torch.Tensor) -> float:
    """Mean log-likelihood of ``actions`` under the agent (NaN without pairs)."""
    if len(obs) == 0:
        return float("nan")
    with torch.no_grad():
        return float(agent.dist(obs).log_prob(actions).mean())


def mean_rmse(agent: Agent, obs: torch.Tensor, actions: torch.Tensor) -> float:
    """RMSE [m/s^2] of the agent's mean action, the deployed one, against ``actions``
    (NaN without pairs). Unlike ``mean_logp`` it does not move with the action std."""
    if len(obs) == 0:
        return float("nan")
    with torch.no_grad():
        return float(((agent.mean_action(obs) - actions) ** 2).mean().sqrt())
