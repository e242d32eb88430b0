"""Scene instances for the encoder: agents and map polylines, fixed-size and masked.

`scene_features(state, config)` reads a `SimulatorState` at its own replanning
step t = `state.timestep` (not only the dataset's current step 10):

- Agents: up to A objects valid at t, the SDC first, then nearest the SDC
  (the same ranking as `sim.selection.nearest_to_sdc(..., include_sdc=True)`).
  Their last H steps (t-H+1 .. t) come from `sim_trajectory`, which in closed
  loop holds the simulated past. Each history is in the agent's own frame:
  origin at its position at t, x along its heading at t.
- Map: lane centres (WOMD types 1-3), road lines (5-13), road edges (14-16),
  stop signs (17), crosswalks (18) and speed bumps (19). Each polyline (a
  contiguous run of one roadgraph `ids`) is cut into n = ceil(length / L)
  pieces of equal arc length, each resampled to P points by linear
  interpolation over arc length, so the resampled points lie on the original
  polyline. The M pieces nearest the SDC (by their closest roadgraph point)
  are kept, in roadgraph order. Each piece is in its own frame: origin at the mean of its P
  points, x along first -> last point. Lane pieces carry the state of the
  traffic light whose `lane_ids` matches their `ids` at step t.
- Every instance has a centre and a unit direction in the scene frame, the
  SDC's pose at t, so every feature is invariant to a rigid transform of the
  world (up to float32 rounding).

Shapes are static: the roadgraph (up to 30000 points) is cut into pieces with
cumulative sums and `jax.ops.segment_min` over one candidate slot per point;
`lax.top_k` keeps the nearest pieces; a fixed-iteration bisection finds the
resampling points. No Python loop over agents or polylines, and one trace
serves every scene of the same padded sizes. Functions take one scene;
`scene_features` maps over any leading batch dims with `vmap`.

Letters: O objects, T timesteps, R roadgraph points, L lights, A agents,
H history steps, M map pieces, P points per piece.
"""
from __future__ import annotations

import enum
import math
from typing import Optional

import chex
import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.config import FeaturesConfig
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState, current_traffic_lights, is_lane_center

# Channels of `SceneFeatures.agent_history`, in order.
AGENT_CHANNELS = ("x", "y", "dx", "dy", "cos_yaw", "sin_yaw", "vel_x", "vel_y",
                  "length", "width", "is_vehicle", "is_pedestrian", "is_cyclist", "valid")
AGENT_DIM = len(AGENT_CHANNELS)
NUM_MAP_TYPES = 20          # WOMD roadgraph codes 0..19
NUM_LIGHT_STATES = 10       # 0: no light; 1 + TrafficLightState (0..8)
_DIST_QUANTUM = 0.01        # m; ranking ties within it are broken by index (stable under rounding)
_OTHERS_RANK = 1e7          # m; added to the distance of objects outside `keep` in select_agents


class MapKind(enum.IntEnum):
  """Instance class of a map piece."""
  LANE = 0
  ROAD_LINE = 1
  ROAD_EDGE = 2
  STOP_SIGN = 3
  CROSSWALK = 4
  SPEED_BUMP = 5


NUM_MAP_KINDS = len(MapKind)


@struct.dataclass
class SceneFeatures:
  """Encoder inputs for one scene (any leading batch dims `...`).

  Agents, (..., A, ...):
    agent_history: (..., A, H, AGENT_DIM) float32 in the agent's frame at t,
      channels `AGENT_CHANNELS`: position, displacement from the previous
      step (0 at the first valid one), heading cos/sin relative to the heading
      at t, velocity, length, width, type one-hot, valid. Zero where invalid.
    agent_history_valid: (..., A, H) bool.
    agent_valid: (..., A) bool: a real agent, valid at t.
    agent_index: (..., A) int32 object slot (in range even where padded).
    agent_types: (..., A) int32 ObjectType codes (0 where padded).
    agent_center, agent_dir: (..., A, 2) position and unit heading at t in
      the scene frame.
  Map pieces, (..., M, ...):
    map_points: (..., M, P, 2) float32 in the piece's frame.
    map_valid: (..., M) bool.
    map_types: (..., M) int32 WOMD roadgraph code (0 where padded).
    map_kind: (..., M) int32 MapKind.
    map_traffic_light: (..., M) int32: 0 no light, else 1 + TrafficLightState.
    map_ids: (..., M) int32 roadgraph polyline id (-1 where padded).
    map_center, map_dir: (..., M, 2) in the scene frame.
  Frame:
    scene_xy: (..., 2), scene_yaw: (...): the world pose of the scene frame
      (the SDC at t). timestep: (...) int32, t.
  """
  agent_history: Array
  agent_history_valid: Array
  agent_valid: Array
  agent_index: Array
  agent_types: Array
  agent_center: Array
  agent_dir: Array
  map_points: Array
  map_valid: Array
  map_types: Array
  map_kind: Array
  map_traffic_light: Array
  map_ids: Array
  map_center: Array
  map_dir: Array
  scene_xy: Array
  scene_yaw: Array
  timestep: Array

  @property
  def num_agents(self) -> int:
    return self.agent_valid.shape[-1]

  @property
  def num_polylines(self) -> int:
    return self.map_valid.shape[-1]

  @property
  def batch_shape(self) -> tuple[int, ...]:
    return tuple(self.agent_valid.shape[:-1])

  @property
  def agent_yaw(self) -> Array:
    """(..., A) heading at t in the scene frame."""
    return jnp.arctan2(self.agent_dir[..., 1], self.agent_dir[..., 0])


