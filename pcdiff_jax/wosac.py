"""Waymo Open Sim Agents Challenge: simulate every sim agent 32 times, export, check.

  cfg = wosac.WosacConfig(eval=evaluation.EvalConfig(method="pcdiff", checkpoint=W))
  summary = wosac.export("validation.tfrecord-*", "sub.binproto", cfg, submission.Metadata(...))
  report = wosac.check(["sub.binproto"], "validation.tfrecord-*")

Who drives whom (`make_actor`): the sim agents are the objects valid at step
10, the SDC included. `cv` and `idm` drive all of them. A learned method
(`pcdiff`, `pcdiff-noprior`, `simpl-ar`) drives the SDC and the
`eval.metrics.max_reactive_agents` sim agents nearest it (its agent cap, raised
at rollout time as in `evaluation.with_agent_cap`); IDM drives the sim agents
beyond the cap (the reactive fallback). A scene with fewer sim agents is
planned in fewer slots (`plan_cap`: 16, 32, 64, ...), the work sized to it.
`ego="idm"` hands the SDC to IDM instead.

What the simulation sees: the scenario read with `history_only` (no logged
state after step 10: objects that appear later never do, and no sim agent's
logged future is read; box sizes are the mean over the history), and the
traffic lights of step 10 held for the whole rollout (the test split has no
later light states). Rollouts r = 0..31 of a scenario use the keys
`split(fold_in(PRNGKey(seed), crc32(scenario_id)), 32)`, so a scenario's
rollouts do not depend on sharding or order; they run `rollouts_per_call` at a
time in one jitted, vmapped closed loop (`evaluation.make_rollout_fn`).
"""
from __future__ import annotations

import dataclasses
import functools
import itertools
import logging
import os
import time
import zlib
from typing import Any, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pcdiff_jax import baselines, evaluation
from pcdiff_jax.baselines import idm
from pcdiff_jax.data import submission, womd
from pcdiff_jax.sim.actors import Actor, combine

log = logging.getLogger(__name__)

# "idm" here is the lane-following IDM ("idm-lane"): the route IDM reads the logged future.
METHODS = ("cv", "idm", "idm-lane") + evaluation.LEARNED
# Reads the logged future: a reference for scoring and validation, never a valid submission.
LOG_REPLAY = "log"
EGOS = ("method", "idm")


@dataclasses.dataclass(frozen=True)
class WosacConfig:
  """eval: the method and its options (`evaluation.EvalConfig`: method,
  checkpoint, sampler, seed; `metrics.max_reactive_agents` is a learned
  method's cap of sim agents besides the SDC). ego: "method" (the method
  drives the SDC too) or "idm". num_rollouts: 32 for a valid submission.
  rollouts_per_call: rollouts per jitted call, or None (default) for `default_rollouts_per_call`
  of the backend: all 32 in one call on an accelerator, 4 on a CPU, where a smaller batch stays
  in cache (docs/BENCHMARKS.md, "WOSAC at WOMD scale"). The rollouts are the same either way up to
  float rounding: each has its own key.
  max_objects: padded object count, or None (default) for the first of
  `womd.OBJECT_BUCKETS` (128, 256, ...) that holds each scene: no scene is
  refused for its size, and the closed loop compiles once per bucket. hold_lights: step 10's traffic lights for the whole rollout.
  size_plans: a learned method plans a scene in the fewest of 16, 32, 64, ... agent slots
  (`plan_slots`) that hold its sim agents, up to its cap: less work on small scenes, the same
  model but other random draws than the full cap (False: always the cap's slots).
  tile_scene: each rollout of a call gets its own copy of the scene, so what depends on the
  scene alone (the road field) is computed per rollout; False (default) shares one copy
  (`evaluation.make_rollout_fn(one_scene=True)`), the same rollouts up to float rounding for
  less CPU (docs/BENCHMARKS.md, "WOSAC at WOMD scale"; `bench` times the two)."""
  eval: evaluation.EvalConfig = evaluation.EvalConfig()
  ego: str = "method"
  num_rollouts: int = submission.NUM_ROLLOUTS
  rollouts_per_call: Optional[int] = None
  max_objects: Optional[int] = None
  hold_lights: bool = True
  size_plans: bool = True
  tile_scene: bool = False

  def validate(self) -> None:
    if self.eval.method not in METHODS + (LOG_REPLAY,):
      raise ValueError(f"unknown WOSAC method {self.eval.method!r}; choose one of {list(METHODS)} "
                       "(log replay and the expert read the logged future)")
    if self.ego not in EGOS:
      raise ValueError(f"unknown ego {self.ego!r}; choose one of {list(EGOS)}")
    if self.num_rollouts < 1 or (self.rollouts_per_call is not None and self.rollouts_per_call < 1):
      raise ValueError("num_rollouts and rollouts_per_call must be >= 1")
    if self.eval.num_steps != submission.NUM_SIM_STEPS or self.eval.init_steps != submission.CURRENT_INDEX + 1:
      raise ValueError("WOSAC simulates steps 11-90: keep num_steps=80 and init_steps=11")


