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


def _rotate(vx: Array, vy: Array, agent_dir: Array) -> tuple[Array, Array]:
  """Scene-frame vectors (A, ...) x and y into each agent's frame (rotation only); agent_dir (A, 2).

  Coordinates travel as separate arrays here: XLA on a CPU is several times slower on arrays
  that end in a size-2 axis (docs/BENCHMARKS.md, "x and y apart")."""
  shape = (agent_dir.shape[0],) + (1,) * (vx.ndim - 1)
  c, s = agent_dir[:, 0].reshape(shape), agent_dir[:, 1].reshape(shape)
  return c * vx + s * vy, -s * vx + c * vy


def _nearest_pieces(rel_x: Array, rel_y: Array, ok: Array, query_x: Array, query_y: Array,
                    k: int) -> tuple[Array, Array]:
  """The k pieces (A, Q, k) whose centres (rel_x, rel_y: (A, M), agent frame) are nearest
  each query point (query_x, query_y: (Q,)), among `ok` (A, M); and whether each is `ok`."""
  d2 = (rel_x[:, None] - query_x[None, :, None]) ** 2 + (rel_y[:, None] - query_y[None, :, None]) ** 2  # (A, Q, M)
  d2 = jnp.where(ok[:, None, :], d2, jnp.inf)
  k = min(k, d2.shape[-1])
  neg, index = jax.lax.top_k(-d2, k)
  return index, jnp.isfinite(neg)


def _one_scene(feats: SceneFeatures) -> Array:
  """lane_inputs of one scene (no batch dims): (A, LANE_DIM)."""
  c, d = feats.map_dir[:, None, 0], feats.map_dir[:, None, 1]                 # (M, 1)
  px, py = feats.map_points[..., 0], feats.map_points[..., 1]              # (M, P)
  points_x = feats.map_center[:, None, 0] + c * px - d * py                 # (M, P) scene frame
  points_y = feats.map_center[:, None, 1] + d * px + c * py
  lane = feats.map_valid & (feats.map_kind == MapKind.LANE)                  # (M,)
  edge = feats.map_valid & (feats.map_kind == MapKind.ROAD_EDGE)
  agent_x, agent_y = feats.agent_center[:, 0], feats.agent_center[:, 1]      # (A,)
  rel_x, rel_y = _rotate(feats.map_center[None, :, 0] - agent_x[:, None],
                         feats.map_center[None, :, 1] - agent_y[:, None], feats.agent_dir)   # (A, M)
  # A piece's chord may point away while a segment of a curved piece is still aligned: only
  # pieces that run backwards are left out here; segments are tested one by one below.
  forward = (feats.map_dir[None, :, 0] * feats.agent_dir[:, None, 0]
             + feats.map_dir[None, :, 1] * feats.agent_dir[:, None, 1]) >= 0.0   # (A, M)

  def segments(index):   # (A, ...) piece indices -> agent-frame segment starts and ends, x and y (A, ..., P - 1)
    shape = (-1,) + (1,) * index.ndim
    x, y = _rotate(points_x[index] - agent_x.reshape(shape), points_y[index] - agent_y.reshape(shape),
                   feats.agent_dir)
    return x[..., :-1], y[..., :-1], x[..., 1:], y[..., 1:]

  ahead = jnp.asarray(LOOKAHEAD)                                             # (L,): points (L, 0)
  index, ok = _nearest_pieces(rel_x, rel_y, lane[None] & forward, ahead, jnp.zeros_like(ahead),
                              _LANE_PIECES)                                  # (A, L, k)
  ax, ay, bx, by = segments(index)                                           # (A, L, k, S)
  sx, sy = bx - ax, by - ay
  length2 = jnp.maximum(sx ** 2 + sy ** 2, 1e-9)
  hx, hy = sx / jnp.sqrt(length2), sy / jnp.sqrt(length2)
  qx = ahead[None, :, None, None]
  u = jnp.clip(((qx - ax) * sx - ay * sy) / length2, 0.0, 1.0)
  point_x, point_y = ax + u * sx, ay + u * sy
  gap2 = (point_x - qx) ** 2 + point_y ** 2                                  # (A, L, k, S)
  gap2 = jnp.where(ok[..., None] & (hx >= _MIN_ALIGN), gap2, jnp.inf)
  flat = lambda v: v.reshape(v.shape[:2] + (-1,))                            # (A, L, k * S)
  best = jnp.argmin(flat(gap2), -1)                                          # (A, L)
  at = lambda v: jnp.take_along_axis(flat(v), best[..., None], -1)[..., 0]   # (A, L)
  found = at(gap2) <= _MAX_LANE_GAP ** 2
  lanes = jnp.stack([jnp.where(found, at(point_x) / _SCALE, 0.0), jnp.where(found, at(point_y) / _SCALE, 0.0),
                     jnp.where(found, at(hx), 0.0), jnp.where(found, at(hy), 0.0),
                     found.astype(jnp.float32)], -1)                         # (A, L, 5)

  # Road edges: the point of each edge segment nearest the agent's lateral axis (x = 0).
  index, ok = _nearest_pieces(rel_x, rel_y, jnp.broadcast_to(edge[None], forward.shape),
                              jnp.zeros(1), jnp.zeros(1), _EDGE_PIECES)
  ax, ay, bx, by = segments(index[:, 0])                                     # (A, k, S)
  sx, sy = bx - ax, by - ay
  u = jnp.clip(-ax * sx / jnp.where(jnp.abs(sx) > 1e-6, sx ** 2, jnp.inf), 0.0, 1.0)
  beside_x, beside_y = ax + u * sx, ay + u * sy
  near = ok[:, 0, :, None] & (jnp.abs(beside_x) <= _EDGE_WINDOW)            # (A, k, S)
  parts = [lanes.reshape(lanes.shape[0], -1)]
  for side in (1.0, -1.0):                                                   # left, right
    lateral = jnp.where(near & (side * beside_y > 0), side * beside_y, jnp.inf)
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
