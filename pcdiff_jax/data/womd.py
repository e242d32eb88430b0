"""WOMD motion tf.Example TFRecords <-> `SimulatorState`.

Reading follows Waymax's loader: trajectories are (O, T) with T = past +
current + future = 10 + 1 + 80, box sizes are the mean over an object's valid
steps, traffic lights are transposed to (L, T) with their slots kept as in the
record, `is_valid = tracks_to_predict != -1`, `is_modeled = tracks_to_predict
== 1`, and a loaded state has `timestep = 0` with sim == log (Waymax keeps
only step 0 valid in the sim trajectory; `sim.env.reset` prepares it for
simulation). Everything is padded to fixed sizes so batches never recompile.

Bad input raises `WomdFormatError` naming the file, record index and field;
`iterate(..., on_error="skip")` logs a warning and skips such a record instead
(a corrupt or truncated file is skipped from the corrupt record on).

Files of WOMD's `scenario/` flavour (serialized `Scenario` protos) read into
the same states (`scenario_proto`); each file's flavour is read from its first
record (`record_format="auto"`) or forced with `record_format`.
"""
from __future__ import annotations

import dataclasses
import functools
import glob as globlib
import itertools
import logging
import os
from typing import Iterable, Iterator, Optional, Sequence, Union

import numpy as np

from pcdiff_jax.sim.datatypes import (ObjectMetadata, RoadgraphPoints, SimulatorState,
                                      TrafficLights, Trajectory)

log = logging.getLogger(__name__)

NUM_PAST, NUM_CURRENT, NUM_FUTURE = 10, 1, 80
TIME_KEYS = ("past", "current", "future")
# state/<time>/<name> feature -> Trajectory field.
OBJECT_TIME_FEATURES = {
    "x": "x", "y": "y", "z": "z", "velocity_x": "vel_x", "velocity_y": "vel_y",
    "bbox_yaw": "yaw", "length": "length", "width": "width", "height": "height",
    "valid": "valid", "timestamp_micros": "timestamp_micros",
}
OBJECT_DERIVED_FEATURES = ("speed", "vel_yaw")  # written, not read (derivable)
OBJECT_FEATURES = ("id", "type", "is_sdc", "tracks_to_predict", "objects_of_interest")
ROADGRAPH_FEATURES = ("xyz", "dir", "type", "id", "valid")
TRAFFIC_LIGHT_FEATURES = ("state", "x", "y", "z", "id", "valid")

_INT_NAMES = {"valid", "timestamp_micros", "is_sdc", "tracks_to_predict", "objects_of_interest",
              "difficulty_level", "type", "id", "state"}


def feature_kind(key: str) -> str:
  """'float', 'int64' or 'bytes': the tf.Example list type of a WOMD feature."""
  if key == "scenario/id":
    return "bytes"
  name = key.rsplit("/", 1)[-1]
  if key in ("state/id", "state/type"):
    return "float"  # WOMD stores object ids and types as floats
  if key in ("roadgraph_samples/xyz", "roadgraph_samples/dir"):
    return "float"
  return "int64" if name in _INT_NAMES else "float"


def required_keys() -> list[str]:
  keys = ["scenario/id"] + [f"state/{k}" for k in OBJECT_FEATURES]
  for t in TIME_KEYS:
    keys += [f"state/{t}/{k}" for k in OBJECT_TIME_FEATURES]
    keys += [f"traffic_light_state/{t}/{k}" for k in TRAFFIC_LIGHT_FEATURES]
  keys += [f"roadgraph_samples/{k}" for k in ROADGRAPH_FEATURES]
  return keys


def all_keys() -> list[str]:
  """Every key our writer emits (the real record's schema)."""
  keys = required_keys() + ["state/difficulty_level"]
  for t in TIME_KEYS:
    keys += [f"state/{t}/{k}" for k in OBJECT_DERIVED_FEATURES]
    keys.append(f"traffic_light_state/{t}/timestamp_micros")
  return sorted(keys)


class WomdFormatError(ValueError):
  """A record does not match the WOMD motion tf.Example schema."""

  def __init__(self, path: str, index: Optional[int], field: Optional[str], message: str):
    where = f"{path}" + (f", record {index}" if index is not None else "")
    where += f", field '{field}'" if field else ""
    super().__init__(f"{where}: {message}")
    self.path, self.index, self.field = path, index, field


@dataclasses.dataclass(frozen=True)
class ScenarioMeta:
  """Where a state came from. Batched states carry tuples, one entry per scenario."""
  scenario_id: Union[str, tuple[str, ...]]
  path: Union[str, tuple[str, ...]]
  record_index: Union[int, tuple[int, ...]]


