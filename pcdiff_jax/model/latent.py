"""The PCA action latent: futures -> actions -> y (d), and back.

A future of T steps (the log, or one of the K proposals) becomes the action
sequence u = [a_1, psid_1, ..., a_T, psid_T] (D_u = 2T = 160) by the inverse
of the kinematic model f (`sim.dynamics.inverse`), in the agent's frame at t
where the initial state is [0, 0, 0, v_t]. A global affine normalisation
(mu_u, sigma_u per dimension) and the top-d principal components V (D_u, d)
are fitted once over the training set, across agents and proposals; then

    encode(u) = ((u - mu_u) / sigma_u) V        (..., d)
    decode(y) = (y V^T) sigma_u + mu_u          (..., T, 2)

and `rollout` turns a latent back into states with f. V has orthonormal
columns, so decode(encode(u)) is the projection of u on the subspace.
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.config import KinematicsConfig
from pcdiff_jax.sim import dynamics, geometry
from pcdiff_jax.sim.datatypes import Array

_MIN_STD = 1e-3


@struct.dataclass
class LatentStats:
  """mean, std: (D_u,); components: (D_u, d) orthonormal columns; explained: (d,)
  fraction of the normalised variance each component explains."""
  mean: Array
  std: Array
  components: Array
  explained: Array

  @property
  def dim(self) -> int:
    return self.components.shape[-1]

  @property
  def horizon(self) -> int:
    return self.components.shape[0] // 2


def initial_states(speed: Array) -> Array:
  """(..., 4) agent-frame states [0, 0, 0, v] at t."""
  z = jnp.zeros_like(speed)
  return jnp.stack([z, z, z, speed], -1)


def actions_from_future(future_xy: Array, future_yaw: Array, future_speed: Array,
                        future_valid: Array, current_speed: Array,
                        cfg: KinematicsConfig = KinematicsConfig()) -> tuple[Array, Array]:
  """Inverse dynamics of agent-frame futures.

  Args: future_xy (..., T, 2), future_yaw, future_speed, future_valid (..., T),
    current_speed (...).
  Returns: actions (..., T, 2) and their valid mask (..., T).
  """
  start = initial_states(current_speed)[..., None, :]
  fut = jnp.concatenate([future_xy, future_yaw[..., None], future_speed[..., None]], -1)
  states = jnp.concatenate([start, fut], -2)
  valid = jnp.concatenate([jnp.ones_like(future_valid[..., :1]), future_valid], -1)
  return dynamics.inverse(states, valid, cfg)


def actions_from_positions(xy: Array, current_speed: Array,
                           cfg: KinematicsConfig = KinematicsConfig()) -> Array:
  """Open-loop ("flat") inverse of agent-frame paths xy (..., T, 2), e.g. proposals.

  Each step's heading is the direction of its displacement (reversed for
  backward motion, held below `min_speed_for_heading`) and its speed the
  displacement along that heading; actions are their differences from the
  previous step (heading 0 and `current_speed`, which broadcasts against
  xy's batch dims, at t). Without clipping, f reproduces the path exactly,
  like `dynamics.inverse`; unlike that closed-loop tracker it never corrects
  a clipped step, so a path that does not start at the agent's speed costs
  one large first action instead of an oscillation that the PCA latent cannot
  represent (proposals are smooth curves, but their start is not constrained
  to the current speed).
  Returns actions (..., T, 2) within bounds.
  """
  speed0 = jnp.broadcast_to(current_speed, xy.shape[:-2])
  prev = jnp.concatenate([jnp.zeros_like(xy[..., :1, :]), xy[..., :-1, :]], -2)
  disp = jnp.moveaxis(xy - prev, -2, 0)                                # (T, ..., 2)

  def body(heading, d):
    dist = jnp.sqrt(jnp.sum(d ** 2, -1) + 1e-12)
    direction = jnp.arctan2(d[..., 1], d[..., 0])
    backwards = jnp.sum(d * geometry.unit(heading), -1) < 0
    target = jnp.where(backwards, direction + jnp.pi, direction)
    moving = dist / cfg.dt > cfg.min_speed_for_heading
    new = jnp.where(moving, heading + geometry.wrap_angle(target - heading), heading)
    speed = jnp.sum(d * geometry.unit(new), -1) / cfg.dt
    return new, (new, speed)

  _, (heading, speed) = jax.lax.scan(body, jnp.zeros_like(speed0), disp)
  heading, speed = jnp.moveaxis(heading, 0, -1), jnp.moveaxis(speed, 0, -1)   # (..., T)
  prev_speed = jnp.concatenate([speed0[..., None], speed[..., :-1]], -1)
  prev_heading = jnp.concatenate([jnp.zeros_like(heading[..., :1]), heading[..., :-1]], -1)
  actions = jnp.stack([(speed - prev_speed) / cfg.dt, (heading - prev_heading) / cfg.dt], -1)
  return dynamics.clip_action(actions, cfg)


def flatten(actions: Array) -> Array:
  """(..., T, 2) -> (..., 2T) as [a_1, psid_1, ..., a_T, psid_T]."""
  return actions.reshape(actions.shape[:-2] + (-1,))


def encode(actions: Array, stats: LatentStats) -> Array:
  """(..., T, 2) actions -> (..., d) latents."""
  return ((flatten(actions) - stats.mean) / stats.std) @ stats.components


def decode(latent: Array, stats: LatentStats) -> Array:
  """(..., d) latents -> (..., T, 2) actions."""
  u = (latent @ stats.components.T) * stats.std + stats.mean
  return u.reshape(u.shape[:-1] + (-1, 2))


def rollout(latent: Array, current_speed: Array, stats: LatentStats,
            cfg: KinematicsConfig = KinematicsConfig(), steps: Optional[int] = None) -> Array:
  """Decoded actions rolled out with f from [0, 0, 0, v]: (..., d) -> (..., T, 4)
  agent-frame states [x, y, psi, v], or only the first `steps` of them. The actions are
  clipped to the model's bounds."""
  actions = dynamics.clip_action(decode(latent, stats), cfg)[..., :steps, :]
  speed = jnp.broadcast_to(current_speed, latent.shape[:-1])
  return dynamics.rollout(initial_states(speed), actions, cfg.dt)


def prior_variance(stats: LatentStats) -> Array:
  """(d,) variance of each latent coordinate over the fit's samples: the
  eigenvalues of the normalised covariance (`explained` x D_u)."""
  return stats.explained * stats.components.shape[0]


def whitened_rms(y: Array, stats: LatentStats) -> Array:
  """(..., d) -> (...): RMS of a latent in units of each component's training spread."""
  return jnp.sqrt(jnp.mean(y ** 2 / prior_variance(stats), -1))


def fit_to_path(y: Array, future_xy: Array, future_valid: Array, current_speed: Array,
                stats: LatentStats, cfg: KinematicsConfig = KinematicsConfig(), sigma: float = 1.0,
                iterations: int = 100, learning_rate: float = 0.15) -> Array:
  """The latent whose rollout follows a path, kept in distribution (MAP).

  Minimises sum_t |p_t(y) - xy_t|^2 / sigma^2 + sum_i y_i^2 / var_i over the
  valid steps, by `iterations` Adam steps from y (e.g. `encode` of the
  inverse actions). Real logs need it: second differences of noisy positions
  give accelerations no driver made, and their projection lies far outside
  the latent's training distribution and still misses the path (RESULTS,
  "Latent targets of real logs").
  Args: y (..., d), future_xy (..., T, 2) agent frame, future_valid (..., T),
    current_speed (...). Returns (..., d).
  """
  import optax   # a training dependency; inference never fits
  inv_var = 1.0 / jnp.maximum(prior_variance(stats), 1e-6)
  speed = jnp.broadcast_to(current_speed, y.shape[:-1])
  opt = optax.adam(learning_rate)

  def loss(y):
    err = jnp.sum((rollout(y, speed, stats, cfg)[..., :2] - future_xy) ** 2, -1)
    return jnp.sum(jnp.where(future_valid, err, 0.0)) / sigma ** 2 + jnp.sum(y ** 2 * inv_var)

  def step(carry, _):
    y, opt_state = carry
    update, opt_state = opt.update(jax.grad(loss)(y), opt_state, y)
    return (y + update, opt_state), None

  (y, _), _ = jax.lax.scan(step, (y, opt.init(y)), None, iterations)
  return y


def fit(actions: np.ndarray, dim: int, weights: Optional[np.ndarray] = None) -> LatentStats:
  """Fits the normalisation and the top-`dim` components to samples (N, T, 2).

  Uses the (D_u x D_u) covariance and `numpy.linalg.eigh` (N can be large).
  """
  u = np.asarray(actions, np.float64).reshape(len(actions), -1)
  if len(u) < 2:
    raise ValueError(f"need at least 2 action samples to fit the latent, got {len(u)}")
  if dim > u.shape[1]:
    raise ValueError(f"latent dim {dim} exceeds the action dimension {u.shape[1]}")
  w = np.ones(len(u)) if weights is None else np.asarray(weights, np.float64)
  w = w / w.sum()
  mean = w @ u
  std = np.sqrt(w @ (u - mean) ** 2)
  std = np.maximum(std, _MIN_STD)
  z = (u - mean) / std
  cov = (z * w[:, None]).T @ z
  evals, evecs = np.linalg.eigh(cov)
  order = np.argsort(evals)[::-1][:dim]
  comps = evecs[:, order]
  # A deterministic sign: the largest-magnitude entry of each component is positive.
  signs = np.sign(comps[np.abs(comps).argmax(0), np.arange(dim)])
  comps = comps * np.where(signs == 0, 1.0, signs)
  explained = evals[order] / max(evals.sum(), 1e-12)
  f32 = lambda a: jnp.asarray(a, jnp.float32)
  return LatentStats(mean=f32(mean), std=f32(std), components=f32(comps), explained=f32(explained))


def placeholder(horizon: int, dim: int) -> LatentStats:
  """Statistics of the right shapes (identity scaling, zero components): a
  template to restore saved statistics into."""
  d_u = 2 * horizon
  return LatentStats(mean=jnp.zeros(d_u), std=jnp.ones(d_u), components=jnp.zeros((d_u, dim)),
                     explained=jnp.zeros(dim))

