"""Closed-loop evaluation: roll a method out over TFRecords and score it.

Writes, under the output folder: `scenarios.jsonl` (one line per scenario,
appended as it finishes, so an interrupted run keeps what it measured),
`metrics.json`, `metrics.md` and `gifs/<scenario_id>.gif`. A scenario that
fails to load or to run is reported in `skipped` and the run goes on.
"""
from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from typing import Any, Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from pcdiff_jax import baselines, distributed
from pcdiff_jax.baselines import idm
from pcdiff_jax import metrics as metrics_lib
from pcdiff_jax.config import RUN_MAP_ANCHOR, MetricsConfig
from pcdiff_jax.data import womd
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model import guidance as guidance_lib
from pcdiff_jax.model.guidance import GuidanceConfig
from pcdiff_jax.policy.config import PolicyConfig
from pcdiff_jax.sim import env
from pcdiff_jax.sim.actors import Actor, combine

log = logging.getLogger(__name__)

METHODS: dict[str, Callable[[int], Actor]] = {
    "log": lambda max_agents: baselines.log_replay(),
    "cv": lambda max_agents: baselines.constant_velocity(baselines.reactive_agents(max_agents)),
    "expert": lambda max_agents: baselines.expert(controlled_fn=baselines.reactive_agents(max_agents)),
    # IDM along each object's logged path (reads the logged future; still objects held).
    "idm": lambda max_agents: baselines.idm_route(controlled_fn=baselines.reactive_agents(max_agents)),
    # IDM along the nearest lane (reads no future; the WOSAC baseline).
    "idm-lane": lambda max_agents: idm.idm(controlled_fn=baselines.reactive_agents(max_agents)),
}


LEARNED = ("pcdiff", "pcdiff-noprior", "simpl-ar")


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """method: a baseline of METHODS or a learned policy of LEARNED (which needs
  `checkpoint`, the training workdir). policy: the diffusion policies'
  settings (`policy.PolicyConfig`; its guidance is set from `guidance`, and
  `pcdiff-noprior` forces prior_init off). ego: the SDC's fixed policy, "log" (replay) or
  "idm". guidance: test-time guidance of the learned diffusion policies
  (`model.guidance`). score_adversary: also score the ego against the most
  threatening agent (the pursuer adversarial guidance would pick) when the
  run is not adversarial, for comparison. max_scenarios: the first N
  scenarios of the files only. simpl_ar_sample: SIMPL-AR draws its modes by
  their probabilities instead of taking the top mode. align_headings: a simulated
  method starts from box headings aligned with the motion where the log's disagree
  (`env.align_headings`); fit_start_velocity: it starts from the velocity of an object's
  last 0.5 s of positions where its tracked one is more than 2 m/s off it
  (`env.fit_current_velocity`); log replay replays the log as it is.

  The learned methods model up to `metrics.max_reactive_agents` + 1 agents
  (the SDC and every evaluated agent), whatever cap they were trained with,
  so every evaluated agent is controlled and none follows its log; the
  attention layers take any agent count, at a cost that grows with it
  (docs/BENCHMARKS.md). map_pieces, map_anchor: the learned model's map crop
  (`FeaturesConfig.max_polylines`, never above the trained model's; `.map_anchor`,
  by default `config.RUN_MAP_ANCHOR`; None keeps the trained model's): fewer pieces
  is a cheaper encoder, at a cost in score measured in docs/BENCHMARKS.md, "WOSAC at
  WOMD scale"."""
  method: str = "cv"
  checkpoint: Optional[str] = None
  ego: str = "log"
  policy: PolicyConfig = PolicyConfig()
  num_rollouts: int = 1
  seeds: int = 1
  num_steps: int = 80
  init_steps: int = env.WOMD_INIT_STEPS
  batch_size: int = 1
  gifs: int = 1
  seed: int = 0
  metrics: MetricsConfig = MetricsConfig()
  guidance: GuidanceConfig = GuidanceConfig()
  score_adversary: bool = False
  max_scenarios: Optional[int] = None
  simpl_ar_sample: bool = False
  align_headings: bool = True
  fit_start_velocity: bool = True
  map_pieces: Optional[int] = None
  map_anchor: Optional[str] = RUN_MAP_ANCHOR

  @property
  def replan_every(self) -> int:
    """Steps between decisions: the diffusion policies' replanning interval, else 1."""
    return self.policy.replan_every if self.method in ("pcdiff", "pcdiff-noprior") else 1

  @property
  def adversarial_scores(self) -> bool:
    return self.guidance.mode == "adversarial" or self.score_adversary


