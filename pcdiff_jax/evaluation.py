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

from pcdiff_jax import baselines
from pcdiff_jax.config import MetricsConfig
from pcdiff_jax.data import womd
from pcdiff_jax.sim import env, metrics
from pcdiff_jax.sim.actors import Actor
from pcdiff_jax.sim.selection import nearest_to_sdc

log = logging.getLogger(__name__)

METHODS: dict[str, Callable[[int], Actor]] = {
    "log": lambda max_agents: baselines.log_replay(),
    "cv": lambda max_agents: baselines.constant_velocity(baselines.reactive_agents(max_agents)),
    "expert": lambda max_agents: baselines.expert(controlled_fn=baselines.reactive_agents(max_agents)),
}


LEARNED = ("pcdiff", "pcdiff-noprior")


@dataclasses.dataclass(frozen=True)
class EvalConfig:
  """method: a baseline of METHODS or a learned policy of LEARNED (which needs
  `checkpoint`, the training workdir). ddim_steps / eta / replan_every: the
  learned policy's sampler and replanning interval."""
  method: str = "cv"
  checkpoint: Optional[str] = None
  ddim_steps: int = 5
  eta: float = 0.0
  replan_every: int = 1
  num_steps: int = 80
  init_steps: int = env.WOMD_INIT_STEPS
  batch_size: int = 1
  gifs: int = 1
  seed: int = 0
  metrics: MetricsConfig = MetricsConfig()


def make_actor(cfg: EvalConfig) -> tuple[Actor, Any]:
  """(actor, params) of `cfg.method`; learned policies load `cfg.checkpoint`."""
  if cfg.method in METHODS:
    return METHODS[cfg.method](cfg.metrics.max_reactive_agents), None
  if cfg.method not in LEARNED:
    raise ValueError(f"unknown method {cfg.method!r}; choose one of {sorted(METHODS) + list(LEARNED)}")
  if not cfg.checkpoint:
    raise ValueError(f"--method {cfg.method} needs --checkpoint (a training workdir)")
  from pcdiff_jax import policy
  from pcdiff_jax.training import diffusion_stage
  use_prior = cfg.method == "pcdiff"
  models, model_cfg = diffusion_stage.load(cfg.checkpoint, use_prior=use_prior)
  pcfg = policy.PolicyConfig(ddim_steps=cfg.ddim_steps, eta=cfg.eta, prior_init=use_prior,
                             replan_every=cfg.replan_every)
  return policy.actor(model_cfg, pcfg), models


def make_rollout_fn(actor: Actor, cfg: EvalConfig):
  """jit(vmap) of reset -> closed-loop rollout, per scenario:
  (states (B,), rngs (B,), params) -> final states. The params (model weights)
  are an argument, not a constant baked into the program."""
  def one(state, rng, params):
    return env.rollout(env.reset(state, cfg.init_steps), actor, cfg.num_steps, rng,
                       params=params).final_state
  return jax.jit(jax.vmap(one, in_axes=(0, 0, None)))


def make_score_fn(cfg: EvalConfig):
  """jit(vmap) of the event counts of rolled-out states (B,) -> EventCounts (B,)."""
  start = cfg.init_steps - 1

  def one(final_state):
    evaluated = nearest_to_sdc(final_state.replace(timestep=jnp.int32(start)),
                               cfg.metrics.max_reactive_agents)
    return metrics.event_counts(final_state.sim_trajectory, final_state.log_trajectory,
                                final_state.roadgraph_points, final_state.object_metadata.object_types,
                                evaluated, start, cfg.metrics.max_road_edge_points)
  return jax.jit(jax.vmap(one))


def _pad_batch(state, size: int):
  """Repeats the last scenario so every batch has the same size (no recompiles)."""
  n = state.shape[0]
  if n == size:
    return state
  return jax.tree_util.tree_map(
      lambda a: jnp.concatenate([a, jnp.repeat(a[-1:], size - n, axis=0)], 0), state)


def _markdown(summary: dict) -> str:
  r = summary["rates"]
  rows = [
      ("collision rate (%)", 100 * r["collision_rate"]),
      ("vehicle-vehicle collision rate (%)", 100 * r["vehicle_collision_rate"]),
      ("off-road rate (%)", 100 * r["offroad_rate"]),
      ("vehicles starting off-road (%)", 100 * r["start_offroad_fraction"]),
      ("runtime per step (ms)", summary["runtime_ms_per_step"]["mean"]),
  ]
  lines = [f"# {summary['method']} on {summary['num_scenarios']} scenario(s)", "",
           "| metric | value |", "|---|---|"]
  lines += [f"| {name} | {value:.2f} |" for name, value in rows]
  lines += ["", f"evaluated agents: {int(r['num_evaluated'])}, of them vehicles: {int(r['num_vehicles'])}; "
            f"skipped scenarios: {len(summary['skipped'])}"]
  return "\n".join(lines) + "\n"