# Padded object counts when `max_num_objects=None`: each scenario takes the
# first that holds it (a few shapes, so a jitted rollout compiles a few times).
OBJECT_BUCKETS = (128, 256, 512, 1024, 2048)


@dataclasses.dataclass(frozen=True)
class LoaderConfig:
  """max_num_objects: the padded object count, or None for the first of
  OBJECT_BUCKETS that holds each scenario (no scene refused for its size)."""
  max_num_objects: Optional[int] = 128
  max_num_rg_points: int = 30000
  max_num_traffic_lights: int = 16
  num_past: int = NUM_PAST
  num_future: int = NUM_FUTURE
  history_only: bool = False   # drop every step after the current one (as in the test split)


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------

def expand_paths(paths: Union[str, os.PathLike, Sequence[Union[str, os.PathLike]]]) -> list[str]:
  """A file, a glob, or a list of either -> sorted, de-duplicated file list."""
  items = [paths] if isinstance(paths, (str, os.PathLike)) else list(paths)
  files: list[str] = []
  for item in items:
    item = os.fspath(item)
    matches = sorted(globlib.glob(item)) if globlib.has_magic(item) else [item]
    if not matches:
      raise FileNotFoundError(f"no TFRecord matches {item!r}")
    for m in matches:
      if not os.path.isfile(m):
        raise FileNotFoundError(f"TFRecord file not found: {m!r}")
      if m not in files:
        files.append(m)
  return files


def quiet_tensorflow_env() -> None:
  """Before TensorFlow's first import: no C++ start-up banner. We use TF only
  to read and write TFRecords (no TF numerics), so oneDNN's kernels do not
  matter, and TF 2.21 prints their notice whatever TF_CPP_MIN_LOG_LEVEL says.
  A user's own setting of either variable wins."""
  os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
  os.environ.setdefault("TF_ENABLE_ONEDNN_OPTS", "0")


RECORD_IO_ENV = "PCDIFF_RECORD_IO"


def record_io() -> str:
  """'tf' or 'python': who reads and writes TFRecords. `PCDIFF_RECORD_IO`
  ('tf', 'python' or 'auto', the default) chooses; 'auto' takes TensorFlow
  when it is installed, else the TensorFlow-free `tfrecord` module (same bytes)."""
  choice = os.environ.get(RECORD_IO_ENV, "auto")
  if choice not in ("auto", "tf", "python"):
    raise ValueError(f"{RECORD_IO_ENV} must be 'auto', 'tf' or 'python', got {choice!r}")
  if choice == "auto":
    import importlib.util
    return "tf" if importlib.util.find_spec("tensorflow") is not None else "python"
  return choice


def _tf():
  quiet_tensorflow_env()
  import tensorflow as tf  # imported lazily: only the loader/writer needs TF
  tf.config.set_visible_devices([], "GPU")  # TF must never take JAX's GPU
  return tf


def _ragged_spec():
  tf = _tf()
  dtypes = {"float": tf.float32, "int64": tf.int64, "bytes": tf.string}
  return {k: tf.io.RaggedFeature(dtypes[feature_kind(k)], row_splits_dtype=tf.int64)
          for k in all_keys()}


def _parse_raw(raw: Sequence[bytes], path: str, first_index: int) -> list:
  """Parses serialized examples into per-record dicts of flat numpy arrays.

  A record that is not a tf.train.Example comes back as a WomdFormatError in
  its place, so one bad record never takes its neighbours with it.
  """
  if record_io() == "python":
    return [_parse_one_python(r, path, first_index + i) for i, r in enumerate(raw)]
  tf = _tf()
  spec = _ragged_spec()
  try:
    parsed = tf.io.parse_example(tf.constant(list(raw)), spec)
  except tf.errors.InvalidArgumentError:
    if len(raw) == 1:
      return [WomdFormatError(path, first_index, None,
                              "not a tf.train.Example in the WOMD schema (could not parse it)")]
    out = []
    for i, r in enumerate(raw):  # find the bad one(s)
      out += _parse_raw([r], path, first_index + i)
    return out
  flat = {k: (v.flat_values.numpy(), v.row_splits.numpy()) for k, v in parsed.items()}
  return [{k: values[splits[i]:splits[i + 1]] for k, (values, splits) in flat.items()}
          for i in range(len(raw))]


@functools.lru_cache(maxsize=1)
def _feature_kinds() -> dict[str, str]:
  return {k: feature_kind(k) for k in all_keys()}


