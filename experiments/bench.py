"""Benchmarks; results go to docs/BENCHMARKS.md.

  python -m experiments.bench --scenarios ../shared/data/womd/motion_data_one_example.tfrecord
  python -m experiments.bench --scenarios ... --sections policy      # only the replanning step

Measures: TFRecord parse speed (scenarios/s, the record replicated into a
temporary file), closed-loop simulator step time (constant-velocity actor,
64 reactive agents, 80 steps as one lax.scan; per batch size), the time of
the collision/off-road metrics, and the scene encoder's forward pass (64
agents, 256 map pieces; per preset: ms per scene and XLA temp memory).

`guidance`: one replanning at 65 agents, 5 DDIM steps, without guidance and
with objective / adversarial guidance (default settings), and the road field's
build (once per scenario).

`lanes`: one cold replanning at 65 agents without and with the denoiser's
lane-relative inputs (`model.lane_context`), and their computation alone.

`policy` (the replanning step of ours, weights untrained: speed does not
depend on their values): the time of one replanning for the reactive agents
split into encode (features + encoder + proposal latents), sample (DDIM) and
decode (latent -> actions -> rollout with f), each with XLA's FLOP count (`mflop`); its scaling with the padded
agent count (8-128), DDIM steps and scenarios per call (vmap); and the
80-step closed loop as one fused `lax.scan` against a Python loop calling the
jitted step. Every closed loop here plans at every step (`replan_every=1`,
10 Hz), the cost a replan at 10 Hz must fit in. These rows plan with one sample (`select_samples=1`); the
default sample selection (S = 8) gets its own rows: a cold
replanning (`replan_select8`) and the 80-step closed loop with every default
(`fused_default_ms_per_step`; without selection's map term or its box overlaps, with one
sample and with four samples too), the actor's state made once per scenario outside the timed loop (its road
field: `default_actor_init_ms`). Compile time is excluded and reported separately.

`wosac` (not in the default sections): seconds per scene of a WOSAC export
of ours (`--wosac-checkpoint`) with every plan in 65 agent slots, plans sized
to the scene (`wosac.plan_cap`), sized plans with a copy of the scene per
rollout (the older path) and sized plans with a smaller map crop
(`--wosac-variants`), all rollouts in one call, and sized plans at N rollouts
per call (`--wosac-rollouts-per-call`), scene by scene, compile excluded.

`devices`: data-parallel training steps/s (the stage-1 step, the preset's
global batch split over N devices) and scenario-parallel closed-loop scenes/s
(cv and ours, untrained weights) over the first N devices, for N in
--device-counts (`pcdiff_jax.distributed`). On a CPU host the N devices are
fake ones that share its cores (this section asks JAX for them before it
starts): the figures show the plumbing, not a speed-up. On a multi-GPU host
they are the real scaling.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import tempfile
import time
from typing import Sequence

import jax
import numpy as np


def _time(fn, repeats: int) -> list[float]:
  out = []
  for _ in range(repeats):
    t0 = time.perf_counter()
    jax.block_until_ready(fn())
    out.append(time.perf_counter() - t0)
  return out


def bench_parse(path: str, copies: int) -> dict:
  from pcdiff_jax.data import womd
  state, meta = womd.load(path)
  with tempfile.TemporaryDirectory() as tmp:
    big = os.path.join(tmp, "bench.tfrecord")
    womd.write(big, [(state, f"{meta.scenario_id}-{i}") for i in range(copies)])
    t0 = time.perf_counter()
    n = sum(1 for _ in womd.iterate_numpy(big))
    elapsed = time.perf_counter() - t0
  return {"scenarios": n, "seconds": elapsed, "scenarios_per_s": n / elapsed}


def bench_rollout(path: str, batch_sizes: list[int], repeats: int) -> list[dict]:
  from pcdiff_jax import evaluation
  from pcdiff_jax.data import womd
  state, _ = womd.load(path)
  cfg = evaluation.EvalConfig(method="cv")
  run = evaluation.make_rollout_fn(evaluation.METHODS["cv"](64), cfg)
  score = evaluation.make_score_fn(cfg)
  rows = []
  for b in batch_sizes:
    batch = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], b, 0), state)
    rngs = jax.random.split(jax.random.PRNGKey(0), b)
    t0 = time.perf_counter()
    final = jax.block_until_ready(run(batch, rngs, None))
    compile_s = time.perf_counter() - t0
    times = _time(lambda: run(batch, rngs, None), repeats)
    jax.block_until_ready(score(final))
    score_times = _time(lambda: score(final), max(1, repeats // 2))
    rows.append({
        "batch": b, "compile_s": compile_s,
        "ms_per_step": 1000 * float(np.mean(times)) / cfg.num_steps,
        "ms_per_step_std": 1000 * float(np.std(times)) / cfg.num_steps,
        "ms_per_scenario_step": 1000 * float(np.mean(times)) / cfg.num_steps / b,
        "metrics_s_per_scenario": float(np.mean(score_times)) / b,
    })
  return rows


def bench_encoder(path: str, presets: list[str], repeats: int) -> list[dict]:
  """Features + encoder forward pass, jitted, on the first record (unbatched)."""
  from pcdiff_jax.config import get_config
  from pcdiff_jax.data import womd
  from pcdiff_jax.model import encoder, features
  from pcdiff_jax.sim import env
  state = env.reset(womd.load(path)[0])
  rows = []
  for name in presets:
    cfg = get_config(name)
    feats = features.scene_features(state, cfg.features)
    params = encoder.init(jax.random.PRNGKey(0), feats, cfg.encoder)
    fwd = jax.jit(lambda p, s: encoder.apply(p, features.scene_features(s, cfg.features), cfg.encoder))
    t0 = time.perf_counter()
    compiled = fwd.lower(params, state).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(params, state))
    times = _time(lambda: compiled(params, state), repeats)
    memory = compiled.memory_analysis()
    rows.append({
        "preset": name, "agents": cfg.features.max_agents, "map_pieces": cfg.features.max_polylines,
        "neighbors": cfg.encoder.num_neighbors, "d_model": cfg.encoder.d_model,
        "params": int(sum(np.size(x) for x in jax.tree_util.tree_leaves(params))),
        "compile_s": compile_s, "ms_per_scene": 1000 * float(np.median(times)),
        "ms_per_scene_min": 1000 * float(np.min(times)),
        "temp_mb": (memory.temp_size_in_bytes / 2**20) if memory is not None else None,
    })
  return rows


def _config_of(preset: str):
  """The Config of a preset name, or the one a model folder (e.g. the shipped
  checkpoints/pcdiff-cpu-v11) runs with: its architecture, inputs and sizes
  and the run-time map crop (`shipped.run_config`), so the timings are those
  of that model (weights stay untrained: they do not change the cost)."""
  if os.path.isdir(preset):
    from pcdiff_jax import shipped
    return shipped.run_config(shipped.read_config(preset))
  from pcdiff_jax.config import get_config
  return get_config(preset)


_MODELS: dict = {}


def _policy_models(state, cfg):
  """Untrained Models for cfg (random orthonormal latent basis), initialised on
  one scene in one jitted call and kept per cfg: built op by op for every row,
  the initialisation took longer than the rows (a minute each, `paper` preset).
  Speed does not depend on the weights' values (docs/DEVELOPING.md)."""
  if cfg in _MODELS:
    return _MODELS[cfg]
  from pcdiff_jax.model import denoiser, encoder, features, latent, planner
  d, horizon = cfg.diffusion.latent_dim, cfg.encoder.horizon
  basis, _ = np.linalg.qr(np.random.default_rng(0).normal(size=(2 * horizon, d)))
  stats = latent.placeholder(horizon, d).replace(components=jax.numpy.asarray(basis, np.float32))

  @jax.jit
  def build(s):
    feats = features.scene_features(s, cfg.features)
    enc = encoder.init(jax.random.PRNGKey(0), feats, cfg.encoder)
    batched = jax.tree_util.tree_map(lambda a: a[None], feats)
    cond = planner.condition(enc, stats, batched, cfg)
    one = jax.tree_util.tree_map(lambda a: a[0], cond.inputs)
    return enc, denoiser.init(jax.random.PRNGKey(1), cond.mu[0], jax.numpy.int32(0), one,
                              cfg.diffusion.denoiser)

  enc, den = build(state)
  _MODELS[cfg] = planner.Models(encoder=enc, denoiser=den, stats=stats)
  return _MODELS[cfg]


