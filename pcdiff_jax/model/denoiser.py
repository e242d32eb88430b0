"""Joint Transformer denoiser over the agents of a scene.

Input per scene: the noisy latents y_s (A, d_y), the diffusion step s, the
encoder's agent tokens (A, c) and scene context (agent + map tokens, with a
validity mask), the agents' centres and unit headings in the scene frame,
and (with the prior) each agent's K proposal latents and probabilities.
Output: the predicted scaled noise sigma * eps (A, d_y).

Each agent token starts as Dense(y_s / scale) + Dense(agent token) + an MLP
of the sinusoidal step embedding. Each of the L pre-norm layers has

1. self-attention across the scene's agents (joint, not per agent), with
   relative pose: edge embeddings of r_ij (as in the encoder: distance,
   angle of the offset and of the headings) are added to the keys and values;
2. cross-attention to the scene context tokens (agents and map pieces);
3. with the prior: cross-attention of each agent to its own K proposal tokens
   Dense([y^k / scale, log p^k]);
4. an MLP; dropout after each residual branch.

Padded agents and context tokens are masked as senders; the output is zero
for padded agents. The final projection starts at zero, so an untrained
model predicts no noise. `compute_dtype` "bfloat16" runs the matmuls in
bfloat16 (parameters and the output stay float32).
"""
from __future__ import annotations

import functools
import math
from typing import Any, Optional

import flax.linen as nn
import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.config import DenoiserConfig
from pcdiff_jax.model.encoder import relative_pose
from pcdiff_jax.model import lane_context
from pcdiff_jax.sim.datatypes import Array

_NEG = -1e9


@struct.dataclass
class DenoiserInputs:
  """One scene's conditioning (any leading batch dims `...`).

  agent_tokens: (..., A, c); agent_valid: (..., A); agent_center,
  agent_dir: (..., A, 2) scene frame; context_tokens: (..., N, c),
  context_valid: (..., N); prior_latents: (..., A, K, d_y); prior_probs:
  (..., A, K); agent_lane: (..., A, F) lane-relative inputs
  (`model.lane_context`; F = 0 when the config does not use them).
  """
  agent_tokens: Array
  agent_valid: Array
  agent_center: Array
  agent_dir: Array
  context_tokens: Array
  context_valid: Array
  prior_latents: Array
  prior_probs: Array
  agent_lane: Array


def step_embedding(s: Array, dim: int) -> Array:
  """Sinusoidal embedding of the step (...,) -> (..., dim)."""
  half = dim // 2
  freqs = jnp.exp(-math.log(10000.0) * jnp.arange(half) / max(half - 1, 1))
  angles = jnp.asarray(s, jnp.float32)[..., None] * freqs
  return jnp.concatenate([jnp.sin(angles), jnp.cos(angles)], -1)


def _attend(q: Array, k: Array, v: Array, mask: Array, heads: int) -> Array:
  """q (Q, d); k, v (Q, S, d) or (S, d); mask (Q, S) -> (Q, d)."""
  d = q.shape[-1]
  hd = d // heads
  split = lambda x: x.reshape(x.shape[:-1] + (heads, hd))
  qh = split(q)                                                       # (Q, H, hd)
  kh, vh = split(k), split(v)
  if kh.ndim == 3:                                                    # shared senders
    logits = jnp.einsum("qhc,shc->qhs", qh, kh)
  else:
    logits = jnp.einsum("qhc,qshc->qhs", qh, kh)
  logits = logits / math.sqrt(hd)
  logits = jnp.where(mask[:, None, :], logits, _NEG)
  w = jax.nn.softmax(logits, -1)
  w = jnp.where(jnp.any(mask, -1)[:, None, None], w, 0.0)            # no sender: zero update
  out = jnp.einsum("qhs,shc->qhc", w, vh) if vh.ndim == 3 else jnp.einsum("qhs,qshc->qhc", w, vh)
  return out.reshape(q.shape)


class DenoiserLayer(nn.Module):
  d_model: int
  num_heads: int
  dropout: float
  use_prior: bool
  dtype: Any = jnp.float32

  @nn.compact
  def __call__(self, h, edges, agent_mask, ctx, ctx_mask, prior, prior_mask, deterministic):
    d = self.d_model
    Dense = functools.partial(nn.Dense, dtype=self.dtype)
    LayerNorm = functools.partial(nn.LayerNorm, dtype=self.dtype)
    drop = lambda x: nn.Dropout(self.dropout)(x, deterministic=deterministic)
    # 1. Agents attend to agents, keys/values shifted by the relative pose edge.
    x = LayerNorm(name="ln_self")(h)
    q = Dense(d, name="self_q")(x)
    k = Dense(d, name="self_k")(x)[None] + Dense(d, name="self_ek")(edges)   # (A, A, d)
    v = Dense(d, name="self_v")(x)[None] + Dense(d, name="self_ev")(edges)
    h = h + drop(Dense(d, name="self_o")(_attend(q, k, v, agent_mask, self.num_heads)))
    # 2. Agents attend to the scene context.
    x = LayerNorm(name="ln_ctx")(h)
    q = Dense(d, name="ctx_q")(x)
    k, v = Dense(d, name="ctx_k")(ctx), Dense(d, name="ctx_v")(ctx)
    mask = jnp.broadcast_to(ctx_mask[None], (h.shape[0], ctx.shape[0]))
    h = h + drop(Dense(d, name="ctx_o")(_attend(q, k, v, mask, self.num_heads)))
    # 3. Each agent attends to its own K proposals.
    if self.use_prior:
      x = LayerNorm(name="ln_prior")(h)
      q = Dense(d, name="prior_q")(x)
      k, v = Dense(d, name="prior_k")(prior), Dense(d, name="prior_v")(prior)   # (A, K, d)
      h = h + drop(Dense(d, name="prior_o")(_attend(q, k, v, prior_mask, self.num_heads)))
    # 4. MLP.
    x = LayerNorm(name="ln_mlp")(h)
    x = Dense(d, name="mlp_out")(nn.gelu(Dense(2 * d, name="mlp_in")(x)))
    return h + drop(x)


