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

With `anchor_inputs` each agent token also gets Dense(anchor / scale), the
latent of one of its proposals chosen per sample (`planner.draw_anchor`).

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
_NO_ANCHOR = "the denoiser's config has anchor_inputs: pass each agent's anchor (planner.draw_anchor)"


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


def _attend(q: Array, k: Array, v: Array, mask: Array, heads: int,
            edge_k: Optional[Array] = None, edge_v: Optional[Array] = None) -> Array:
  """q (Q, d); k, v (S, d) shared by every receiver, or (Q, S, d) each
  receiver's own; mask (Q, S) -> (Q, d). edge_k, edge_v (Q, S, d): per-pair
  terms added to the keys and values (the relative pose edges), as
  q.k_j + q.e_ij and sum_j w_ij v_j + sum_j w_ij e'_ij: the (Q, S, d) sums
  are never formed, which makes one denoiser call over 8 samples of 65 agents
  1.3x faster on a CPU (docs/BENCHMARKS.md, "The default's step back under
  32 ms")."""
  d = q.shape[-1]
  hd = d // heads
  split = lambda x: x.reshape(x.shape[:-1] + (heads, hd))
  qh, kh, vh = split(q), split(k), split(v)                           # (Q, H, hd), ([Q,] S, H, hd)
  shared = kh.ndim == 3
  logits = jnp.einsum("qhc,shc->qhs" if shared else "qhc,qshc->qhs", qh, kh)
  if edge_k is not None:
    logits = logits + jnp.einsum("qhc,qshc->qhs", qh, split(edge_k))
  logits = logits / math.sqrt(hd)
  logits = jnp.where(mask[:, None, :], logits, _NEG)
  w = jax.nn.softmax(logits, -1)
  w = jnp.where(jnp.any(mask, -1)[:, None, None], w, 0.0)            # no sender: zero update
  out = jnp.einsum("qhs,shc->qhc" if shared else "qhs,qshc->qhc", w, vh)
  if edge_v is not None:
    out = out + jnp.einsum("qhs,qshc->qhc", w, split(edge_v))
  return out.reshape(q.shape)


class LayerContext(struct.PyTreeNode):
  """One layer's projections of what does not change along a sampling chain:
  edge keys/values (A, A, d), context keys/values (N, d), proposal keys/values
  (A, K, d) (None without the prior)."""
  edge_k: Array
  edge_v: Array
  ctx_k: Array
  ctx_v: Array
  prior_k: Optional[Array]
  prior_v: Optional[Array]


class DenoiserContext(struct.PyTreeNode):
  """Everything the denoiser computes from its DenoiserInputs alone: the
  agents' input tokens (A, d) (agent token and lane inputs, projected), the
  masks and one LayerContext per layer. Computed once per scene and shared by
  every step of a chain and by every sample of that scene (`context`)."""
  base: Array
  agent_mask: Array
  ctx_mask: Array
  prior_mask: Optional[Array]
  agent_valid: Array
  layers: tuple


class DenoiserLayer(nn.Module):
  d_model: int
  num_heads: int
  dropout: float
  use_prior: bool
  dtype: Any = jnp.float32

  def setup(self):
    d = self.d_model
    Dense = functools.partial(nn.Dense, d, dtype=self.dtype)
    LayerNorm = functools.partial(nn.LayerNorm, dtype=self.dtype)
    self.ln_self, self.ln_ctx, self.ln_mlp = LayerNorm(), LayerNorm(), LayerNorm()
    self.self_q, self.self_k, self.self_v, self.self_o = Dense(), Dense(), Dense(), Dense()
    self.self_ek, self.self_ev = Dense(), Dense()
    self.ctx_q, self.ctx_k, self.ctx_v, self.ctx_o = Dense(), Dense(), Dense(), Dense()
    if self.use_prior:
      self.ln_prior = LayerNorm()
      self.prior_q, self.prior_k, self.prior_v, self.prior_o = Dense(), Dense(), Dense(), Dense()
    self.mlp_in = nn.Dense(2 * d, dtype=self.dtype)
    self.mlp_out = Dense()
    self.drop = nn.Dropout(self.dropout)

  def context(self, edges: Array, ctx: Array, prior: Optional[Array]) -> LayerContext:
    """The y-independent projections (edges (A, A, d), ctx (N, d), prior (A, K, d))."""
    pk = pv = None
    if self.use_prior:
      pk, pv = self.prior_k(prior), self.prior_v(prior)
    return LayerContext(edge_k=self.self_ek(edges), edge_v=self.self_ev(edges),
                        ctx_k=self.ctx_k(ctx), ctx_v=self.ctx_v(ctx), prior_k=pk, prior_v=pv)

  def __call__(self, h: Array, c: LayerContext, masks: DenoiserContext, deterministic: bool) -> Array:
    drop = lambda x: self.drop(x, deterministic=deterministic)
    # 1. Agents attend to agents, keys/values shifted by the relative pose edge.
    x = self.ln_self(h)
    h = h + drop(self.self_o(_attend(self.self_q(x), self.self_k(x), self.self_v(x), masks.agent_mask,
                                     self.num_heads, c.edge_k, c.edge_v)))
    # 2. Agents attend to the scene context.
    x = self.ln_ctx(h)
    mask = jnp.broadcast_to(masks.ctx_mask[None], (h.shape[0], masks.ctx_mask.shape[0]))
    h = h + drop(self.ctx_o(_attend(self.ctx_q(x), c.ctx_k, c.ctx_v, mask, self.num_heads)))
    # 3. Each agent attends to its own K proposals.
    if self.use_prior:
      x = self.ln_prior(h)
      h = h + drop(self.prior_o(_attend(self.prior_q(x), c.prior_k, c.prior_v, masks.prior_mask,
                                        self.num_heads)))
    # 4. MLP.
    x = self.mlp_out(nn.gelu(self.mlp_in(self.ln_mlp(h))))
    return h + drop(x)