def _compiled_ms(fn, args, repeats: int) -> dict:
  t0 = time.perf_counter()
  compiled = jax.jit(fn).lower(*args).compile()
  compile_s = time.perf_counter() - t0
  jax.block_until_ready(compiled(*args))
  times = _time(lambda: compiled(*args), repeats)
  return {"ms": 1000 * float(np.median(times)), "ms_std": 1000 * float(np.std(times)),
          "compile_s": compile_s, "mflop": _mflop(compiled)}


def _mflop(compiled) -> float | None:
  """XLA's count of the floating-point operations of one call, in millions: unlike a time, it
  does not depend on what else the cores run (None where the backend does not report it)."""
  try:
    cost = compiled.cost_analysis()
  except Exception:  # noqa: BLE001 - optional backend feature
    return None
  cost = cost[0] if isinstance(cost, (list, tuple)) and cost else cost
  flops = cost.get("flops") if isinstance(cost, dict) else None
  return None if flops is None else float(flops) / 1e6


def bench_replan_parts(state, cfg, ddim_steps: int, repeats: int) -> dict:
  """encode / sample / decode / whole replanning of one scene."""
  from pcdiff_jax import policy
  from pcdiff_jax.model import features, latent, planner
  from pcdiff_jax.sim import dynamics
  models = _policy_models(state, cfg)
  rng = jax.random.PRNGKey(2)

  def encode(m, s):
    feats = jax.tree_util.tree_map(lambda a: a[None], features.scene_features(s, cfg.features))
    return feats, planner.condition(m.encoder, m.stats, feats, cfg)

  def sample(m, cond, r):
    return planner.sample(m.denoiser, cond, cfg, r, ddim_steps, 0.0)

  def decode(m, feats, cond, y0):
    states = planner.decode_states(m.stats, cond, y0, cfg)
    actions = dynamics.clip_action(latent.decode(y0, m.stats), cfg.kinematics)
    return actions, features.agent_to_world(states[..., :2], states[..., 2], feats)

  pcfg = policy.PolicyConfig(ddim_steps=ddim_steps, select_samples=1)
  select = policy.PolicyConfig(ddim_steps=ddim_steps)   # the default sample selection
  feats, cond = jax.jit(encode)(models, state)
  y0 = jax.jit(sample)(models, cond, rng)
  row = {"agents": cfg.features.max_agents, "ddim_steps": ddim_steps,
         "encode": _compiled_ms(encode, (models, state), repeats),
         "sample": _compiled_ms(sample, (models, cond, rng), repeats),
         "decode": _compiled_ms(decode, (models, feats, cond, y0), repeats),
         "replan": _compiled_ms(lambda m, s, r: policy.plan_actions(m, s, cfg, pcfg, r),
                                (models, state, rng), repeats),
         # The default's road field (its selection's map term) is built once per scenario: outside.
         f"replan_select{select.select_samples}": _compiled_ms(
             lambda m, s, r, road: policy.plan_actions(m, s, cfg, select, r, road=road),
             (models, state, rng, jax.jit(lambda s: policy.road_for(s, select))(state)), repeats)}
  return row


