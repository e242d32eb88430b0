"""SIMPL-style scene encoder: instance tokens, relative pose edges, SFT layers, proposals.

Pipeline (one scene; `apply` maps over leading batch dims):

1. Agent net: each agent's history (H, AGENT_DIM) in its own frame ->
   residual 1-D convolutions over time -> [last step, masked max over steps]
   -> d. Map net: each piece's P points in its own frame -> P-1 pieces
   [midpoint, vector] -> PointNet (per-point MLP, concat with the max-pool,
   MLP, max-pool) -> d, plus embeddings of the WOMD type, the MapKind and the
   traffic light state. N = A + M tokens.
2. Relative pose encoding for a receiver i and a sender j, from the scene-
   frame centres c and unit directions q only (so the encoder is invariant to
   a rigid transform of the world): p_ij = c_j - c_i,
   r_ij = [|p_ij| / radius, cos, sin of angle(q_i, p_ij), cos, sin of
   angle(q_i, q_j)] -> MLP -> edge embedding e_ij.
3. Symmetric Fusion Transformer layers (SIMPL, post-norm):
   m_ij = ReLU(LN(W [e_ij, h_i, h_j])), computed as W_e e_ij + W_i h_i + W_j h_j
   (the same linear map, the node terms once per node);
   h_i <- LN(h_i + MHA(q = h_i, k = v = m_i.)), h_i <- LN(h_i + FFN(h_i));
   e_ij <- LN(e_ij + ReLU(LN(W_u m_ij))) (not in the last layer).
   Attention ignores padded senders; padded receivers give finite garbage
   that no valid token reads.
4. Head per agent: K mode embeddings -> a score each (softmax ->
   probabilities) and Bezier control points of degree n in the agent's frame,
   the first fixed at the origin (the agent's pose at t), so every proposal
   starts where the agent is. Trajectory = Bernstein basis at tau = s / T,
   s = 1..T, times the control points; yaw = direction of the curve's
   derivative (held at 0, the heading at t, where the curve is stationary).

Edges. `EncoderConfig.num_neighbors = k` gives each token
its k nearest tokens (by centre distance, itself included, padded ones
masked); k = 0 gives all N^2 pairs (broadcasts instead of gathers). Measured
on the 2-core CPU of these machines (shared with other jobs, so times vary by
up to 2x), jitted float32, one scene of the real sample with A = 64 agents and
M = 256 pieces (N = 320, all valid): temp memory from
`compiled.memory_analysis()` and the fastest wall time of 3-5 runs (the
range over repeated measurements where there were several).

  preset  edges        forward                 forward + backward
  cpu     all pairs    159 MB, 183-294 ms      1.1 GB,  0.96-1.6 s
  cpu     k = 32        16 MB,  17-24 ms       123 MB,  0.16-0.18 s
  paper   all pairs    316 MB, 1.78 s          4.2 GB,  8.3 s
  paper   k = 64        63 MB, 258 ms          822 MB,  1.36 s
  paper   k = 32        32 MB,  74 ms          429 MB,  0.37 s

(cpu: d = 64, 2 layers, 4 heads, 0.22 M parameters; paper: d = 128, 4
layers, 8 heads, 1.27 M parameters.) The cost is the per-edge matmuls (memory,
key, value and edge update: 4 d x d per edge and layer), so it scales with
N k. The presets use k nearest neighbours (tiny 16, cpu 32, paper 64): 5-10x
less memory and time than all pairs, which decides whether training batches
and closed-loop replanning fit on a CPU, while 64 neighbours still hold the
agents and map pieces within a few tens of metres of each token, and four
layers pass information further. SIMPL attends over all pairs; `k = 0` does
the same here, so the choice can be revisited once quality is measured.
"""
from __future__ import annotations

import math
from typing import Any, Optional

import chex
import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.config import EncoderConfig
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model import lane_context
from pcdiff_jax.model.features import SceneFeatures
from pcdiff_jax.sim.datatypes import Array

_NEG = -1e9            # attention logit of a masked sender
_MIN_SPEED_SQ = 1e-6   # (m per unit tau)^2 below which a proposal's yaw is held
_DIST_QUANTUM = 0.01   # m, resolution of the neighbour ranking
DT = 0.1               # s, the WOMD step
VX = features_lib.AGENT_CHANNELS.index("vel_x")


