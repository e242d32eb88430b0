"""Training examples: encoder features and future targets, cached once per dataset.

Parsing a WOMD record (20-30k roadgraph points) and cutting its map into
pieces costs far more than a training step of the `cpu` encoder, so the
examples are built once, in jitted batches, and kept as numpy arrays in
`WORKDIR/cache/<split>-<key>.npz`. The key hashes the features config, the
horizon, the replanning steps and the input files (names, sizes, mtimes): a
changed input rebuilds the cache; an interrupted build leaves no file (it is
written to a temporary name and renamed).

An example is the scene at a replanning step t (`current_steps`, 10 = WOMD's
current step by default): `SceneFeatures` for the encoder and `Targets`, the
logged future t+1 .. t+T of each selected agent in that agent's frame at t.
Bad records are skipped with a warning naming the file and record (the count
is returned), never fatal.

Batches are a pure function of (seed, step): epoch e visits a permutation
drawn from (seed, e), so a resumed run sees exactly the batches it would have.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import json
import logging
import os
from typing import Iterator, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.config import FeaturesConfig
from pcdiff_jax.data import womd
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model.features import SceneFeatures
from pcdiff_jax.sim import dynamics, geometry
from pcdiff_jax.sim import metrics as sim_metrics
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState

log = logging.getLogger(__name__)

_BUILD_BATCH = 8
_CACHE_VERSION = 1


@struct.dataclass
class Targets:
  """Logged futures of the selected agents, in each agent's frame at t.

  future_xy: (..., A, T, 2); future_yaw: (..., A, T) relative to the heading
  at t; future_speed: (..., A, T) signed speed; future_valid: (..., A, T);
  current_speed: (..., A) signed speed at t (the kinematic state at t is
  [0, 0, 0, current_speed] in the agent frame).
  """
  future_xy: Array
  future_yaw: Array
  future_speed: Array
  future_valid: Array
  current_speed: Array


@struct.dataclass
class Example:
  feats: SceneFeatures
  targets: Targets


def log_overlaps_ahead(state: SimulatorState, idx: Array, horizon: int) -> Array:
  """(A,) bool: object idx[a]'s logged box overlaps another valid logged box at some step of
  (t, t + horizon], t = state.timestep. Real labels of queued and parked cars overlap (log
  replay collides with 6.6% of the real val agents, docs/RESULTS.md, "Table I (real WOMD val)");
  synthetic logs never do."""
  hits = sim_metrics.overlap(state.log_trajectory)                      # (O, T_all)
  steps = jnp.arange(hits.shape[-1])
  ahead = (steps > state.timestep) & (steps <= state.timestep + horizon)
  return jnp.any(hits[idx] & ahead[None], axis=-1)


def log_leaves_road_ahead(state: SimulatorState, idx: Array, horizon: int) -> Array:
  """(A,) bool: object idx[a] is a vehicle whose logged box is on the mapped road at
  t = state.timestep and off it at some step of (t, t + horizon]: real drivers turn into lots
  and driveways the map does not hold. A car parked off the road stays in. Leaving them out did
  not keep a real round's cars on the road (docs/RESULTS.md, "Ablation: fine-tuning on real
  scenes", R10)."""
  off = sim_metrics.offroad(state.log_trajectory, state.roadgraph_points)   # (O, T_all)
  steps = jnp.arange(off.shape[-1])
  ahead = (steps > state.timestep) & (steps <= state.timestep + horizon)
  now = off[idx, state.timestep]
  vehicle = state.object_metadata.object_types[idx] == ObjectType.VEHICLE
  return vehicle & ~now & jnp.any(off[idx] & ahead[None], axis=-1)


def dropped_labels(state: SimulatorState, idx: Array, horizon: int, drop_log_overlaps: bool,
                   drop_log_offroad: bool) -> Array:
  """(A,) bool: the agents left out of training by the two drops (real scenes' labels)."""
  drop = jnp.zeros(idx.shape, bool)
  if drop_log_overlaps:
    drop = drop | log_overlaps_ahead(state, idx, horizon)
  if drop_log_offroad:
    drop = drop | log_leaves_road_ahead(state, idx, horizon)
  return drop