def bench_replan_batch(state, cfg, batch_sizes: list[int], repeats: int) -> list[dict]:
  """One replanning per scenario, vmapped over B copies of the scene."""
  from pcdiff_jax import policy
  models = _policy_models(state, cfg)
  pcfg = policy.PolicyConfig(ddim_steps=cfg.diffusion.ddim_steps, select_samples=1)
  rows = []
  for b in batch_sizes:
    batch = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], b, 0), state)
    rngs = jax.random.split(jax.random.PRNGKey(0), b)
    fn = jax.vmap(lambda s, r, m: policy.plan_actions(m, s, cfg, pcfg, r), in_axes=(0, 0, None))
    t = _compiled_ms(fn, (batch, rngs, models), repeats)
    rows.append({"batch": b, **t, "ms_per_scenario": t["ms"] / b})
  return rows


def bench_fused_vs_loop(state, cfg, num_steps: int, repeats: int) -> dict:
  """The closed loop of ours: one lax.scan over num_steps against a Python
  loop over the jitted (select_action + env.step)."""
  from pcdiff_jax import policy
  from pcdiff_jax.sim import env
  models = _policy_models(state, cfg)
  actor = policy.actor(cfg, policy.PolicyConfig(ddim_steps=cfg.diffusion.ddim_steps, warm_start=False,
                                                select_samples=1, replan_every=1))
  rng = jax.random.PRNGKey(0)
  start = env.reset(state)
  fused = lambda s, r, m: env.rollout(s, actor, num_steps, r, params=m).final_state
  fused_t = _compiled_ms(fused, (start, rng, models), repeats)

  @jax.jit
  def one_step(s, actor_state, r, m, k):
    out = actor.select_action(m, s, actor_state, jax.random.fold_in(r, k))
    return env.step(s, out.action, out.is_controlled), out.actor_state

  def python_loop(s, r, m):
    actor_state = actor.init(r, s)
    for k in range(num_steps):
      s, actor_state = one_step(s, actor_state, r, m, k)
    return s

  jax.block_until_ready(python_loop(start, rng, models))          # compile
  loop_times = _time(lambda: python_loop(start, rng, models), repeats)
  # Warm-started replanning (the default's warm DDIM steps from its warm step after the first plan), one sample.
  warm = policy.actor(cfg, policy.PolicyConfig(ddim_steps=cfg.diffusion.ddim_steps, warm_start=True,
                                               select_samples=1, replan_every=1))
  warm_t = _compiled_ms(lambda s, r, m: env.rollout(s, warm, num_steps, r, params=m).final_state,
                        (start, rng, models), repeats)
  row = {"agents": cfg.features.max_agents, "steps": num_steps,
         "fused_ms_per_step": fused_t["ms"] / num_steps, "fused_compile_s": fused_t["compile_s"],
         "loop_ms_per_step": 1000 * float(np.median(loop_times)) / num_steps,
         "fused_warm_start_ms_per_step": warm_t["ms"] / num_steps}
  # The default policy (warm start, temporal ensemble, sample selection with its map term), it
  # without the map term, without selection and with 4 samples (docs/RESULTS.md, "Ablation: samples per
  # replan"). The actor's state (the road field of the map term) is made once per scenario, outside: its cost is its own row.
  default = dataclasses.replace(policy.PolicyConfig(), replan_every=1)   # a plan at every step: 10 Hz
  for name, pcfg in (("fused_default_ms_per_step", default),
                     ("fused_default_nomap_ms_per_step", dataclasses.replace(default, select_map_weight=0.0)),
                     ("fused_default_select1_ms_per_step", dataclasses.replace(default, select_samples=1)),
                     ("fused_default_select4_ms_per_step", dataclasses.replace(default, select_samples=4)),
                     ("fused_default_no_still_gate_ms_per_step",
                      dataclasses.replace(default, still_gate=(0.0, 0.0), max_curvature=0.0)),
                     ("fused_default_no_follow_ms_per_step", dataclasses.replace(default, follow=(0.0, 0.0))),
                     ("fused_default_circles_ms_per_step", dataclasses.replace(default, select_boxes=False)),
                     ("fused_default_no_crossing_ms_per_step", dataclasses.replace(default, follow_crossing=False)),
                     ("fused_default_no_rear_guard_ms_per_step", dataclasses.replace(default, rear_guard=False)),
                     ("fused_default_no_map_spare_ms_per_step",
                      dataclasses.replace(default, select_map_spare=(0.0, 0.0))),
                     ("fused_default_pedestrians_sampled_ms_per_step",
                      dataclasses.replace(default, pedestrian_plan="sample"))):
    act = policy.actor(cfg, pcfg)
    init = jax.jit(act.init)(rng, start)
    row[name] = _compiled_ms(
        lambda s, r, m, a0, act=act: env.rollout(s, act, num_steps, r, params=m, actor_state=a0).final_state,
        (start, rng, models, init), repeats)["ms"] / num_steps
  row["default_actor_init_ms"] = _compiled_ms(policy.actor(cfg, default).init, (rng, start), repeats)["ms"]
  return row