class Denoiser(nn.Module):
  """(y_s (A, d_y), s (), DenoiserInputs of one scene) -> scaled noise (A, d_y).

  `context(inputs)` computes the y-independent part once (a DenoiserContext);
  `denoise(y, s, context)` is one evaluation. Submodule names are those of
  the first (compact) version, so every shipped checkpoint loads.
  """
  config: DenoiserConfig
  latent_dim: int

  def setup(self):
    cfg = self.config
    d = cfg.d_model
    dtype = jnp.bfloat16 if cfg.compute_dtype == "bfloat16" else jnp.float32
    Dense = functools.partial(nn.Dense, d, dtype=dtype)
    # Names as the compact version auto-assigned them (outer Dense first).
    self.Dense_0, self.Dense_1 = Dense(), Dense()                        # step embedding MLP
    self.in_y, self.in_ctx = Dense(), Dense()
    if cfg.lane_inputs:   # zero-initialised: a model trained without them is unchanged at first
      self.in_lane = Dense(kernel_init=nn.initializers.zeros)
    if cfg.anchor_inputs:   # the same for the anchor proposal
      self.in_anchor = Dense(kernel_init=nn.initializers.zeros)
    self.Dense_2, self.Dense_3 = Dense(), Dense()                        # relative pose edge MLP
    self.ctx_proj = Dense()
    if cfg.use_prior:
      self.prior_in = Dense()
    self.layers = [DenoiserLayer(d, cfg.num_heads, cfg.dropout, cfg.use_prior, dtype, name=f"layer_{i}")
                   for i in range(cfg.num_layers)]
    self.ln_out = nn.LayerNorm()
    self.out = nn.Dense(self.latent_dim, kernel_init=nn.initializers.zeros, dtype=dtype)

  def context(self, inputs: DenoiserInputs) -> DenoiserContext:
    cfg = self.config
    av = inputs.agent_valid
    base = self.in_ctx(inputs.agent_tokens)
    if cfg.lane_inputs:
      base = base + self.in_lane(inputs.agent_lane)
    centre = jnp.where(av[:, None], inputs.agent_center, 0.0)
    direction = jnp.where(av[:, None], inputs.agent_dir, jnp.array([1.0, 0.0]))
    rpe = relative_pose(centre, direction, None, cfg.radius)            # (A, A, 5)
    edges = self.Dense_2(nn.gelu(self.Dense_3(rpe)))                    # (A, A, d)
    ctx = self.ctx_proj(inputs.context_tokens)
    prior = prior_mask = None
    if cfg.use_prior:
      logp = jnp.log(jnp.maximum(inputs.prior_probs, 1e-6))[..., None]
      prior = self.prior_in(jnp.concatenate([inputs.prior_latents / cfg.latent_scale, logp], -1))
      prior_mask = jnp.broadcast_to(av[:, None], inputs.prior_probs.shape)
    return DenoiserContext(
        base=base, agent_mask=jnp.broadcast_to(av[None], (av.shape[0], av.shape[0])),
        ctx_mask=inputs.context_valid, prior_mask=prior_mask, agent_valid=av,
        layers=tuple(layer.context(edges, ctx, prior) for layer in self.layers))

  def denoise(self, y: Array, s: Array, c: DenoiserContext, deterministic: bool = True,
              anchor: Optional[Array] = None) -> Array:
    """anchor (A, d_y): each agent's anchor proposal latent, required with
    `anchor_inputs` (per sample, so it is not part of the shared context)."""
    scale = self.config.latent_scale
    temb = self.Dense_0(nn.gelu(self.Dense_1(step_embedding(s, self.config.d_model))))
    h = self.in_y(y / scale) + c.base + temb[None]
    if self.config.anchor_inputs:
      if anchor is None:
        raise ValueError(_NO_ANCHOR)
      h = h + self.in_anchor(anchor / scale)
    for layer, lc in zip(self.layers, c.layers):
      h = layer(h, lc, c, deterministic)
    out = self.out(self.ln_out(h)).astype(jnp.float32) * scale
    return jnp.where(c.agent_valid[:, None], out, 0.0)

  def __call__(self, y: Array, s: Array, inputs: DenoiserInputs, deterministic: bool = True,
               anchor: Optional[Array] = None) -> Array:
    return self.denoise(y, s, self.context(inputs), deterministic, anchor)