def _parse_one_python(raw: bytes, path: str, index: int):
  from pcdiff_jax.data import tfrecord
  try:
    return tfrecord.parse_example(raw, _feature_kinds())
  except Exception:  # DecodeError, or a feature stored with another list type
    return WomdFormatError(path, index, None, "not a tf.train.Example in the WOMD schema (could not parse it)")


def _check_length(ex: dict, key: str, expected: int, path: str, index: int) -> np.ndarray:
  value = ex[key]
  if value.size == 0:
    raise WomdFormatError(path, index, key, "required feature is missing or empty")
  if value.size != expected:
    raise WomdFormatError(path, index, key, f"has {value.size} values, expected {expected}")
  return value


def _object_traj(ex: dict, num_obj: int, cfg: LoaderConfig, path: str, index: int) -> dict:
  """Concatenated (num_obj, T) arrays per Trajectory field, in raw dtypes."""
  steps = {"past": cfg.num_past, "current": NUM_CURRENT, "future": cfg.num_future}
  out = {}
  for feat, field in OBJECT_TIME_FEATURES.items():
    parts = []
    for t in TIME_KEYS:
      key = f"state/{t}/{feat}"
      parts.append(_check_length(ex, key, num_obj * steps[t], path, index).reshape(num_obj, steps[t]))
    out[field] = np.concatenate(parts, axis=1)
  return out


def _traffic_lights(ex: dict, cfg: LoaderConfig, path: str, index: int) -> dict:
  steps = {"past": cfg.num_past, "current": NUM_CURRENT, "future": cfg.num_future}
  num_lights = ex["traffic_light_state/current/state"].size
  if num_lights == 0:
    raise WomdFormatError(path, index, "traffic_light_state/current/state",
                          "required feature is missing or empty")
  out = {}
  for feat in TRAFFIC_LIGHT_FEATURES:
    parts = []
    for t in TIME_KEYS:
      key = f"traffic_light_state/{t}/{feat}"
      # Stored time-major (steps, L); Waymax's layout is (L, T).
      parts.append(_check_length(ex, key, num_lights * steps[t], path, index).reshape(steps[t], num_lights).T)
    out[feat] = np.concatenate(parts, axis=1)
  return out


def _pad(a: np.ndarray, size: int, axis: int, value) -> np.ndarray:
  pad = [(0, 0)] * a.ndim
  pad[axis] = (0, size - a.shape[axis])
  return np.pad(a, pad, constant_values=value)


def _check_finite(values: np.ndarray, valid: np.ndarray, key: str, path: str, index: int) -> None:
  bad = ~np.isfinite(values) & valid
  if np.any(bad):
    raise WomdFormatError(path, index, key, f"{int(bad.sum())} non-finite value(s) at valid entries")