EGOS = ("log", "idm")


def make_actor(cfg: EvalConfig) -> tuple[Actor, Any]:
  """(actor, params) of `cfg.method` with the ego policy `cfg.ego`; learned
  policies load `cfg.checkpoint`."""
  if cfg.ego not in EGOS:
    raise ValueError(f"unknown ego policy {cfg.ego!r}; choose one of {list(EGOS)}")
  cfg.guidance.validate()
  if cfg.guidance.mode != "none" and cfg.method not in ("pcdiff", "pcdiff-noprior"):
    raise ValueError(f"guidance {cfg.guidance.mode!r} needs a diffusion policy (pcdiff, pcdiff-noprior), "
                     f"not {cfg.method!r}")
  actor, params = _method_actor(cfg)
  if cfg.ego == "idm":
    ego = idm.idm(controlled_fn=idm.sdc_only, name="idm-ego")
    actor = combine([actor, ego], name=f"{actor.name}+idm-ego")
  return actor, params


def _method_actor(cfg: EvalConfig) -> tuple[Actor, Any]:
  if cfg.method in METHODS:
    return METHODS[cfg.method](cfg.metrics.max_reactive_agents), None
  if cfg.method not in LEARNED:
    raise ValueError(f"unknown method {cfg.method!r}; choose one of {sorted(METHODS) + list(LEARNED)}")
  if not cfg.checkpoint:
    raise ValueError(f"--method {cfg.method} needs --checkpoint (a training workdir)")
  from pcdiff_jax import policy
  from pcdiff_jax.training import diffusion_stage, encoder_stage
  if cfg.method == "simpl-ar":
    from pcdiff_jax.baselines import simpl_ar
    enc, model_cfg = encoder_stage.load_simpl_ar(cfg.checkpoint)
    ar = simpl_ar.SimplARConfig(sample=cfg.simpl_ar_sample)
    return simpl_ar.simpl_ar(run_config(model_cfg, cfg), ar), enc
  use_prior = cfg.method == "pcdiff"
  models, model_cfg = diffusion_stage.load(cfg.checkpoint, use_prior=use_prior)
  # pcdiff-noprior's model has no proposal prior; pcdiff's may still start from N(0, I).
  pcfg = dataclasses.replace(cfg.policy, prior_init=use_prior and cfg.policy.prior_init, guidance=cfg.guidance)
  return policy.actor(run_config(model_cfg, cfg), pcfg), models


def run_config(model_cfg, cfg: EvalConfig):
  """The learned model's config as `cfg` runs it: room for every evaluated
  agent (`with_agent_cap`) and the map crop of `cfg.map_pieces` (at most the
  pieces it was trained with) / `.map_anchor`."""
  model_cfg = with_agent_cap(model_cfg, cfg.metrics)
  if cfg.map_pieces is not None and cfg.map_pieces < 1:
    raise ValueError(f"map_pieces must be >= 1, got {cfg.map_pieces}")
  pieces = None if cfg.map_pieces is None else min(cfg.map_pieces, model_cfg.features.max_polylines)
  crop = {name: value for name, value in (("max_polylines", pieces), ("map_anchor", cfg.map_anchor))
          if value is not None}
  if cfg.map_anchor not in (None,) + features_lib.MAP_ANCHORS:
    raise ValueError(f"unknown map_anchor {cfg.map_anchor!r}; choose one of {list(features_lib.MAP_ANCHORS)}")
  return dataclasses.replace(model_cfg, features=dataclasses.replace(model_cfg.features, **crop))