CPU_ROLLOUTS_PER_CALL = 4
# The export's map crop for a learned method (`experiments.wosac --map-pieces`): the 192 pieces
# nearest the SDC score as the model's 256 do on the 36 real val scenes (0.701 / 0.750 against
# 0.699 / 0.751 on the clean-heading / degree-stored ones) at 1.2x the export's throughput
# (docs/BENCHMARKS.md, "WOSAC export: the model's map crop against 192 pieces").
EXPORT_MAP_PIECES = 192


def default_rollouts_per_call(num_rollouts: int, platform: Optional[str] = None) -> int:
  """Rollouts per jitted call when the config leaves it open: every rollout on an accelerator
  (one wide batch), CPU_ROLLOUTS_PER_CALL on a CPU (1.19x less CPU time than 32 per call for a
  16-slot scene; docs/BENCHMARKS.md, "WOSAC at WOMD scale")."""
  platform = platform or jax.default_backend()
  return num_rollouts if platform != "cpu" else min(num_rollouts, CPU_ROLLOUTS_PER_CALL)


def sim_agents_mask(state) -> jax.Array:
  """(..., O) the sim agents of a state at its current step (after
  `sim.reset`: step 10): every object valid there, the SDC included."""
  return state.current_sim_trajectory.valid[..., 0]


def with_sdc(actor: Actor) -> Actor:
  """A learned actor that also drives the SDC, which its plans always model
  (it is the first agent of every plan): the SDC joins its controlled set at
  `init` (`policy.PlanState.controlled`, or SIMPL-AR's mask)."""
  def init(rng, state):
    inner = actor.init(rng, state)
    sdc = state.object_metadata.is_sdc & state.current_sim_trajectory.valid[..., 0]
    if isinstance(inner, jax.Array):
      return inner | sdc
    return inner.replace(controlled=inner.controlled | sdc)
  return Actor(select_action=actor.select_action, init=init, name=actor.name)


def make_actor(cfg: WosacConfig) -> tuple[Actor, Any]:
  """(actor, params): the method on every sim agent (see the module docstring)."""
  cfg.validate()
  if cfg.eval.method == LOG_REPLAY:
    raise ValueError("log replay has no actor: it copies the log (`log_replay`)")
  if cfg.eval.method == "cv":
    return drive_all(baselines.constant_velocity(sim_agents_mask), None, learned=False, ego=cfg.ego)
  if cfg.eval.method in ("idm", "idm-lane"):
    return drive_all(idm.idm(controlled_fn=sim_agents_mask), None, learned=False, ego=cfg.ego)
  actor, models = evaluation.make_actor(dataclasses.replace(cfg.eval, ego="log"))
  return drive_all(actor, models, learned=True, ego=cfg.ego)


