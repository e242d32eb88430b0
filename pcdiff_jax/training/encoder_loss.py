"""Stage 1 objective and metrics: multimodal proposals against the logged future.

Loss (SIMPL): winner-takes-all regression plus mode classification. For each
agent with at least one valid future step, the best mode k* minimises the
mean displacement over the valid steps; the loss is SmoothL1 (Huber, delta
1 m) on the x, y of mode k* over those steps plus `cls_weight` x the cross
entropy of the mode logits against k*. Averaged over agents.

Metrics (the Argoverse / WOMD conventions, on agents valid at t and at the
last step t+T): minADE_K and minFDE_K (m) over K modes; miss rate, the
fraction with minFDE above `miss_threshold` (2 m); brier-minFDE = minFDE +
(1 - p)^2 with p the probability of the mode that attains minFDE. The
constant-velocity baseline (the velocity at t held for T steps) is scored on
the same agents. Each metric is returned as a sum with its count so batches
aggregate exactly.
"""
from __future__ import annotations

import jax.numpy as jnp
import optax

from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model.encoder import EncoderOutput
from pcdiff_jax.model.features import SceneFeatures
from pcdiff_jax.sim.datatypes import Array
from pcdiff_jax.training.data import Targets

_VX = features_lib.AGENT_CHANNELS.index("vel_x")


def _safe_div(a: Array, b: Array) -> Array:
  return a / jnp.maximum(b, 1.0)


def proposal_loss(out: EncoderOutput, targets: Targets, cls_weight: float = 1.0,
                  huber_delta: float = 1.0) -> tuple[Array, dict]:
  """WTA SmoothL1 + mode cross entropy. out.trajectories (..., A, K, T, 2).

  Returns the scalar loss and {"loss", "reg", "cls"} (agent means).
  """
  pred = out.trajectories
  tgt, valid = targets.future_xy[..., None, :, :], targets.future_valid[..., None, :]
  dist = jnp.linalg.norm(pred - tgt + 1e-9, axis=-1)                 # (..., A, K, T)
  steps = jnp.sum(valid, -1)                                          # (..., A, 1)
  ade = _safe_div(jnp.sum(jnp.where(valid, dist, 0.0), -1), steps)   # (..., A, K)
  best = jnp.argmin(ade, -1)                                          # (..., A)
  agent = out.agent_valid & jnp.any(targets.future_valid, -1)
  huber = optax.huber_loss(pred, tgt, delta=huber_delta).sum(-1)     # (..., A, K, T)
  huber = _safe_div(jnp.sum(jnp.where(valid, huber, 0.0), -1), steps)
  reg = jnp.take_along_axis(huber, best[..., None], -1)[..., 0]       # (..., A)
  cls = optax.softmax_cross_entropy_with_integer_labels(out.logits, best)
  n = jnp.sum(agent)
  reg = _safe_div(jnp.sum(jnp.where(agent, reg, 0.0)), n)
  cls = _safe_div(jnp.sum(jnp.where(agent, cls, 0.0)), n)
  loss = reg + cls_weight * cls
  return loss, {"loss": loss, "reg": reg, "cls": cls}


def constant_velocity(feats: SceneFeatures, horizon: int, dt: float = 0.1) -> Array:
  """(..., A, T, 2) the velocity at t held, in each agent's frame."""
  vel = feats.agent_history[..., -1, _VX:_VX + 2]                     # (..., A, 2)
  s = dt * jnp.arange(1, horizon + 1, dtype=vel.dtype)
  return vel[..., None, :] * s[:, None]


def prediction_metrics(out: EncoderOutput, feats: SceneFeatures, targets: Targets,
                       miss_threshold: float = 2.0) -> dict:
  """Sums over the scored agents; divide by "count" (see `finalize`)."""
  pred, valid = out.trajectories, targets.future_valid
  horizon = valid.shape[-1]
  scored = out.agent_valid & valid[..., -1]                           # (..., A)
  dist = jnp.linalg.norm(pred - targets.future_xy[..., None, :, :], axis=-1)   # (..., A, K, T)
  steps = jnp.sum(valid, -1)[..., None]
  ade = _safe_div(jnp.sum(jnp.where(valid[..., None, :], dist, 0.0), -1), steps)
  fde = dist[..., -1]                                                 # (..., A, K)
  min_ade, min_fde = jnp.min(ade, -1), jnp.min(fde, -1)
  p_best = jnp.take_along_axis(out.probs, jnp.argmin(fde, -1)[..., None], -1)[..., 0]
  cv = constant_velocity(feats, horizon)
  cv_dist = jnp.linalg.norm(cv - targets.future_xy, axis=-1)          # (..., A, T)
  cv_ade = _safe_div(jnp.sum(jnp.where(valid, cv_dist, 0.0), -1), steps[..., 0])
  total = lambda v: jnp.sum(jnp.where(scored, v, 0.0))
  return {
      "count": jnp.sum(scored).astype(jnp.float32),
      "min_ade": total(min_ade), "min_fde": total(min_fde),
      "miss_rate": total((min_fde > miss_threshold).astype(jnp.float32)),
      "brier_min_fde": total(min_fde + (1.0 - p_best) ** 2),
      "cv_ade": total(cv_ade), "cv_fde": total(cv_dist[..., -1]),
      "cv_miss_rate": total((cv_dist[..., -1] > miss_threshold).astype(jnp.float32)),
  }


def finalize(sums: dict) -> dict:
  """Means from accumulated sums (count kept as the number of scored agents)."""
  count = max(float(sums["count"]), 1.0)
  return {k: (float(v) if k == "count" else float(v) / count) for k, v in sums.items()}