def with_agent_cap(model_cfg, metrics: MetricsConfig):
  """The model config with room for the SDC and every evaluated agent."""
  features = dataclasses.replace(model_cfg.features, max_agents=metrics.max_reactive_agents + 1)
  return dataclasses.replace(model_cfg, features=features)


def make_rollout_fn(actor: Actor, cfg: EvalConfig, mesh: Optional[Mesh] = None,
                    one_scene: bool = False):
  """jit(vmap) of reset -> closed-loop rollout, per scenario:
  (states (B,), rngs (B,), params) -> final states. The params (model weights)
  are an argument, not a constant baked into the program. With a `mesh`
  (`pcdiff_jax.distributed.data_mesh`) the B scenarios are split along its
  `data` axis (B a multiple of its devices) and the params replicated.
  one_scene: (state, rngs (B,), params) -> B rollouts of one unbatched scene;
  what depends on the scene alone (the policy's road field, the map's arcs)
  is then computed once per call instead of once per rollout."""
  align = cfg.align_headings and cfg.method != "log"
  fit_velocity = cfg.fit_start_velocity and cfg.method != "log"

  def one(state, rng, params):
    start = env.simulated_start(state, cfg.init_steps, align, fit_velocity)
    return env.rollout(start, actor, cfg.num_steps, rng, params=params).final_state
  fn = jax.vmap(one, in_axes=(None if one_scene else 0, 0, None))
  if mesh is None:
    return jax.jit(fn)
  data = distributed.batch_sharded(mesh)
  return jax.jit(fn, in_shardings=(data, data, distributed.replicated(mesh)), out_shardings=data)


def make_score_fn(cfg: EvalConfig, mesh: Optional[Mesh] = None):
  """jit(vmap) of the scores of rolled-out states (B,) -> metrics.RolloutScores (B,),
  split over the `data` axis of `mesh` when one is given."""
  start = cfg.init_steps - 1

  def one(final_state):
    scores = metrics_lib.score_rollout(final_state, start, cfg.num_steps,
                                       cfg.metrics.max_reactive_agents, cfg.metrics.max_road_edge_points)
    if not cfg.adversarial_scores:
      return scores
    return scores.replace(adversarial=metrics_lib.adversarial_scores(
        final_state, start, pursuer_at_start(final_state, cfg), cfg.metrics.max_road_edge_points))
  if mesh is None:
    return jax.jit(jax.vmap(one))
  data = distributed.batch_sharded(mesh)
  return jax.jit(jax.vmap(one), in_shardings=data, out_shardings=data)


def pursuer_at_start(final_state, cfg: EvalConfig) -> jax.Array:
  """() the pursuer's object slot of one rolled-out scene: the user's, or the
  most threatening evaluated vehicle at the rollout start. The policy fixes its
  pursuer there from the same candidates (its reactive set = the evaluated
  agents), so this recomputes it."""
  if cfg.guidance.adversary >= 0:
    return jnp.int32(cfg.guidance.adversary)
  start = cfg.init_steps - 1
  at_start = final_state.replace(timestep=jnp.int32(start))
  return guidance_lib.most_threatening(
      at_start, metrics_lib.evaluated_agents(final_state, start, cfg.metrics.max_reactive_agents))


def _config_record(cfg: EvalConfig) -> dict:
  """cfg as a dict, with the map and collision weights guidance actually used
  (None stands for the mode's default)."""
  record = dataclasses.asdict(cfg)
  record["guidance"]["w_map"] = cfg.guidance.map_weight
  record["guidance"]["w_coll"] = cfg.guidance.coll_weight
  return record


def pad_batch(state, size: int):
  """Repeats the last scenario so every batch has the same size (no recompiles)."""
  n = state.shape[0]
  if n == size:
    return state
  return jax.tree_util.tree_map(
      lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], size - n, axis=0)], 0), state)