@struct.dataclass
class EncoderOutput:
  """Encoder outputs for one scene (any leading batch dims `...`).

  agent_tokens: (..., A, d), agent_valid: (..., A);
  map_tokens: (..., M, d), map_valid: (..., M): the scene context.
  trajectories: (..., A, K, T, 2) proposals in each agent's frame at t.
  yaws: (..., A, K, T) proposal headings in the agent's frame.
  control_points: (..., A, K, n + 1, 2) Bezier control points (first = 0).
  logits, probs: (..., A, K) mode scores and their softmax.
  Padded agents get all-zero proposals (and finite, meaningless scores).
  """
  agent_tokens: Array
  agent_valid: Array
  map_tokens: Array
  map_valid: Array
  trajectories: Array
  yaws: Array
  control_points: Array
  logits: Array
  probs: Array

  @property
  def context_tokens(self) -> Array:
    """(..., A + M, d) agent tokens then map tokens."""
    return jnp.concatenate([self.agent_tokens, self.map_tokens], axis=-2)

  @property
  def context_valid(self) -> Array:
    """(..., A + M) bool."""
    return jnp.concatenate([self.agent_valid, self.map_valid], axis=-1)


def proposals_to_scene(out: EncoderOutput, feats: SceneFeatures) -> tuple[Array, Array]:
  """Proposals in the scene frame: xy (..., A, K, T, 2), yaw (..., A, K, T)."""
  return features_lib.agent_to_scene(out.trajectories, out.yaws, feats)


def proposals_to_world(out: EncoderOutput, feats: SceneFeatures) -> tuple[Array, Array]:
  """Proposals in the world frame: xy (..., A, K, T, 2), yaw (..., A, K, T)."""
  return features_lib.agent_to_world(out.trajectories, out.yaws, feats)


# ----------------------------------------------------------------------------
# Bezier curves.


def bezier_basis(degree: int, horizon: int) -> tuple[np.ndarray, np.ndarray]:
  """Bernstein basis and its derivative at tau = s / T, s = 1..T.

  Returns: (T, n + 1) B with curve = B @ control points, and (T, n + 1) dB
  with d curve / d tau = dB @ control points.
  """
  tau = np.arange(1, horizon + 1, dtype=np.float64) / horizon
  n = degree
  basis = np.stack([math.comb(n, k) * tau ** k * (1 - tau) ** (n - k) for k in range(n + 1)], -1)
  lower = np.stack([math.comb(n - 1, k) * tau ** k * (1 - tau) ** (n - 1 - k)
                    for k in range(n)], -1)                 # (T, n)
  # d/dtau sum_k b_{k,n} P_k = n sum_k b_{k,n-1} (P_{k+1} - P_k)
  deriv = np.zeros((horizon, n + 1))
  deriv[:, 1:] += n * lower
  deriv[:, :-1] -= n * lower
  return basis.astype(np.float32), deriv.astype(np.float32)


def _heading(vel: Array) -> Array:
  """atan2 of (..., 2) with a finite gradient; 0 where the speed is ~0."""
  moving = jnp.sum(vel ** 2, axis=-1) > _MIN_SPEED_SQ
  safe = jnp.where(moving[..., None], vel, jnp.array([1.0, 0.0]))
  return jnp.where(moving, jnp.arctan2(safe[..., 1], safe[..., 0]), 0.0)


# ----------------------------------------------------------------------------
# Modules.


class AgentNet(nn.Module):
  """(A, H, AGENT_DIM) histories, (A, H) valid -> (A, d)."""
  d_model: int
  blocks: int

  @nn.compact
  def __call__(self, history: Array, valid: Array) -> Array:
    x = nn.relu(nn.LayerNorm()(nn.Dense(self.d_model)(history)))     # (A, H, d)
    for _ in range(self.blocks):                                      # layers, not agents
      y = nn.relu(nn.LayerNorm()(nn.Conv(self.d_model, (3,), padding="SAME")(x)))
      y = nn.LayerNorm()(nn.Conv(self.d_model, (3,), padding="SAME")(y))
      x = nn.relu(x + y)
    pooled = jnp.max(jnp.where(valid[..., None], x, -1e4), axis=-2)  # (A, d)
    pooled = jnp.where(jnp.any(valid, -1)[..., None], pooled, 0.0)
    out = nn.Dense(self.d_model)(jnp.concatenate([x[..., -1, :], pooled], -1))
    return nn.relu(nn.LayerNorm()(out))