# ----------------------------------------------------------------------------
# Frames.


def _rotate(v: Array, cos: Array, sin: Array) -> Array:
  """Rotates (..., 2) vectors by the angle with (...) `cos`, `sin`."""
  return jnp.stack([cos * v[..., 0] - sin * v[..., 1], sin * v[..., 0] + cos * v[..., 1]], -1)


def agent_to_scene(xy: Array, yaw: Array, features: SceneFeatures) -> tuple[Array, Array]:
  """Agent-frame points and headings -> scene frame.

  Args: xy (..., A, *X, 2), yaw (..., A, *X) in each agent's frame at t (e.g.
    proposals (..., A, K, T, 2)); `features` with batch dims `...`.
  Returns: the same shapes in the scene frame.
  """
  extra = xy.ndim - features.agent_center.ndim          # len(X)
  expand = lambda a: a.reshape(a.shape + (1,) * extra)
  cos, sin = expand(features.agent_dir[..., 0]), expand(features.agent_dir[..., 1])
  centre = features.agent_center.reshape(
      features.agent_center.shape[:-1] + (1,) * extra + (2,))
  out_xy = _rotate(xy, cos, sin) + centre
  out_yaw = geometry.wrap_angle(yaw + jnp.arctan2(sin, cos))
  return out_xy, out_yaw


def scene_to_world(xy: Array, yaw: Array, features: SceneFeatures) -> tuple[Array, Array]:
  """Scene-frame points (..., *X, 2) and headings (..., *X) -> world frame."""
  extra = xy.ndim - 1 - features.scene_yaw.ndim
  s_yaw = features.scene_yaw.reshape(features.scene_yaw.shape + (1,) * extra)
  s_xy = features.scene_xy.reshape(features.scene_xy.shape[:-1] + (1,) * extra + (2,))
  out_xy = _rotate(xy, jnp.cos(s_yaw), jnp.sin(s_yaw)) + s_xy
  return out_xy, geometry.wrap_angle(yaw + s_yaw)


def agent_to_world(xy: Array, yaw: Array, features: SceneFeatures) -> tuple[Array, Array]:
  """Agent-frame points (..., A, *X, 2) and headings (..., A, *X) -> world frame."""
  return scene_to_world(*agent_to_scene(xy, yaw, features), features)


def scatter_to_objects(values: Array, features: SceneFeatures, num_objects: int,
                       fill: float = 0.0) -> Array:
  """Per-agent values (A, ...) -> per-object (O, ...) via `agent_index`.

  Objects that are not a valid agent get `fill`. One scene (vmap for batches).
  """
  idx = jnp.where(features.agent_valid, features.agent_index, num_objects)  # padded: dropped
  out = jnp.full((num_objects,) + values.shape[1:], fill, values.dtype)
  return out.at[idx].set(values, mode="drop")


def hide_history(features: SceneFeatures, keep_steps: int, agents: Optional[Array] = None) -> SceneFeatures:
  """`features` (..., A, H, ...) with each agent's history before its last `keep_steps` steps
  invalid and zeroed, for the agents (..., A) where `agents` is true (every agent when None).
  Both the policy's `encoder_history` and the encoder's history dropout in training use it."""
  h = features.agent_history_valid.shape[-1]
  hidden = jnp.arange(h) < h - keep_steps                                    # (H,)
  if agents is not None:
    hidden = agents[..., None] & hidden                                      # (..., A, H)
  return features.replace(agent_history_valid=features.agent_history_valid & ~hidden,
                          agent_history=jnp.where(hidden[..., None], 0.0, features.agent_history))


