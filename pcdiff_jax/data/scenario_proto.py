"""WOMD `scenario/` records (serialized `Scenario` protos) <-> the tf.Example flavour.

The reader turns one Scenario into the flat per-feature arrays a parsed WOMD
motion tf.Example gives (`state/...`, `traffic_light_state/...`,
`roadgraph_samples/...`), the way Waymo's own converter
(`waymo_open_dataset/data_conversion/scenario_conversion.cc`) fills them, so
`womd` pads, checks and loads both flavours into the same `SimulatorState`:

- objects: every track, in the Scenario's order, when they fit in
  `max_objects`; otherwise the SDC, the `tracks_to_predict`, the other tracks
  valid at the current step (nearest the SDC first), then the rest (most valid
  states first), kept in the Scenario's order. Tracks valid at the current step
  (the WOSAC sim agents) are never dropped: more of them than `max_objects` is
  an error. Invalid states read as -1 (the converter's fill value);
  `tracks_to_predict` is 1 for a required prediction valid at the current step,
  0 for any other track; `objects_of_interest` marks the listed track ids.
- traffic lights: slot i at step t is the i-th lane state of
  `dynamic_map_states[t]` (the converter's layout), at most `max_lights` per step.
- roadgraph: every map feature in the Scenario's order, resampled like the
  converter (Catmull-Rom along polylines, index-based, every `polyline_spacing`
  metres of the source's 0.5 m spacing; polygon sides every `polygon_spacing`
  metres, closed), direction = unit vector to the next sample (0 at the end).
  The default 0.5 m keeps every source point, the density of the public
  tf.Example files (measured on the real record: median 0.49 m); the current
  converter's default is 1.0 m. Types: lanes 0-3, road lines 5-13, road edges
  14-16, stop sign 17, crosswalk 18, speed bump 19, driveway 20.
- headings: radians. A scene whose headings are in degrees (any beyond pi; some public
  scenes converted back from JSON store them so) is read in radians (`headings_in_degrees`).
- timestamps: `round(timestamps_seconds * 1e6)` (the converter truncates a
  float32 copy, which can be 1 us lower).

A Scenario with fewer states than 91 (the test split has 11) reads with the
missing steps invalid. The writer is the inverse for a `SimulatorState`
(one track per real object slot, one map feature per run of roadgraph points
with the same id and type), used to test the reader and to hand our scenes
to tools that take Scenario protos (Waymo's sim agents evaluator).

Bad input raises `ScenarioFormatError(field, message)`; `womd` adds the file
and record index.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from pcdiff_jax.data import waymo_protos as pb

SOURCE_SPACING = 0.5      # metres between a Scenario's polyline points (Waymo's converter constant)
POLYLINE_SPACING = 0.5
POLYGON_SPACING = 0.5
HEADING_TOLERANCE = 1e-3  # radians beyond pi that float32 rounding of a wrapped heading can give
LANE_TYPES = range(0, 4)          # LaneCenter.type + 0
ROAD_LINE_TYPES = range(5, 14)    # RoadLine.type + 5
ROAD_EDGE_TYPES = range(14, 17)   # RoadEdge.type + 14
STOP_SIGN, CROSSWALK, SPEED_BUMP, DRIVEWAY = 17, 18, 19, 20
_POLYGONS = {"crosswalk": CROSSWALK, "speed_bump": SPEED_BUMP, "driveway": DRIVEWAY}
_TIME_PARTS = ("past", "current", "future")
_STATE_FIELDS = {"x": "center_x", "y": "center_y", "z": "center_z", "length": "length", "width": "width",
                 "height": "height", "bbox_yaw": "heading", "velocity_x": "velocity_x",
                 "velocity_y": "velocity_y"}


class ScenarioFormatError(ValueError):
  """A record is not a usable Scenario proto; `field` names the proto field."""

  def __init__(self, field: Optional[str], message: str):
    super().__init__(message)
    self.field = field


def parse(raw: bytes):
  """Serialized bytes -> Scenario, or ScenarioFormatError."""
  try:
    return pb.Scenario.FromString(raw)
  except Exception as err:  # protobuf's DecodeError and friends
    raise ScenarioFormatError(None, f"not a Scenario proto (could not parse it: {err})") from None


def is_scenario(raw: bytes) -> bool:
  """Whether `raw` parses as a Scenario holding a scenario id or tracks."""
  try:
    scenario = pb.Scenario.FromString(raw)
  except Exception:
    return False
  return bool(scenario.scenario_id) or len(scenario.tracks) > 0


# --------------------------------------------------------------------------
# Roadgraph sampling (Waymo's converter, vectorised)
# --------------------------------------------------------------------------

def _sample_count(n: int, spacing: float, source_spacing: float) -> int:
  """The converter's loop `while int(count * spacing / source_spacing) < n - 1:
  count += 1`, started near its end instead of at 0."""
  count = max(0, int((n - 1) * source_spacing / spacing) - 2)
  while count > 0 and int((count - 1) * spacing / source_spacing) >= n - 1:
    count -= 1
  while int(count * spacing / source_spacing) < n - 1:
    count += 1
  return count


def resample_polyline(points: np.ndarray, spacing: float = POLYLINE_SPACING,
                      source_spacing: float = SOURCE_SPACING) -> np.ndarray:
  """(N, 3) -> (M, 3) float64 samples every `spacing` metres of a polyline
  whose points are `source_spacing` apart: linear on the first and last
  segments, Catmull-Rom elsewhere, plus the last point unless within 1 cm of
  the last sample. spacing == source_spacing returns the points themselves."""
  points = np.asarray(points, np.float64).reshape(-1, 3)
  n = len(points)
  if n == 0:
    return points
  spacing = source_spacing if spacing <= 0 else spacing
  if spacing == source_spacing:   # every source point (alpha is 0): the same values without the spline
    out = points[:n - 1]
    if n == 1 or np.sum((points[-1] - out[-1]) ** 2) > 0.01 ** 2:
      out = np.concatenate([out, points[-1:]], 0)
    return out
  count = _sample_count(n, spacing, source_spacing)
  dist = np.arange(count) * spacing
  left = (dist / source_spacing).astype(np.int64)
  alpha = ((dist - left * source_spacing) / source_spacing)[:, None]
  p1, p2 = points[left], points[np.minimum(left + 1, n - 1)]
  out = p1 + alpha * (p2 - p1)
  spline = (left >= 1) & (left <= n - 3)
  if spline.any():
    i = left[spline]
    q0, q1, q2, q3 = points[i - 1], points[i], points[i + 1], points[i + 2]
    a = alpha[spline]
    ca = 0.5 * (-q0 + 3.0 * q1 - 3.0 * q2 + q3)
    cb = 0.5 * (2.0 * q0 - 5.0 * q1 + 4.0 * q2 - q3)
    cc = 0.5 * (-q0 + q2)
    out[spline] = q1 + a * (cc + a * (cb + a * ca))
  if count == 0 or np.sum((points[-1] - out[-1]) ** 2) > 0.01 ** 2:
    out = np.concatenate([out, points[-1:]], 0)
  return out


def sample_polygon(points: np.ndarray, spacing: float = POLYGON_SPACING) -> np.ndarray:
  """(N, 3) polygon corners -> (M, 3) samples along its sides every
  `spacing` metres (corners only if spacing <= 0), closed with the first point."""
  points = np.asarray(points, np.float64).reshape(-1, 3)
  if len(points) == 0:
    return points
  out = []
  for start, end in zip(points, np.concatenate([points[1:], points[:1]])):
    if spacing <= 0:
      out.append(start[None])
      continue
    ray = end - start
    num = max(int(1 + np.linalg.norm(ray) / spacing), 2)
    out.append(start + ray * (np.arange(num - 1)[:, None] / (num - 1)))
  out.append(points[:1])
  return np.concatenate(out, 0)


def directions(points: np.ndarray, ends: Optional[np.ndarray] = None) -> np.ndarray:
  """(M, 3) unit vectors from each sample to the next; 0 for the last one,
  and for the last sample of each feature when `ends` (their indices) is
  given (several features' samples back to back)."""
  d = np.zeros_like(points)
  if len(points) > 1:
    seg = np.diff(points, axis=0)
    norm = np.linalg.norm(seg, axis=1, keepdims=True)
    d[:-1] = np.where(norm > 0, seg / np.where(norm > 0, norm, 1.0), 0.0)
  if ends is not None:
    d[ends] = 0.0
  return d


def _xyz(points) -> np.ndarray:
  return np.array([(p.x, p.y, p.z) for p in points], np.float64).reshape(-1, 3)


def feature_samples(feature, polyline_spacing: float = POLYLINE_SPACING,
                    polygon_spacing: float = POLYGON_SPACING) -> tuple[np.ndarray, int]:
  """One MapFeature -> ((M, 3) samples, roadgraph type); M = 0 for an empty
  or unknown feature."""
  kind = feature.WhichOneof("feature_data")
  if kind == "lane":
    return resample_polyline(_xyz(feature.lane.polyline), polyline_spacing), LANE_TYPES[0] + feature.lane.type
  if kind == "road_line":
    return (resample_polyline(_xyz(feature.road_line.polyline), polyline_spacing),
            ROAD_LINE_TYPES[0] + feature.road_line.type)
  if kind == "road_edge":
    return (resample_polyline(_xyz(feature.road_edge.polyline), polyline_spacing),
            ROAD_EDGE_TYPES[0] + feature.road_edge.type)
  if kind == "stop_sign":
    return _xyz([feature.stop_sign.position]), STOP_SIGN
  if kind in _POLYGONS:
    return sample_polygon(_xyz(getattr(feature, kind).polygon), polygon_spacing), _POLYGONS[kind]
  return np.zeros((0, 3)), -1


# --------------------------------------------------------------------------
# Reading: Scenario -> tf.Example-style arrays
# --------------------------------------------------------------------------

def headings_in_degrees(headings: np.ndarray) -> bool:
  """True when a scene's valid box headings (any shape) are in degrees. WOMD's are radians
  in [-pi, pi]; some public scenes converted back from JSON store degrees (13 of the 36 real
  val scenes in ../shared, 36 of the 167 train; their boxes then spin in place). One heading
  beyond pi is enough: a scene of dozens of objects in degrees nearly always has one."""
  return bool(np.any(np.abs(headings) > np.pi + HEADING_TOLERANCE))


def radians_from_degrees(headings: np.ndarray) -> np.ndarray:
  """Degrees -> radians in [-pi, pi)."""
  return (np.deg2rad(headings) + np.pi) % (2 * np.pi) - np.pi


def _track_arrays(tracks, num_steps: int) -> dict[str, np.ndarray]:
  """(O, num_steps) arrays of every ObjectState field, -1 where invalid; headings in
  radians (`headings_in_degrees`)."""
  num = len(tracks)
  out = {k: np.full((num, num_steps), -1.0, np.float64) for k in _STATE_FIELDS}
  valid = np.zeros((num, num_steps), bool)
  for i, track in enumerate(tracks):
    for t, s in enumerate(track.states[:num_steps]):
      if not s.valid:
        continue
      valid[i, t] = True
      out["x"][i, t], out["y"][i, t], out["z"][i, t] = s.center_x, s.center_y, s.center_z
      out["length"][i, t], out["width"][i, t], out["height"][i, t] = s.length, s.width, s.height
      out["bbox_yaw"][i, t] = s.heading
      out["velocity_x"][i, t], out["velocity_y"][i, t] = s.velocity_x, s.velocity_y
  out["valid"] = valid
  if headings_in_degrees(out["bbox_yaw"][valid]):
    out["bbox_yaw"] = np.where(valid, radians_from_degrees(out["bbox_yaw"]), -1.0)
  return out


def _choose_tracks(scenario, valid: np.ndarray, xy_now: np.ndarray, current: int, max_objects,
                   required: set) -> np.ndarray:
  """Track indices to keep (sorted, Scenario order), for the first size of
  `max_objects` (an int or increasing sizes) that holds every sim agent."""
  num = len(scenario.tracks)
  now = valid[:, current]
  sizes = (max_objects,) if np.isscalar(max_objects) else tuple(max_objects)
  for max_objects in sizes:
    if num <= max_objects:
      return np.arange(num)
    if now.sum() <= max_objects:
      break
  else:
    raise ScenarioFormatError("tracks", f"{int(now.sum())} tracks are valid at the current step (the sim "
                                        f"agents), more than max_num_objects={max_objects}")
  sdc = scenario.sdc_track_index
  dist = np.linalg.norm(xy_now - xy_now[sdc], axis=1)
  is_required = np.isin(np.arange(num), sorted(required))
  group = np.where(np.arange(num) == sdc, 0, np.where(is_required & now, 1, np.where(now, 2, 3)))
  key2 = np.where(now, dist, -valid.sum(axis=1))   # nearest first; else most valid states first
  order = np.lexsort((np.arange(num), key2, group))
  return np.sort(order[:max_objects])


def scenario_to_example(scenario, num_past: int = 10, num_future: int = 80, max_objects=128,
                        max_lights: int = 16, polyline_spacing: float = POLYLINE_SPACING,
                        polygon_spacing: float = POLYGON_SPACING) -> dict[str, np.ndarray]:
  """A Scenario (message or bytes) -> {tf.Example feature key: flat array},
  the arrays `womd` reads from a parsed WOMD motion tf.Example. max_objects:
  an int, or increasing sizes (`womd.OBJECT_BUCKETS`) of which the first that
  holds every sim agent is used."""
  if isinstance(scenario, (bytes, bytearray)):
    scenario = parse(bytes(scenario))
  num_steps = num_past + 1 + num_future
  current = num_past
  if not scenario.scenario_id:
    raise ScenarioFormatError("scenario_id", "required field is missing or empty")
  if scenario.HasField("current_time_index") and scenario.current_time_index != current:
    raise ScenarioFormatError("current_time_index", f"is {scenario.current_time_index}, expected {current}")
  num_t = len(scenario.timestamps_seconds)
  if not current < num_t <= num_steps:
    raise ScenarioFormatError("timestamps_seconds", f"has {num_t} steps, expected {current + 1} to {num_steps}")
  ts = np.asarray(scenario.timestamps_seconds, np.float64)
  if not np.all(np.isfinite(ts)):
    raise ScenarioFormatError("timestamps_seconds", "has non-finite values")
  tracks = scenario.tracks
  if len(tracks) == 0:
    raise ScenarioFormatError("tracks", "required field is missing or empty")
  for i, track in enumerate(tracks):
    if len(track.states) != num_t:
      raise ScenarioFormatError(f"tracks[{i}].states", f"has {len(track.states)} states, expected {num_t} "
                                                       "(one per timestamps_seconds entry)")
  if not scenario.HasField("sdc_track_index") or not 0 <= scenario.sdc_track_index < len(tracks):
    raise ScenarioFormatError("sdc_track_index", f"is {scenario.sdc_track_index if scenario.HasField('sdc_track_index') else 'missing'}, "
                                                 f"expected a track index in [0, {len(tracks)})")
  required = set()
  for j, rp in enumerate(scenario.tracks_to_predict):
    if not 0 <= rp.track_index < len(tracks):
      raise ScenarioFormatError(f"tracks_to_predict[{j}].track_index",
                                f"is {rp.track_index}, expected a track index in [0, {len(tracks)})")
    required.add(rp.track_index)

  arrays = _track_arrays(tracks, num_steps)
  valid = arrays["valid"]
  for name, field in _STATE_FIELDS.items():
    if not np.all(np.isfinite(arrays[name][valid])):
      raise ScenarioFormatError(f"tracks[*].states[*].{field}", "non-finite value(s) at valid states")
  xy_now = np.stack([arrays["x"][:, current], arrays["y"][:, current]], -1)
  keep = _choose_tracks(scenario, valid, xy_now, current, max_objects, required)
  interest = set(scenario.objects_of_interest)
  ids = np.array([tracks[i].id for i in keep], np.float32)
  ex: dict[str, np.ndarray] = {
      "scenario/id": np.array([scenario.scenario_id.encode()], object),
      "state/id": ids,
      "state/type": np.array([tracks[i].object_type for i in keep], np.float32),
      "state/is_sdc": (keep == scenario.sdc_track_index).astype(np.int64),
      "state/tracks_to_predict": np.array([int(i in required and valid[i, current]) for i in keep], np.int64),
      "state/objects_of_interest": np.array([int(tracks[i].id in interest) for i in keep], np.int64),
  }
  micros = np.full(num_steps, -1, np.int64)
  micros[:num_t] = np.round(ts * 1e6).astype(np.int64)
  per_step = {name: arrays[name][keep] for name in _STATE_FIELDS}
  per_step["valid"] = valid[keep].astype(np.int64)
  per_step["timestamp_micros"] = np.where(valid[keep], micros[None], -1)
  bounds = {"past": (0, current), "current": (current, current + 1), "future": (current + 1, num_steps)}
  for part, (a, b) in bounds.items():
    for name, values in per_step.items():
      ex[f"state/{part}/{name}"] = values[:, a:b].reshape(-1)

  # Traffic lights: (steps, L) time-major like the tf.Example.
  dyn = scenario.dynamic_map_states
  L = max(max_lights, 1)
  lights = {"x": np.full((num_steps, L), -1.0), "y": np.full((num_steps, L), -1.0),
            "z": np.full((num_steps, L), -1.0), "state": np.full((num_steps, L), -1, np.int64),
            "id": np.full((num_steps, L), -1, np.int64), "valid": np.zeros((num_steps, L), np.int64)}
  for t, dms in enumerate(dyn[:num_steps]):
    for i, lane_state in enumerate(dms.lane_states[:L]):
      p = lane_state.stop_point
      lights["x"][t, i], lights["y"][t, i], lights["z"][t, i] = p.x, p.y, p.z
      lights["state"][t, i], lights["id"][t, i], lights["valid"][t, i] = lane_state.state, lane_state.lane, 1
  for part, (a, b) in bounds.items():
    for name, values in lights.items():
      ex[f"traffic_light_state/{part}/{name}"] = values[a:b].reshape(-1)

  # Roadgraph: every feature's samples, then the per-point arrays in one pass.
  xyz, types, rg_ids, which = [], [], [], []
  for j, feature in enumerate(scenario.map_features):
    samples, rg_type = feature_samples(feature, polyline_spacing, polygon_spacing)
    if len(samples):
      xyz.append(samples)
      types.append(rg_type)
      rg_ids.append(feature.id)
      which.append(j)
  if not xyz:
    raise ScenarioFormatError("map_features", "no map feature with points (the roadgraph would be empty)")
  counts = np.array([len(p) for p in xyz])
  points = np.concatenate(xyz)
  bad = ~np.all(np.isfinite(points), axis=1)
  if bad.any():
    j = which[int(np.searchsorted(np.cumsum(counts), np.argmax(bad), side="right"))]
    raise ScenarioFormatError(f"map_features[{j}]", "non-finite point coordinates")
  ex["roadgraph_samples/xyz"] = points.astype(np.float32).reshape(-1)
  ex["roadgraph_samples/dir"] = directions(points, ends=np.cumsum(counts) - 1).astype(np.float32).reshape(-1)
  ex["roadgraph_samples/type"] = np.repeat(np.array(types, np.int64), counts)
  ex["roadgraph_samples/id"] = np.repeat(np.array(rg_ids, np.int64), counts)
  ex["roadgraph_samples/valid"] = np.ones(len(points), np.int64)
  return ex


# --------------------------------------------------------------------------
# Writing: SimulatorState -> Scenario
# --------------------------------------------------------------------------

def _step_seconds(timestamps: np.ndarray, valid: np.ndarray) -> np.ndarray:
  """(T,) seconds per step from per-object (O, T) micros; steps no object
  covers are filled 0.1 s apart from the nearest covered step."""
  num_t = timestamps.shape[1]
  known = valid.any(axis=0)
  micros = np.where(valid, timestamps, np.iinfo(np.int64).min).max(axis=0).astype(np.float64)
  steps = np.arange(num_t)
  if not known.any():
    return steps * 0.1
  ref = np.nonzero(known)[0]
  nearest = ref[np.abs(steps[:, None] - ref[None]).argmin(axis=1)]
  return np.where(known, micros, micros[nearest] + (steps - nearest) * 100_000.0) / 1e6


def _map_feature(feature_id: int, rg_type: int, points: np.ndarray):
  mp = [pb.MapPoint(x=float(x), y=float(y), z=float(z)) for x, y, z in points.astype(np.float64)]
  feature = pb.MapFeature(id=int(feature_id))
  if rg_type in LANE_TYPES:
    feature.lane.type = rg_type - LANE_TYPES[0]
    feature.lane.polyline.extend(mp)
  elif rg_type in ROAD_LINE_TYPES:
    feature.road_line.type = rg_type - ROAD_LINE_TYPES[0]
    feature.road_line.polyline.extend(mp)
  elif rg_type in ROAD_EDGE_TYPES:
    feature.road_edge.type = rg_type - ROAD_EDGE_TYPES[0]
    feature.road_edge.polyline.extend(mp)
  elif rg_type in _POLYGONS.values():
    kind = {v: k for k, v in _POLYGONS.items()}[rg_type]
    if len(mp) > 1 and np.array_equal(points[0], points[-1]):
      mp = mp[:-1]   # the samples close the polygon; the proto lists its corners once
    getattr(feature, kind).polygon.extend(mp)
  else:
    raise ScenarioFormatError("roadgraph_points.types", f"type {rg_type} has no Scenario map feature")
  return feature


def state_to_scenario(state, scenario_id: str, trajectory: str = "log", num_past: int = 10):
  """An unbatched `SimulatorState` -> Scenario proto (the writer behind
  `womd.write(..., record_format="scenario")`).

  Tracks: the real object slots (`is_valid`), in slot order; box sizes per
  step as stored; `tracks_to_predict` = the modeled objects (difficulty
  NONE: the state does not keep it). Lights: each step's valid slots, in slot
  order. Map: one feature per run of valid roadgraph points sharing an id and
  a type; a stop sign per point.
  """
  if state.shape:
    raise ValueError(f"state_to_scenario takes one scenario, got batch dims {state.shape}")
  traj = state.log_trajectory if trajectory == "log" else state.sim_trajectory
  t = {f: np.asarray(getattr(traj, f)) for f in ("x", "y", "z", "vel_x", "vel_y", "yaw", "length",
                                                  "width", "height", "valid", "timestamp_micros")}
  md = state.object_metadata
  real = np.nonzero(np.asarray(md.is_valid))[0]
  if real.size == 0:
    raise ScenarioFormatError("tracks", "the state has no real object (object_metadata.is_valid)")
  is_sdc = np.asarray(md.is_sdc)[real]
  if is_sdc.sum() != 1:
    raise ScenarioFormatError("sdc_track_index", f"expected exactly one SDC, found {int(is_sdc.sum())}")
  valid = t["valid"][real]
  num_t = valid.shape[1]
  scenario = pb.Scenario(scenario_id=scenario_id, current_time_index=num_past,
                         sdc_track_index=int(np.argmax(is_sdc)))
  scenario.timestamps_seconds.extend(_step_seconds(t["timestamp_micros"][real], valid).tolist())
  ids = np.asarray(md.ids)[real]
  types = np.asarray(md.object_types)[real]
  for k, slot in enumerate(real):
    track = scenario.tracks.add(id=int(ids[k]), object_type=int(types[k]))
    for step in range(num_t):
      if not valid[k, step]:
        track.states.add(valid=False)
        continue
      track.states.add(center_x=float(t["x"][slot, step]), center_y=float(t["y"][slot, step]),
                       center_z=float(t["z"][slot, step]), length=float(t["length"][slot, step]),
                       width=float(t["width"][slot, step]), height=float(t["height"][slot, step]),
                       heading=float(t["yaw"][slot, step]), velocity_x=float(t["vel_x"][slot, step]),
                       velocity_y=float(t["vel_y"][slot, step]), valid=True)
  scenario.objects_of_interest.extend(int(i) for i in ids[np.asarray(md.objects_of_interest)[real]])
  for k in np.nonzero(np.asarray(md.is_modeled)[real])[0]:
    scenario.tracks_to_predict.add(track_index=int(k))

  tl = state.log_traffic_light
  tl_arrays = {f: np.asarray(getattr(tl, f)) for f in ("x", "y", "z", "state", "lane_ids", "valid")}
  for step in range(num_t):
    dms = scenario.dynamic_map_states.add()
    for i in np.nonzero(tl_arrays["valid"][:, step])[0]:
      dms.lane_states.add(lane=int(tl_arrays["lane_ids"][i, step]), state=int(tl_arrays["state"][i, step]),
                          stop_point=pb.MapPoint(x=float(tl_arrays["x"][i, step]), y=float(tl_arrays["y"][i, step]),
                                                 z=float(tl_arrays["z"][i, step])))

  rg = state.roadgraph_points
  rg_valid = np.asarray(rg.valid)
  xyz = np.stack([np.asarray(rg.x), np.asarray(rg.y), np.asarray(rg.z)], -1)[rg_valid]
  rg_types, rg_ids = np.asarray(rg.types)[rg_valid], np.asarray(rg.ids)[rg_valid]
  if len(rg_types):
    change = np.nonzero((np.diff(rg_types) != 0) | (np.diff(rg_ids) != 0))[0] + 1
    for a, b in zip(np.r_[0, change], np.r_[change, len(rg_types)]):
      if rg_types[a] == STOP_SIGN:
        for p in range(a, b):
          feature = scenario.map_features.add(id=int(rg_ids[p]))
          feature.stop_sign.position.CopyFrom(pb.MapPoint(x=float(xyz[p, 0]), y=float(xyz[p, 1]), z=float(xyz[p, 2])))
        continue
      scenario.map_features.append(_map_feature(rg_ids[a], int(rg_types[a]), xyz[a:b]))
  return scenario