class MapNet(nn.Module):
  """(M, P, 2) points in each piece's frame + categorical attributes -> (M, d)."""
  d_model: int

  @nn.compact
  def __call__(self, points: Array, types: Array, kind: Array, light: Array) -> Array:
    mid = 0.5 * (points[..., 1:, :] + points[..., :-1, :])
    vec = points[..., 1:, :] - points[..., :-1, :]
    x = jnp.concatenate([mid, vec], -1)                               # (M, P-1, 4)
    x = nn.relu(nn.LayerNorm()(nn.Dense(self.d_model)(x)))
    x = nn.Dense(self.d_model)(x)
    for _ in range(2):                                                # PointNet blocks
      pooled = jnp.broadcast_to(jnp.max(x, -2, keepdims=True), x.shape)
      x = nn.relu(nn.LayerNorm()(nn.Dense(self.d_model)(jnp.concatenate([x, pooled], -1))))
    x = jnp.max(x, axis=-2)                                           # (M, d)
    emb = lambda n, v: nn.Embed(n, self.d_model)(jnp.clip(v, 0, n - 1))
    x = x + emb(features_lib.NUM_MAP_TYPES, types) + emb(features_lib.NUM_MAP_KINDS, kind) \
        + emb(features_lib.NUM_LIGHT_STATES, light)
    return nn.relu(nn.LayerNorm()(nn.Dense(self.d_model)(x)))


def neighbours(centre: Array, valid: Array, k: int) -> tuple[Optional[Array], Array]:
  """Edge set: each receiver's senders (N, k) (None: all N, in order) and an (N, k) mask.

  k >= N or k == 0: all pairs, index None (edges are broadcasts, not
  gathers). Otherwise each token's k nearest tokens by centre distance
  (itself first); padded senders are masked.
  """
  n = centre.shape[0]
  if k <= 0 or k >= n:
    return None, jnp.broadcast_to(valid[None], (n, n))
  centre = jax.lax.stop_gradient(centre)                              # ranks only
  # x and y apart: faster on a CPU (docs/BENCHMARKS.md, "x and y apart").
  dx, dy = (centre[:, None, i] - centre[None, :, i] for i in (0, 1))
  dist = jnp.sqrt(dx ** 2 + dy ** 2)                                  # (N, N)
  # Rank on centimetres, ties by index: rounding noise cannot swap tokens at
  # the same distance (common in regular maps) in and out of the set.
  key = jnp.floor(dist / _DIST_QUANTUM + 0.5)
  key = jnp.where(valid[None], key, jnp.inf)
  key = jnp.where(jnp.eye(n, dtype=bool), -1.0, key)                  # self first
  neg, idx = jax.lax.top_k(-key, k)
  return idx, jnp.isfinite(neg) & valid[idx]


def senders(x: Array, idx: Optional[Array]) -> Array:
  """Per-edge sender values: x (N, ...) -> (N, k, ...), or (1, N, ...) for all pairs."""
  return x[None] if idx is None else x[idx]


def relative_pose(centre: Array, direction: Array, idx: Optional[Array], radius: float) -> Array:
  """(N, k, 5) [|p| / radius, cos, sin angle(q_i, p_ij), cos, sin angle(q_i, q_j)]."""
  # x and y apart (N, k): faster on a CPU (docs/BENCHMARKS.md, "x and y apart").
  px, py = (senders(centre[:, i], idx) - centre[:, None, i] for i in (0, 1))
  qx, qy = direction[:, None, 0], direction[:, None, 1]               # (N, 1)
  jx, jy = senders(direction[:, 0], idx), senders(direction[:, 1], idx)
  dist = jnp.sqrt(px ** 2 + py ** 2 + 1e-12)
  cos_a, sin_a = (qx * px + qy * py) / dist, (qx * py - qy * px) / dist
  cos_h, sin_h = qx * jx + qy * jy, qx * jy - qy * jx
  return jnp.stack(jnp.broadcast_arrays(dist / radius, cos_a, sin_a, cos_h, sin_h), -1)