# Metrics reported as mean and std over seeds, with their Table-I labels.
HEADLINE = (("collision_rate", "collision (%)", 100.0), ("offroad_rate", "off-road (%)", 100.0),
            ("realism", "realism (W1)", 1.0), ("min_ade", "minADE (m)", 1.0),
            ("still_moved_rate", "still moved (%)", 100.0),
            ("runtime_ms_per_replan", "runtime / replan (ms)", 1.0))


def _markdown(summary: dict) -> str:
  head = "| method | " + " | ".join(label for _, label, _ in HEADLINE) + " |"
  cells = []
  for key, _, scale in HEADLINE:
    m = summary[key]
    cells.append(f"{scale * m['mean']:.2f} ± {scale * m['std']:.2f}")
  lines = [f"# {summary['method']} on {summary['num_scenarios']} scenario(s)", "", head,
           "|" + "---|" * (len(HEADLINE) + 1), f"| {summary['method']} | " + " | ".join(cells) + " |", ""]
  r = summary["rates"]
  lines += [f"Mean ± std over {summary['seeds']} seed(s), {summary['num_rollouts']} rollout(s) per "
            f"scenario and seed (minADE: the best of them). Collision rate with the objects that "
            f"enter later counted as partners too: {100 * r['collision_with_entering_rate']:.2f}%; "
            f"of the collision rate, {100 * r['collision_with_replayed_rate']:.2f} points are "
            f"agents hit by (or hitting) an object that replays its log. "
            f"Vehicle-vehicle collision rate "
            f"{100 * r['vehicle_collision_rate']:.2f}%; pedestrians and cyclists overlapping a "
            f"vehicle {100 * r['vru_vehicle_collision_rate']:.2f}% (of {int(r['num_vrus'])}); "
            f"vehicles starting off-road "
            f"{100 * r['start_offroad_fraction']:.2f}%; of the off-road rate, "
            f"{100 * r['offroad_past_log_rate']:.2f} points are vehicles that left the road only "
            f"after their log had ended. Evaluated agents per seed: "
            f"{int(r['num_evaluated'])} (vehicles {int(r['num_vehicles'])}; still in the log, moving < 1 m: "
            f"{int(r['num_still_agents'])}); minADE per kind: {_per_kind(r)}; skipped scenarios: "
            f"{len(summary['skipped'])}. Controlled agents lost mid-rollout: {summary['lost_agents']} of "
            f"{summary['controlled_agents']} (all seeds); objects following their log: "
            f"{summary['log_following_agents']}. Runtime: one jitted closed-loop call over "
            f"{summary['runtime_ms_per_replan']['scenarios_per_call']} scenario rollouts, per step, "
            "compile excluded."]
  adv = summary.get("adversarial")
  if adv:
    lines += ["", "| adversarial | ego-adv collision (%) | adversary off-road (%) | min distance (m) | "
              "impact speed (m/s) |", "|---|---|---|---|---|",
              f"| {adv['num_pairs']} pairs | {100 * adv['ego_adv_collision_rate']:.2f} | "
              f"{100 * adv['adv_offroad_rate']:.2f} | {adv['min_distance']:.2f} | {adv['impact_speed']:.2f} |"]
  return "\n".join(lines) + "\n"


def _per_kind(rates: dict) -> str:
  """'vehicles 1.20 m (4227), pedestrians ...' from a seed-mean of `metrics.aggregate`."""
  kinds = []
  for name, _ in metrics_lib.ADE_KINDS:
    n = int(rates.get(f"num_ade_{name}", 0))
    if n:
      kinds.append(f"{name}s {rates[f'min_ade_{name}']:.2f} m ({n})")
  return ", ".join(kinds) or "none"


_ADVERSARIAL = ("num_pairs", "ego_adv_collision_rate", "adv_offroad_rate", "min_distance", "impact_speed")


def _mean_std(values) -> dict:
  v = np.asarray(values, np.float64)
  return {"mean": float(np.mean(v)), "std": float(np.std(v))}