# ----------------------------------------------------------------------------
# Agents.


def _scene_pose(state: SimulatorState) -> tuple[Array, Array]:
  """World position (2,) and heading () of the SDC at t (zeros without an SDC)."""
  cur = state.current_sim_trajectory                       # (O, 1)
  is_sdc = state.object_metadata.is_sdc
  has = jnp.any(is_sdc)
  i = jnp.argmax(is_sdc)
  xy = jnp.where(has, cur.xy[i, 0], 0.0)
  yaw = jnp.where(has, cur.yaw[i, 0], 0.0)
  return xy, yaw


def select_agents(state: SimulatorState, max_agents: int,
                  keep: Optional[Array] = None) -> tuple[Array, Array]:
  """Object slots of the agents to model: the SDC first, then the objects of
  `keep` (O,) bool (the agents a policy controls: they are never dropped for a
  closer newcomer), then the others, nearest the SDC first within each group.

  Without `keep`, the same set as `sim.selection.nearest_to_sdc(state,
  max_agents, include_sdc=True)`, in rank order. Only objects valid at the
  current step are chosen. One scene.
  Returns: index (A,) int32 (in range everywhere), valid (A,) bool.
  """
  cur = state.current_sim_trajectory
  valid = cur.valid[:, 0]
  is_sdc = state.object_metadata.is_sdc
  xy = cur.xy[:, 0]                                        # (O, 2)
  sdc_xy = jnp.sum(jnp.where(is_sdc[:, None], xy, 0.0), axis=0)
  dist = jnp.linalg.norm(xy - sdc_xy, axis=-1)
  if keep is not None:   # a group rank below every distance keeps them ahead of the others
    dist = jnp.where(keep, dist, dist + _OTHERS_RANK)
  dist = jnp.where(valid, dist, jnp.inf)
  dist = jnp.where(is_sdc & valid, -1.0, dist)
  order = jnp.argsort(dist, stable=True)
  num_objects = dist.shape[0]
  n = min(max_agents, num_objects)
  index = jnp.zeros((max_agents,), jnp.int32).at[:n].set(order[:n].astype(jnp.int32))
  ok = jnp.zeros((max_agents,), bool).at[:n].set(jnp.isfinite(dist[order[:n]]))
  return index, ok


def _agent_features(state: SimulatorState, index: Array, valid: Array, history: int,
                    scene_xy: Array, scene_yaw: Array):
  traj = state.sim_trajectory
  t = state.timestep
  steps = t - history + 1 + jnp.arange(history)             # (H,)
  in_range = steps >= 0
  steps = jnp.clip(steps, 0, traj.num_timesteps - 1)
  take = lambda a: a[index][:, steps]                       # (A, H)
  x, y, yaw = take(traj.x), take(traj.y), take(traj.yaw)
  vx, vy = take(traj.vel_x), take(traj.vel_y)
  length, width = take(traj.length), take(traj.width)
  hv = take(traj.valid) & in_range[None] & valid[:, None]   # (A, H)

  xy = jnp.stack([x, y], -1)                                # (A, H, 2)
  origin, yaw_t = xy[:, -1], yaw[:, -1]                     # (A, 2), (A,)
  pos = geometry.to_local(xy, origin[:, None], yaw_t[:, None])
  c, s = jnp.cos(yaw_t)[:, None], jnp.sin(yaw_t)[:, None]
  vel = _rotate(jnp.stack([vx, vy], -1), c, -s)             # rotate by -yaw_t
  dyaw = yaw - yaw_t[:, None]
  prev_ok = jnp.concatenate([jnp.zeros_like(hv[:, :1]), hv[:, :-1]], axis=1)
  disp = pos - jnp.concatenate([pos[:, :1], pos[:, :-1]], axis=1)
  disp = jnp.where((hv & prev_ok)[..., None], disp, 0.0)
  types = jnp.where(valid, state.object_metadata.object_types[index], 0)
  onehot = jnp.stack([types == ObjectType.VEHICLE, types == ObjectType.PEDESTRIAN,
                      types == ObjectType.CYCLIST], -1).astype(jnp.float32)   # (A, 3)
  onehot = jnp.broadcast_to(onehot[:, None], hv.shape + (3,))
  hist = jnp.concatenate([
      pos, disp, jnp.cos(dyaw)[..., None], jnp.sin(dyaw)[..., None], vel,
      length[..., None], width[..., None], onehot, hv[..., None].astype(jnp.float32)], -1)
  hist = jnp.where(hv[..., None], hist, 0.0)                # (A, H, AGENT_DIM)

  centre = geometry.to_local(origin, scene_xy, scene_yaw)
  rel = yaw_t - scene_yaw
  direction = jnp.stack([jnp.cos(rel), jnp.sin(rel)], -1)
  centre = jnp.where(valid[:, None], centre, 0.0)
  direction = jnp.where(valid[:, None], direction, 0.0)
  return hist, hv, types, centre, direction


