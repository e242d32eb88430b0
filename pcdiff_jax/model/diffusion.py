"""Proposal-scaled VP diffusion in the action latent: schedule, noising, DDIM, DDPM.

Per agent i the encoder's K proposal latents y_i^k give a prior centre and a
per-dimension scale,

    mu_i = mean_k y_i^k,      sigma_i = std_k y_i^k + eps_sigma        (d,)

(mu = 0, sigma = 1 without the prior). The forward process keeps the VP
schedule (linear beta in [beta_min, beta_max], S steps, abar_s = prod (1 -
beta)) but scales the noise by sigma:

    y_s = sqrt(abar_s) y_0 + sqrt(1 - abar_s) sigma * eps,

the denoiser predicts the scaled noise sigma * eps, and the one-step
estimate is y0_hat = (y_s - sqrt(1 - abar_s) sigma eps_hat) / sqrt(abar_s).
Sampling starts from the shifted Gaussian sqrt(abar_S) mu + sqrt(1 - abar_S)
sigma * eps, the forward marginal at S of a y_0 near the proposals.

DDIM (Song et al.) over any subsequence of n steps s_n > ... > s_1 of the
S steps, as one `lax.scan`:

    y0 = y0_hat(y_s)           (then the guidance hook may edit y0)
    n_hat = (y_s - sqrt(abar_s) y0) / sqrt(1 - abar_s)        (scaled noise)
    c = eta sqrt((1 - abar_p) / (1 - abar_s)) sqrt(1 - abar_s / abar_p)
    y_p = sqrt(abar_p) y0 + sqrt(1 - abar_p - c^2) n_hat + c sigma z,

with abar_p = 1 after the last step. With n = S and eta = 1 this is the
ancestral DDPM sampler (`ddpm_sample`); eta = 0 is deterministic.

Shapes: latents (..., A, d); `denoise(y, s) -> scaled noise` closes over the
scene context and is called with one scalar step s for the whole batch.
"""
from __future__ import annotations

from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.sim.datatypes import Array

DenoiseFn = Callable[[Array, Array], Array]
# guide(y0, y_s, s, step_index) -> y0; applied where `guide_steps[step_index]`.
GuideFn = Callable[[Array, Array, Array, Array], Array]


@struct.dataclass
class Schedule:
  """betas, alphas_cumprod: (S,) float32; step s in [0, S) uses index s."""
  betas: Array
  alphas_cumprod: Array

  @property
  def num_steps(self) -> int:
    return self.betas.shape[0]


def linear_schedule(num_steps: int = 100, beta_min: float = 1e-4, beta_max: float = 5e-2) -> Schedule:
  betas = np.linspace(beta_min, beta_max, num_steps, dtype=np.float64)
  abar = np.cumprod(1.0 - betas)
  return Schedule(betas=jnp.asarray(betas, jnp.float32), alphas_cumprod=jnp.asarray(abar, jnp.float32))


PRIOR_SPREADS = ("uniform", "weighted")


def prior_from_proposals(proposal_latents: Array, eps_sigma: float,
                         probs: Optional[Array] = None) -> tuple[Array, Array]:
  """(..., K, d) -> mu (..., d), sigma (..., d) over the K proposals: their
  mean and std, or with probs (..., K) the probability-weighted mean and std
  (a parked car whose encoder says 'stays' with p = 0.98 then gets a prior
  about its stay mode, not one spread over five moves it finds unlikely)."""
  if probs is None:
    mu = jnp.mean(proposal_latents, axis=-2)
    return mu, jnp.std(proposal_latents, axis=-2) + eps_sigma
  p = (probs / jnp.maximum(jnp.sum(probs, -1, keepdims=True), 1e-9))[..., None]   # (..., K, 1)
  mu = jnp.sum(p * proposal_latents, axis=-2)
  var = jnp.sum(p * jnp.square(proposal_latents - mu[..., None, :]), axis=-2)
  return mu, jnp.sqrt(var + 1e-12) + eps_sigma


def standard_prior(shape: tuple[int, ...]) -> tuple[Array, Array]:
  """The no-prior variant: mu = 0, sigma = 1."""
  return jnp.zeros(shape), jnp.ones(shape)


def _abar(schedule: Schedule, s: Array) -> Array:
  """abar at step s, 1.0 for s < 0 (the clean end)."""
  return jnp.where(s >= 0, schedule.alphas_cumprod[jnp.clip(s, 0, schedule.num_steps - 1)], 1.0)


def q_sample(y0: Array, s: Array, noise: Array, sigma: Array, schedule: Schedule) -> Array:
  """y_s given y0, unit noise eps and the prior scale sigma. s broadcasts over y0[..., :1]."""
  a = _abar(schedule, s)[..., None]
  return jnp.sqrt(a) * y0 + jnp.sqrt(1.0 - a) * sigma * noise


