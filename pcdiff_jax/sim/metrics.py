"""Per-object, per-step events and the paper's aggregate rates.

Events (Waymax semantics): `pairwise_overlap` (exact oriented-box overlap per
step), `offroad` (a box corner on the outer side of the nearest road edge).
Aggregates (shared/DESIGN.md "Metric definitions"), counted per scenario so
that batches and seeds sum exactly:

- collision: an evaluated agent overlaps another object present at the start
  step (WOSAC's sim agents) at some simulated step; pairs that already overlap
  in the log at the start step are not counted (WOMD has such pairs). Objects
  whose track starts later are replayed from the log but are not collision
  partners: in real logs such a track often continues one that ended (the
  tracker lost a parked car and found it again under a new id), so the car
  kept in place would "collide" with itself (`collided_with_entering` counts
  them; docs/RESULTS.md, "Table I (real WOMD val)"). `collided_any` counts every
  overlap with any object; `collided_with_replayed` the collisions (as `collided`) with an
  object that replays its log and so cannot react (the SDC on its log, objects beyond the
  reactive set: rear-ended agents, mostly; "Where ours collides");
  `vehicle_collided` counts evaluated vehicles hitting another vehicle (WOMD
  logs have pedestrian boxes that overlap each other and parked cars);
  `vru_vehicle_collided` evaluated pedestrians and cyclists overlapping a vehicle, so a
  walker struck by a car is told apart from walkers overlapping in a group.
- off-road: an evaluated vehicle on the road at the start step is off it at
  some later step (`became_offroad`); vehicles that start off the road are
  counted separately (`start_offroad`). Pedestrians and cyclists are not
  checked: sidewalks are off-road by the road-edge definition.
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import (Array, ObjectType, RoadgraphPoints, Trajectory,
                                      is_road_edge)


def pairwise_overlap(traj: Trajectory) -> Array:
  """(..., T, O, O) bool: boxes i and j overlap at step t, both valid, i != j.

  Computed step by step (`lax.map` over T) to keep memory at O^2 per step.
  """
  def per_step(fields):
    x, y, yaw, length, width, valid = fields                  # each (..., O)
    hit = geometry.pairwise_box_overlap(x, y, yaw, length, width)
    both = valid[..., :, None] & valid[..., None, :]
    eye = jnp.eye(x.shape[-1], dtype=bool)
    return hit & both & ~eye
  fields = tuple(jnp.moveaxis(a, -1, 0) for a in (
      traj.x, traj.y, traj.yaw, traj.length, traj.width, traj.valid))
  out = jax.lax.map(per_step, fields)                          # (T, ..., O, O)
  return jnp.moveaxis(out, 0, -3)


def overlap(traj: Trajectory) -> Array:
  """(..., O, T) bool: the object overlaps some other valid object at step t."""
  return jnp.swapaxes(jnp.any(pairwise_overlap(traj), axis=-1), -1, -2)


def road_edges(roadgraph: RoadgraphPoints, center_xy: Array, max_points: int):
  """The `max_points` valid road-edge samples nearest `center_xy` (..., 2).

  Returns xy (..., E, 2), dir (..., E, 2), ids (..., E), valid (..., E), in
  record order so that polylines stay contiguous.
  """
  edge = roadgraph.valid & is_road_edge(roadgraph.types)
  dist = jnp.linalg.norm(roadgraph.xy - center_xy[..., None, :], axis=-1)
  dist = jnp.where(edge, dist, jnp.inf)
  k = min(max_points, roadgraph.num_points)
  _, idx = jax.lax.top_k(-dist, k)
  idx = jnp.sort(idx, axis=-1)
  take = lambda a: jnp.take_along_axis(a, idx, axis=-1)
  return (jnp.stack([take(roadgraph.x), take(roadgraph.y)], -1),
          jnp.stack([take(roadgraph.dir_x), take(roadgraph.dir_y)], -1),
          take(roadgraph.ids), take(edge))


OFFROAD_EDGE_POINTS = 512    # road-edge samples searched per object and chunk of steps
OFFROAD_CHUNK_STEPS = 10     # steps that share one search (1 s at 10 Hz)


def offroad(traj: Trajectory, roadgraph: RoadgraphPoints,
            max_edge_points: int = OFFROAD_EDGE_POINTS, chunk_steps: int = OFFROAD_CHUNK_STEPS) -> Array:
  """(..., O, T) bool: some box corner is off the road (positive signed distance).

  Each object's corners over each `chunk_steps` steps are tested against the
  `max_edge_points` road-edge samples nearest its mean centre over those steps,
  which hold each corner's nearest sample unless an object crosses more than
  that many samples' span in one chunk: on every real val and train rollout the
  flags equal a search of every sample (Waymax's test), at less cost. A crop
  around one point of the scene misjudged cars far from it (docs/RESULTS.md,
  "Our metrics against Waymax's"). Invalid steps are False.
  """
  if traj.x.ndim > 2:   # leading batch dims
    batched_map = 0 if roadgraph.x.ndim > 1 else None
    return jax.vmap(lambda tr, rg: offroad(tr, rg, max_edge_points, chunk_steps),
                    in_axes=(0, batched_map))(traj, roadgraph)
  num_objects, num_steps = traj.x.shape
  chunks = -(-num_steps // chunk_steps)
  pad = lambda a: jnp.pad(a, ((0, 0), (0, chunks * chunk_steps - num_steps)), mode="edge")
  x, y, yaw, length, width = (pad(a) for a in (traj.x, traj.y, traj.yaw, traj.length, traj.width))
  valid = jnp.pad(traj.valid, ((0, 0), (0, chunks * chunk_steps - num_steps)))
  split = lambda a: a.reshape(num_objects, chunks, chunk_steps)
  count = jnp.sum(split(valid), -1)
  mean = lambda a: jnp.where(count > 0, jnp.sum(jnp.where(split(valid), split(a), 0.0), -1)
                             / jnp.maximum(count, 1), split(a)[..., 0])
  centre = jnp.stack([mean(x), mean(y)], -1)                                   # (O, C, 2)
  corners = geometry.box_corners(x, y, yaw, length, width)                     # (O, C*S, 4, 2)
  corners = corners.reshape(num_objects, chunks, chunk_steps * 4, 2)

  def one_object(fields):
    centre, corners = fields                                                   # (C, 2), (C, S*4, 2)
    xy, direction, ids, edge = jax.vmap(lambda c: road_edges(roadgraph, c, max_edge_points))(centre)  # (C, K, ...)
    return geometry.signed_distance_to_road_edges(corners, xy, direction, ids, edge)
  sd = jax.lax.map(one_object, (centre, corners))                              # (O, C, S*4)
  off = jnp.any(sd.reshape(num_objects, chunks * chunk_steps, 4) > 0.0, -1)[:, :num_steps]
  return off & traj.valid


def _offroad_of_subset(sim: Trajectory, roadgraph: RoadgraphPoints, max_edge_points: int,
                       subset: Array, start_step: int, size: int) -> Array:
  """`offroad` from `start_step` on, computed for the (at most `size`) objects
  of `subset` (..., O) and False elsewhere: (..., O, T - start_step)."""
  num_objects = subset.shape[-1]
  size = min(size, num_objects)
  index = jnp.argsort(~subset, axis=-1, stable=True)[..., :size]          # subset first
  take = lambda a: jnp.take_along_axis(a[..., start_step:], index[..., None], axis=-2)
  part = jax.tree_util.tree_map(take, sim)
  off = offroad(part, roadgraph, max_edge_points)                          # (..., size, T')
  off = off & jnp.take_along_axis(subset, index, axis=-1)[..., None]
  full = jnp.zeros(subset.shape + off.shape[-1:], bool)
  put = lambda f, i, o: f.at[i].set(o)
  for _ in range(subset.ndim - 1):
    put = jax.vmap(put)
  return put(full, index, off)


@struct.dataclass
class EventCounts:
  """Per-scenario counts (...,) int32; sum over scenarios, then divide."""
  num_evaluated: Array
  collided: Array
  collided_with_entering: Array  # collided, objects whose track starts after the start step included
  collided_any: Array
  collided_with_replayed: Array  # collided, with an object replaying its log among the partners
  vehicle_collided: Array      # evaluated vehicles overlapping another vehicle
  num_vehicles: Array          # evaluated vehicles
  vru_vehicle_collided: Array  # evaluated pedestrians and cyclists overlapping a vehicle
  num_vrus: Array              # evaluated pedestrians and cyclists
  start_offroad: Array         # ... off the road at the start step
  became_offroad: Array        # ... on the road at the start, off it later
  offroad_any: Array           # ... off the road at some simulated step
  offroad_past_log: Array      # became_offroad, but only at steps after its log had ended

  def rates(self) -> dict[str, float]:
    """The paper's rates over everything summed (host-side)."""
    total = jax.tree_util.tree_map(lambda a: float(jnp.sum(a)), self)
    on_road = total.num_vehicles - total.start_offroad
    return {
        "collision_rate": total.collided / max(total.num_evaluated, 1.0),
        "collision_with_entering_rate": total.collided_with_entering / max(total.num_evaluated, 1.0),
        "collision_any_rate": total.collided_any / max(total.num_evaluated, 1.0),
        "collision_with_replayed_rate": total.collided_with_replayed / max(total.num_evaluated, 1.0),
        "vehicle_collision_rate": total.vehicle_collided / max(total.num_vehicles, 1.0),
        "vru_vehicle_collision_rate": total.vru_vehicle_collided / max(total.num_vrus, 1.0),
        "offroad_rate": total.became_offroad / max(on_road, 1.0),
        "offroad_any_rate": total.offroad_any / max(total.num_vehicles, 1.0),
        # The share of offroad_rate (same denominator) from agents that left
        # the road only after their log had ended (e.g. a synthetic route
        # leaving the map): there the map, not the log, is all a method has.
        "offroad_past_log_rate": total.offroad_past_log / max(on_road, 1.0),
        "start_offroad_fraction": total.start_offroad / max(total.num_vehicles, 1.0),
        "num_evaluated": total.num_evaluated,
        "num_vehicles": total.num_vehicles,
        "num_vrus": total.num_vrus,
    }


def event_counts(sim: Trajectory, log: Trajectory, roadgraph: RoadgraphPoints,
                 object_types: Array, evaluated: Array, start_step: int,
                 max_edge_points: int = OFFROAD_EDGE_POINTS, max_evaluated: Optional[int] = None,
                 replayed: Optional[Array] = None) -> EventCounts:
  """Collision and off-road counts of a rollout.

  Args:
    sim, log: (..., O, T) simulated and logged trajectories.
    roadgraph: (..., P). object_types: (..., O).
    evaluated: (..., O) bool, the agents to score (valid at `start_step`).
    start_step: the step simulation starts from (10 for WOMD); only steps
      after it count as events.
    max_evaluated: an upper bound on evaluated.sum(); when given, the
      off-road test (the costly part: every box corner against every edge
      sample) runs on those objects and steps >= start_step only.
    replayed: (..., O) bool, the objects that replay their log (not the
      method's); None: none.
  """
  num_t = sim.num_timesteps
  after = jnp.arange(num_t) > start_step                       # (T,)
  evaluated = evaluated & sim.valid[..., start_step]

  pairs = pairwise_overlap(sim)                                # (..., T, O, O)
  log_pairs_at_start = pairwise_overlap(jax.tree_util.tree_map(
      lambda a: a[..., start_step:start_step + 1], log))[..., 0, :, :]
  later = pairs & after[:, None, None]
  collided_any = jnp.any(later, axis=(-3, -1))                 # (..., O)
  new_with_entering = later & ~log_pairs_at_start[..., None, :, :]
  present = sim.valid[..., start_step]                         # (..., O) the sim agents
  new_pairs = new_with_entering & present[..., None, None, :]
  collided = jnp.any(new_pairs, axis=(-3, -1))
  if replayed is None:
    replayed = jnp.zeros_like(present)
  collided_with_replayed = jnp.any(new_pairs & replayed[..., None, None, :], axis=(-3, -1))
  is_vehicle = object_types == ObjectType.VEHICLE
  vehicle_collided = jnp.any(new_pairs & is_vehicle[..., None, None, :], axis=(-3, -1))
  vru = evaluated & ((object_types == ObjectType.PEDESTRIAN) | (object_types == ObjectType.CYCLIST))

  if max_evaluated is None:
    off = offroad(sim, roadgraph, max_edge_points)[..., start_step:]           # (..., O, T')
  else:
    off = _offroad_of_subset(sim, roadgraph, max_edge_points, evaluated, start_step, max_evaluated)
  vehicle = evaluated & is_vehicle
  start_off = off[..., 0]
  off_later = jnp.any(off[..., 1:], axis=-1)
  last_logged = jnp.max(jnp.where(log.valid, jnp.arange(num_t), -1), axis=-1)         # (..., O)
  logged = jnp.arange(start_step, num_t) <= last_logged[..., None]                    # (..., O, T')
  off_while_logged = jnp.any(off[..., 1:] & logged[..., 1:], axis=-1)

  count = lambda m: jnp.sum(m, axis=-1).astype(jnp.int32)
  return EventCounts(
      num_evaluated=count(evaluated),
      collided=count(collided & evaluated),
      collided_with_entering=count(jnp.any(new_with_entering, axis=(-3, -1)) & evaluated),
      collided_any=count(collided_any & evaluated),
      collided_with_replayed=count(collided_with_replayed & evaluated),
      vehicle_collided=count(vehicle_collided & vehicle),
      num_vehicles=count(vehicle),
      vru_vehicle_collided=count(vehicle_collided & vru),
      num_vrus=count(vru),
      start_offroad=count(start_off & vehicle),
      became_offroad=count(off_later & ~start_off & vehicle),
      offroad_any=count(off_later & vehicle),
      offroad_past_log=count(off_later & ~off_while_logged & ~start_off & vehicle),
  )