def bench_policy(path: str, preset: str, agent_counts: list[int], ddim_steps: list[int],
                 batch_sizes: list[int], repeats: int) -> dict:
  from pcdiff_jax.data import womd
  from pcdiff_jax.sim import env
  base = _config_of(preset)
  state = env.reset(womd.load(path)[0])
  with_agents = lambda a: dataclasses.replace(
      base, features=dataclasses.replace(base.features, max_agents=a))
  def shown(name, row):   # each row as it comes: a long run cut short keeps what it measured
    print(f"policy/{name}: {json.dumps(row)}", flush=True)
    return row

  return {
      "preset": preset,
      "parts_by_agents": [shown("agents", bench_replan_parts(state, with_agents(a), base.diffusion.ddim_steps,
                                                             repeats)) for a in agent_counts],
      "parts_by_ddim_steps": [shown("ddim_steps", bench_replan_parts(state, base, n, repeats))
                              for n in ddim_steps],
      "replan_by_batch": shown("batch", bench_replan_batch(state, base, batch_sizes, repeats)),
      "fused_vs_loop": shown("fused", bench_fused_vs_loop(womd.load(path)[0], base, 80, max(1, repeats // 2))),
  }


def bench_guidance(path: str, preset: str, repeats: int) -> dict:
  """One replanning of one scene (65 agents, 5 DDIM steps) without guidance,
  with objective and with adversarial guidance (default GuidanceConfig), the
  road field built beforehand as the actor does at init; and that build."""
  from pcdiff_jax import policy
  from pcdiff_jax.data import womd
  from pcdiff_jax.model.guidance import GuidanceConfig, road_of
  from pcdiff_jax.sim import env
  state = env.reset(womd.load(path)[0])
  cfg = _config_of(preset)
  models = _policy_models(state, cfg)
  rng = jax.random.PRNGKey(2)
  out = {"agents": cfg.features.max_agents, "ddim_steps": 5}
  for mode in ("none", "objective", "adversarial"):
    g = dataclasses.replace(GuidanceConfig(), mode=mode)
    pcfg = policy.PolicyConfig(ddim_steps=5, guidance=g)
    road = jax.jit(lambda s: road_of(s, g))(state)
    adversary = jax.jit(lambda s: policy.pursuer_of(s, cfg, g))(state)
    out[mode] = _compiled_ms(lambda m, s, r, rd: policy.plan_actions(m, s, cfg, pcfg, r, adversary, road=rd),
                             (models, state, rng, road), repeats)
  g = dataclasses.replace(GuidanceConfig(), mode="objective")
  out["road_field_build"] = _compiled_ms(lambda s: road_of(s, g), (state,), repeats)
  out["road_field"] = {"size": g.field_size, "spacing_m": g.field_spacing, "edge_points": g.max_edge_points}
  return out


def bench_lane_inputs(path: str, preset: str, repeats: int) -> dict:
  """What the denoiser's lane-relative inputs (`DenoiserConfig.lane_inputs`,
  the shipped model's since v6) cost: one cold replanning of one scene (65
  agents, 5 DDIM steps) without and with them, and their computation alone."""
  from pcdiff_jax import policy
  from pcdiff_jax.data import womd
  from pcdiff_jax.model import features, lane_context
  from pcdiff_jax.sim import env
  state = env.reset(womd.load(path)[0])
  base = _config_of(preset)
  rng = jax.random.PRNGKey(2)
  pcfg = policy.PolicyConfig(ddim_steps=5, warm_start=False)
  out = {"agents": base.features.max_agents, "ddim_steps": 5}
  for name, on in (("without", False), ("with", True)):
    cfg = dataclasses.replace(base, diffusion=dataclasses.replace(base.diffusion, denoiser=dataclasses.replace(
        base.diffusion.denoiser, lane_inputs=on)))
    models = _policy_models(state, cfg)
    out[name] = _compiled_ms(lambda m, s, r: policy.plan_actions(m, s, cfg, pcfg, r), (models, state, rng), repeats)
  feats = jax.jit(lambda s: features.scene_features(s, base.features))(state)
  out["lane_inputs_alone"] = _compiled_ms(lane_context.lane_inputs, (feats,), repeats)
  return out


def bench_devices(path: str, preset: str, counts: list[int], train_steps: int, rollout_batch: int,
                  rollout_steps: int, repeats: int) -> dict:
  """Training steps/s and rollout scenes/s on meshes of the first N devices
  (N = 1 is the one-device code path, without a mesh)."""
  from pcdiff_jax import distributed, evaluation, policy
  from pcdiff_jax.config import MetricsConfig
  from pcdiff_jax.data import womd
  from pcdiff_jax.sim import env
  from pcdiff_jax.training import data as data_lib
  from pcdiff_jax.training import encoder_stage, trainer
  cfg = _config_of(preset)
  state = womd.load(path)[0]
  counts = [n for n in counts if n <= jax.device_count()]
  mesh_of = lambda n: distributed.data_mesh(n) if n > 1 else None
  # Training: the stage-1 step on the record at t = 10, tiled to the global batch (the
  # preset's, rounded up to a multiple of the largest mesh).
  batch_size = -(-cfg.encoder_train.batch_size // max(counts)) * max(counts)
  one = jax.jit(lambda s: data_lib.example_at(s, 10, cfg.features, cfg.encoder.horizon))(state)
  examples = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], batch_size, 0), one)
  params = jax.device_get(jax.jit(lambda ex: encoder_stage.init_params(cfg, ex, 0))(examples))
  tx = trainer.make_optimizer(cfg.encoder_train)
  train_rows = []
  for n in counts:
    mesh = mesh_of(n)
    if mesh is not None and batch_size % n:
      continue
    step = trainer.make_train_step(encoder_stage.make_loss_fn(cfg), tx, mesh=mesh)
    st = trainer.create_state(params, tx, 0)
    st, batch = ((jax.device_put(st, jax.devices()[0]), jax.device_put(examples, jax.devices()[0]))
                 if mesh is None else (distributed.replicate(st, mesh), distributed.shard_batch(examples, mesh)))
    t0 = time.perf_counter()
    st, _ = jax.block_until_ready(step(st, batch))
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for _ in range(train_steps):
      st, metrics = step(st, batch)
    jax.block_until_ready(metrics)
    elapsed = time.perf_counter() - t0
    train_rows.append({"devices": n, "global_batch": batch_size, "steps_per_s": train_steps / elapsed,
                       "examples_per_s": train_steps * batch_size / elapsed, "first_step_s": compile_s})
  # Closed loop: `rollout_batch` copies of the record per call, split over the devices.
  metrics_cfg = MetricsConfig(max_reactive_agents=cfg.features.max_agents - 1)
  model_cfg = evaluation.with_agent_cap(cfg, metrics_cfg)
  models = _policy_models(env.reset(state), model_cfg)
  actors = {"cv": (evaluation.METHODS["cv"](metrics_cfg.max_reactive_agents), None),
            "pcdiff": (policy.actor(model_cfg, policy.PolicyConfig(ddim_steps=cfg.diffusion.ddim_steps,
                                                                  replan_every=1)), models)}
  scenes = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], rollout_batch, 0), state)
  rngs = jax.random.split(jax.random.PRNGKey(0), rollout_batch)
  rollout_rows = []
  for method, (actor, weights) in actors.items():
    ecfg = evaluation.EvalConfig(method=method, num_steps=rollout_steps, metrics=metrics_cfg)
    for n in counts:
      mesh = mesh_of(n)
      if mesh is not None and rollout_batch % n:
        continue
      run = evaluation.make_rollout_fn(actor, ecfg, mesh)
      args = (scenes, rngs, weights) if mesh is None else (
          *jax.device_put((scenes, rngs), distributed.batch_sharded(mesh)), distributed.replicate(weights, mesh))
      t0 = time.perf_counter()
      jax.block_until_ready(run(*args))
      compile_s = time.perf_counter() - t0
      seconds = float(np.median(_time(lambda: run(*args), repeats)))
      rollout_rows.append({"method": method, "devices": n, "scenes_per_call": rollout_batch,
                           "steps": rollout_steps, "scenes_per_s": rollout_batch / seconds,
                           "scene_steps_per_s": rollout_batch * rollout_steps / seconds,
                           "first_call_s": compile_s})
  return {"preset": preset, "platform": jax.devices()[0].platform, "available_devices": jax.device_count(),
          "train_encoder_step": train_rows, "closed_loop": rollout_rows}