def predict_y0(y_s: Array, s: Array, scaled_noise: Array, schedule: Schedule) -> Array:
  a = _abar(schedule, s)[..., None]
  return (y_s - jnp.sqrt(1.0 - a) * scaled_noise) / jnp.sqrt(a)


def initial_sample(mu: Array, sigma: Array, noise: Array, schedule: Schedule,
                   start_step: Optional[int] = None) -> Array:
  """The shifted Gaussian sqrt(abar_s) mu + sqrt(1 - abar_s) sigma eps at
  s = start_step (default S - 1, the end of the forward process)."""
  s = schedule.num_steps - 1 if start_step is None else start_step
  return q_sample(mu, jnp.asarray(s), noise, sigma, schedule)


def ddim_timesteps(num_steps: int, num_sample_steps: int, start_step: Optional[int] = None) -> np.ndarray:
  """Descending steps (n,) from `start_step` (default S-1) to 0 when n > 1,
  evenly spaced (static, numpy)."""
  start = num_steps - 1 if start_step is None else start_step
  if not 0 <= start < num_steps:
    raise ValueError(f"the start step must be in [0, {num_steps - 1}], got {start}")
  if not 1 <= num_sample_steps <= start + 1:
    raise ValueError(f"DDIM steps must be in [1, {start + 1}], got {num_sample_steps}")
  steps = np.round(np.linspace(start, 0, num_sample_steps)).astype(np.int32)
  return np.unique(steps)[::-1].copy()


def ddim_sample(denoise: DenoiseFn, mu: Array, sigma: Array, schedule: Schedule, rng: Array,
                num_sample_steps: int, eta: float = 0.0, guide: Optional[GuideFn] = None,
                guide_steps: Optional[np.ndarray] = None, init_noise: Optional[Array] = None,
                start_step: Optional[int] = None) -> Array:
  """DDIM from the shifted Gaussian; returns y_0 (..., d).

  Args:
    denoise: (y_s, s) -> predicted scaled noise, same shape as y_s.
    mu, sigma: (..., d) prior centre and scale.
    num_sample_steps: n (static); eta: 0 deterministic, 1 DDPM-like.
    guide: optional hook editing the y0 estimate; guide_steps: (n,) bool,
      which of the n steps (in sampling order) call it (default: none).
    start_step: the diffusion step the chain starts from (static; default
      S - 1). A warm start noises a previous plan `mu` only to an
      intermediate step and denoises from there (SceneDiffuser's amortised
      rollout, done in the latent): mu stays where the data agrees with it.
  """
  steps, prev, use_guide = _chain(schedule, num_sample_steps, start_step, guide_steps)
  rng_init, rng_steps = jax.random.split(rng)
  if init_noise is None:
    init_noise = jax.random.normal(rng_init, mu.shape, mu.dtype)
  y = initial_sample(mu, sigma, init_noise, schedule, int(steps[0]))
  update = _ddim_update(denoise, sigma, schedule, eta, guide)

  def body(y, inputs):
    return update(y, *inputs), None

  n = len(steps)
  keys = jax.random.split(rng_steps, n)
  y, _ = jax.lax.scan(body, y, (jnp.asarray(steps), jnp.asarray(prev), jnp.asarray(use_guide),
                                jnp.arange(n), keys))
  return y