class HeadProjection(nn.Module):
  """The kernel (d, heads, c) and bias (heads, c) of a per-head projection, the parameters
  `nn.DenseGeneral((heads, c))` would make under the same name (same tree, same init), for
  layers that apply them to a reduced input instead of every edge."""
  num_heads: int
  head_dim: int

  @nn.compact
  def __call__(self, in_dim: int) -> tuple[Array, Array]:
    shape = (self.num_heads, self.head_dim)
    # DenseGeneral initialises the flattened (in, heads * c) kernel, then reshapes it.
    init = lambda rng: nn.initializers.lecun_normal()(rng, (in_dim, math.prod(shape))).reshape((in_dim,) + shape)
    kernel = self.param("kernel", init)
    bias = self.param("bias", lambda rng: jnp.zeros(shape))
    return kernel, bias


class SFTLayer(nn.Module):
  """One Symmetric Fusion Transformer layer over a k-neighbour edge set.

  The key and value projections are linear in the edge memory m_ij, so they are applied once
  per receiver instead of once per edge: logits q_i . (W_k m_ij + b_k) = (W_k^T q_i) . m_ij +
  q_i . b_k, and sum_j w_ij (W_v m_ij + b_v) = W_v (sum_j w_ij m_ij) + b_v sum_j w_ij. The
  same function as projecting every edge (equal up to float rounding), with two of a layer's
  four d x d matmuls per edge gone (docs/BENCHMARKS.md, "WOSAC export: one job per core and the
  encoder's attention").
  """
  d_model: int
  num_heads: int
  ffn_multiplier: int
  update_edges: bool
  dropout: float

  @nn.compact
  def __call__(self, h: Array, e: Array, idx: Optional[Array], mask: Array,
               deterministic: bool):
    """h (N, d), e (N, k, d), idx (N, k) or None (all pairs), mask (N, k) -> (h, e)."""
    d, nh = self.d_model, self.num_heads
    c = d // nh
    drop = lambda x: nn.Dropout(self.dropout)(x, deterministic=deterministic)
    # W [e_ij, h_i, h_j] as W_e e_ij + W_i h_i + W_j h_j.
    hi = nn.Dense(d, use_bias=False, name="mem_i")(h)                 # (N, d)
    hj = nn.Dense(d, use_bias=False, name="mem_j")(h)                 # (N, d)
    mem = nn.Dense(d, name="mem_e")(e) + hi[:, None] + senders(hj, idx)  # (N, k, d)
    mem = nn.relu(nn.LayerNorm(name="mem_ln")(mem))
    q = nn.DenseGeneral((nh, c), name="query")(h)                     # (N, heads, c)
    key_w, key_b = HeadProjection(nh, c, name="key")(d)               # (d, heads, c), (heads, c)
    val_w, val_b = HeadProjection(nh, c, name="value")(d)
    q_mem = jnp.einsum("nhc,dhc->nhd", q, key_w)                       # (N, heads, d)
    logits = jnp.einsum("nhd,nkd->nhk", q_mem, mem) + jnp.einsum("nhc,hc->nh", q, key_b)[..., None]
    logits = jnp.where(mask[:, None], logits / math.sqrt(c), _NEG)     # (N, heads, k)
    weights = drop(jax.nn.softmax(logits, axis=-1))
    pooled = jnp.einsum("nhk,nkd->nhd", weights, mem)                  # (N, heads, d)
    att = jnp.einsum("nhd,dhc->nhc", pooled, val_w) + jnp.sum(weights, -1)[..., None] * val_b
    att = nn.DenseGeneral(d, axis=(-2, -1), name="out")(att)          # (N, d)
    h = nn.LayerNorm(name="ln_att")(h + drop(att))
    ffn = nn.Dense(d)(nn.relu(nn.Dense(self.ffn_multiplier * d)(h)))
    h = nn.LayerNorm(name="ln_ffn")(h + drop(ffn))
    if self.update_edges:
      upd = nn.relu(nn.LayerNorm(name="edge_ln_in")(nn.Dense(d, name="edge_upd")(mem)))
      e = nn.LayerNorm(name="edge_ln")(e + drop(upd))
    return h, e


