"""Recovery examples: agents displaced from their log, with a future that re-joins it.

A policy trained only on logged states never sees an agent that is off its
lane or heading askew, yet that is where its own small errors put it in closed
loop, and where a drift starts compounding (ChauffeurNet's perturbations,
CAT-K's covariate shift: ../shared/REFERENCES.md). `perturb` moves some agents
of a training batch sideways by `delta` and turns them by `eps` at the current
step, and replaces their target by a path that starts at the displaced pose
and blends back onto the logged future within `rejoin_seconds`.

It works on cached examples, inside the jitted train step, at no parsing cost:
the agent's whole history moves rigidly with its current pose, so its
history features (in its own frame) are unchanged and only its scene-frame
pose (`agent_center`, `agent_dir`) moves; every relation to the map and the
other agents follows from that pose. The target is built in the agent's old
frame, then re-expressed in the new one:

  o(tau) = delta h00(tau) + R v0 sin(eps) h10(tau),  tau = t / R in [0, 1]
  p(t) = log(t) + o(t) n(t)      (n: the log's left normal at t)

h00, h10 are cubic Hermite bases, so the path starts at the displaced
position with the displaced heading and meets the log with its position and
direction at t = R (o = 0 after). Perturbed: vehicles (not slot 0, the SDC)
faster than `min_speed` whose future is valid up to R, each with probability
`prob`; delta ~ U(-max_lateral, max_lateral), eps ~ U(-max_heading, max_heading).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from pcdiff_jax.config import PerturbConfig
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array, ObjectType
from pcdiff_jax.training.data import Example

_VX = features_lib.AGENT_CHANNELS.index("vel_x")


def _hermite(tau: Array) -> tuple[Array, Array, Array, Array]:
  """h00, h10 and their derivatives d/dtau on tau in [0, 1] (0 past 1)."""
  inside = tau <= 1.0
  t2, t3 = tau ** 2, tau ** 3
  h00 = jnp.where(inside, 2 * t3 - 3 * t2 + 1, 0.0)
  h10 = jnp.where(inside, t3 - 2 * t2 + tau, 0.0)
  d00 = jnp.where(inside, 6 * t2 - 6 * tau, 0.0)
  d10 = jnp.where(inside, 3 * t2 - 4 * tau + 1, 0.0)
  return h00, h10, d00, d10


def rejoin_targets(future_xy: Array, future_yaw: Array, future_speed: Array, speed0: Array,
                   delta: Array, eps: Array, rejoin_seconds: float, dt: float):
  """The re-joining future of agents displaced by (delta, eps), in their new frame.

  future_xy (..., T, 2), future_yaw, future_speed (..., T): the log in the old
  agent frame; speed0, delta, eps (...). Returns xy (..., T, 2), yaw (..., T).
  """
  horizon = future_xy.shape[-2]
  t = dt * (1 + jnp.arange(horizon))                                      # (T,)
  tau = t / rejoin_seconds
  h00, h10, d00, d10 = _hermite(tau)
  slope = rejoin_seconds * speed0 * jnp.sin(eps)                          # (...,)
  offset = delta[..., None] * h00 + slope[..., None] * h10                # (..., T)
  rate = (delta[..., None] * d00 + slope[..., None] * d10) / rejoin_seconds   # do/dt
  normal = jnp.stack([-jnp.sin(future_yaw), jnp.cos(future_yaw)], -1)    # (..., T, 2)
  xy = future_xy + offset[..., None] * normal
  yaw = future_yaw + jnp.arctan2(rate, jnp.maximum(jnp.abs(future_speed), 1.0))
  origin = jnp.stack([jnp.zeros_like(delta), delta], -1)[..., None, :]   # (..., 1, 2)
  new_xy = geometry.to_local(xy, origin, eps[..., None])
  return new_xy, geometry.wrap_angle(yaw - eps[..., None])


def perturb(batch: Example, rng: Array, cfg: PerturbConfig, dt: float = 0.1) -> Example:
  """A batch (..., A, ...) with some agents displaced and re-joining their log."""
  if cfg.prob <= 0.0:
    return batch
  feats, tg = batch.feats, batch.targets
  shape = feats.agent_valid.shape                                         # (..., A)
  k_pick, k_lat, k_head = jax.random.split(rng, 3)
  speed0 = feats.agent_history[..., -1, _VX]
  rejoin_steps = min(int(round(cfg.rejoin_seconds / dt)), tg.future_valid.shape[-1])
  slot = jnp.arange(shape[-1])
  eligible = (feats.agent_valid & (feats.agent_types == ObjectType.VEHICLE) & (slot > 0)
              & (speed0 > cfg.min_speed) & jnp.all(tg.future_valid[..., :rejoin_steps], -1))
  pick = eligible & (jax.random.uniform(k_pick, shape) < cfg.prob)
  delta = jnp.where(pick, jax.random.uniform(k_lat, shape, minval=-1.0, maxval=1.0) * cfg.max_lateral, 0.0)
  eps = jnp.where(pick, jax.random.uniform(k_head, shape, minval=-1.0, maxval=1.0) * cfg.max_heading, 0.0)
  xy, yaw = rejoin_targets(tg.future_xy, tg.future_yaw, tg.future_speed, speed0, delta, eps,
                           cfg.rejoin_seconds, dt)
  valid = tg.future_valid
  targets = tg.replace(future_xy=jnp.where(pick[..., None, None] & valid[..., None], xy, tg.future_xy),
                       future_yaw=jnp.where(pick[..., None] & valid, yaw, tg.future_yaw))
  left = jnp.stack([-feats.agent_dir[..., 1], feats.agent_dir[..., 0]], -1)
  c, s = jnp.cos(eps)[..., None], jnp.sin(eps)[..., None]
  d = feats.agent_dir
  new_dir = jnp.concatenate([c * d[..., :1] - s * d[..., 1:], s * d[..., :1] + c * d[..., 1:]], -1)
  feats = feats.replace(agent_center=feats.agent_center + delta[..., None] * left, agent_dir=new_dir)
  return Example(feats=feats, targets=targets)


def drop_history(batch: Example, rng: Array, prob: float) -> Example:
  """A batch (..., A, ...) in which each valid agent, with probability `prob`,
  keeps only the current step of its history (ChauffeurNet's past-motion
  dropout, ../shared/REFERENCES.md): in closed loop the history is the policy's
  own, and proposals that extrapolate it compound its braking (docs/RESULTS.md,
  "Ablation: history dropout"). The current step (pose, speed) stays."""
  if prob <= 0.0:
    return batch
  pick = batch.feats.agent_valid & (jax.random.uniform(rng, batch.feats.agent_valid.shape) < prob)   # (..., A)
  feats = features_lib.hide_history(batch.feats, 1, pick)
  return Example(feats=feats, targets=batch.targets)