def drive_all(actor: Actor, params: Any, learned: bool, ego: str = "method",
              fallback: bool = True) -> tuple[Actor, Any]:
  """(actor, params) driving every sim agent: `actor` itself (a baseline
  over `sim_agents_mask`), or for a learned actor, IDM on every sim agent with
  the learned one (plus the SDC unless ego="idm") over it; ego="idm" hands
  the SDC to IDM last. Later actors win where they control an object.
  fallback=False leaves the IDM fallback out: for a scene whose sim agents
  the learned actor (and the IDM ego) control all of, the same rollouts up to
  float rounding (every actor gets the same key), for less compute."""
  actors, all_params = [actor], [params]
  if learned:
    learned_actor = with_sdc(actor) if ego == "method" else actor
    actors, all_params = [learned_actor], [params]
    if fallback:
      actors, all_params = [idm.idm(controlled_fn=sim_agents_mask, name="idm-fallback")] + actors, [None] + all_params
  if ego == "idm":
    actors.append(idm.idm(controlled_fn=idm.sdc_only, name="idm-ego"))
    all_params.append(None)
  if len(actors) == 1:
    return actors[0], all_params[0]
  return combine(actors, name="+".join(a.name for a in actors)), tuple(all_params)


def hold_current_lights(state, current: int = submission.CURRENT_INDEX):
  """The traffic lights of step `current` repeated at every later step."""
  tl = state.log_traffic_light
  index = np.minimum(np.arange(tl.valid.shape[-1]), current)
  return state.replace(log_traffic_light=jax.tree_util.tree_map(lambda a: a[..., index], tl))


def rollout_keys(seed: int, scenario_id: str, num_rollouts: int) -> jax.Array:
  """(R, 2) the rollout keys of one scenario (independent of shards and order)."""
  key = jax.random.fold_in(jax.random.PRNGKey(seed), zlib.crc32(scenario_id.encode()) & 0x7FFFFFFF)
  return jax.random.split(key, num_rollouts)


def num_parameters(params: Any) -> int:
  return int(sum(np.size(a) for a in jax.tree_util.tree_leaves(params)))


@dataclasses.dataclass
class ScenarioResult:
  """One scenario's rollouts: object_ids (A,) the sim agents; trajectories
  (R, A, 80, 4) [x, y, z, heading]; lost: sim-agent steps the simulation left
  invalid (held at the last valid pose; 0 for every shipped method)."""
  object_ids: np.ndarray
  trajectories: np.ndarray
  lost: int


def log_replay(state, num_rollouts: int) -> ScenarioResult:
  """`num_rollouts` identical copies of the logged future of every sim agent
  (a state read with the full log): the reference WOSAC reports, not a valid
  submission. A submission has every step of every sim agent, so the steps the
  log leaves invalid (occlusions, objects leaving the sensors' range) are
  imputed as a tracker coasts (`impute_log_gaps`), not held in place: a held
  box stands in the lane and the agents behind it drive through it, collisions
  that are not in the log (docs/WOSAC.md, "Log replay")."""
  current = submission.CURRENT_INDEX
  log_traj = state.log_trajectory
  valid = np.asarray(log_traj.valid)
  agents = np.nonzero(valid[:, current])[0]
  poses = np.stack([np.asarray(getattr(log_traj, f))[agents] for f in ("x", "y", "z", "yaw")], -1)
  out = impute_log_gaps(poses[:, current:], valid[agents, current:])[None, :, 1:]  # (1, A, 80, 4)
  ids = np.asarray(state.object_metadata.ids)[agents]
  return ScenarioResult(object_ids=ids, trajectories=np.repeat(out, num_rollouts, 0), lost=0)


def impute_log_gaps(poses: np.ndarray, valid: np.ndarray) -> np.ndarray:
  """(A, S, 4) [x, y, z, yaw] poses with each invalid step filled: a gap between
  two valid steps is interpolated linearly (yaw along the shorter turn), and the
  steps after the last valid one continue at the velocity of the last two valid
  steps (one valid step: held), yaw held. `valid` (A, S); step 0 must be valid.
  Returns float32 (A, S, 4)."""
  poses = np.asarray(poses, np.float64)
  out = poses.copy()
  steps = np.arange(poses.shape[1])
  for a in np.nonzero(~valid.all(1))[0]:        # only agents with gaps; a few per scene
    known = steps[valid[a]]
    if known.size == 0 or known[0] != 0:
      raise ValueError(f"agent {a}: the first pose (the current step) must be valid")
    yaw = np.unwrap(poses[a, known, 3])
    for c in range(3):
      out[a, :, c] = np.interp(steps, known, poses[a, known, c])
    out[a, :, 3] = (np.interp(steps, known, yaw) + np.pi) % (2 * np.pi) - np.pi
    last = known[-1]
    if known.size > 1 and last < steps[-1]:
      before = known[-2]
      velocity = (poses[a, last, :3] - poses[a, before, :3]) / (last - before)
      out[a, last + 1:, :3] = poses[a, last, :3] + velocity * (steps[last + 1:, None] - last)
  return out.astype(np.float32)


