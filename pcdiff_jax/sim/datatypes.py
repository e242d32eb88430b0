"""Waymax-compatible simulator datatypes.

Field names, shapes, dtypes and meanings follow Waymax so that a Waymax
`SimulatorState` and ours are interchangeable (see shared/DESIGN.md). Every
class is a frozen `flax.struct` pytree, accepts any leading batch dims, and
carries an explicit `valid` mask. Shapes use O objects, T timesteps, P
roadgraph points, L traffic lights, D action features.

Library code reads a state only through Waymax's own surface (the fields and
the properties Waymax's classes have: `shape`, `num_objects`, `xy`, `speed`,
`current_sim_trajectory`, ...), so that a real Waymax state works wherever
ours does (tests/test_waymax_surface.py checks it on classes with exactly
that surface). What Waymax's classes lack is a module-level function here
taking the state (`current_traffic_lights`, `sdc_index`, `num_timesteps`);
the properties of the same meaning on our classes (`current_traffic_light`,
`ObjectMetadata.sdc_index`, `total_timesteps`) are conveniences for users
of our classes only.
"""
from __future__ import annotations

import enum
from typing import Any, Optional

import chex
import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.sim import geometry

Array = Any  # jax.Array or np.ndarray; library code accepts both.

DT_SECONDS = 0.1  # WOMD is logged at 10 Hz.


class ObjectType(enum.IntEnum):
  """WOMD `state/type` codes."""
  UNSET = 0
  VEHICLE = 1
  PEDESTRIAN = 2
  CYCLIST = 3
  OTHER = 4


class RoadgraphType(enum.IntEnum):
  """WOMD `roadgraph_samples/type` codes."""
  UNKNOWN = -1
  LANE_UNDEFINED = 0
  LANE_FREEWAY = 1
  LANE_SURFACE_STREET = 2
  LANE_BIKE_LANE = 3
  ROAD_LINE_UNKNOWN = 5
  ROAD_LINE_BROKEN_SINGLE_WHITE = 6
  ROAD_LINE_SOLID_SINGLE_WHITE = 7
  ROAD_LINE_SOLID_DOUBLE_WHITE = 8
  ROAD_LINE_BROKEN_SINGLE_YELLOW = 9
  ROAD_LINE_BROKEN_DOUBLE_YELLOW = 10
  ROAD_LINE_SOLID_SINGLE_YELLOW = 11
  ROAD_LINE_SOLID_DOUBLE_YELLOW = 12
  ROAD_LINE_PASSING_DOUBLE_YELLOW = 13
  ROAD_EDGE_UNKNOWN = 14
  ROAD_EDGE_BOUNDARY = 15
  ROAD_EDGE_MEDIAN = 16
  STOP_SIGN = 17
  CROSSWALK = 18
  SPEED_BUMP = 19


class TrafficLightState(enum.IntEnum):
  """WOMD `traffic_light_state/*/state` codes."""
  UNKNOWN = 0
  ARROW_STOP = 1
  ARROW_CAUTION = 2
  ARROW_GO = 3
  STOP = 4
  CAUTION = 5
  GO = 6
  FLASHING_STOP = 7
  FLASHING_CAUTION = 8


def is_lane_center(types: Array) -> Array:
  return (types >= RoadgraphType.LANE_FREEWAY) & (types <= RoadgraphType.LANE_BIKE_LANE)


def is_road_line(types: Array) -> Array:
  return (types >= RoadgraphType.ROAD_LINE_BROKEN_SINGLE_WHITE) & (
      types <= RoadgraphType.ROAD_LINE_PASSING_DOUBLE_YELLOW)


def is_road_edge(types: Array) -> Array:
  """Road edges (boundary or median); Waymax's off-road check uses these."""
  return (types == RoadgraphType.ROAD_EDGE_BOUNDARY) | (types == RoadgraphType.ROAD_EDGE_MEDIAN)


def _check_dtype(name: str, value: Array, dtype) -> None:
  if value.dtype != dtype:
    raise ValueError(f"{name} has dtype {value.dtype}, expected {np.dtype(dtype)}")


def _check_same_shape(cls_name: str, fields: dict[str, Array]) -> tuple[int, ...]:
  shapes = {k: tuple(v.shape) for k, v in fields.items()}
  first = next(iter(shapes.values()))
  bad = {k: s for k, s in shapes.items() if s != first}
  if bad:
    raise ValueError(f"{cls_name}: fields disagree on shape, expected {first}, got {bad}")
  return first