def _chain(schedule: Schedule, num_sample_steps: int, start_step: Optional[int],
           guide_steps: Optional[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
  """Static (n,) steps, the step each goes to, and which steps call the guide."""
  steps = ddim_timesteps(schedule.num_steps, num_sample_steps, start_step)
  prev = np.concatenate([steps[1:], [-1]]).astype(np.int32)
  use_guide = np.zeros(len(steps), bool) if guide_steps is None else np.asarray(guide_steps, bool)
  if use_guide.shape != steps.shape:
    raise ValueError(f"guide_steps must have shape {steps.shape}, got {use_guide.shape}")
  return steps, prev, use_guide


def _ddim_update(denoise: DenoiseFn, sigma: Array, schedule: Schedule, eta: float,
                 guide: Optional[GuideFn]):
  """One DDIM step y_s -> y_p: (y, s, p, use_guide, step_index, key) -> y."""
  def update(y, s, p, g, i, key):
    scaled = denoise(y, s)
    y0 = predict_y0(y, s, scaled, schedule)
    if guide is not None:
      y0 = jax.lax.cond(g, lambda v: guide(v, y, s, i), lambda v: v, y0)
    a_s, a_p = _abar(schedule, s), _abar(schedule, p)
    n_hat = (y - jnp.sqrt(a_s) * y0) / jnp.sqrt(1.0 - a_s)
    c = eta * jnp.sqrt((1.0 - a_p) / (1.0 - a_s)) * jnp.sqrt(jnp.maximum(1.0 - a_s / a_p, 0.0))
    z = jax.random.normal(key, y.shape, y.dtype)
    return jnp.sqrt(a_p) * y0 + jnp.sqrt(jnp.maximum(1.0 - a_p - c ** 2, 0.0)) * n_hat + c * sigma * z
  return update


def ddim_sample_either(denoise: DenoiseFn, mu: Array, sigma: Array, schedule: Schedule, rng: Array,
                       use_first: Array, first_steps: int, then_steps: int, then_start: int,
                       eta: float = 0.0, guide: Optional[GuideFn] = None,
                       first_guide_steps: Optional[np.ndarray] = None,
                       then_guide_steps: Optional[np.ndarray] = None,
                       init_noise: Optional[Array] = None) -> Array:
  """`ddim_sample` with `first_steps` from S - 1 where `use_first` (a traced
  bool), else with `then_steps` from `then_start` (a warm start), as one
  `lax.while_loop` over the chosen chain. Same result as the matching
  `ddim_sample` call. Why not `lax.cond` between two samplers: under vmap a
  cond runs both branches; a while loop runs until the longest chain of the
  batch is done, so a batch whose scenes all warm-start pays only the short
  chain (the first replan of a rollout is the only cold one). init_noise (the
  shape of mu): the unit noise of the first chain; the warm one draws its own."""
  first = _chain(schedule, first_steps, None, first_guide_steps)
  then = _chain(schedule, then_steps, then_start, then_guide_steps)
  n = max(len(first[0]), len(then[0]))
  pad = lambda a: np.concatenate([a, np.repeat(a[-1:], n - len(a))])
  pick = lambda a, b: jnp.where(use_first, jnp.asarray(pad(a)), jnp.asarray(pad(b)))
  steps, prev, use_guide = (pick(a, b) for a, b in zip(first, then))
  count = jnp.where(use_first, len(first[0]), len(then[0]))
  rng_init, rng_steps = jax.random.split(rng)
  keys_first = jax.random.split(rng_steps, len(first[0]))
  keys_then = jax.random.split(rng_steps, len(then[0]))
  typed = jnp.issubdtype(keys_first.dtype, jax.dtypes.prng_key)
  raw = lambda k: jax.random.key_data(k) if typed else k
  pad_keys = lambda k: jnp.concatenate([raw(k), jnp.repeat(raw(k)[-1:], n - k.shape[0], 0)], 0)
  keys = jnp.where(use_first, pad_keys(keys_first), pad_keys(keys_then))
  fresh = jax.random.normal(rng_init, mu.shape, mu.dtype)
  # A given init_noise (consistent noise) starts the first chain only: re-noising every warm
  # start with the same draw pushes each agent the same way at every replan (on 50 val scenes
  # 56% collisions and 53% off-road against 14% and 15% with the v5 model).
  init_noise = fresh if init_noise is None else jnp.where(use_first, init_noise, fresh)
  y = q_sample(mu, steps[0], init_noise, sigma, schedule)
  update = _ddim_update(denoise, sigma, schedule, eta, guide)

  def body(carry):
    i, y = carry
    key = jax.random.wrap_key_data(keys[i]) if typed else keys[i]
    return i + 1, update(y, steps[i], prev[i], use_guide[i], i, key)
  _, y = jax.lax.while_loop(lambda c: c[0] < count, body, (jnp.int32(0), y))
  return y


def ddpm_sample(denoise: DenoiseFn, mu: Array, sigma: Array, schedule: Schedule, rng: Array) -> Array:
  """Ancestral sampling with the DDPM posterior q(y_{s-1} | y_s, y0_hat), all S steps.

  Posterior mean coefficients (Ho et al. eq. 7) with the variance beta_tilde
  sigma^2; a reference for the DDIM sampler.
  """
  num = schedule.num_steps
  rng_init, rng_steps = jax.random.split(rng)
  y = initial_sample(mu, sigma, jax.random.normal(rng_init, mu.shape, mu.dtype), schedule)
  betas, abar = schedule.betas, schedule.alphas_cumprod

  def body(y, inputs):
    s, key = inputs
    y0 = predict_y0(y, s, denoise(y, s), schedule)
    a_s, a_p = abar[s], _abar(schedule, s - 1)
    beta = betas[s]
    mean = (jnp.sqrt(a_p) * beta / (1 - a_s)) * y0 + (jnp.sqrt(1 - beta) * (1 - a_p) / (1 - a_s)) * y
    var = beta * (1 - a_p) / (1 - a_s)
    z = jax.random.normal(key, y.shape, y.dtype)
    return mean + jnp.sqrt(var) * sigma * z, None

  steps = jnp.arange(num - 1, -1, -1)
  y, _ = jax.lax.scan(body, y, (steps, jax.random.split(rng_steps, num)))
  return y