def example_to_numpy_state(ex: dict, path: str, index: int, cfg: LoaderConfig) -> tuple[dict, str]:
  """One parsed record -> (nested dict of padded numpy arrays, scenario id)."""
  scenario_id = ex["scenario/id"]
  if scenario_id.size != 1:
    raise WomdFormatError(path, index, "scenario/id", "required feature is missing")
  scenario_id = scenario_id[0].decode()
  num_obj = ex["state/id"].size
  if num_obj == 0:
    raise WomdFormatError(path, index, "state/id", "required feature is missing or empty")
  meta = {k: _check_length(ex, f"state/{k}", num_obj, path, index) for k in OBJECT_FEATURES}
  traj = _object_traj(ex, num_obj, cfg, path, index)
  if cfg.history_only:  # the converter's fill value after the current step
    traj = {k: np.concatenate([v[:, :cfg.num_past + 1], np.full_like(v[:, cfg.num_past + 1:], 0 if k == "valid" else -1)], 1)
            for k, v in traj.items()}
  valid = traj["valid"] == 1
  for field in ("x", "y", "z", "vel_x", "vel_y", "yaw", "length", "width", "height"):
    _check_finite(traj[field], valid, f"state/*/{field}", path, index)
  if np.any(np.abs(traj["timestamp_micros"]) > np.iinfo(np.int32).max):
    raise WomdFormatError(path, index, "state/*/timestamp_micros", "does not fit int32")

  current = cfg.num_past
  if not valid[:, current].any():
    raise WomdFormatError(path, index, "state/current/valid", "no object is valid at the current step")
  num_sdc = int((meta["is_sdc"] == 1).sum())
  if num_sdc != 1:
    raise WomdFormatError(path, index, "state/is_sdc", f"expected exactly one SDC, found {num_sdc}")

  # Objects: keep every slot if they fit, else the slots holding real objects.
  real = np.nonzero((meta["tracks_to_predict"] != -1) & valid.any(axis=1))[0]
  for n_pad in object_sizes(cfg.max_num_objects):
    keep = np.arange(num_obj) if num_obj <= n_pad else real
    if keep.size <= n_pad:
      break
  else:
    raise WomdFormatError(path, index, "state/id",
                          f"{real.size} valid objects exceed max_num_objects={n_pad}")

  # Box sizes: mean over valid steps (Waymax), computed in float64 so that a
  # constant size reads back bit-identical; never-valid slots keep raw values.
  sizes = {}
  count = valid.sum(axis=1, keepdims=True)
  for field in ("length", "width", "height"):
    raw = traj[field].astype(np.float64)
    mean = (raw * valid).sum(axis=1, keepdims=True) / np.maximum(count, 1)
    sizes[field] = np.where(count > 0, np.broadcast_to(mean, raw.shape), raw).astype(np.float32)

  def obj(a, pad_value, dtype):
    return _pad(np.asarray(a)[keep].astype(dtype), n_pad, 0, pad_value)

  trajectory = {f: obj(traj[f], -1.0, np.float32) for f in ("x", "y", "z", "vel_x", "vel_y", "yaw")}
  # Waymax's loader wraps the stored yaw (WOMD stores some unwrapped along
  # time) into [-pi, pi): the same float32 arithmetic, so values are equal.
  trajectory["yaw"] = wrap_yaw(trajectory["yaw"])
  trajectory.update({f: obj(sizes[f], -1.0, np.float32) for f in sizes})
  trajectory["valid"] = obj(valid, False, bool)
  trajectory["timestamp_micros"] = obj(traj["timestamp_micros"], -1, np.int32)
  ttp = meta["tracks_to_predict"]
  metadata = {
      "ids": obj(meta["id"], -1, np.int32),
      "object_types": obj(meta["type"], -1, np.int32),
      "is_sdc": obj(meta["is_sdc"] == 1, False, bool),
      "is_modeled": obj(ttp == 1, False, bool),
      "is_valid": obj(ttp != -1, False, bool),
      "objects_of_interest": obj(meta["objects_of_interest"] == 1, False, bool),
      "is_controlled": np.zeros(n_pad, bool),
  }

  # Roadgraph.
  num_points = ex["roadgraph_samples/type"].size
  if num_points == 0:
    raise WomdFormatError(path, index, "roadgraph_samples/type", "required feature is missing or empty")
  xyz = _check_length(ex, "roadgraph_samples/xyz", 3 * num_points, path, index).reshape(num_points, 3)
  dirs = _check_length(ex, "roadgraph_samples/dir", 3 * num_points, path, index).reshape(num_points, 3)
  rg_valid = _check_length(ex, "roadgraph_samples/valid", num_points, path, index) == 1
  rg_types = ex["roadgraph_samples/type"]
  rg_ids = _check_length(ex, "roadgraph_samples/id", num_points, path, index)
  _check_finite(xyz, rg_valid[:, None], "roadgraph_samples/xyz", path, index)
  _check_finite(dirs, rg_valid[:, None], "roadgraph_samples/dir", path, index)
  rg_keep = np.arange(num_points)
  if num_points > cfg.max_num_rg_points:
    # Waymax keeps the points nearest the SDC; we keep record order among them
    # so polylines stay contiguous (the off-road check relies on it).
    sdc = int(np.argmax(meta["is_sdc"] == 1))
    sdc_xy = np.array([traj["x"][sdc, current], traj["y"][sdc, current]])
    dist = np.where(rg_valid, np.linalg.norm(xyz[:, :2] - sdc_xy, axis=1), np.inf)
    rg_keep = np.sort(np.argsort(dist, kind="stable")[:cfg.max_num_rg_points])

  def rg(a, pad_value, dtype):
    return _pad(np.asarray(a)[rg_keep].astype(dtype), cfg.max_num_rg_points, 0, pad_value)

  roadgraph = {
      "x": rg(xyz[:, 0], -1.0, np.float32), "y": rg(xyz[:, 1], -1.0, np.float32),
      "z": rg(xyz[:, 2], -1.0, np.float32), "dir_x": rg(dirs[:, 0], 0.0, np.float32),
      "dir_y": rg(dirs[:, 1], 0.0, np.float32), "dir_z": rg(dirs[:, 2], 0.0, np.float32),
      "types": rg(rg_types, -1, np.int32), "ids": rg(rg_ids, -1, np.int32),
      "valid": rg(rg_valid, False, bool),
  }

  # Traffic lights.
  tl = _traffic_lights(ex, cfg, path, index)
  if cfg.history_only:
    tl = {k: np.concatenate([v[:, :cfg.num_past + 1], np.full_like(v[:, cfg.num_past + 1:], 0 if k == "valid" else -1)], 1)
          for k, v in tl.items()}
  tl_valid = tl["valid"] == 1
  _check_finite(np.stack([tl["x"], tl["y"], tl["z"]]), tl_valid[None], "traffic_light_state/*/xyz", path, index)
  num_lights = tl["state"].shape[0]
  if num_lights > cfg.max_num_traffic_lights:
    used = tl_valid.any(axis=1)
    if used[cfg.max_num_traffic_lights:].any():
      raise WomdFormatError(path, index, "traffic_light_state/current/state",
                            f"{num_lights} light slots exceed max_num_traffic_lights="
                            f"{cfg.max_num_traffic_lights}")
    tl = {k: v[:cfg.max_num_traffic_lights] for k, v in tl.items()}
    tl_valid = tl_valid[:cfg.max_num_traffic_lights]
  L = cfg.max_num_traffic_lights
  lights = {
      "x": _pad(tl["x"].astype(np.float32), L, 0, -1.0), "y": _pad(tl["y"].astype(np.float32), L, 0, -1.0),
      "z": _pad(tl["z"].astype(np.float32), L, 0, -1.0), "state": _pad(tl["state"].astype(np.int32), L, 0, -1),
      "lane_ids": _pad(tl["id"].astype(np.int32), L, 0, -1), "valid": _pad(tl_valid, L, 0, False),
  }
  return {"trajectory": trajectory, "metadata": metadata, "roadgraph": roadgraph,
          "lights": lights}, scenario_id