@struct.dataclass
class Trajectory:
  """Object trajectories, each field (..., O, T).

  x, y, z: centre position (m); vel_x, vel_y: velocity (m/s); yaw: box heading
  (rad); length, width, height: box size (m); valid: bool; timestamp_micros:
  int32.
  """
  x: Array
  y: Array
  z: Array
  vel_x: Array
  vel_y: Array
  yaw: Array
  valid: Array
  timestamp_micros: Array
  length: Array
  width: Array
  height: Array

  FLOAT_FIELDS = ("x", "y", "z", "vel_x", "vel_y", "yaw", "length", "width", "height")

  @property
  def shape(self) -> tuple[int, ...]:
    """(..., O, T)."""
    return tuple(self.x.shape)

  @property
  def num_objects(self) -> int:
    return self.shape[-2]

  @property
  def num_timesteps(self) -> int:
    return self.shape[-1]

  @property
  def xy(self) -> Array:
    """(..., O, T, 2)."""
    return jnp.stack([self.x, self.y], axis=-1)

  @property
  def xyz(self) -> Array:
    """(..., O, T, 3)."""
    return jnp.stack([self.x, self.y, self.z], axis=-1)

  @property
  def vel_xy(self) -> Array:
    """(..., O, T, 2)."""
    return jnp.stack([self.vel_x, self.vel_y], axis=-1)

  @property
  def speed(self) -> Array:
    """(..., O, T) speed magnitude, m/s."""
    return jnp.sqrt(self.vel_x ** 2 + self.vel_y ** 2)

  @property
  def vel_yaw(self) -> Array:
    """(..., O, T) direction of the velocity vector."""
    return jnp.arctan2(self.vel_y, self.vel_x)

  @property
  def bbox_corners(self) -> Array:
    """(..., O, T, 4, 2) box corners, counter-clockwise from front-left."""
    return geometry.box_corners(self.x, self.y, self.yaw, self.length, self.width)

  @classmethod
  def zeros(cls, shape: tuple[int, ...]) -> "Trajectory":
    """All-invalid trajectory of shape (..., O, T)."""
    f = jnp.zeros(shape, jnp.float32)
    return cls(x=f, y=f, z=f, vel_x=f, vel_y=f, yaw=f, length=f, width=f, height=f,
               valid=jnp.zeros(shape, bool), timestamp_micros=jnp.zeros(shape, jnp.int32))

  def validate(self) -> None:
    fields = {k: getattr(self, k) for k in self.FLOAT_FIELDS + ("valid", "timestamp_micros")}
    _check_same_shape("Trajectory", fields)
    for k in self.FLOAT_FIELDS:
      _check_dtype(f"Trajectory.{k}", fields[k], jnp.float32)
    _check_dtype("Trajectory.valid", self.valid, jnp.bool_)
    _check_dtype("Trajectory.timestamp_micros", self.timestamp_micros, jnp.int32)


@struct.dataclass
class ObjectMetadata:
  """Per-object metadata, each field (..., O).

  ids, object_types (ObjectType codes): int32. is_sdc: the self-driving car;
  is_modeled: WOMD `tracks_to_predict == 1`; is_valid: the slot holds a real
  object; objects_of_interest; is_controlled: controlled by a policy.
  """
  ids: Array
  object_types: Array
  is_sdc: Array
  is_modeled: Array
  is_valid: Array
  objects_of_interest: Array
  is_controlled: Array

  @property
  def shape(self) -> tuple[int, ...]:
    """(..., O)."""
    return tuple(self.ids.shape)

  @property
  def num_objects(self) -> int:
    return self.ids.shape[-1]

  @property
  def sdc_index(self) -> Array:
    """(...,) index of the SDC (0 if none is marked). Not on Waymax's class:
    library code calls the module-level `sdc_index(metadata)`."""
    return sdc_index(self)

  def validate(self) -> None:
    fields = {k: getattr(self, k) for k in (
        "ids", "object_types", "is_sdc", "is_modeled", "is_valid", "objects_of_interest",
        "is_controlled")}
    _check_same_shape("ObjectMetadata", fields)
    for k in ("ids", "object_types"):
      _check_dtype(f"ObjectMetadata.{k}", fields[k], jnp.int32)
    for k in ("is_sdc", "is_modeled", "is_valid", "objects_of_interest", "is_controlled"):
      _check_dtype(f"ObjectMetadata.{k}", fields[k], jnp.bool_)
    # One SDC per scenario at most (WOMD has exactly one).
    if not isinstance(self.is_sdc, jax.core.Tracer):
      counts = np.asarray(self.is_sdc).sum(axis=-1)
      if np.any(counts > 1):
        raise ValueError("ObjectMetadata.is_sdc: more than one SDC in a scenario")