# ----------------------------------------------------------------------------
# Map.


def map_kind_of(types: Array) -> Array:
  """(...) MapKind of WOMD roadgraph codes; -1 for codes that are not kept."""
  kind = jnp.full(types.shape, -1, jnp.int32)
  kind = jnp.where(is_lane_center(types), MapKind.LANE, kind)
  kind = jnp.where((types >= 5) & (types <= 13), MapKind.ROAD_LINE, kind)
  kind = jnp.where((types >= 14) & (types <= 16), MapKind.ROAD_EDGE, kind)
  kind = jnp.where(types == 17, MapKind.STOP_SIGN, kind)
  kind = jnp.where(types == 18, MapKind.CROSSWALK, kind)
  kind = jnp.where(types == 19, MapKind.SPEED_BUMP, kind)
  return kind


def _segmented_cumsum(values: Array, starts: Array) -> Array:
  """Inclusive cumulative sum that restarts where `starts` (R,) is True.

  Sums stay as small as one polyline's length, so float32 rounding does not
  grow with the size of the map.
  """
  def combine(a, b):
    fa, va = a
    fb, vb = b
    return fa | fb, jnp.where(fb, vb, va + vb)
  return jax.lax.associative_scan(combine, (starts, values))[1]


@struct.dataclass
class _RoadgraphArcs:
  """Per-point arc-length bookkeeping of the kept roadgraph points, each (R,)."""
  keep: Array          # point belongs to a kept polyline
  arc: Array           # arc length from the polyline's first point, m
  first: Array         # index of the polyline's first point
  last: Array          # index of the polyline's last point
  piece: Array         # index of the piece of its polyline that holds the point
  piece_len: Array     # arc length of each piece of the polyline, m
  slot: Array          # candidate piece slot in [0, R), R where not kept


def _roadgraph_arcs(state: SimulatorState, segment_length: float) -> _RoadgraphArcs:
  rg = state.roadgraph_points
  r = rg.num_points
  idx = jnp.arange(r)
  keep = rg.valid & (map_kind_of(rg.types) >= 0)
  # Polylines are contiguous runs of one id; a run starts where the id changes.
  same_prev = jnp.concatenate([jnp.zeros((1,), bool),
                               (rg.ids[1:] == rg.ids[:-1]) & keep[1:] & keep[:-1]])
  same_next = jnp.concatenate([same_prev[1:], jnp.zeros((1,), bool)])
  starts = keep & ~same_prev
  xy = rg.xy
  step = jnp.linalg.norm(xy - jnp.concatenate([xy[:1], xy[:-1]]), axis=-1)
  step = jnp.where(same_prev, step, 0.0)
  arc = _segmented_cumsum(step, starts)                      # (R,)
  first = jax.lax.cummax(jnp.where(starts, idx, 0))
  last = jax.lax.cummin(jnp.where(keep & ~same_next, idx, r - 1), reverse=True)
  total = arc[last]
  n_pieces = jnp.maximum(jnp.ceil(total / segment_length), 1.0)
  piece_len = total / n_pieces
  piece = jnp.floor(arc / jnp.maximum(piece_len, 1e-6))
  piece = jnp.clip(piece, 0.0, n_pieces - 1.0).astype(jnp.int32)
  prev_piece = jnp.concatenate([piece[:1], piece[:-1]])
  new_slot = starts | (same_prev & (piece != prev_piece))
  slot = jnp.cumsum(new_slot.astype(jnp.int32)) - 1
  slot = jnp.where(keep, slot, r)                            # r: out of range, dropped
  return _RoadgraphArcs(keep=keep, arc=arc, first=first, last=last, piece=piece,
                        piece_len=piece_len, slot=slot)