class Denoiser(nn.Module):
  """(y_s (A, d_y), s (), DenoiserInputs of one scene) -> scaled noise (A, d_y)."""
  config: DenoiserConfig
  latent_dim: int

  @nn.compact
  def __call__(self, y: Array, s: Array, inputs: DenoiserInputs, deterministic: bool = True) -> Array:
    cfg = self.config
    d = cfg.d_model
    dtype = jnp.bfloat16 if cfg.compute_dtype == "bfloat16" else jnp.float32
    Dense = functools.partial(nn.Dense, dtype=dtype)
    av = inputs.agent_valid
    scale = cfg.latent_scale
    temb = Dense(d)(nn.gelu(Dense(d)(step_embedding(s, d))))
    h = (Dense(d, name="in_y")(y / scale) + Dense(d, name="in_ctx")(inputs.agent_tokens)
         + temb[None])
    if cfg.lane_inputs:   # zero-initialised: a model trained without them is unchanged at first
      h = h + Dense(d, kernel_init=nn.initializers.zeros, name="in_lane")(inputs.agent_lane)
    centre = jnp.where(av[:, None], inputs.agent_center, 0.0)
    direction = jnp.where(av[:, None], inputs.agent_dir, jnp.array([1.0, 0.0]))
    rpe = relative_pose(centre, direction, None, cfg.radius)            # (A, A, 5)
    edges = Dense(d)(nn.gelu(Dense(d)(rpe)))                        # (A, A, d)
    agent_mask = jnp.broadcast_to(av[None], (av.shape[0], av.shape[0]))
    ctx = Dense(d, name="ctx_proj")(inputs.context_tokens)
    prior = prior_mask = None
    if cfg.use_prior:
      logp = jnp.log(jnp.maximum(inputs.prior_probs, 1e-6))[..., None]
      prior = Dense(d, name="prior_in")(
          jnp.concatenate([inputs.prior_latents / scale, logp], -1))     # (A, K, d)
      prior_mask = jnp.broadcast_to(av[:, None], inputs.prior_probs.shape)
    for i in range(cfg.num_layers):
      h = DenoiserLayer(d, cfg.num_heads, cfg.dropout, cfg.use_prior, dtype, name=f"layer_{i}")(
          h, edges, agent_mask, ctx, inputs.context_valid, prior, prior_mask, deterministic)
    out = Dense(self.latent_dim, kernel_init=nn.initializers.zeros, name="out")(
        nn.LayerNorm(name="ln_out")(h)).astype(jnp.float32) * scale
    return jnp.where(av[:, None], out, 0.0)


def init(rng: Array, y: Array, s: Array, inputs: DenoiserInputs, config: DenoiserConfig) -> Any:
  """Parameters for one scene's shapes (pass unbatched y (A, d_y) and inputs)."""
  # Jitted: an eager init compiles every op on its own.
  return jax.jit(Denoiser(config, y.shape[-1]).init)(rng, y, s, inputs)


def with_new_inputs(params: Any, config: DenoiserConfig) -> Any:
  """Parameters of a model trained without the optional inputs that `config`
  turns on (`lane_inputs`), extended by their zero-initialised projections:
  the extended model computes the same function until it is trained."""
  inner = params["params"]
  if config.lane_inputs and "in_lane" not in inner:
    inner = {**inner, "in_lane": lane_context.zero_projection(config.d_model)}
  return {**params, "params": inner}


def apply(params: Any, y: Array, s: Array, inputs: DenoiserInputs, config: DenoiserConfig,
          rng: Optional[Array] = None) -> Array:
  """Batched over the leading dim B of y (B, A, d_y) and inputs; s () or (B,).

  Dropout is on when `rng` is given.
  """
  model = Denoiser(config, y.shape[-1])
  s = jnp.broadcast_to(jnp.asarray(s), y.shape[:1])
  if rng is None:
    return jax.vmap(lambda yy, ss, ii: model.apply(params, yy, ss, ii))(y, s, inputs)
  keys = jax.random.split(rng, y.shape[0])
  return jax.vmap(lambda yy, ss, ii, kk: model.apply(
      params, yy, ss, ii, deterministic=False, rngs={"dropout": kk}))(y, s, inputs, keys)