def wrap_yaw(yaw: np.ndarray) -> np.ndarray:
  """float32 yaw wrapped into [-pi, pi) (as Waymax's loader does)."""
  yaw = np.asarray(yaw, np.float32)
  pi = np.float32(np.pi)
  return ((yaw + pi) % np.float32(2 * np.pi) - pi).astype(np.float32)


def numpy_to_state(arrays: dict, to_jax: bool = True) -> SimulatorState:
  """Nested numpy dict (optionally with a leading batch dim) -> SimulatorState.

  As Waymax's loader returns it: timestep = 0, and the sim trajectory is the
  log at t = 0 only, zeros and invalid after (`sim.reset` then fills the
  history up to the current step). Code that reads a loaded state at a later
  step reads its log (e.g. `training.data.example_at`) or resets it first.
  """
  import jax.numpy as jnp
  conv = jnp.asarray if to_jax else np.asarray
  log = arrays["trajectory"]
  first = np.arange(log["x"].shape[-1]) == 0                                  # (T,)
  sim = {k: np.where(first, v, np.zeros((), v.dtype)) for k, v in log.items()}
  traj = Trajectory(**{k: conv(v) for k, v in log.items()})
  batch = log["x"].shape[:-2]
  state = SimulatorState(
      sim_trajectory=Trajectory(**{k: conv(v) for k, v in sim.items()}),
      log_trajectory=traj,
      log_traffic_light=TrafficLights(**{k: conv(v) for k, v in arrays["lights"].items()}),
      object_metadata=ObjectMetadata(**{k: conv(v) for k, v in arrays["metadata"].items()}),
      timestep=conv(np.zeros(batch, np.int32)),
      roadgraph_points=RoadgraphPoints(**{k: conv(v) for k, v in arrays["roadgraph"].items()}),
  )
  return state


def _records(path: str, chunk: int) -> Iterator[tuple[int, list[bytes]]]:
  """(first index, raw records) chunks of a TFRecord file, via tf.data (or `tfrecord`)."""
  if record_io() == "python":
    yield from _records_python(path, chunk)
    return
  tf = _tf()
  dataset = tf.data.TFRecordDataset(path).batch(chunk)
  index = 0
  iterator = iter(dataset)
  while True:
    try:
      batch = next(iterator)
    except StopIteration:
      return
    except (tf.errors.DataLossError, tf.errors.InvalidArgumentError) as err:
      # Chunks are read whole; locate the bad record by re-reading one by one.
      yield from _records_one_by_one(path, index, err)
      return
    raw = list(batch.numpy())
    yield index, raw
    index += len(raw)


def _records_one_by_one(path: str, start: int, err) -> Iterator[tuple[int, list[bytes]]]:
  tf = _tf()
  iterator = iter(tf.data.TFRecordDataset(path).skip(start))
  index = start
  while True:
    try:
      raw = next(iterator)
    except StopIteration:  # the error was in a later chunk that now reads fine
      return
    except (tf.errors.DataLossError, tf.errors.InvalidArgumentError) as e:
      raise WomdFormatError(path, index, None,
                            f"corrupted or truncated TFRecord ({e.message.splitlines()[0]})") from None
    yield index, [raw.numpy()]
    index += 1