def _resample(arc: Array, xy: Array, first: Array, last: Array, query: Array) -> Array:
  """Points at arc lengths `query` (M, P) along polylines [first, last] (M,).

  Bisection with a fixed number of steps finds the largest j in [first,
  last] with arc[j] <= query, then interpolates linearly to j + 1.
  Returns (M, P, 2).
  """
  r = arc.shape[0]
  lo = jnp.broadcast_to(first[:, None], query.shape)
  hi = jnp.broadcast_to(last[:, None], query.shape)

  def body(_, bounds):
    lo, hi = bounds
    mid = (lo + hi + 1) // 2
    ok = arc[mid] <= query
    return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid - 1)

  lo, _ = jax.lax.fori_loop(0, max(1, math.ceil(math.log2(r))) + 1, body, (lo, hi))
  nxt = jnp.minimum(lo + 1, last[:, None])
  span = arc[nxt] - arc[lo]
  frac = jnp.clip((query - arc[lo]) / jnp.where(span > 0, span, 1.0), 0.0, 1.0)
  frac = jnp.where(span > 0, frac, 0.0)
  return xy[lo] + frac[..., None] * (xy[nxt] - xy[lo])


MAP_ANCHORS = ("sdc", "agents")


def _map_anchor_distance(rg_xy: Array, scene_xy: Array, anchor_xy: Array,
                         anchor_valid: Array, anchor: str) -> Array:
  """(R,) the distance that ranks map points for the crop: to the SDC
  ("sdc"), or to the nearest modelled agent ("agents": every agent keeps the
  map around it however far from the SDC, so a smaller crop still covers a
  spread-out scene)."""
  if anchor == "sdc":
    return jnp.linalg.norm(rg_xy - scene_xy, axis=-1)
  if anchor != "agents":
    raise ValueError(f"unknown map_anchor {anchor!r}; choose one of {list(MAP_ANCHORS)}")
  # A loop over the agents on (R,) x and y, one square root after the min: no (R, A) array,
  # which XLA does not fuse inside the closed loop's scan (docs/BENCHMARKS.md, "The map crop
  # anchored on the agents").
  x, y = rg_xy[:, 0], rg_xy[:, 1]

  def nearer(i, d2):
    dx, dy = x - anchor_xy[i, 0], y - anchor_xy[i, 1]
    return jnp.where(anchor_valid[i], jnp.minimum(d2, dx * dx + dy * dy), d2)

  return jnp.sqrt(jax.lax.fori_loop(0, anchor_xy.shape[0], nearer, jnp.full(x.shape, jnp.inf)))


