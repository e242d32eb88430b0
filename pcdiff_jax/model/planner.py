"""Encoder -> proposal prior -> DDIM -> decoded joint plans, as pure functions.

Used by stage-2 training (conditioning), its validation and the closed-loop
policy. Everything takes a batch of scenes (B, ...) and is jit-able.

  cond = condition(models, feats, cfg)      # frozen encoder + proposal latents
  y0 = sample(models, cond, cfg, rng, ...)  # (B, A, d) joint latent plan
  states = decode_states(models, cond, y0)  # (B, A, T, 4) agent frame
"""
from __future__ import annotations

from typing import Any, Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.config import Config
from pcdiff_jax.model import denoiser as denoiser_lib
from pcdiff_jax.model import diffusion, encoder, lane_context, latent
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model.denoiser import DenoiserInputs
from pcdiff_jax.model.features import SceneFeatures
from pcdiff_jax.model.latent import LatentStats
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array

_VX = features_lib.AGENT_CHANNELS.index("vel_x")
_LEN = features_lib.AGENT_CHANNELS.index("length")


@struct.dataclass
class Models:
  """Everything sampling needs: encoder and denoiser parameters, latent statistics."""
  encoder: Any
  denoiser: Any
  stats: LatentStats


@struct.dataclass
class Conditioning:
  """Per-scene inputs of the sampler (batch dims `...`).

  inputs: DenoiserInputs (batch B, or 1: one scene's inputs shared by B
  samples of it, the denoiser's context then computed once); mu, sigma:
  (..., A, d) prior centre and scale
  (0 and 1 without the prior); speed: (..., A) signed speed at t (the initial
  state of every decoded rollout is [0, 0, 0, speed] in the agent frame);
  proposals: (..., A, K, d) proposal latents; probs: (..., A, K); anchor:
  (..., A, d) each agent's anchor proposal latent when the denoiser reads one
  (`draw_anchor`), else None.
  """
  inputs: DenoiserInputs
  mu: Array
  sigma: Array
  speed: Array
  proposals: Array
  probs: Array
  anchor: Optional[Array] = None


def agent_speed(feats: SceneFeatures) -> Array:
  """(..., A) forward speed at t: the x velocity in the agent's own frame."""
  return feats.agent_history[..., -1, _VX]


def agent_size(feats: SceneFeatures) -> tuple[Array, Array]:
  """(..., A) length and width at t."""
  return feats.agent_history[..., -1, _LEN], feats.agent_history[..., -1, _LEN + 1]


def proposal_latents(out: encoder.EncoderOutput, speed: Array, stats: LatentStats,
                     cfg: Config) -> Array:
  """(..., A, K, d) latents of the K proposals (inverse dynamics, then PCA)."""
  actions = latent.actions_from_positions(out.trajectories, speed[..., None], cfg.kinematics)
  return latent.encode(actions, stats)


def condition(encoder_params: Any, stats: LatentStats, feats: SceneFeatures, cfg: Config) -> Conditioning:
  """Frozen encoder and proposal prior for a batch of scenes (no gradient)."""
  out = jax.lax.stop_gradient(encoder.apply(encoder_params, feats, cfg.encoder))
  speed = agent_speed(feats)
  props = proposal_latents(out, speed, stats, cfg)                      # (..., A, K, d)
  if cfg.diffusion.denoiser.use_prior:
    if cfg.diffusion.prior_spread not in diffusion.PRIOR_SPREADS:
      raise ValueError(f"diffusion.prior_spread must be one of {diffusion.PRIOR_SPREADS}, "
                       f"got {cfg.diffusion.prior_spread!r}")
    weights = out.probs if cfg.diffusion.prior_spread == "weighted" else None
    mu, sigma = diffusion.prior_from_proposals(props, cfg.diffusion.eps_sigma, weights)
  else:
    mu, sigma = diffusion.standard_prior(props.shape[:-2] + props.shape[-1:])
  inputs = DenoiserInputs(
      agent_tokens=out.agent_tokens, agent_valid=out.agent_valid,
      agent_center=feats.agent_center, agent_dir=feats.agent_dir,
      context_tokens=out.context_tokens, context_valid=out.context_valid,
      prior_latents=props, prior_probs=out.probs,
      agent_lane=(lane_context.lane_inputs(feats) if cfg.diffusion.denoiser.lane_inputs
                  else jnp.zeros(feats.agent_valid.shape + (0,), jnp.float32)))
  return Conditioning(inputs=inputs, mu=mu, sigma=sigma, speed=speed, proposals=props,
                      probs=out.probs)