def evaluate(scenarios: Sequence[str] | str, out_dir: str, cfg: EvalConfig,
             progress: bool = True, mesh: Optional[Mesh] = None) -> dict:
  """Runs `cfg.method` over every scenario, `cfg.seeds` times with
  `cfg.num_rollouts` rollouts each; returns and writes the summary.
  `mesh`: each call's batch_size x num_rollouts rollouts are split over its
  devices (one process); the keys are drawn as on one device, so the results
  are the one-device run's."""
  files = womd.expand_paths(scenarios)  # fail early, naming the missing path
  n_roll = cfg.num_rollouts
  call_size = cfg.batch_size * n_roll
  if mesh is not None:
    distributed.check_divisible(call_size, mesh, "the rollouts per call (--batch-size x --num-rollouts)")
  actor, params = make_actor(cfg)
  os.makedirs(out_dir, exist_ok=True)
  run = make_rollout_fn(actor, cfg, mesh)
  score = make_score_fn(cfg, mesh)
  if mesh is not None:
    params = distributed.replicate(params, mesh)
  per_scenario_path = os.path.join(out_dir, "scenarios.jsonl")
  skipped: list[dict] = []
  per_seed: list[dict] = []
  step_ms: list[float] = []   # per replanning step of one call (all its scenarios)
  # The diffusion policies plan every `replan_every` steps and only execute in
  # between; the other methods decide at every step.
  every = cfg.replan_every
  num_replans = -(-cfg.num_steps // every)
  gifs_done, num_done, calls = 0, 0, 0
  from tqdm.auto import tqdm
  with open(per_scenario_path, "a") as per_scenario:
    for seed in range(cfg.seeds):
      scores_seed = []
      load_errors: list = []
      batches = womd.iterate(files, batch_size=cfg.batch_size, with_meta=True, on_error="skip",
                             skipped=load_errors, max_scenarios=cfg.max_scenarios, max_num_objects=None)
      bar = tqdm(batches, desc=f"{cfg.method} seed {seed}", unit="batch", disable=not progress)
      for batch_index, (state, meta) in enumerate(bar):
        n = state.shape[0]
        key = jax.random.fold_in(jax.random.fold_in(jax.random.PRNGKey(cfg.seed), seed), batch_index)
        rngs = jax.random.split(key, call_size)
        try:
          tiled = jax.tree_util.tree_map(lambda a: jnp.repeat(a, n_roll, axis=0),
                                         pad_batch(state, cfg.batch_size))
          if mesh is not None:
            tiled, rngs = jax.device_put((tiled, rngs), distributed.batch_sharded(mesh))
          t0 = time.perf_counter()
          final = jax.block_until_ready(run(tiled, rngs, params))
          elapsed = time.perf_counter() - t0
          scores = jax.device_get(score(final))
        except Exception as err:  # a bad scenario must not end a long job
          log.warning("skipping batch %s (%s): %s", batch_index, meta.scenario_id, err)
          if seed == 0:
            skipped += [{"scenario_id": s, "path": p, "record": r, "error": str(err)}
                        for s, p, r in zip(meta.scenario_id, meta.path, meta.record_index)]
          continue
        if calls > 0:  # the first call includes compilation
          step_ms.append(1000 * elapsed / num_replans)
        calls += 1
        scores = jax.tree_util.tree_map(lambda a: np.asarray(a).reshape((cfg.batch_size, n_roll) +
                                                                        a.shape[1:])[:n], scores)
        scores_seed.append(scores)
        for i in range(n):
          one = jax.tree_util.tree_map(lambda a: a[i:i + 1], scores)
          row = {"scenario_id": meta.scenario_id[i], "path": meta.path[i], "record": meta.record_index[i],
                 "seed": seed}
          row.update({k: v for k, v in metrics_lib.aggregate(one).items()
                      if k in ("collision_rate", "collision_with_replayed_rate", "offroad_rate",
                               "min_ade", "num_evaluated",
                               "lost_agents", "log_following_agents", "still_moved_rate",
                               "num_still_agents")})
          per_scenario.write(json.dumps(row) + "\n")
          per_scenario.flush()
          if gifs_done < cfg.gifs:
            first = jax.tree_util.tree_map(lambda a: a[i * n_roll:i * n_roll + 1], final)
            _write_gif(first, 0, meta.scenario_id[i], out_dir, cfg.init_steps - 1,
                       cfg.init_steps - 1 + cfg.num_steps)
            gifs_done += 1
        if seed == 0:
          num_done += n
      if seed == 0:
        skipped += [{"scenario_id": None, "path": e.path, "record": e.index, "error": str(e)}
                    for e in load_errors]
      if scores_seed:
        stacked = metrics_lib.concatenate_scores(scores_seed)
        per_seed.append(metrics_lib.aggregate(stacked))
  if not per_seed:
    raise RuntimeError(f"no scenario could be evaluated; skipped: {skipped}")
  if not step_ms:  # a single call: time a second, warm one
    t0 = time.perf_counter()
    jax.block_until_ready(run(tiled, rngs, params))
    step_ms.append(1000 * (time.perf_counter() - t0) / num_replans)
  lost = [m["lost_agents"] for m in per_seed]
  if any(lost):
    log.warning("%s lost %s controlled agent(s) mid-rollout (per seed; of %s controlled): an actor "
                "must keep every controlled agent valid", cfg.method, lost,
                [m["controlled_agents"] for m in per_seed])
  summary = {
      "method": cfg.method,
      "num_scenarios": num_done,
      "lost_agents": int(sum(lost)),
      "controlled_agents": int(sum(m["controlled_agents"] for m in per_seed)),
      "log_following_agents": int(sum(m["log_following_agents"] for m in per_seed)),
      "seeds": len(per_seed),
      "num_rollouts": n_roll,
      **{k: _mean_std([m[k] for m in per_seed]) for k, _, _ in HEADLINE[:-1]},
      "vehicle_collision_rate": _mean_std([m["vehicle_collision_rate"] for m in per_seed]),
      "vru_vehicle_collision_rate": _mean_std([m["vru_vehicle_collision_rate"] for m in per_seed]),
      "runtime_ms_per_replan": {**_mean_std(step_ms), "scenarios_per_call": call_size,
                                "ms_per_scenario": float(np.mean(step_ms)) / call_size,
                                "replan_every": cfg.replan_every, "note": "compile excluded"},
      "rates": {k: float(np.mean([m[k] for m in per_seed])) for k in per_seed[0]},
      **({"adversarial": {k: float(np.nanmean([m[k] for m in per_seed])) for k in _ADVERSARIAL},
          "adversarial_std": {k: float(np.nanstd([m[k] for m in per_seed])) for k in _ADVERSARIAL}}
         if cfg.adversarial_scores else {}),
      "per_seed": per_seed,
      "skipped": skipped,
      "config": _config_record(cfg),
      "device": str(jax.devices()[0]),
      "devices": 1 if mesh is None else int(mesh.devices.size),
  }
  with open(os.path.join(out_dir, "metrics.json"), "w") as f:
    json.dump(summary, f, indent=2)
  with open(os.path.join(out_dir, "metrics.md"), "w") as f:
    f.write(_markdown(summary))
  return summary


def _write_gif(final_state, index: int, scenario_id: str, out_dir: str, start: int, stop: int) -> None:
  """The GIF of rollout `index`: steps start..stop, the simulated ones (later steps were never run)."""
  from pcdiff_jax import viz
  one = jax.tree_util.tree_map(lambda a: np.asarray(a[index]), final_state)
  os.makedirs(os.path.join(out_dir, "gifs"), exist_ok=True)
  viz.render_rollout_gif(one, os.path.join(out_dir, "gifs", f"{scenario_id}.gif"), start=start,
                         stop=min(stop, one.sim_trajectory.x.shape[-1] - 1))