def _records_python(path: str, chunk: int) -> Iterator[tuple[int, list[bytes]]]:
  from pcdiff_jax.data import tfrecord
  index, raw = 0, []
  try:
    for record in tfrecord.read_records(path):
      raw.append(record)
      if len(raw) == chunk:
        yield index, raw
        index, raw = index + len(raw), []
  except tfrecord.RecordError as err:
    if raw:
      yield index, raw
    raise WomdFormatError(path, err.index, None, f"corrupted or truncated TFRecord ({err})") from None
  if raw:
    yield index, raw


RECORD_FORMATS = ("auto", "tf_example", "scenario")


def detect_format(raw: bytes, path: str = "<bytes>", index: int = 0) -> str:
  """'tf_example' or 'scenario': the WOMD flavour of one serialized record."""
  from pcdiff_jax.data import tfrecord
  keys = tfrecord.is_example(raw) or []
  if any(k == "scenario/id" or k.startswith("state/") for k in keys):
    return "tf_example"
  from pcdiff_jax.data import scenario_proto
  if scenario_proto.is_scenario(raw):
    return "scenario"
  raise WomdFormatError(path, index, None, "neither a WOMD motion tf.Example nor a WOMD Scenario proto")


def object_sizes(max_num_objects: Optional[int]) -> tuple[int, ...]:
  """The padded object counts to try, smallest first."""
  return OBJECT_BUCKETS if max_num_objects is None else (max_num_objects,)


def pad_objects(arrays: dict, size: int) -> dict:
  """A scenario's numpy arrays (`iterate_numpy`) padded to `size` objects
  with the loader's fill values (-1, False), to batch it with larger ones."""
  def pad(a):
    fill = False if a.dtype == bool else -1
    return _pad(a, size, 0, fill)
  return {**arrays, "trajectory": {k: pad(v) for k, v in arrays["trajectory"].items()},
          "metadata": {k: pad(v) for k, v in arrays["metadata"].items()}}


def _parse_scenarios(raw: Sequence[bytes], path: str, first_index: int, cfg: LoaderConfig) -> Iterator:
  """Scenario protos -> the per-record dicts `_parse_raw` gives (errors in
  place), one at a time: a reader that stops early converts no more."""
  from pcdiff_jax.data import scenario_proto
  for i, r in enumerate(raw):
    try:
      yield scenario_proto.scenario_to_example(
          r, num_past=cfg.num_past, num_future=cfg.num_future, max_objects=object_sizes(cfg.max_num_objects),
          max_lights=cfg.max_num_traffic_lights)
    except scenario_proto.ScenarioFormatError as err:
      yield WomdFormatError(path, first_index + i, err.field, str(err))


def iterate_numpy(paths, cfg: LoaderConfig = LoaderConfig(), on_error: str = "raise",
                  chunk: int = 32, skipped: Optional[list] = None,
                  record_format: str = "auto") -> Iterator[tuple[dict, ScenarioMeta]]:
  """Yields (numpy arrays, ScenarioMeta) for each record of `paths`, in order.

  With on_error='skip', each skipped record's WomdFormatError is logged and
  appended to `skipped` (when given). record_format: 'auto' (each file's
  first record decides), 'tf_example' or 'scenario'.
  """
  if on_error not in ("raise", "skip"):
    raise ValueError(f"on_error must be 'raise' or 'skip', got {on_error!r}")
  if record_format not in RECORD_FORMATS:
    raise ValueError(f"record_format must be one of {RECORD_FORMATS}, got {record_format!r}")
  for path in expand_paths(paths):
    kind = None if record_format == "auto" else record_format
    try:
      for first, raw in _records(path, chunk):
        if raw and kind is None:
          kind = detect_format(raw[0], path, first)
        parsed = (_parse_scenarios(raw, path, first, cfg) if kind == "scenario"
                  else _parse_raw(raw, path, first) if raw else [])
        for i, ex in enumerate(parsed):
          index = first + i
          try:
            if isinstance(ex, WomdFormatError):
              raise ex
            arrays, sid = example_to_numpy_state(ex, path, index, cfg)
          except WomdFormatError as err:
            if on_error == "raise":
              raise
            log.warning("skipping bad scenario: %s", err)
            if skipped is not None:
              skipped.append(err)
            continue
          yield arrays, ScenarioMeta(scenario_id=sid, path=path, record_index=index)
    except WomdFormatError as err:
      if on_error == "raise":
        raise
      log.warning("skipping rest of file: %s", err)
      if skipped is not None:
        skipped.append(err)