def repeat_samples(cond: Conditioning, num: int) -> Conditioning:
  """One scene's conditioning (batch 1) as `num` samples of it (batch num);
  the denoiser's inputs stay one copy, so its context is computed once."""
  tiled = jax.tree_util.tree_map(lambda a: jnp.repeat(a, num, axis=0), cond.replace(inputs=None))
  return tiled.replace(inputs=cond.inputs)


def centre_on_top_mode(cond: Conditioning) -> Conditioning:
  """The same prior centred on each agent's most likely proposal latent instead
  of the mean of its K proposals (sigma unchanged). A test-time option: the
  mean of the modes is not a mode (with the v2 models it started with a turn)."""
  best = jnp.argmax(cond.probs, -1)                                        # (..., A)
  top = jnp.take_along_axis(cond.proposals, best[..., None, None], axis=-2)[..., 0, :]
  return cond.replace(mu=top)


def _proposal_distances(cond: Conditioning, y: Array) -> Array:
  """(..., A, K) squared distances from y (..., A, d) to each agent's proposal latents."""
  return jnp.sum(jnp.square(cond.proposals - y[..., None, :]), -1)


def nearest_proposal(cond: Conditioning, y: Array) -> Array:
  """(..., A) the index of each agent's proposal latent nearest y (..., A, d)."""
  return jnp.argmin(_proposal_distances(cond, y), -1)


def with_anchor(cond: Conditioning, index: Array) -> Conditioning:
  """cond with each agent's anchor, and prior centre, its proposal `index` (..., A)."""
  anchor = jnp.take_along_axis(cond.proposals, index[..., None, None], axis=-2)[..., 0, :]
  return cond.replace(anchor=anchor, mu=anchor)


def draw_anchor(cond: Conditioning, cfg: Config, rng: Array, previous: Optional[Array] = None,
                has: Optional[Array] = None, tau: float = 0.0, temperature: float = 1.0) -> Conditioning:
  """The anchors of a sampling chain when the denoiser reads them (`anchor_inputs`;
  else cond unchanged): each agent's proposal k drawn with probability p_k
  (p_k^(1 / temperature), normalised; temperature 0: the most likely), or,
  where it has a previous plan (previous (..., A, d), has (A,)), with probability
  p_k exp(-|previous - y_k|^2 / 2 tau^2) (tau 0: the nearest proposal), so a
  replan keeps the mode it committed to."""
  if not cfg.diffusion.denoiser.anchor_inputs:
    return cond
  k_prior, k_kept = jax.random.split(rng)
  logp = jnp.log(jnp.maximum(cond.probs, 1e-9))                                       # (..., A, K)
  if temperature > 0:
    index = jax.random.categorical(k_prior, logp / temperature)                        # (..., A)
  else:
    index = jnp.argmax(logp, -1)
  if previous is not None:
    dist2 = _proposal_distances(cond, previous)
    kept = (jax.random.categorical(k_kept, logp - dist2 / (2.0 * tau ** 2)) if tau > 0
            else jnp.argmin(dist2, -1))
    index = jnp.where(has, kept, index)
  return with_anchor(cond, index)


def schedule_of(cfg: Config) -> diffusion.Schedule:
  d = cfg.diffusion
  return diffusion.linear_schedule(d.num_steps, d.beta_min, d.beta_max)


def _denoiser_fn(denoiser_params: Any, cond: Conditioning, d):
  """denoise(y, s) for one chain: the denoiser's y-independent part (edge,
  context and proposal projections) is computed here once. XLA already hoisted
  it out of the step loop; what this saves is its repetition per sample, as
  cond.inputs with a batch of 1 are shared by all the samples of a scene."""
  ctx = denoiser_lib.context(denoiser_params, cond.inputs, d.denoiser, d.latent_dim)
  return lambda y, s: denoiser_lib.apply_with_context(denoiser_params, y, s, ctx, d.denoiser, cond.anchor)