def targets_at(state: SimulatorState, feats: SceneFeatures, horizon: int,
               drop_log_overlaps: bool = False, drop_log_offroad: bool = False) -> Targets:
  """Targets of one scene at t = state.timestep for the agents of `feats`.

  Steps past the end of the log are invalid. Reads the log trajectory for
  the future and the sim trajectory for the pose at t (equal in a dataset).
  drop_log_overlaps: an agent whose logged box overlaps another in the horizon
  (`log_overlaps_ahead`) gets no valid step, so it is not trained on; drop_log_offroad: so
  a vehicle whose log leaves the mapped road (`log_leaves_road_ahead`).
  """
  t = state.timestep
  idx = feats.agent_index
  states = dynamics.states_from_trajectory(state.log_trajectory)        # (O, T_all, 4)
  sim_now = dynamics.states_from_trajectory(state.sim_trajectory)[idx, t]   # (A, 4)
  steps = t + 1 + jnp.arange(horizon)
  in_range = steps < state.log_trajectory.num_timesteps
  steps = jnp.clip(steps, 0, state.log_trajectory.num_timesteps - 1)
  fut = states[idx][:, steps]                                            # (A, T, 4)
  valid = state.log_trajectory.valid[idx][:, steps] & in_range[None] & feats.agent_valid[:, None]
  valid = valid & ~dropped_labels(state, idx, horizon, drop_log_overlaps, drop_log_offroad)[:, None]
  origin, yaw0 = sim_now[:, None, :2], sim_now[:, None, 2]
  xy = geometry.to_local(fut[..., :2], origin, yaw0)
  yaw = geometry.wrap_angle(fut[..., 2] - yaw0)
  zero = lambda a: jnp.where(valid if a.ndim == 2 else valid[..., None], a, 0.0)
  return Targets(future_xy=zero(xy), future_yaw=zero(yaw), future_speed=zero(fut[..., 3]),
                 future_valid=valid,
                 current_speed=jnp.where(feats.agent_valid, sim_now[:, 3], 0.0))


def example_at(state: SimulatorState, step: int, config: FeaturesConfig, horizon: int,
               drop_log_overlaps: bool = False, drop_log_offroad: bool = False) -> Example:
  """One scene's Example of the log at replanning step `step`: the state is
  read with its sim trajectory set to the log (a loaded state, as Waymax's,
  has only t = 0 simulated)."""
  state = state.replace(sim_trajectory=state.log_trajectory, timestep=jnp.asarray(step, jnp.int32))
  feats = features_lib.scene_features(state, config)
  return Example(feats=feats, targets=targets_at(state, feats, horizon, drop_log_overlaps, drop_log_offroad))


# ----------------------------------------------------------------------------
# Cache.


@dataclasses.dataclass(frozen=True)
class CacheSpec:
  """What a cache of logged examples holds: features, horizon, the steps cut into examples, and
  whether agents whose logged boxes overlap another in the horizon, or vehicles whose logs leave
  the mapped road, are left out (real scenes)."""
  features: FeaturesConfig
  horizon: int = 80
  current_steps: tuple[int, ...] = (10,)
  drop_log_overlaps: bool = False
  drop_log_offroad: bool = False


def _flatten(tree) -> dict[str, np.ndarray]:
  leaves, _ = jax.tree_util.tree_flatten_with_path(tree)
  return {jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in leaves}


def _unflatten(template, arrays: dict[str, np.ndarray]):
  leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
  return jax.tree_util.tree_unflatten(treedef, [arrays[jax.tree_util.keystr(p)] for p, _ in leaves])


def cache_key(files: Sequence[str], spec: CacheSpec) -> str:
  h = hashlib.sha1()
  fields = dataclasses.asdict(spec)
  for name in ("drop_log_overlaps", "drop_log_offroad"):
    if not fields[name]:   # caches built before the field keep their keys
      del fields[name]
  h.update(json.dumps({"v": _CACHE_VERSION, "spec": fields}, sort_keys=True).encode())
  for f in files:
    st = os.stat(f)
    h.update(f"{os.path.abspath(f)}:{st.st_size}:{int(st.st_mtime)}".encode())
  return h.hexdigest()[:12]


@functools.lru_cache(maxsize=8)
def _example_fn(spec: CacheSpec):
  """One jitted builder per spec: the train and val sets share its compile."""
  def one(state):
    exs = [example_at(state, s, spec.features, spec.horizon, spec.drop_log_overlaps, spec.drop_log_offroad)
           for s in spec.current_steps]
    return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *exs)      # (S, ...)
  return jax.jit(jax.vmap(one))