def _stack(items: list[dict]) -> dict:
  import jax
  size = max(a["metadata"]["ids"].shape[0] for a in items)   # scenes of different buckets: the largest
  items = [pad_objects(a, size) for a in items]
  return jax.tree_util.tree_map(lambda *xs: np.stack(xs), *items)


def iterate(paths, batch_size: Optional[int] = None, max_num_objects: Optional[int] = 128,
            max_num_rg_points: int = 30000, max_num_traffic_lights: int = 16,
            on_error: str = "raise", with_meta: bool = False, drop_remainder: bool = False,
            to_jax: bool = True, skipped: Optional[list] = None,
            max_scenarios: Optional[int] = None, record_format: str = "auto",
            history_only: bool = False) -> Iterator:
  """Reads WOMD motion TFRecords into padded `SimulatorState`s.

  Args:
    paths: a file, a glob, or a list of files/globs (read in sorted order).
    batch_size: None yields single states (O, T); an int yields batched
      states (B, O, T); the last smaller batch is kept unless drop_remainder.
    max_num_objects, max_num_rg_points, max_num_traffic_lights: fixed padded
      sizes (records larger than these: see the module docstring);
      max_num_objects=None pads each scenario to the first of OBJECT_BUCKETS
      that holds it, and a batch to its largest scenario's.
    on_error: 'raise' (default) or 'skip' bad records with a warning.
    with_meta: also yield a `ScenarioMeta` (scenario ids, file, record index).
    skipped: a list that collects the errors of skipped records.
    max_scenarios: stop after this many scenarios (None: all).
    record_format: 'auto' (tf.Example or Scenario proto, from each file's
      first record), 'tf_example' or 'scenario'.
    history_only: keep only the steps up to the current one (the rest
      invalid, -1), as in WOMD's test split: for simulations that must not see
      the logged future (box sizes are then the mean over the history).
  Yields:
    SimulatorState, or (SimulatorState, ScenarioMeta) when with_meta.
  """
  cfg = LoaderConfig(max_num_objects=max_num_objects, max_num_rg_points=max_num_rg_points,
                     max_num_traffic_lights=max_num_traffic_lights, history_only=history_only)
  source = iterate_numpy(paths, cfg, on_error=on_error, skipped=skipped, record_format=record_format)
  if max_scenarios is not None:
    source = itertools.islice(source, max_scenarios)
  if batch_size is None:
    for arrays, meta in source:
      state = numpy_to_state(arrays, to_jax=to_jax)
      yield (state, meta) if with_meta else state
    return
  pending: list[tuple[dict, ScenarioMeta]] = []
  for item in source:
    pending.append(item)
    if len(pending) == batch_size:
      yield _batch(pending, with_meta, to_jax)
      pending = []
  if pending and not drop_remainder:
    yield _batch(pending, with_meta, to_jax)


def _batch(items, with_meta: bool, to_jax: bool):
  state = numpy_to_state(_stack([a for a, _ in items]), to_jax=to_jax)
  if not with_meta:
    return state
  meta = ScenarioMeta(scenario_id=tuple(m.scenario_id for _, m in items),
                      path=tuple(m.path for _, m in items),
                      record_index=tuple(m.record_index for _, m in items))
  return state, meta


def load(path: str, index: int = 0, **kwargs) -> tuple[SimulatorState, ScenarioMeta]:
  """The `index`-th record of `path` as (state, meta)."""
  for i, item in enumerate(iterate(path, with_meta=True, **kwargs)):
    if i == index:
      return item
  raise WomdFormatError(path, index, None, "record index out of range")


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------

def _split_time(a: np.ndarray, num_past: int) -> dict[str, np.ndarray]:
  """(X, T) -> past (X, num_past), current (X, 1), future (X, rest)."""
  return {"past": a[:, :num_past], "current": a[:, num_past:num_past + 1],
          "future": a[:, num_past + 1:]}