def sample(denoiser_params: Any, cond: Conditioning, cfg: Config, rng: Array,
           num_steps: Optional[int] = None, eta: Optional[float] = None,
           prior_init: bool = True, guide=None, guide_steps=None,
           init_noise: Optional[Array] = None, centre: Optional[Array] = None,
           start_step: Optional[int] = None) -> Array:
  """DDIM joint plans (B, A, d) for a batch of scenes.

  prior_init False starts from N(0, I) with unit noise scale (the no-prior
  variant); the denoiser still reads whatever tokens its config uses.
  init_noise (B, A, d): the unit noise of the initial sample (default: drawn from rng).
  A denoiser with anchor inputs and no cond.anchor gets anchors drawn from the
  proposal probabilities (`draw_anchor`).
  centre (B, A, d) and start_step (static): a warm start, the chain starts
  from `centre` noised to `start_step` (`diffusion.ddim_sample`).
  """
  d = cfg.diffusion
  num_steps = d.ddim_steps if num_steps is None else num_steps
  eta = d.eta if eta is None else eta
  if cond.anchor is None:   # a denoiser with anchor inputs: drawn from the probabilities
    cond = draw_anchor(cond, cfg, jax.random.fold_in(rng, 1))
  mu, sigma = (cond.mu, cond.sigma) if prior_init else diffusion.standard_prior(cond.mu.shape)
  mu = mu if centre is None else centre

  denoise = _denoiser_fn(denoiser_params, cond, d)
  return diffusion.ddim_sample(denoise, mu, sigma, schedule_of(cfg), rng, num_steps, eta,
                               guide=guide, guide_steps=guide_steps, init_noise=init_noise,
                               start_step=start_step)


def sample_cold_or_warm(denoiser_params: Any, cond: Conditioning, cfg: Config, rng: Array,
                        cold: Array, centre: Array, num_steps: int, warm_steps: int, warm_start: int,
                        eta: Optional[float] = None, prior_init: bool = True, guide=None,
                        cold_guide_steps=None, warm_guide_steps=None,
                        init_noise: Optional[Array] = None) -> Array:
  """Joint plans (B, A, d): the cold `num_steps` sampler from the prior where
  `cold` (a traced bool), else the warm one from `centre` noised to
  `warm_start` (`diffusion.ddim_sample_either`: one while loop, so a vmapped
  batch does not pay both chains)."""
  d = cfg.diffusion
  eta = d.eta if eta is None else eta
  if cond.anchor is None:
    cond = draw_anchor(cond, cfg, jax.random.fold_in(rng, 1))
  mu, sigma = (cond.mu, cond.sigma) if prior_init else diffusion.standard_prior(cond.mu.shape)
  mu = jnp.where(cold, mu, centre)

  denoise = _denoiser_fn(denoiser_params, cond, d)
  return diffusion.ddim_sample_either(denoise, mu, sigma, schedule_of(cfg), rng, cold, num_steps,
                                      warm_steps, warm_start, eta, guide=guide,
                                      first_guide_steps=cold_guide_steps,
                                      then_guide_steps=warm_guide_steps, init_noise=init_noise)


def decode_states(stats: LatentStats, cond: Conditioning, y0: Array, cfg: Config,
                  steps: Optional[int] = None) -> Array:
  """(..., A, d) latents -> (..., A, T, 4) agent-frame states [x, y, psi, v] (the first
  `steps` of them: the rollout is causal)."""
  return latent.rollout(y0, cond.speed, stats, cfg.kinematics, steps)


def to_scene(states: Array, feats: SceneFeatures) -> tuple[Array, Array]:
  """Agent-frame states (..., A, T, 4) -> scene-frame xy (..., A, T, 2), yaw (..., A, T)."""
  return features_lib.agent_to_scene(states[..., :2], states[..., 2], feats)


def scene_overlap(states: Array, feats: SceneFeatures) -> Array:
  """(...,) bool: two valid agents' boxes overlap at some step of the plans (..., A, T, 4)."""
  xy, yaw = to_scene(states, feats)
  length, width = agent_size(feats)
  valid = feats.agent_valid

  def one_scene(xy, yaw, length, width, valid):
    def per_step(carry, inputs):
      p, h = inputs                                                    # (A, 2), (A,)
      hit = geometry.pairwise_box_overlap(p[:, 0], p[:, 1], h, length, width)
      both = valid[:, None] & valid[None] & ~jnp.eye(valid.shape[0], dtype=bool)
      return carry | jnp.any(hit & both), None
    out, _ = jax.lax.scan(per_step, jnp.zeros((), bool),
                          (jnp.moveaxis(xy, -2, 0), jnp.moveaxis(yaw, -1, 0)))
    return out

  batch = valid.shape[:-1]
  fn = one_scene
  for _ in batch:
    fn = jax.vmap(fn)
  return fn(xy, yaw, length, width, valid)