def evaluate(scenarios: Sequence[str] | str, out_dir: str, cfg: EvalConfig,
             progress: bool = True) -> dict:
  """Runs `cfg.method` over every scenario; returns and writes the summary."""
  files = womd.expand_paths(scenarios)  # fail early, naming the missing path
  actor, params = make_actor(cfg)
  os.makedirs(out_dir, exist_ok=True)
  run = make_rollout_fn(actor, cfg)
  score = make_score_fn(cfg)
  per_scenario_path = os.path.join(out_dir, "scenarios.jsonl")
  skipped: list[dict] = []
  totals: Optional[metrics.EventCounts] = None
  step_ms: list[float] = []
  gifs_done, num_done = 0, 0
  load_errors: list = []
  batches = womd.iterate(files, batch_size=cfg.batch_size, with_meta=True, on_error="skip",
                         skipped=load_errors)
  try:
    from tqdm import tqdm
    batches = tqdm(batches, desc=f"rollout {cfg.method}", unit="batch", disable=not progress)
  except ImportError:  # progress bars are a nicety
    pass
  with open(per_scenario_path, "a") as per_scenario:
    for batch_index, (state, meta) in enumerate(batches):
      n = state.shape[0]
      rngs = jax.random.split(jax.random.fold_in(jax.random.PRNGKey(cfg.seed), batch_index), cfg.batch_size)
      try:
        t0 = time.perf_counter()
        final = jax.block_until_ready(run(_pad_batch(state, cfg.batch_size), rngs, params))
        elapsed = time.perf_counter() - t0
        counts = score(final)
      except Exception as err:  # a bad scenario must not end a long job
        log.warning("skipping batch %s (%s): %s", batch_index, meta.scenario_id, err)
        skipped += [{"scenario_id": s, "path": p, "record": r, "error": str(err)}
                    for s, p, r in zip(meta.scenario_id, meta.path, meta.record_index)]
        continue
      if batch_index > 0:  # the first call includes compilation
        step_ms.append(1000 * elapsed / cfg.num_steps)
      counts = jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], counts)
      totals = counts if totals is None else jax.tree_util.tree_map(
          lambda a, b: np.concatenate([a, b]), totals, counts)
      for i in range(n):
        row = {"scenario_id": meta.scenario_id[i], "path": meta.path[i], "record": meta.record_index[i]}
        row.update({k: int(v[i]) for k, v in dataclasses.asdict(counts).items()})
        per_scenario.write(json.dumps(row) + "\n")
        per_scenario.flush()
        if gifs_done < cfg.gifs:
          _write_gif(final, i, meta.scenario_id[i], out_dir, cfg.init_steps - 1)
          gifs_done += 1
      num_done += n
  skipped += [{"scenario_id": None, "path": e.path, "record": e.index, "error": str(e)}
              for e in load_errors]
  if totals is None:
    raise RuntimeError(f"no scenario could be evaluated; skipped: {skipped}")
  if not step_ms:  # a single batch: time a second, warm call
    t0 = time.perf_counter()
    jax.block_until_ready(run(_pad_batch(state, cfg.batch_size), rngs, params))
    step_ms.append(1000 * (time.perf_counter() - t0) / cfg.num_steps)
  summary = {
      "method": cfg.method,
      "num_scenarios": num_done,
      "rates": metrics.EventCounts(**{k: jnp.asarray(v) for k, v in dataclasses.asdict(totals).items()}).rates(),
      "runtime_ms_per_step": {"mean": float(np.mean(step_ms)), "std": float(np.std(step_ms)),
                              "batch_size": cfg.batch_size, "note": "compile excluded"},
      "skipped": skipped,
      "config": dataclasses.asdict(cfg),
      "device": str(jax.devices()[0]),
  }
  with open(os.path.join(out_dir, "metrics.json"), "w") as f:
    json.dump(summary, f, indent=2)
  with open(os.path.join(out_dir, "metrics.md"), "w") as f:
    f.write(_markdown(summary))
  return summary


def _write_gif(final_state, index: int, scenario_id: str, out_dir: str, start: int) -> None:
  from pcdiff_jax import viz
  one = jax.tree_util.tree_map(lambda a: np.asarray(a[index]), final_state)
  os.makedirs(os.path.join(out_dir, "gifs"), exist_ok=True)
  viz.render_rollout_gif(one, os.path.join(out_dir, "gifs", f"{scenario_id}.gif"), start=start)