def _map_features(state: SimulatorState, config: FeaturesConfig, scene_xy: Array,
                  scene_yaw: Array, anchor_xy: Array, anchor_valid: Array):
  rg = state.roadgraph_points
  r = rg.num_points
  m, p = config.max_polylines, config.points_per_polyline
  arcs = _roadgraph_arcs(state, config.segment_length)
  idx = jnp.arange(r)
  # One candidate slot per point is enough: a piece holds at least one point.
  first_point = jax.ops.segment_min(idx, arcs.slot, num_segments=r)       # (R,)
  dist = _map_anchor_distance(rg.xy, scene_xy, anchor_xy, anchor_valid, config.map_anchor)
  piece_dist = jax.ops.segment_min(jnp.where(arcs.keep, dist, jnp.inf), arcs.slot,
                                   num_segments=r)                        # (R,), inf if empty
  # Rank on centimetres so that rounding noise cannot reorder near-ties.
  key = -jnp.floor(piece_dist / _DIST_QUANTUM + 0.5)
  if m > r:
    key = jnp.concatenate([key, jnp.full((m - r,), -jnp.inf)])
  _, chosen = jax.lax.top_k(key, m)                                       # (M,)
  # Roadgraph order, not rank order: rounding noise can swap the ranks of
  # pieces at about the same distance, but not their slots.
  chosen = jnp.sort(jnp.where(jnp.isfinite(key[chosen]) & (chosen < r), chosen, r))
  valid = chosen < r
  fp = jnp.clip(first_point[jnp.clip(chosen, 0, r - 1)], 0, r - 1)       # (M,)

  first, last = arcs.first[fp], arcs.last[fp]
  start = arcs.piece[fp].astype(jnp.float32) * arcs.piece_len[fp]
  u = jnp.linspace(0.0, 1.0, p)
  query = start[:, None] + u[None] * arcs.piece_len[fp][:, None]          # (M, P)
  pts = _resample(arcs.arc, rg.xy, first, last, query)                    # (M, P, 2) world

  centre = jnp.mean(pts, axis=1)                                          # (M, 2)
  tangent = pts[:, -1] - pts[:, 0]
  tlen = jnp.linalg.norm(tangent, axis=-1, keepdims=True)
  pdir = rg.dir_xy[fp]
  plen = jnp.linalg.norm(pdir, axis=-1, keepdims=True)
  scene_x = jnp.stack([jnp.cos(scene_yaw), jnp.sin(scene_yaw)])
  # Degenerate pieces (a stop sign, a closed loop): the point's stored
  # direction, else the scene's x axis; both turn with the world.
  direction = jnp.where(tlen > 1e-3, tangent / jnp.maximum(tlen, 1e-3),
                        jnp.where(plen > 0.5, pdir / jnp.maximum(plen, 0.5), scene_x))
  yaw = jnp.arctan2(direction[:, 1], direction[:, 0])                     # (M,)
  local = geometry.to_local(pts, centre[:, None], yaw[:, None])           # (M, P, 2)

  types = rg.types[fp]
  ids = rg.ids[fp]
  lights = current_traffic_lights(state)                                  # (L, 1)
  match = ((ids[:, None] == lights.lane_ids[None, :, 0]) & lights.valid[None, :, 0]
           & is_lane_center(types)[:, None])                              # (M, L)
  light_state = lights.state[jnp.argmax(match, axis=1), 0]
  light = jnp.where(jnp.any(match, axis=1), 1 + light_state, 0)

  centre_s = geometry.to_local(centre, scene_xy, scene_yaw)
  dir_s = _rotate(direction, jnp.cos(scene_yaw), -jnp.sin(scene_yaw))
  v2 = valid[:, None]
  return dict(
      map_points=jnp.where(v2[..., None], local, 0.0),
      map_valid=valid,
      map_types=jnp.where(valid, types, 0).astype(jnp.int32),
      map_kind=jnp.where(valid, map_kind_of(types), 0).astype(jnp.int32),
      map_traffic_light=jnp.where(valid, light, 0).astype(jnp.int32),
      map_ids=jnp.where(valid, ids, -1).astype(jnp.int32),
      map_center=jnp.where(v2, centre_s, 0.0),
      map_dir=jnp.where(v2, dir_s, 0.0))


# ----------------------------------------------------------------------------
# Entry point.


def _scene_features_one(state: SimulatorState, config: FeaturesConfig,
                        keep: Optional[Array] = None) -> SceneFeatures:
  scene_xy, scene_yaw = _scene_pose(state)
  index, valid = select_agents(state, config.max_agents, keep)
  hist, hv, types, centre, direction = _agent_features(
      state, index, valid, config.history_steps, scene_xy, scene_yaw)
  return SceneFeatures(
      agent_history=hist, agent_history_valid=hv, agent_valid=valid, agent_index=index,
      agent_types=types.astype(jnp.int32), agent_center=centre, agent_dir=direction,
      **_map_features(state, config, scene_xy, scene_yaw,
                      state.current_sim_trajectory.xy[index, 0], valid),
      scene_xy=scene_xy, scene_yaw=scene_yaw, timestep=jnp.asarray(state.timestep, jnp.int32))


def scene_features(state: SimulatorState, config: FeaturesConfig,
                   keep: Optional[Array] = None) -> SceneFeatures:
  """Builds the encoder's instances from `state` at its step t = `state.timestep`.

  Args:
    state: a SimulatorState with any leading batch dims `...` (one timestep
      per scenario).
    config: padded sizes A = max_agents, H = history_steps, M = max_polylines,
      P = points_per_polyline, and the piece length L = segment_length.
    keep: optional (..., O) bool, objects modelled before any other after the
      SDC (`select_agents`): a policy's controlled agents.
  Returns:
    SceneFeatures with batch dims `...` (see its docstring for shapes).
  Not jitted: jit at the entry point that calls it.
  """
  batch = state.shape
  chex.assert_shape(state.timestep, batch)
  given = keep is not None
  keep = keep if given else jnp.zeros(state.object_metadata.ids.shape, bool)
  fn = lambda s, k: _scene_features_one(s, config, k if given else None)
  for _ in batch:
    fn = jax.vmap(fn)
  out = fn(state, keep)
  a, h, m, p = (config.max_agents, config.history_steps, config.max_polylines,
                config.points_per_polyline)
  chex.assert_shape(out.agent_history, batch + (a, h, AGENT_DIM))
  chex.assert_shape(out.map_points, batch + (m, p, 2))
  return out
