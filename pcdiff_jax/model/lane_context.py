"""Lane-relative inputs of each agent: where its lane is, and how far the road edges are.

The encoder's tokens say where an agent and the map pieces are, but the
denoiser has to infer from them a quantity it needs at every replan: how far
the agent is beside its lane and where that lane bends next. Closed-loop
rollouts drift right of the log by half a metre and under-steer on left
curves (measured with the v5 model, CHANGELOG.md): this module states those quantities
explicitly, computed from the scene features alone (no new data field):

  lanes ahead   for each look-ahead distance L in `LOOKAHEAD` (m), the lane
                centre point nearest the point L ahead of the agent (on the
                polylines' segments), among the segments that run within
                60 degrees of the agent's heading: its position (x, y) / 10 m and direction (cos, sin)
                in the agent's frame, and whether one was found within 6 m;
  road edges    the lateral distance (/ 10 m, clipped at 1) to the nearest
                road edge on the left and on the right, measured across the
                agent's heading (the point of each edge segment nearest the
                agent's lateral axis, within 4 m ahead or behind), and
                whether one was found.

Output (..., A, LANE_DIM) float32, zero for padded agents.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from pcdiff_jax.model.features import MapKind, SceneFeatures
from pcdiff_jax.sim.datatypes import Array

LOOKAHEAD = (0.0, 5.0, 10.0, 20.0, 40.0)   # m
_SCALE = 10.0                             # m
_MAX_LANE_GAP = 6.0                       # m, from the look-ahead point
_MIN_ALIGN = 0.5                          # cos 60 degrees
_EDGE_WINDOW = 4.0                        # m, along the agent's heading
# Map pieces searched per query (nearest piece centres first): every agent
# against every segment costs 9 ms per 65-agent scene on 2 CPU cores; the
# nearest pieces hold the answer (pieces are <= 20 m; tests/test_lane_context.py
# checks it against the exhaustive search on real and synthetic scenes).
_LANE_PIECES = 16
_EDGE_PIECES = 16
LANE_DIM = 5 * len(LOOKAHEAD) + 4


def _rotate(v: Array, agent_dir: Array) -> Array:
  """Scene-frame vectors (A, ..., 2) into each agent's frame (rotation only); agent_dir (A, 2)."""
  shape = (agent_dir.shape[0],) + (1,) * (v.ndim - 2)
  c, s = agent_dir[:, 0].reshape(shape), agent_dir[:, 1].reshape(shape)
  return jnp.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1]], -1)


def _nearest_pieces(rel_center: Array, ok: Array, query: Array, k: int) -> tuple[Array, Array]:
  """The k pieces (A, Q, k) whose centres (A, M, 2, agent frame) are nearest
  each query point (Q, 2), among `ok` (A, M); and whether each is `ok`."""
  d2 = jnp.sum((rel_center[:, None, :, :] - query[None, :, None, :]) ** 2, -1)   # (A, Q, M)
  d2 = jnp.where(ok[:, None, :], d2, jnp.inf)
  k = min(k, d2.shape[-1])
  neg, index = jax.lax.top_k(-d2, k)
  return index, jnp.isfinite(neg)