def build_examples(paths, spec: CacheSpec, progress: bool = True,
                   limit: Optional[int] = None) -> tuple[Example, list[str], int]:
  """Examples of every scenario of `paths` at each step of `spec.current_steps`.

  Returns: the stacked Example (N, ...) as numpy, the scenario ids (N,)
  and the number of skipped bad records. Raises ValueError when no record
  could be read.
  """
  from tqdm.auto import tqdm
  fn = _example_fn(spec)
  skipped: list = []
  chunks, ids, pending = [], [], []

  def flush():
    n = len(pending)
    batch = womd._stack(pending + [pending[-1]] * (_BUILD_BATCH - n))  # fixed shape: no recompile
    out = jax.device_get(fn(womd.numpy_to_state(batch)))
    chunks.append(jax.tree_util.tree_map(lambda a: a[:n].reshape((-1,) + a.shape[2:]), out))
    pending.clear()

  bar = tqdm(desc="examples", unit="scene", disable=not progress, total=limit)
  for arrays, meta in womd.iterate_numpy(paths, on_error="skip", skipped=skipped):
    pending.append(arrays)
    ids.extend([f"{meta.scenario_id}@{s}" for s in spec.current_steps])
    bar.update(1)
    if len(pending) == _BUILD_BATCH:
      flush()
    if limit is not None and len(ids) >= limit * len(spec.current_steps):
      break
  if pending:
    flush()
  bar.close()
  if not chunks:
    raise ValueError(f"no readable scenario in {paths!r} ({len(skipped)} skipped)")
  examples = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *chunks)
  return examples, ids, len(skipped)


def _template() -> Example:
  """An Example with placeholder leaves: its tree structure unflattens a cache file."""
  return Example(feats=SceneFeatures(**{f.name: 0 for f in dataclasses.fields(SceneFeatures)}),
                 targets=Targets(**{f.name: 0 for f in dataclasses.fields(Targets)}))


def load_or_build(paths, spec: CacheSpec, cache_dir: str, split: str,
                  progress: bool = True, limit: Optional[int] = None) -> tuple[Example, dict]:
  """Cached examples of `paths` (built and saved on the first call).

  Returns: Example (N, ...) numpy and info {"ids", "skipped", "path"}.
  """
  files = womd.expand_paths(paths)
  key = cache_key(files, spec) + (f"-first{limit}" if limit else "")
  path = os.path.join(cache_dir, f"{split}-{key}.npz")
  if os.path.exists(path):
    examples, info = read_examples(path)
    return examples, {**info, "path": path}
  examples, ids, skipped = build_examples(files, spec, progress=progress, limit=limit)
  os.makedirs(cache_dir, exist_ok=True)
  info = {"ids": ids, "skipped": skipped, "files": files}
  write_examples(path, examples, info)
  return examples, {**info, "path": path}


def write_examples(path: str, examples: Example, info: dict) -> None:
  """Writes numpy examples and a JSON-able info dict to `path` (.npz) atomically:
  a temporary name, then renamed, so an interrupted write leaves no file."""
  tmp = path + ".tmp.npz"
  np.savez(tmp, __info__=np.array(json.dumps(info)), **_flatten(examples))
  os.replace(tmp, path)


def read_examples(path: str) -> tuple[Example, dict]:
  """(examples, info) of a file written by `write_examples`."""
  with np.load(path, allow_pickle=False) as z:
    arrays = {k: z[k] for k in z.files}
  info = json.loads(str(arrays.pop("__info__")))
  return _unflatten(_template(), arrays), info


def num_examples(examples) -> int:
  """Leading size of a stacked pytree of examples."""
  return int(jax.tree_util.tree_leaves(examples)[0].shape[0])


def batch_at(examples: Example, step: int, batch_size: int, seed: int) -> Example:
  """The training batch of global `step`: a pure function of (seed, step)."""
  n = num_examples(examples)
  if n < batch_size:
    idx = np.random.default_rng([seed, step]).integers(0, n, size=batch_size)
  else:
    per_epoch = n // batch_size
    epoch, i = divmod(step, per_epoch)
    perm = np.random.default_rng([seed, epoch]).permutation(n)
    idx = np.sort(perm[i * batch_size:(i + 1) * batch_size])
  return jax.tree_util.tree_map(lambda a: a[idx], examples)


def eval_batches(examples: Example, batch_size: int) -> Iterator[tuple[Example, np.ndarray]]:
  """Fixed-size batches over all examples, in order; the last is padded by
  repeating example 0. Yields (batch, mask (B,) of real examples)."""
  n = num_examples(examples)
  for start in range(0, n, batch_size):
    idx = np.arange(start, start + batch_size)
    mask = idx < n
    idx = np.where(mask, idx, 0)
    yield jax.tree_util.tree_map(lambda a: a[idx], examples), mask