class ProposalHead(nn.Module):
  """(A, d) agent tokens, (A,) forward speeds -> logits (A, K), control points
  (A, K, n + 1, 2) in the agent frame.

  P0 = 0 (the agent's position). With `anchor_velocity`, P1 = (v T dt / n, 0):
  the curve's derivative at the start is the agent's velocity (dt = horizon
  duration / T); the head predicts the remaining n - 1 points.
  """
  d_model: int
  num_modes: int
  degree: int
  scale: float = 1.0
  anchor_velocity: bool = True
  duration: float = 8.0            # s, the horizon

  @nn.compact
  def __call__(self, h: Array, speed: Array) -> tuple[Array, Array]:
    d, k = self.d_model, self.num_modes
    modes = nn.Dense(k * d)(h).reshape(h.shape[:-1] + (k, d))         # (A, K, d)
    modes = nn.relu(nn.LayerNorm()(modes))
    score = nn.Dense(d)(modes)
    logits = nn.Dense(1)(nn.relu(nn.LayerNorm()(score)))[..., 0]      # (A, K)
    reg = nn.relu(nn.LayerNorm()(nn.Dense(d)(modes)))
    num_free = self.degree - 1 if self.anchor_velocity else self.degree
    # The scale puts the initial control points at tens of metres, the size of
    # the targets, instead of ~1 m (a long first phase of training otherwise).
    free = self.scale * nn.Dense(2 * num_free)(reg)
    free = free.reshape(h.shape[:-1] + (k, num_free, 2))
    fixed = [jnp.zeros(free.shape[:-2] + (1, 2), free.dtype)]
    if self.anchor_velocity:
      p1 = jnp.stack([speed * self.duration / self.degree, jnp.zeros_like(speed)], -1)
      fixed.append(jnp.broadcast_to(p1[:, None, None, :], free.shape[:-2] + (1, 2)).astype(free.dtype))
    return logits, jnp.concatenate(fixed + [free], axis=-2)           # (A, K, n+1, 2)