@struct.dataclass
class RoadgraphPoints:
  """Road graph samples, each field (..., P).

  x, y, z: position; dir_x, dir_y, dir_z: unit direction to the next sample of
  the same polyline; types: RoadgraphType codes; ids: polyline id; valid.
  """
  x: Array
  y: Array
  z: Array
  dir_x: Array
  dir_y: Array
  dir_z: Array
  types: Array
  ids: Array
  valid: Array

  @property
  def shape(self) -> tuple[int, ...]:
    """(..., P)."""
    return tuple(self.x.shape)

  @property
  def num_points(self) -> int:
    return self.x.shape[-1]

  @property
  def xy(self) -> Array:
    """(..., P, 2)."""
    return jnp.stack([self.x, self.y], axis=-1)

  @property
  def xyz(self) -> Array:
    """(..., P, 3)."""
    return jnp.stack([self.x, self.y, self.z], axis=-1)

  @property
  def dir_xy(self) -> Array:
    """(..., P, 2)."""
    return jnp.stack([self.dir_x, self.dir_y], axis=-1)

  @property
  def dir_xyz(self) -> Array:
    """(..., P, 3)."""
    return jnp.stack([self.dir_x, self.dir_y, self.dir_z], axis=-1)

  def validate(self) -> None:
    fields = {k: getattr(self, k) for k in (
        "x", "y", "z", "dir_x", "dir_y", "dir_z", "types", "ids", "valid")}
    _check_same_shape("RoadgraphPoints", fields)
    for k in ("x", "y", "z", "dir_x", "dir_y", "dir_z"):
      _check_dtype(f"RoadgraphPoints.{k}", fields[k], jnp.float32)
    for k in ("types", "ids"):
      _check_dtype(f"RoadgraphPoints.{k}", fields[k], jnp.int32)
    _check_dtype("RoadgraphPoints.valid", self.valid, jnp.bool_)


@struct.dataclass
class TrafficLights:
  """Logged traffic light states, each field (..., L, T).

  x, y, z: stop point; state: TrafficLightState codes; lane_ids: the lane the
  light controls; valid. Slots are kept as in the record (WOMD may reorder
  lights between steps; match on lane_ids per step).
  """
  x: Array
  y: Array
  z: Array
  state: Array
  lane_ids: Array
  valid: Array

  @property
  def shape(self) -> tuple[int, ...]:
    """(..., L, T)."""
    return tuple(self.x.shape)

  @property
  def num_traffic_lights(self) -> int:
    return self.shape[-2]

  @property
  def num_timesteps(self) -> int:
    return self.shape[-1]

  @property
  def xy(self) -> Array:
    """(..., L, T, 2)."""
    return jnp.stack([self.x, self.y], axis=-1)

  def validate(self) -> None:
    fields = {k: getattr(self, k) for k in ("x", "y", "z", "state", "lane_ids", "valid")}
    _check_same_shape("TrafficLights", fields)
    for k in ("x", "y", "z"):
      _check_dtype(f"TrafficLights.{k}", fields[k], jnp.float32)
    for k in ("state", "lane_ids"):
      _check_dtype(f"TrafficLights.{k}", fields[k], jnp.int32)
    _check_dtype("TrafficLights.valid", self.valid, jnp.bool_)


@struct.dataclass
class Action:
  """Per-object action: data (..., O, D) float32, valid (..., O, 1) bool.

  D = 2 for the kinematic model [accel, yaw_rate] and for Waymax's bicycle
  model [accel, curvature]; D = 5 for state dynamics [x, y, yaw, vel_x, vel_y].
  """
  data: Array
  valid: Array

  @property
  def shape(self) -> tuple[int, ...]:
    """(..., O)."""
    return tuple(self.data.shape[:-1])

  def validate(self) -> None:
    _check_dtype("Action.data", self.data, jnp.float32)
    _check_dtype("Action.valid", self.valid, jnp.bool_)
    if tuple(self.valid.shape) != tuple(self.data.shape[:-1]) + (1,):
      raise ValueError(f"Action.valid has shape {self.valid.shape}, expected "
                       f"{tuple(self.data.shape[:-1]) + (1,)}")


def _time_onehot(timestep: Array, num_timesteps: int) -> Array:
  """(..., 1, T) bool, True at `timestep` (broadcasts over objects)."""
  t = jnp.asarray(timestep)[..., None, None]
  return jnp.arange(num_timesteps) == t