def plan_cap(num_sim_agents: int, cap: int) -> int:
  """The agent cap (plan slots besides the SDC's) a learned method plans a scene
  with under `WosacConfig.size_plans`: the first of 15, 31, 63, ... (16, 32, 64
  slots) that holds `num_sim_agents` (the SDC excluded), or `cap` when that is
  smaller."""
  bucket = 15
  while bucket < num_sim_agents and bucket < cap:
    bucket = 2 * bucket + 1
  return min(bucket, cap)


@functools.lru_cache(maxsize=64)
def _uncovered_sim_agents(learned: Actor, init_steps: int, idm_ego: bool):
  """jit(state -> () bool): a sim agent at the start is outside the learned
  actor's controlled set (the SDC counts as covered under the IDM ego). Jitted,
  so the rest of the actor's init (its road field) is never computed."""
  from pcdiff_jax.sim import env

  def uncovered(state):
    reset = env.reset(state, init_steps)
    inner = learned.init(jax.random.PRNGKey(0), reset)
    covered = inner if isinstance(inner, jax.Array) else inner.controlled
    if idm_ego:
      covered = covered | reset.object_metadata.is_sdc
    return jnp.any(sim_agents_mask(reset) & ~covered)
  return jax.jit(uncovered)


@dataclasses.dataclass(frozen=True)
class _LearnedRuns:
  """A learned method's jitted closed loops at one agent cap: with the IDM
  fallback and without it (`drive_all`), and the actor whose controlled set
  decides between them."""
  learned: Actor
  run: Any
  params: Any
  run_alone: Any
  params_alone: Any