def _one_scene(feats: SceneFeatures) -> Array:
  """lane_inputs of one scene (no batch dims): (A, LANE_DIM)."""
  c, d = feats.map_dir[:, None, 0], feats.map_dir[:, None, 1]                 # (M, 1)
  px, py = feats.map_points[..., 0], feats.map_points[..., 1]              # (M, P)
  points = jnp.stack([feats.map_center[:, None, 0] + c * px - d * py,
                      feats.map_center[:, None, 1] + d * px + c * py], -1)    # (M, P, 2) scene frame
  lane = feats.map_valid & (feats.map_kind == MapKind.LANE)                  # (M,)
  edge = feats.map_valid & (feats.map_kind == MapKind.ROAD_EDGE)
  rel_center = _rotate(feats.map_center[None] - feats.agent_center[:, None], feats.agent_dir)  # (A, M, 2)
  # A piece's chord may point away while a segment of a curved piece is still aligned: only
  # pieces that run backwards are left out here; segments are tested one by one below.
  forward = jnp.sum(feats.map_dir[None] * feats.agent_dir[:, None], -1) >= 0.0   # (A, M)

  def segments(index):   # (A, ...) piece indices -> agent-frame segment ends (A, ..., P - 1, 2)
    centre = feats.agent_center.reshape((-1,) + (1,) * index.ndim + (2,))
    pts = _rotate(points[index] - centre, feats.agent_dir)
    return pts[..., :-1, :], pts[..., 1:, :]

  ahead = jnp.stack([jnp.asarray(LOOKAHEAD), jnp.zeros(len(LOOKAHEAD))], -1)   # (L, 2)
  index, ok = _nearest_pieces(rel_center, lane[None] & forward, ahead, _LANE_PIECES)   # (A, L, k)
  a, b = segments(index)                                                     # (A, L, k, S, 2)
  seg = b - a
  length2 = jnp.maximum(jnp.sum(seg ** 2, -1), 1e-9)
  heading = seg / jnp.sqrt(length2)[..., None]
  query = ahead[None, :, None, None, :]
  u = jnp.clip(jnp.sum((query - a) * seg, -1) / length2, 0.0, 1.0)
  point = a + u[..., None] * seg
  gap2 = jnp.sum((point - query) ** 2, -1)                                    # (A, L, k, S)
  gap2 = jnp.where(ok[..., None] & (heading[..., 0] >= _MIN_ALIGN), gap2, jnp.inf)
  flat = lambda v: v.reshape(v.shape[:2] + (-1,) + v.shape[4:])               # (A, L, k * S, ...)
  gap2, point, heading = flat(gap2), flat(point), flat(heading)
  best = jnp.argmin(gap2, -1)                                                # (A, L)
  found = jnp.take_along_axis(gap2, best[..., None], -1)[..., 0] <= _MAX_LANE_GAP ** 2
  at = lambda v: jnp.take_along_axis(v, best[..., None, None], -2)[..., 0, :]
  lanes = jnp.concatenate([jnp.where(found[..., None], at(point) / _SCALE, 0.0),
                           jnp.where(found[..., None], at(heading), 0.0),
                           found[..., None].astype(jnp.float32)], -1)        # (A, L, 5)

  # Road edges: the point of each edge segment nearest the agent's lateral axis (x = 0).
  index, ok = _nearest_pieces(rel_center, jnp.broadcast_to(edge[None], forward.shape),
                              jnp.zeros((1, 2)), _EDGE_PIECES)
  a, b = segments(index[:, 0])                                               # (A, k, S, 2)
  seg = b - a
  u = jnp.clip(-a[..., 0] * seg[..., 0] / jnp.where(jnp.abs(seg[..., 0]) > 1e-6, seg[..., 0] ** 2, jnp.inf),
               0.0, 1.0)
  beside = a + u[..., None] * seg
  near = ok[:, 0, :, None] & (jnp.abs(beside[..., 0]) <= _EDGE_WINDOW)      # (A, k, S)
  parts = [lanes.reshape(lanes.shape[0], -1)]
  for side in (1.0, -1.0):                                                   # left, right
    lateral = jnp.where(near & (side * beside[..., 1] > 0), side * beside[..., 1], jnp.inf)
    closest = jnp.min(lateral, (-1, -2))
    has = jnp.isfinite(closest)
    parts += [jnp.where(has, jnp.minimum(closest / _SCALE, 1.0), 1.0)[..., None],
              has[..., None].astype(jnp.float32)]
  out = jnp.concatenate(parts, -1)
  return jnp.where(feats.agent_valid[:, None], out, 0.0)


def zero_projection(d_model: int) -> dict:
  """Parameters of a zero-initialised Dense(LANE_DIM -> d_model): how a model
  trained without lane inputs gets them (`denoiser.with_new_inputs`,
  `encoder.with_new_inputs`) and still computes the same function."""
  return {"kernel": jnp.zeros((LANE_DIM, d_model), jnp.float32), "bias": jnp.zeros((d_model,), jnp.float32)}


def lane_inputs(feats: SceneFeatures) -> Array:
  """(..., A, LANE_DIM) lane-relative inputs of every agent (module doc)."""
  batch = feats.agent_valid.shape[:-1]
  if not batch:
    return _one_scene(feats)
  flat = jax.tree_util.tree_map(lambda v: v.reshape((-1,) + v.shape[len(batch):]), feats)
  out = jax.vmap(_one_scene)(flat)
  return out.reshape(batch + out.shape[1:])