class SceneEncoder(nn.Module):
  """SceneFeatures of one scene -> EncoderOutput."""
  config: EncoderConfig

  @nn.compact
  def __call__(self, feats: SceneFeatures, deterministic: bool = True) -> EncoderOutput:
    cfg = self.config
    d = cfg.d_model
    av, mv = feats.agent_valid, feats.map_valid
    # Zero every padded input so nothing from a padded slot reaches the net.
    hist = jnp.where(feats.agent_history_valid[..., None] & av[:, None, None],
                     feats.agent_history, 0.0)
    pts = jnp.where(mv[:, None, None], feats.map_points, 0.0)
    agents = AgentNet(d, cfg.agent_blocks, name="agent_net")(
        hist, feats.agent_history_valid & av[:, None])                 # (A, d)
    polys = MapNet(d, name="map_net")(pts, feats.map_types, feats.map_kind,
                                      feats.map_traffic_light)        # (M, d)
    lane = None
    if cfg.lane_inputs:   # zero-initialised: a model trained without them is unchanged at first
      lane = lane_context.lane_inputs(feats)                          # (A, LANE_DIM)
      agents = agents + nn.Dense(d, kernel_init=nn.initializers.zeros, name="in_lane")(lane)
    h = jnp.concatenate([agents, polys], 0)                           # (N, d)
    valid = jnp.concatenate([av, mv], 0)                              # (N,)
    centre = jnp.where(valid[:, None], jnp.concatenate([feats.agent_center, feats.map_center]), 0.0)
    direction = jnp.where(valid[:, None], jnp.concatenate([feats.agent_dir, feats.map_dir]),
                          jnp.array([1.0, 0.0]))

    idx, mask = neighbours(centre, valid, cfg.num_neighbors)          # (N, k)
    rpe = relative_pose(centre, direction, idx, cfg.radius)           # (N, k, 5)
    e = nn.relu(nn.LayerNorm()(nn.Dense(d)(rpe)))
    e = nn.relu(nn.LayerNorm()(nn.Dense(d)(e)))                       # (N, k, d)
    for layer in range(cfg.num_layers):                               # layers, not instances
      h, e = SFTLayer(d, cfg.num_heads, cfg.ffn_multiplier,
                      update_edges=layer < cfg.num_layers - 1, dropout=cfg.dropout,
                      name=f"sft_{layer}")(h, e, idx, mask, deterministic)
    num_agents = av.shape[0]
    agent_tokens, map_tokens = h[:num_agents], h[num_agents:]
    head_in = agent_tokens
    if lane is not None:   # a short path from where the lane goes to the proposals' shape
      head_in = head_in + nn.Dense(d, kernel_init=nn.initializers.zeros, name="head_lane")(lane)

    speed = hist[:, -1, VX]                                          # (A,) agent frame
    logits, ctrl = ProposalHead(d, cfg.num_modes, cfg.bezier_degree, cfg.proposal_scale,
                                cfg.anchor_velocity, cfg.horizon * DT,
                                name="head")(head_in, speed)
    basis, deriv = bezier_basis(cfg.bezier_degree, cfg.horizon)
    ctrl = jnp.where(av[:, None, None, None], ctrl, 0.0)              # padded agents stand still
    exact = jax.lax.Precision.HIGHEST   # metres: a GPU's TF32 default would round them by centimetres
    traj = jnp.einsum("ts,aksc->aktc", basis, ctrl, precision=exact)  # (A, K, T, 2)
    vel = jnp.einsum("ts,aksc->aktc", deriv, ctrl, precision=exact)   # (A, K, T, 2)
    return EncoderOutput(
        agent_tokens=agent_tokens, agent_valid=av, map_tokens=map_tokens, map_valid=mv,
        trajectories=traj, yaws=_heading(vel), control_points=ctrl, logits=logits,
        probs=jax.nn.softmax(logits, axis=-1))


# ----------------------------------------------------------------------------
# Pure entry points.


def _first(feats: SceneFeatures) -> SceneFeatures:
  batch = feats.batch_shape
  return jax.tree_util.tree_map(lambda x: x[(0,) * len(batch)], feats)


def init(rng: Array, feats: SceneFeatures, config: EncoderConfig) -> Any:
  """Parameters of the encoder for features of this padded size (batched or not)."""
  # Jitted: an eager init compiles every op on its own (tens of seconds on CPU).
  return jax.jit(SceneEncoder(config).init)(rng, _first(feats))


def with_new_inputs(params: Any, config: EncoderConfig) -> Any:
  """Parameters of an encoder trained without the optional inputs that
  `config` turns on (`lane_inputs`), extended by their zero-initialised
  projections: the extended encoder computes the same function until trained."""
  inner = params["params"]
  if config.lane_inputs:
    inner = {**inner, **{name: lane_context.zero_projection(config.d_model)
                         for name in ("in_lane", "head_lane") if name not in inner}}
  return {**params, "params": inner}


def apply(params: Any, feats: SceneFeatures, config: EncoderConfig,
          rng: Optional[Array] = None) -> EncoderOutput:
  """Runs the encoder on SceneFeatures with any leading batch dims.

  Dropout is on when `rng` is given (training), off otherwise.
  Returns an EncoderOutput with the same batch dims.
  """
  batch = feats.batch_shape
  a, m = feats.num_agents, feats.num_polylines
  chex.assert_shape(feats.agent_center, batch + (a, 2))
  chex.assert_shape(feats.map_center, batch + (m, 2))
  model = SceneEncoder(config)
  if rng is None:
    fn = lambda f: model.apply(params, f, deterministic=True)
    for _ in batch:
      fn = jax.vmap(fn)
    return fn(feats)
  flat = jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[len(batch):]), feats)
  count = flat.agent_valid.shape[0]
  rngs = jax.random.split(rng, count)
  out = jax.vmap(lambda f, r: model.apply(params, f, deterministic=False,
                                          rngs={"dropout": r}))(flat, rngs)
  return jax.tree_util.tree_map(lambda x: x.reshape(batch + x.shape[1:]), out)