def state_to_example(state: SimulatorState, scenario_id: str, trajectory: str = "log",
                     num_past: int = NUM_PAST, difficulty_level: Optional[np.ndarray] = None):
  """An unbatched SimulatorState -> tf.train.Example in the WOMD motion schema.

  Args:
    state: one scenario (O, T), e.g. from `iterate` or the synthetic generator.
    scenario_id: written to `scenario/id`.
    trajectory: 'log' writes the log trajectory; 'sim' writes the simulated one
      (e.g. to save closed-loop rollouts as WOMD records).
  """
  if state.shape:
    raise ValueError(f"state_to_example takes one scenario, got batch dims {state.shape}")
  traj = state.log_trajectory if trajectory == "log" else state.sim_trajectory
  t = {f: np.asarray(getattr(traj, f)) for f in Trajectory.FLOAT_FIELDS + ("valid", "timestamp_micros")}
  valid = t["valid"]
  speed = np.where(valid, np.hypot(t["vel_x"], t["vel_y"]), -1.0).astype(np.float32)
  vel_yaw = np.where(valid, np.arctan2(t["vel_y"], t["vel_x"]), -1.0).astype(np.float32)
  md = state.object_metadata
  is_valid = np.asarray(md.is_valid)
  feats: dict[str, np.ndarray] = {
      "state/id": np.asarray(md.ids, np.float32),
      "state/type": np.asarray(md.object_types, np.float32),
      "state/is_sdc": np.asarray(md.is_sdc, np.int64),
      "state/tracks_to_predict": np.where(is_valid, np.asarray(md.is_modeled, np.int64), -1),
      "state/objects_of_interest": np.asarray(md.objects_of_interest, np.int64),
      "state/difficulty_level": (np.zeros(is_valid.shape, np.int64) if difficulty_level is None
                                 else np.asarray(difficulty_level, np.int64)),
  }
  per_field = dict(t, speed=speed, vel_yaw=vel_yaw)
  names = {v: k for k, v in OBJECT_TIME_FEATURES.items()}
  names.update(speed="speed", vel_yaw="vel_yaw")
  for field, values in per_field.items():
    for key, part in _split_time(values, num_past).items():
      feats[f"state/{key}/{names[field]}"] = part
  rg = state.roadgraph_points
  feats["roadgraph_samples/xyz"] = np.stack([rg.x, rg.y, rg.z], -1)
  feats["roadgraph_samples/dir"] = np.stack([rg.dir_x, rg.dir_y, rg.dir_z], -1)
  feats["roadgraph_samples/type"] = np.asarray(rg.types, np.int64)[:, None]
  feats["roadgraph_samples/id"] = np.asarray(rg.ids, np.int64)[:, None]
  feats["roadgraph_samples/valid"] = np.asarray(rg.valid, np.int64)[:, None]
  tl = state.log_traffic_light
  tl_fields = {"state": tl.state, "x": tl.x, "y": tl.y, "z": tl.z, "id": tl.lane_ids, "valid": tl.valid}
  sdc = int(np.argmax(np.asarray(md.is_sdc)))
  ts = np.asarray(state.log_trajectory.timestamp_micros)[sdc]
  for name, values in tl_fields.items():
    for key, part in _split_time(np.asarray(values), num_past).items():
      feats[f"traffic_light_state/{key}/{name}"] = part.T  # time-major on disk
  for key, part in _split_time(ts[None], num_past).items():
    feats[f"traffic_light_state/{key}/timestamp_micros"] = part[0]

  from pcdiff_jax.data import tfrecord
  features = {k: (feature_kind(k), np.asarray(v).reshape(-1)) for k, v in feats.items()}
  features["scenario/id"] = ("bytes", [scenario_id.encode()])
  # The private-pool Example: its bytes are tf.train.Example's (`tfrecord`).
  return tfrecord.make_example(features)


def write(path: str, items: Iterable[tuple[SimulatorState, str]], trajectory: str = "log",
          record_format: str = "tf_example") -> int:
  """Writes (state, scenario_id) pairs to a TFRecord; returns the count.
  record_format: 'tf_example' (WOMD motion tf.Examples) or 'scenario'
  (Scenario protos, `scenario_proto.state_to_scenario`).

  Writes to `path + '.tmp'` and renames at the end, so an interrupted write
  never leaves a truncated file under the final name.
  """
  if record_format not in ("tf_example", "scenario"):
    raise ValueError(f"record_format must be 'tf_example' or 'scenario', got {record_format!r}")
  if record_format == "scenario":
    from pcdiff_jax.data.scenario_proto import state_to_scenario as encode
  else:
    encode = state_to_example
  tmp = f"{path}.tmp"
  count = 0
  if record_io() == "python":
    from pcdiff_jax.data import tfrecord
    with open(tmp, "wb") as f:
      for state, scenario_id in items:
        tfrecord.write_record(f, encode(state, scenario_id, trajectory=trajectory).SerializeToString(
            deterministic=True))
        count += 1
  else:
    with _tf().io.TFRecordWriter(tmp) as writer:
      for state, scenario_id in items:
        writer.write(encode(state, scenario_id, trajectory=trajectory).SerializeToString(deterministic=True))
        count += 1
  os.replace(tmp, path)
  return count