def bench_wosac_plans(path: str, checkpoint: str, num_scenes: int, num_rollouts: int,
                      variants: Sequence[str] = ("full", "sized"), map_pieces: int = 128,
                      map_anchor: str = "sdc", per_call: Sequence[int] = ()) -> list[dict]:
  """Seconds per scene of a WOSAC export (`wosac.Simulator.simulate`) in each
  of `variants`, all `num_rollouts` in one call: "full" (every plan in the cap's
  65 slots), "sized" (slots sized to the scene, `WosacConfig.size_plans`) and
  "cropped" (sized, and the map crop `map_pieces` / `map_anchor`); and
  "sized_per_call{N}" for each N of `per_call` (sized, N rollouts per call), for
  the first `num_scenes` scenes of `path`; each timed call follows an untimed one
  of the same scene (its compile). "tiled" (and "tiled_per_call{N}") give each
  rollout its own copy of the scene (`WosacConfig.tile_scene`, the older path).
  Ratios are CPU time against "sized"."""
  from pcdiff_jax import evaluation, wosac
  from pcdiff_jax.data import womd
  crops = {"full": {}, "sized": {}, "tiled": {}, "cropped": {"map_pieces": map_pieces, "map_anchor": map_anchor}}
  configs = {name: (crops[name], num_rollouts, name != "full") for name in variants}
  configs.update({f"sized_per_call{n}": ({}, n, True) for n in per_call})
  if "tiled" in variants:
    configs.update({f"tiled_per_call{n}": ({}, n, True) for n in per_call})
  sims = {name: wosac.Simulator(wosac.WosacConfig(
      eval=evaluation.EvalConfig(method="pcdiff", checkpoint=checkpoint, **crop),
      num_rollouts=num_rollouts, rollouts_per_call=calls, size_plans=sized,
      tile_scene=name.startswith("tiled")))
      for name, (crop, calls, sized) in configs.items()}
  rows = []
  for state, meta in womd.iterate([path], with_meta=True, history_only=True, max_num_objects=None,
                                  max_scenarios=num_scenes, to_jax=False):
    agents = int(np.asarray(state.log_trajectory.valid)[:, 10].sum())
    sized = next((sim for name, sim in sims.items() if name != "full"), None)
    row = {"scenario_id": meta.scenario_id, "sim_agents": agents,
           "cap": sized.learned_run(state)[2] if sized else None}
    for name, sim in sims.items():
      sim.simulate(state, meta.scenario_id)
      t0, c0 = time.perf_counter(), time.process_time()
      sim.simulate(state, meta.scenario_id)
      row[f"{name}_s"], row[f"{name}_cpu_s"] = time.perf_counter() - t0, time.process_time() - c0
    for name in sims:
      if name != "sized" and "sized" in sims:
        row[f"sized_over_{name}_cpu"] = row["sized_cpu_s"] / row[f"{name}_cpu_s"]
    print(json.dumps(row), flush=True)
    rows.append(row)
  return rows