class Simulator:
  """The jitted closed loop of one method, `rollouts_per_call` rollouts per
  call. A learned method has two per agent cap: with the IDM fallback, and
  without it for the scenes whose every sim agent the learned actor drives
  (the same rollouts up to float rounding, less compute); each compiles once
  per object bucket and agent cap (`plan_cap`)."""

  def __init__(self, cfg: WosacConfig):
    self.cfg = cfg
    self.learned = None
    self._by_cap: dict[int, _LearnedRuns] = {}
    self._programs: set = set()    # (closed loop, padded objects) pairs already compiled
    self.compiled_last = False      # whether the last `simulate` compiled a program
    if cfg.eval.method == LOG_REPLAY:
      cfg.validate()
      self.actor, self.params, self.run = None, None, None
      return
    if cfg.eval.method not in evaluation.LEARNED:
      self.actor, self.params = make_actor(cfg)
      self.run = evaluation.make_rollout_fn(self.actor, cfg.eval, one_scene=not cfg.tile_scene)
      return
    cfg.validate()
    full = self._runs_at(cfg.eval.metrics.max_reactive_agents)
    self.learned, self.run, self.params = full.learned, full.run, full.params

  def _runs_at(self, cap: int) -> _LearnedRuns:
    """The learned method's closed loops with `cap` agents besides the SDC, built once."""
    if cap not in self._by_cap:
      cfg = self.cfg
      metrics = dataclasses.replace(cfg.eval.metrics, max_reactive_agents=cap)
      actor, models = evaluation.make_actor(dataclasses.replace(cfg.eval, ego="log", metrics=metrics))
      with_fallback, params = drive_all(actor, models, learned=True, ego=cfg.ego)
      alone, params_alone = drive_all(actor, models, learned=True, ego=cfg.ego, fallback=False)
      self._by_cap[cap] = _LearnedRuns(
          learned=with_sdc(actor) if cfg.ego == "method" else actor,
          run=evaluation.make_rollout_fn(with_fallback, cfg.eval, one_scene=not cfg.tile_scene), params=params,
          run_alone=evaluation.make_rollout_fn(alone, cfg.eval, one_scene=not cfg.tile_scene),
          params_alone=params_alone)
    return self._by_cap[cap]

  def needs_fallback(self, state, learned: Optional[Actor] = None) -> bool:
    """Whether a sim agent of this (unbatched, loaded) scene is left to the
    IDM fallback: the learned actor's (default: at the full cap) controlled
    set at `init`, outside jit."""
    uncovered = _uncovered_sim_agents(learned or self.learned, self.cfg.eval.init_steps, self.cfg.ego == "idm")
    return bool(uncovered(state))


  def learned_run(self, state) -> tuple[Any, Any, int]:
    """(run, params, cap) of a learned method for one loaded scene: the agent
    cap `plan_cap` sizes to it (or the full cap), without the IDM fallback
    where the learned actor drives every sim agent."""
    cap = self.cfg.eval.metrics.max_reactive_agents
    if self.cfg.size_plans:
      now = np.asarray(state.log_trajectory.valid)[:, submission.CURRENT_INDEX]
      sdc = bool((now & np.asarray(state.object_metadata.is_sdc)).any())
      cap = plan_cap(int(now.sum()) - sdc, cap)
    runs = self._runs_at(cap)
    if self.needs_fallback(state, runs.learned):
      return runs.run, runs.params, cap
    return runs.run_alone, runs.params_alone, cap

  def simulate(self, state, scenario_id: str) -> ScenarioResult:
    """One loaded (unbatched) scenario -> its rollouts."""
    cfg = self.cfg
    self.compiled_last = False
    if cfg.eval.method == LOG_REPLAY:
      return log_replay(state, cfg.num_rollouts)
    if cfg.hold_lights:
      state = hold_current_lights(state)
    current = submission.CURRENT_INDEX
    log_valid = np.asarray(state.log_trajectory.valid)
    agents = np.nonzero(log_valid[:, current])[0]
    keys = rollout_keys(cfg.eval.seed, scenario_id, cfg.num_rollouts)
    per_call = min(cfg.rollouts_per_call or default_rollouts_per_call(cfg.num_rollouts), cfg.num_rollouts)
    calls = -(-cfg.num_rollouts // per_call)
    keys = jnp.concatenate([keys, jnp.repeat(keys[-1:], calls * per_call - cfg.num_rollouts, 0)])
    if cfg.tile_scene:
      scene = jax.tree_util.tree_map(lambda a: jnp.repeat(jnp.asarray(a)[None], per_call, 0), state)
    else:
      scene = jax.tree_util.tree_map(jnp.asarray, state)
    run, params = self.run, self.params
    if self.learned is not None:
      run, params, _ = self.learned_run(state)
    program = (id(run), np.shape(state.log_trajectory.x))
    self.compiled_last = program not in self._programs
    self._programs.add(program)
    parts = []
    for c in range(calls):
      final = run(scene, keys[c * per_call:(c + 1) * per_call], params)
      traj = final.sim_trajectory
      fields = jax.device_get((traj.x, traj.y, traj.z, traj.yaw, traj.valid))
      parts.append([np.asarray(f)[:, agents, current + 1:] for f in fields])
    x, y, z, yaw, valid = (np.concatenate([p[i] for p in parts])[:cfg.num_rollouts] for i in range(5))
    out = np.stack([x, y, z, yaw], -1).astype(np.float32)          # (R, A, 80, 4)
    lost = int((~valid).sum())
    if lost:
      out = _hold_last_valid(out, valid, np.stack([np.asarray(getattr(state.log_trajectory, f))[agents, current]
                                                   for f in ("x", "y", "z", "yaw")], -1))
    ids = np.asarray(state.object_metadata.ids)[agents]
    return ScenarioResult(object_ids=ids, trajectories=out, lost=lost)


def _hold_last_valid(out: np.ndarray, valid: np.ndarray, start: np.ndarray) -> np.ndarray:
  """(R, A, S, 4) with each invalid step replaced by the last valid one (the
  step-10 pose `start` (A, 4) before any)."""
  steps = np.arange(out.shape[2])
  last = np.maximum.accumulate(np.where(valid, steps, -1), axis=2)            # (R, A, S)
  held = np.take_along_axis(out, np.maximum(last, 0)[..., None], axis=2)
  return np.where((last >= 0)[..., None], held, start[None, :, None, :]).astype(np.float32)


def select_files(scenarios, shard: Optional[tuple[int, int]] = None) -> list[str]:
  """The input files, or shard (index, count)'s share of them (every count-th file)."""
  files = womd.expand_paths(scenarios)
  if shard is None:
    return files
  index, count = shard
  if not 0 <= index < count:
    raise ValueError(f"shard {index}/{count}: the index must be in [0, {count})")
  if count > len(files):
    raise ValueError(f"{count} shards but only {len(files)} input file(s): shards split the files, "
                     "use at most one shard per file")
  return files[index::count]


class Interrupted(Exception):
  """An export stopped (Ctrl-C, SIGTERM) after `count` scenarios, kept in
  `path` (a valid submission of those scenarios, named `*.partial`)."""

  def __init__(self, path: str, count: int):
    super().__init__(f"interrupted after {count} scenarios: they are in {path} (a valid submission of "
                     "those scenarios; the same command goes on from it, or rename it to check or score it)")
    self.path, self.count = path, count


# What an export of `path` leaves while it is not finished: the stream being written, an
# interrupted run's scenarios, the copy a resuming run reads from.
_UNFINISHED = (".tmp", ".partial", ".resume")


def run_record_path(path: str) -> str:
  """The settings of the export that writes `path`, kept until it is finished, so that only
  the same export resumes from what an earlier run of it left."""
  return f"{path}.run.json"


def _settings_mismatch(path: str, settings: dict) -> Optional[str]:
  """None when `run_record_path(path)` holds these settings, else what differs."""
  import json
  try:
    with open(run_record_path(path)) as f:
      old = json.load(f)
  except (OSError, ValueError):
    return f"{run_record_path(path)} is missing or unreadable"
  diff = [k for k in settings if old.get(k) != settings[k]]
  return f"{', '.join(diff)} differ" if diff else None


def _resume_writer(path: str, settings: dict, metadata: submission.Metadata, resume: bool,
                   finished_too: bool) -> tuple[submission.SubmissionWriter, int]:
  """A writer of `path` that holds what an earlier, unfinished run of the same export wrote
  (its `.partial`, `.tmp` after a kill, and with finished_too `path` itself: a part finished
  before another job failed), and how many agents those hold.

  The largest of those files is a superset of the others (every run starts from it), so it
  is kept and the rest removed; it is copied record by record (a record cut short by a kill
  is dropped) and removed once copied. Settings other than the earlier run's are a
  ValueError; resume=False (`--overwrite`) starts again."""
  import json
  found = [f for f in [path] * finished_too + [path + s for s in _UNFINISHED] if os.path.exists(f)]
  if found and not resume:
    for f in found:
      os.remove(f)
    found = []
  if found:
    why = _settings_mismatch(path, settings)
    if why is not None:
      raise ValueError(f"{found[0]} is left by an export with other settings ({why}): run that export again "
                       "to finish it, or pass --overwrite to start this one afresh")
  with open(run_record_path(path), "w") as f:
    json.dump(settings, f, indent=1)
  source, agents = path + ".resume", 0
  if found:
    best = max(found, key=submission.count_scenarios)
    if best != source:
      os.replace(best, source)
    for f in found:
      if f not in (best, source) and os.path.exists(f):
        os.remove(f)
  writer = submission.SubmissionWriter(path, metadata)
  if os.path.exists(source):
    from pcdiff_jax.data import waymo_protos as pb
    for payload in submission.iter_scenario_records(source):
      rollouts = pb.ScenarioRollouts.FromString(payload)
      writer.add_serialized(payload, rollouts.scenario_id)
      agents += len(rollouts.joint_scenes[0].simulated_trajectories) if rollouts.joint_scenes else 0
    writer.flush()
    os.remove(source)
  return writer, agents


def export(scenarios, out: str, cfg: WosacConfig, metadata: submission.Metadata,
           shard: Optional[tuple[int, int]] = None, max_scenarios: Optional[int] = None,
           progress: bool = True, part: Optional[tuple[int, int]] = None, resume: bool = True) -> dict:
  """Simulates every scenario of `scenarios` (or the shard's files; with part (j, n), the
  j-th of every n of their scenarios, written to `part_path`) and
  writes the submission file. An earlier run of the same export that was stopped or killed
  is resumed: its scenarios are kept, the rest simulated (the same file as one uninterrupted
  run: a scenario's rollouts depend on its id only); resume=False starts again. Returns
  a summary (path, counts, `resumed_scenarios`, mean and
  median seconds per scenario with the first, compiling one left out: a
  later scene in a new object bucket still compiles its own program; and
  `steady_seconds_per_scenario`, the mean over the scenes that compiled
  nothing, the per-scene cost at WOMD scale, where each program compiles once).
  An empty `metadata.num_model_parameters` is filled with the method's parameter count."""
  files = select_files(scenarios, shard)
  path = submission.shard_path(out, *(shard or (None, None)))
  if part is not None:
    path = part_path(path, *part)
  simulator = Simulator(cfg)
  if metadata.num_model_parameters == "":
    metadata = dataclasses.replace(metadata, num_model_parameters=submission.format_num_parameters(
        num_parameters(simulator.params)))
  from tqdm.auto import tqdm
  seconds, compiled, lost, fallback = [], [], 0, 0
  cap = cfg.eval.metrics.max_reactive_agents + 1   # the learned agents and the SDC (method or IDM ego)
  items = womd.iterate(files, with_meta=True, history_only=cfg.eval.method != LOG_REPLAY, max_num_objects=cfg.max_objects,
                       max_scenarios=max_scenarios, to_jax=False)
  if part is not None:
    items = itertools.islice(items, part[0], None, part[1])
  settings = {"config": repr(cfg), "files": [os.path.abspath(f) for f in files], "part": list(part or []),
              "max_scenarios": max_scenarios}
  writer, agents = _resume_writer(path, settings, metadata, resume, finished_too=part is not None)
  resumed = writer.count
  try:
    for index, (state, meta) in enumerate(tqdm(items, desc=f"wosac {cfg.eval.method}", unit="scenario",
                                               disable=not progress)):
      if index < resumed:   # written by an earlier run: the same scenarios, in the same order
        if meta.scenario_id != writer.scenario_ids[index]:
          raise ValueError(f"{path}: scenario {index} of the earlier run is {writer.scenario_ids[index]}, "
                           f"the input's is {meta.scenario_id}: pass --overwrite to start again")
        continue
      t0 = time.perf_counter()
      result = simulator.simulate(state, meta.scenario_id)
      writer.add(submission.scenario_rollouts(meta.scenario_id, result.object_ids, result.trajectories))
      seconds.append(time.perf_counter() - t0)
      compiled.append(simulator.compiled_last)
      lost += result.lost
      agents += len(result.object_ids)
      if cfg.eval.method in evaluation.LEARNED:
        fallback += max(0, len(result.object_ids) - cap)
    if writer.count == 0 and part is None:   # a part may be empty: more parts than scenarios
      raise ValueError(f"no scenario in {files}")
  except KeyboardInterrupt:
    if writer.count == 0:
      writer.abort()
      os.remove(run_record_path(path))
      raise
    raise Interrupted(writer.close_partial(), writer.count) from None
  except BaseException:
    if writer.count == 0:
      writer.abort()
      os.remove(run_record_path(path))
    else:   # nothing written is lost: the same command goes on from it
      log.warning("the %d scenarios written are kept in %s", writer.count, writer.close_partial())
    raise
  writer.close()
  if part is None:   # a finished part keeps its settings until the parts are merged
    os.remove(run_record_path(path))
  if lost:
    log.warning("%d sim-agent steps were invalid in the simulation and were held at the last valid pose", lost)
  timed = seconds[1:] or seconds or [float("nan")]
  steady = [t for t, c in zip(seconds, compiled) if not c]
  return {"path": path, "num_scenarios": writer.count, "resumed_scenarios": resumed,
          "sim_agents": agents, "fallback_agents": fallback,
          "lost_steps": lost, "num_rollouts": cfg.num_rollouts,
          "seconds_per_scenario": float(np.mean(timed)), "median_seconds_per_scenario": float(np.median(timed)),
          "first_scenario_seconds": seconds[0] if seconds else None, "compiling_scenarios": int(sum(compiled)),
          "steady_seconds_per_scenario": float(np.mean(steady)) if steady else None,
          "metadata": dataclasses.asdict(metadata)}


def part_path(path: str, index: int, count: int) -> str:
  """Where part `index` of `count` of the submission `path` is written (`export(part=...)`)."""
  return f"{path}.part{index}of{count}"


def merge_parts(path: str, count: int):
  """Writes `path` from its `count` complete parts (part j holds scenarios j, j + count, ...),
  in the input's scenario order, with their metadata, and removes them. Returns the number of
  scenarios and the metadata (a SimAgentsChallengeSubmission without rollouts)."""
  subs = [submission.read(part_path(path, j, count)) for j in range(count)]
  parts = [list(sub.scenario_rollouts) for sub in subs]
  head = type(subs[0])()
  head.CopyFrom(subs[0])
  del head.scenario_rollouts[:]
  with submission.SubmissionWriter(path, _Fixed(head)) as writer:
    for i in range(max(map(len, parts))):
      for rollouts in parts:
        if i < len(rollouts):
          writer.add(rollouts[i])
  for j in range(count):
    os.remove(part_path(path, j, count))
    settings = run_record_path(part_path(path, j, count))
    if os.path.exists(settings):
      os.remove(settings)
  return writer.count, head


@dataclasses.dataclass(frozen=True)
class _Fixed:
  """Metadata already in proto form, as `SubmissionWriter` takes it."""
  proto: Any

  def to_proto(self):
    return self.proto


def check(paths: Sequence[str], scenarios, max_objects: Optional[int] = None, strict: bool = False,
          num_rollouts: int = submission.NUM_ROLLOUTS) -> dict:
  """Checks submission file(s) against the scenarios they simulate: every
  official rule (`submission.check_rollouts`), every scenario exactly once,
  no unknown scenario, and the metadata (`submission.check_metadata`: errors
  with `strict`, else warnings, since a local evaluation does not need them).
  Returns {"errors": [...], "warnings": [...], counts}."""
  files = []
  for p in paths:
    files += womd.expand_paths(p)
  expected: dict[str, tuple[list[int], dict]] = {}
  for state, meta in womd.iterate(scenarios, with_meta=True, history_only=True, max_num_objects=max_objects,
                                  to_jax=False):
    now = np.asarray(state.log_trajectory.valid)[:, submission.CURRENT_INDEX]
    ids = np.asarray(state.object_metadata.ids)
    xy = np.stack([np.asarray(state.log_trajectory.x)[:, submission.CURRENT_INDEX],
                   np.asarray(state.log_trajectory.y)[:, submission.CURRENT_INDEX]], -1)
    expected[meta.scenario_id] = (submission.sim_agent_ids(ids, now),
                                  {int(i): tuple(p) for i, p, v in zip(ids, xy, now) if v})
  errors, warnings, seen, names = [], [], {}, set()
  for path in files:
    sub = submission.read(path)
    names.add(sub.unique_method_name)
    problems = submission.check_metadata(sub, path)
    (errors if strict else warnings).extend(problems)
    for rollouts in sub.scenario_rollouts:
      sid = rollouts.scenario_id
      if sid in seen:
        errors.append(f"{path}: scenario {sid} is also in {seen[sid]} (each scenario exactly once)")
        continue
      seen[sid] = path
      if sid not in expected:
        errors.append(f"{path}: scenario {sid!r} is not in --scenarios")
        continue
      e, w = submission.check_rollouts(rollouts, expected[sid][0], num_rollouts=num_rollouts,
                                       start_xy=expected[sid][1])
      errors += e
      warnings += w
  missing = sorted(set(expected) - set(seen))
  if missing:
    errors.append(f"{len(missing)} scenario(s) of --scenarios have no rollouts: "
                  f"{missing[:5]}{' ...' if len(missing) > 5 else ''}")
  if len(names) > 1:
    warnings.append(f"the files name different methods: {sorted(names)}")
  return {"errors": errors, "warnings": warnings, "files": len(files), "scenarios": len(expected),
          "scenarios_submitted": len(seen)}