def slice_time(tree: Any, timestep: Array) -> Any:
  """Takes step `timestep` (shape (...)) of every (..., X, T) leaf -> (..., X, 1).

  Works for batched states with one timestep per scenario, without vmap.
  """
  def take(x):
    idx = jnp.broadcast_to(jnp.asarray(timestep)[..., None, None], x.shape[:-1] + (1,))
    return jnp.take_along_axis(x, idx.astype(jnp.int32), axis=-1)
  return jax.tree_util.tree_map(take, tree)


def update_time(tree: Any, timestep: Array, new: Any) -> Any:
  """Writes (..., X, 1) leaves of `new` into step `timestep` of (..., X, T) leaves."""
  def put(old, value):
    onehot = _time_onehot(timestep, old.shape[-1])
    return jnp.where(onehot, value.astype(old.dtype), old)
  return jax.tree_util.tree_map(put, tree, new)


@struct.dataclass
class SimulatorState:
  """A scenario being simulated; any leading batch dims.

  sim_trajectory, log_trajectory: (..., O, T); log_traffic_light: (..., L, T);
  object_metadata: (..., O); roadgraph_points: (..., P); timestep: (...) int32,
  the index of the current step; sdc_paths: None (not in public WOMD).
  """
  sim_trajectory: Trajectory
  log_trajectory: Trajectory
  log_traffic_light: TrafficLights
  object_metadata: ObjectMetadata
  timestep: Array
  roadgraph_points: RoadgraphPoints
  sdc_paths: Optional[Any] = None

  @property
  def shape(self) -> tuple[int, ...]:
    """Leading batch dims."""
    return tuple(self.sim_trajectory.shape[:-2])

  @property
  def batch_dims(self) -> tuple[int, ...]:
    return self.shape

  @property
  def num_objects(self) -> int:
    return self.sim_trajectory.num_objects

  @property
  def total_timesteps(self) -> int:
    """T. Not on Waymax's class: library code calls `num_timesteps(state)`."""
    return num_timesteps(self)

  @property
  def remaining_timesteps(self) -> Array:
    return num_timesteps(self) - 1 - self.timestep

  @property
  def is_done(self) -> Array:
    return self.remaining_timesteps <= 0

  @property
  def current_sim_trajectory(self) -> Trajectory:
    """(..., O, 1) the sim trajectory at `timestep`."""
    return slice_time(self.sim_trajectory, self.timestep)

  @property
  def current_log_trajectory(self) -> Trajectory:
    """(..., O, 1) the log trajectory at `timestep`."""
    return slice_time(self.log_trajectory, self.timestep)

  @property
  def current_traffic_light(self) -> TrafficLights:
    """(..., L, 1) the logged lights at `timestep`. Not on Waymax's class:
    library code calls `current_traffic_lights(state)`."""
    return current_traffic_lights(self)

  def validate(self) -> None:
    self.sim_trajectory.validate()
    self.log_trajectory.validate()
    self.log_traffic_light.validate()
    self.object_metadata.validate()
    self.roadgraph_points.validate()
    batch = self.shape
    chex.assert_shape(self.timestep, batch)
    _check_dtype("SimulatorState.timestep", self.timestep, jnp.int32)
    if self.log_trajectory.shape != self.sim_trajectory.shape:
      raise ValueError(f"log_trajectory {self.log_trajectory.shape} and sim_trajectory "
                       f"{self.sim_trajectory.shape} differ in shape")
    if tuple(self.object_metadata.ids.shape) != batch + (self.num_objects,):
      raise ValueError(f"object_metadata has shape {self.object_metadata.ids.shape}, "
                       f"expected {batch + (self.num_objects,)}")
    if tuple(self.roadgraph_points.x.shape[:-1]) != batch:
      raise ValueError("roadgraph_points batch dims differ from the trajectories'")
    if self.log_traffic_light.shape[:-2] != batch or (
        self.log_traffic_light.num_timesteps != self.total_timesteps):
      raise ValueError(f"log_traffic_light has shape {self.log_traffic_light.shape}, expected "
                       f"{batch} + (L, {self.total_timesteps})")


# ----------------------------------------------------------------------------
# What Waymax's classes do not have, as functions of any state with Waymax's
# surface (ours or Waymax's own).


def sdc_index(metadata: ObjectMetadata) -> Array:
  """(...,) int32 slot of the SDC in an ObjectMetadata (0 if none is marked)."""
  return jnp.argmax(metadata.is_sdc, axis=-1).astype(jnp.int32)


def num_timesteps(state: SimulatorState) -> int:
  """T, the number of steps of the log (static)."""
  return state.log_trajectory.num_timesteps


def current_traffic_lights(state: SimulatorState) -> TrafficLights:
  """(..., L, 1) the logged traffic lights at `state.timestep`."""
  return slice_time(state.log_traffic_light, state.timestep)