SECTIONS = ("parse", "rollout", "encoder", "policy", "guidance", "lanes", "devices", "wosac")


def main(argv=None) -> int:
  p = argparse.ArgumentParser(prog="python -m experiments.bench", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", required=True, help="a WOMD-format TFRecord (the first record is used)")
  p.add_argument("--parse-copies", type=int, default=200)
  p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 4, 16])
  p.add_argument("--repeats", type=int, default=5)
  p.add_argument("--encoder-presets", nargs="*", default=["cpu", "paper"],
                 help="config presets for the encoder benchmark (none: skip it)")
  p.add_argument("--policy-preset", default="cpu",
                 help="config preset of the policy benchmark, or a model folder whose config to time "
                      "(e.g. checkpoints/pcdiff-cpu-v11: the shipped model's inputs and sizes)")
  p.add_argument("--agents", type=int, nargs="+", default=[8, 16, 32, 65, 128],
                 help="padded agent counts (SDC included) for the policy scaling")
  p.add_argument("--ddim-steps", type=int, nargs="+", default=[1, 5, 10, 25])
  p.add_argument("--policy-batch-sizes", type=int, nargs="+", default=[1, 4, 16])
  p.add_argument("--device-counts", type=int, nargs="+", default=[1, 2, 4],
                 help="devices: mesh sizes (on a CPU host, fake devices are made for the largest)")
  p.add_argument("--device-train-steps", type=int, default=5, help="devices: timed training steps")
  p.add_argument("--device-batch", type=int, default=4, help="devices: scenes per closed-loop call")
  p.add_argument("--device-rollout-steps", type=int, default=80, help="devices: closed-loop steps")
  p.add_argument("--wosac-checkpoint", default=None,
                 help="wosac: the learned model (default: the shipped one, pcdiff_jax.shipped.checkpoint_dir())")
  p.add_argument("--wosac-scenes", type=int, default=4, help="wosac: the first N scenes of --scenarios")
  p.add_argument("--wosac-rollouts", type=int, default=32, help="wosac: rollouts per scene (one jitted call)")
  p.add_argument("--wosac-variants", nargs="+", default=["full", "sized"], choices=("full", "sized", "tiled", "cropped"),
                 help="wosac: 65 slots, slots sized to the scene (the default), sized with a copy of the scene "
                      "per rollout (also at each N below), sized + the map crop below")
  p.add_argument("--wosac-map-pieces", type=int, default=128, help="wosac: the cropped variant's map pieces")
  p.add_argument("--wosac-rollouts-per-call", type=int, nargs="*", default=[],
                 help="wosac: also the sized variant at N rollouts per call, for each N")
  p.add_argument("--wosac-map-anchor", default="sdc", choices=("sdc", "agents"),
                 help="wosac: the cropped variant's map anchor")
  p.add_argument("--sections", nargs="+", default=[s for s in SECTIONS if s not in ("devices", "wosac")],
                 choices=SECTIONS, help="default: all but devices and wosac")
  p.add_argument("--json", help="also write the results here")
  args = p.parse_args(argv)
  if not os.path.isfile(args.scenarios):
    p.error(f"--scenarios: file not found: {args.scenarios}")
  for name in ("agents", "ddim_steps", "policy_batch_sizes", "batch_sizes", "device_counts"):
    if min(getattr(args, name)) < 1:
      p.error(f"--{name.replace('_', '-')} values must be >= 1")
  for name in ("device_train_steps", "device_batch", "device_rollout_steps"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if "devices" in args.sections:
    try:   # fake CPU devices for the largest mesh; a GPU / TPU backend keeps its own
      jax.config.update("jax_num_cpu_devices", max(args.device_counts))
    except RuntimeError:   # JAX already started (bench called from Python): the devices it has
      pass
  results = {"device": str(jax.devices()[0]), "cpu_count": os.cpu_count()}
  if "parse" in args.sections:
    results["parse"] = bench_parse(args.scenarios, args.parse_copies)
  if "rollout" in args.sections:
    results["rollout_cv_64_agents"] = bench_rollout(args.scenarios, args.batch_sizes, args.repeats)
  if "encoder" in args.sections:
    results["encoder_forward"] = bench_encoder(args.scenarios, args.encoder_presets, args.repeats)
  if "policy" in args.sections:
    results["policy"] = bench_policy(args.scenarios, args.policy_preset, args.agents, args.ddim_steps,
                                     args.policy_batch_sizes, args.repeats)
  if "lanes" in args.sections:
    results["lane_inputs"] = bench_lane_inputs(args.scenarios, args.policy_preset, args.repeats)
  if "guidance" in args.sections:
    results["guidance"] = bench_guidance(args.scenarios, args.policy_preset, args.repeats)
  if "devices" in args.sections:
    results["devices"] = bench_devices(args.scenarios, args.policy_preset, args.device_counts,
                                       args.device_train_steps, args.device_batch, args.device_rollout_steps,
                                       args.repeats)
  if "wosac" in args.sections:
    from pcdiff_jax import shipped
    checkpoint = args.wosac_checkpoint or shipped.checkpoint_dir()
    results["wosac_plans"] = bench_wosac_plans(args.scenarios, checkpoint, args.wosac_scenes,
                                               args.wosac_rollouts, args.wosac_variants,
                                               args.wosac_map_pieces, args.wosac_map_anchor,
                                               args.wosac_rollouts_per_call)
  print(json.dumps(results, indent=2))
  if args.json:
    with open(args.json, "w") as f:
      json.dump(results, f, indent=2)
  return 0


if __name__ == "__main__":
  raise SystemExit(main())