def init(rng: Array, y: Array, s: Array, inputs: DenoiserInputs, config: DenoiserConfig) -> Any:
  """Parameters for one scene's shapes (pass unbatched y (A, d_y) and inputs)."""
  # Jitted: an eager init compiles every op on its own. `deterministic` stays a
  # Python bool (a traced one breaks dropout's check when its rate is not 0).
  module = Denoiser(config, y.shape[-1])
  return jax.jit(lambda rng, y, s, inputs: module.init(rng, y, s, inputs, True, jnp.zeros_like(y)))(
      rng, y, s, inputs)


def with_new_inputs(params: Any, config: DenoiserConfig) -> Any:
  """Parameters of a model trained without the optional inputs that `config`
  turns on (`lane_inputs`, `anchor_inputs`), extended by their zero-initialised
  projections: the extended model computes the same function until it is trained."""
  inner = params["params"]
  if config.lane_inputs and "in_lane" not in inner:
    inner = {**inner, "in_lane": lane_context.zero_projection(config.d_model)}
  if config.anchor_inputs and "in_anchor" not in inner:
    d_y = inner["in_y"]["kernel"].shape[0]
    inner = {**inner, "in_anchor": {"kernel": jnp.zeros((d_y, config.d_model), jnp.float32),
                                    "bias": jnp.zeros((config.d_model,), jnp.float32)}}
  return {**params, "params": inner}


def context(params: Any, inputs: DenoiserInputs, config: DenoiserConfig, latent_dim: int) -> DenoiserContext:
  """The y-independent part of the denoiser for a batch of scenes (leading dim
  B of inputs): compute it once per chain, outside the loop over steps."""
  model = Denoiser(config, latent_dim)
  return jax.vmap(lambda ii: model.apply(params, ii, method=Denoiser.context))(inputs)


def apply_with_context(params: Any, y: Array, s: Array, ctx: DenoiserContext,
                       config: DenoiserConfig, anchor: Optional[Array] = None) -> Array:
  """`apply` (deterministic) from a precomputed context: y (B, A, d_y), s () or
  (B,); ctx batched over B, or over 1 to share one scene's context among B
  samples of it; anchor (B, A, d_y), required with `anchor_inputs` (else unread)."""
  model = Denoiser(config, y.shape[-1])
  s = jnp.broadcast_to(jnp.asarray(s), y.shape[:1])
  one = lambda yy, ss, cc, aa: model.apply(params, yy, ss, cc, True, aa, method=Denoiser.denoise)
  if ctx.agent_valid.shape[0] == 1 and y.shape[0] > 1:
    shared = jax.tree_util.tree_map(lambda a: a[0], ctx)
    return jax.vmap(lambda yy, ss, aa: one(yy, ss, shared, aa))(y, s, anchor)
  return jax.vmap(one)(y, s, ctx, anchor)


def apply(params: Any, y: Array, s: Array, inputs: DenoiserInputs, config: DenoiserConfig,
          rng: Optional[Array] = None, anchor: Optional[Array] = None) -> Array:
  """Batched over the leading dim B of y (B, A, d_y) and inputs; s () or (B,);
  anchor (B, A, d_y), required with `anchor_inputs` (else unread). Dropout is on
  when `rng` is given.
  """
  model = Denoiser(config, y.shape[-1])
  s = jnp.broadcast_to(jnp.asarray(s), y.shape[:1])
  if rng is None:
    return jax.vmap(lambda yy, ss, ii, aa: model.apply(params, yy, ss, ii, True, aa))(y, s, inputs, anchor)
  keys = jax.random.split(rng, y.shape[0])
  return jax.vmap(lambda yy, ss, ii, kk, aa: model.apply(
      params, yy, ss, ii, deterministic=False, anchor=aa, rngs={"dropout": kk}))(y, s, inputs, keys, anchor)
