"""Closed-loop diagnostics: why a policy leaves its log (replay, drift, first action, parked cars,
slow starters).

  python -m experiments.diagnose --checkpoint runs/cpu --scenarios runs/val20.tfrecord replay
  python -m experiments.diagnose --checkpoint runs/cpu --scenarios runs/val20.tfrecord drift --method pcdiff
  python -m experiments.diagnose --checkpoint runs/cpu --scenarios runs/val20.tfrecord first-action

replay        executes one 8 s plan made at the rollout start, open loop, for
              every reactive agent, and scores it like a closed-loop run:
              `log` (the logged future through inverse dynamics), `log-latent`
              (the same, projected on the PCA latent and decoded), `top1` (the
              encoder's most likely proposal), `top1-latent` (its latent
              projection), `oracle` (the proposal closest to the log),
              `sample` (one cold DDIM plan of the policy, 5 steps) and
              `sample-guided` (the same under objective guidance). Tells
              what the representation itself costs before any diffusion, and
              how good one sampled plan is without the 10 Hz corrections.
drift         closed-loop rollout of a method; the controlled agents' offset
              from their log in the log's own frame (lateral: left positive;
              longitudinal: ahead positive), heading error, and speed minus
              the log's for the agents the log has moving (> 2 m/s), at 1,
              2, 4, 6, 8 s; that column includes the log's starters, so even
              constant velocity falls behind it: the cruising column (moving
              in the log at the start and at t) is the closed-loop slow-down.
              --solo also simulates each evaluated agent moving at the start
              alone, every other object on its log, and compares its speed
              with the same agent's in the joint run: a slow-down the solo
              run keeps is the policy's own, not its reaction to the others.
parked        open-loop plans for the vehicles parked in the log (path under
              0.5 m over the 8 s after t, valid for half of them): the end
              displacement of `--samples` plans per agent made at t, cold
              (the default sampler from the prior) and warm from the agent's
              most likely proposal noised to each of `--warm-steps` (one DDIM
              step, as a warm replan), against the proposal itself decoded.
              A parked car whose plans end metres away creeps in closed loop.
starters      the evaluated agents (WOSAC's: the SDC and tracks_to_predict)
              that start slower than 3 m/s and travel more than 5 m in the
              log: the 8 s travel of each of the encoder's proposals at the
              rollout start against the log's, their probability-weighted
              mean, and whether the still gate holds the agent. Proposals
              that stop a car the log drives away keep it still in closed
              loop (WOSAC's linear-speed likelihood).
first-action  the first action [accel, yaw rate] of the plans the policy
              makes at the rollout start, against the log's, for moving
              vehicles (> 2 m/s): a mean yaw rate far from the log's is a
              bias that 10 Hz replanning integrates into drift; and by
              starting speed, each plan's speed change over its first second
              (also the same denoiser started from N(0, I) instead of the
              proposal prior: the prior centre's share of a braking plan).
"""
from __future__ import annotations

import argparse
import itertools
import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from experiments import _args
from pcdiff_jax import evaluation, metrics as metrics_lib, policy
from pcdiff_jax.config import get_config
from pcdiff_jax.data import realism, womd
from pcdiff_jax.model import encoder, features as features_lib, latent, planner
from pcdiff_jax.sim import dynamics, env
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, ObjectType

PLANS = ("log", "log-latent", "top1", "top1-latent", "oracle", "sample", "sample-guided")
DRIFT_SECONDS = (1, 2, 4, 6, 8)
MOVING_SPEED = 2.0   # m/s: drift's speed column covers the agents the log has moving faster


def _scenes(path: str, num: int):
  """The first `num` scenarios of path, stacked into one batch (B,)."""
  states = list(itertools.islice(womd.iterate(path), num))
  if not states:
    raise SystemExit(f"{path}: no scenario could be read")
  return jax.tree_util.tree_map(lambda *a: jnp.stack(a), *states), len(states)


def _log_actions(state, horizon: int, cfg):
  """(O, T, 2) actions that make f track each object's logged future from t, and (O, T) valid."""
  t = state.timestep
  s = jax.lax.dynamic_slice_in_dim(dynamics.states_from_trajectory(state.log_trajectory), t, horizon + 1, 1)
  v = jax.lax.dynamic_slice_in_dim(state.log_trajectory.valid, t, horizon + 1, 1)
  return dynamics.inverse(s, v, cfg.kinematics)


def _plan(kind: str, models, cfg):
  """(state, rng) -> per-object actions (O, T, 2) and planned (O,) for a replay kind."""
  def make(state, rng):
    if kind in ("sample", "sample-guided"):
      from pcdiff_jax.model import guidance
      mode = "objective" if kind == "sample-guided" else "none"
      cold = policy.PolicyConfig(warm_start=False, guidance=guidance.GuidanceConfig(mode=mode))
      actions, planned, _ = policy.plan_actions(models, state, cfg, cold, rng)
      return actions, planned
    feats = features_lib.scene_features(state, cfg.features)
    num_objects = state.object_metadata.ids.shape[-1]
    planned = features_lib.scatter_to_objects(feats.agent_valid, feats, num_objects, fill=False).astype(bool)
    project = lambda a: dynamics.clip_action(latent.decode(latent.encode(a, models.stats), models.stats),
                                             cfg.kinematics)
    if kind in ("log", "log-latent"):
      actions, _ = _log_actions(state, cfg.encoder.horizon, cfg)
      return (project(actions) if kind == "log-latent" else actions), planned
    out = encoder.apply(models.encoder, feats, cfg.encoder)
    speed = planner.agent_speed(feats)
    proposals = latent.actions_from_positions(out.trajectories, speed[:, None], cfg.kinematics)  # (A, K, T, 2)
    if kind == "oracle":
      start = latent.initial_states(jnp.broadcast_to(speed[:, None], proposals.shape[:2]))
      states = dynamics.rollout(start, proposals, cfg.kinematics.dt)
      xy, _ = features_lib.agent_to_world(states[..., :2], states[..., 2], feats)          # (A, K, T, 2)
      t = state.timestep
      future = jax.lax.dynamic_slice_in_dim(state.log_trajectory.xy, t + 1, cfg.encoder.horizon, 1)
      valid = jax.lax.dynamic_slice_in_dim(state.log_trajectory.valid, t + 1, cfg.encoder.horizon, 1)
      future, valid = future[feats.agent_index], valid[feats.agent_index]
      error = jnp.sum(jnp.linalg.norm(xy - future[:, None], axis=-1) * valid[:, None], -1)
      best = jnp.argmin(error, -1)
    else:
      best = jnp.argmax(out.probs, -1)
    chosen = jnp.take_along_axis(proposals, best[:, None, None, None], 1)[:, 0]
    if kind == "top1-latent":
      chosen = project(chosen)
    return features_lib.scatter_to_objects(chosen, feats, num_objects), planned
  return make


def _replay_actor(kind: str, models, cfg) -> Actor:
  """Executes the plan made at `init` open loop (reactive agents; the rest follow the log)."""
  make = _plan(kind, models, cfg)

  def init(rng, state):
    plan, planned = make(state, rng)
    return (policy.reactive_set(state, cfg), plan, planned, jnp.zeros((), jnp.int32))

  def select_action(params, state, actor_state, rng):
    del params, rng
    controlled, plan, planned, age = actor_state
    valid = controlled & planned & state.current_sim_trajectory.valid[..., 0]
    now = jnp.take(plan, jnp.minimum(age, plan.shape[1] - 1), axis=1)
    return ActorOutput(actor_state=(controlled, plan, planned, age + 1),
                       action=Action(data=jnp.where(valid[:, None], now, 0.0), valid=valid[:, None]),
                       is_controlled=controlled)
  return Actor(select_action=select_action, init=init, name=f"replay-{kind}")


def replay(args, models, cfg, batch, num) -> dict:
  ecfg = evaluation.EvalConfig(method="log")
  score = evaluation.make_score_fn(ecfg)
  rngs = jax.random.split(jax.random.PRNGKey(args.seed), num)
  rows = {}
  for kind in args.plans.split(","):
    if kind not in PLANS:
      raise SystemExit(f"--plans: unknown plan {kind!r}; choose from {list(PLANS)}")
    final = evaluation.make_rollout_fn(_replay_actor(kind, models, cfg), ecfg)(batch, rngs, None)
    agg = metrics_lib.aggregate(jax.tree_util.tree_map(lambda a: np.asarray(a)[:, None], score(final)))
    rows[kind] = {k: float(agg[k]) for k in ("collision_rate", "offroad_rate", "realism", "min_ade")}
    print(f"| {kind} | " + " | ".join(f"{v:.3f}" for v in rows[kind].values()) + " |", flush=True)
  return rows


def _drift_policy(args) -> policy.PolicyConfig:
  """drift's PolicyConfig: its flags, then --policy (ValueError / TypeError names a bad field)."""
  pcfg = policy.PolicyConfig(replan_every=args.replan_every, ddim_steps=args.ddim_steps,
                             consistent_noise=args.consistent_noise, execute=args.execute,
                             warm_start=args.warm_start)
  pcfg = policy.with_overrides(pcfg, args.policy)
  policy.validate(get_config("cpu"), pcfg)   # the presets share these ranges
  return pcfg


def _mean_or_nan(values: np.ndarray, mask: np.ndarray) -> float:
  """Mean of values[mask]; NaN when the mask selects nothing."""
  return float(values[mask].mean()) if mask.any() else float("nan")


def _solo_actor(inner: Actor) -> Actor:
  """`inner`, controlling only the objects marked in objects_of_interest (the rest follow their log)."""
  def select_action(params, state, actor_state, rng):
    out = inner.select_action(params, state, actor_state, rng)
    return out.replace(is_controlled=out.is_controlled & state.object_metadata.objects_of_interest)
  return Actor(select_action=select_action, init=inner.init, name=f"{inner.name}-solo")


def _solo_copies(batch, start: int):
  """One copy of its scene per evaluated non-SDC agent moving at `start` (> MOVING_SPEED), that
  agent alone marked in objects_of_interest: the copies (N,) and each one's (scene, object)."""
  md, log = batch.object_metadata, batch.log_trajectory
  pick = (np.asarray(md.is_modeled) & ~np.asarray(md.is_sdc) & np.asarray(log.valid[..., start])
          & (np.asarray(log.speed[..., start]) > MOVING_SPEED))
  who = [(int(b), int(o)) for b, o in zip(*np.nonzero(pick))]
  if not who:
    return None, who
  scene = np.array([b for b, _ in who])
  only = np.zeros((len(who), pick.shape[1]), bool)
  only[np.arange(len(who)), [o for _, o in who]] = True
  copies = jax.tree_util.tree_map(lambda a: a[scene], batch)
  return copies.replace(object_metadata=copies.object_metadata.replace(objects_of_interest=jnp.asarray(only))), who


def _solo_rows(args, actor, params, ecfg, batch, final, dt: float) -> dict:
  """Per DRIFT_SECONDS: speed minus the log's of the agents moving at the start and at t, solo and joint."""
  start = ecfg.init_steps - 1
  copies, who = _solo_copies(batch, start)
  rows = {f"{sec}s": dict(speed_diff_solo=float("nan"), speed_diff_joint_same=float("nan"), solo_agents=0)
          for sec in DRIFT_SECONDS}
  if not who:
    return rows
  rngs = jax.random.split(jax.random.PRNGKey(args.seed), len(who))
  solo = jax.device_get(evaluation.make_rollout_fn(_solo_actor(actor), ecfg)(copies, rngs, params))
  k, (b, o) = np.arange(len(who)), tuple(np.array(who).T)
  for sec in DRIFT_SECONDS:
    t = start + int(round(sec / dt))
    log_speed = np.asarray(final.log_trajectory.speed)[b, o, t]
    ok = (np.asarray(final.log_trajectory.valid)[b, o, t] & np.asarray(solo.sim_trajectory.valid)[k, o, t]
          & np.asarray(final.sim_trajectory.valid)[b, o, t] & (log_speed > MOVING_SPEED))
    solo_speed = np.asarray(solo.sim_trajectory.speed)[k, o, t]
    joint_speed = np.asarray(final.sim_trajectory.speed)[b, o, t]
    rows[f"{sec}s"] = dict(
        speed_diff_solo=_mean_or_nan(solo_speed - log_speed, ok),
        speed_diff_joint_same=_mean_or_nan(joint_speed - log_speed, ok), solo_agents=int(ok.sum()),
        # [scene, object, the log's speed, solo, joint] of each agent counted (m/s)
        solo_per_agent=[[int(b[i]), int(o[i]), round(float(log_speed[i]), 2), round(float(solo_speed[i]), 2),
                         round(float(joint_speed[i]), 2)] for i in np.nonzero(ok)[0]])
  return rows


def drift(args, models, cfg, batch, num) -> dict:
  del models
  pcfg = _drift_policy(args)
  ecfg = evaluation.EvalConfig(method=args.method, checkpoint=args.checkpoint, policy=pcfg)
  actor, params = evaluation.make_actor(ecfg)
  rngs = jax.random.split(jax.random.PRNGKey(args.seed), num)
  final = jax.device_get(evaluation.make_rollout_fn(actor, ecfg)(batch, rngs, params))
  solo = _solo_rows(args, actor, params, ecfg, batch, final, cfg.kinematics.dt) if args.solo else {}
  sim, log = final.sim_trajectory, final.log_trajectory
  ok = np.asarray(sim.valid & log.valid) & np.asarray(final.object_metadata.is_controlled)[..., None]
  yaw = np.asarray(log.yaw)
  dx, dy = np.asarray(sim.x - log.x), np.asarray(sim.y - log.y)
  lateral = -np.sin(yaw) * dx + np.cos(yaw) * dy
  longitudinal = np.cos(yaw) * dx + np.sin(yaw) * dy
  log_speed = np.asarray(log.speed)
  speed_diff = np.asarray(sim.speed) - log_speed
  heading = (np.asarray(sim.yaw - log.yaw) + np.pi) % (2 * np.pi) - np.pi
  start = ecfg.init_steps - 1
  rows = {}
  for sec in DRIFT_SECONDS:
    t = start + int(round(sec / cfg.kinematics.dt))
    m = ok[..., t]
    moving = m & (log_speed[..., t] > MOVING_SPEED)
    cruising = moving & (log_speed[..., start] > MOVING_SPEED)
    rows[f"{sec}s"] = dict(lateral_mean=float(lateral[..., t][m].mean()),
                           lateral_abs=float(np.abs(lateral[..., t][m]).mean()),
                           longitudinal_mean=float(longitudinal[..., t][m].mean()),
                           heading_mean=float(heading[..., t][m].mean()),
                           heading_abs=float(np.abs(heading[..., t][m]).mean()), agents=int(m.sum()),
                           speed_diff_mean=_mean_or_nan(speed_diff[..., t], moving),
                           moving_agents=int(moving.sum()),
                           speed_diff_cruising=_mean_or_nan(speed_diff[..., t], cruising),
                           cruising_agents=int(cruising.sum()), **solo.get(f"{sec}s", {}))
    r = rows[f"{sec}s"]
    line = (f"| {sec} s | {r['lateral_mean']:+.2f} | {r['lateral_abs']:.2f} | {r['longitudinal_mean']:+.2f} | "
            f"{r['heading_mean']:+.3f} | {r['heading_abs']:.3f} | {r['agents']} | {r['speed_diff_mean']:+.2f} | "
            f"{r['moving_agents']} | {r['speed_diff_cruising']:+.2f} | {r['cruising_agents']} |")
    if solo:
      line += f" {r['speed_diff_solo']:+.2f} | {r['speed_diff_joint_same']:+.2f} | {r['solo_agents']} |"
    print(line, flush=True)
  return rows


SPEED_BINS = (2.0, 6.0, 10.0, 14.0, 18.0, np.inf)   # m/s: first-action's starting-speed bins


def first_action(args, models, cfg, batch, num) -> dict:
  """First planned action statistics over the batch's moving vehicles; and, by starting speed,
  each plan's mean speed change over its first second (`sample_standard_init`: the same
  denoiser started from N(0, I), which tells the prior centre's share of a braking plan;
  `warm_from_log_W`: one warm replan from the log's own future noised to step W, which tells
  whether a re-draw keeps the speed of the plan it replaces)."""
  def one(state, rng):
    state = env.reset(state)
    feats = features_lib.scene_features(state, cfg.features)
    cond = planner.condition(models.encoder, models.stats, jax.tree_util.tree_map(lambda a: a[None], feats), cfg)
    y0 = planner.sample(models.denoiser, cond, cfg, rng, args.ddim_steps, 0.0, prior_init=args.prior)
    y0_standard = planner.sample(models.denoiser, cond, cfg, rng, args.ddim_steps, 0.0, prior_init=False)
    decode = lambda y: dynamics.clip_action(latent.decode(y, models.stats), cfg.kinematics)
    log, log_valid = _log_actions(state, cfg.encoder.horizon, cfg)
    log, log_valid = log[feats.agent_index], log_valid[feats.agent_index]
    out = encoder.apply(models.encoder, feats, cfg.encoder)
    speed = planner.agent_speed(feats)
    proposals = latent.actions_from_positions(out.trajectories, speed[:, None], cfg.kinematics)
    top1 = jnp.take_along_axis(proposals, jnp.argmax(out.probs, -1)[:, None, None, None], 1)[:, 0]
    log_latent = latent.encode(log, models.stats)
    plans = dict(log=log, log_latent=decode(log_latent), top1=top1,
                 prior_centre=decode(cond.mu[0]), sample=decode(y0[0]),
                 sample_standard_init=decode(y0_standard[0]))
    centre = jnp.where(jnp.all(log_valid, -1)[:, None], log_latent, cond.mu[0])[None]
    for step in args.warm_steps:   # a warm replan whose previous plan was the log's own future
      y = planner.sample(models.denoiser, cond, cfg, rng, 1, 0.0, centre=centre, start_step=step)
      plans[f"warm_from_log_{step}"] = decode(y[0])
    moving = (feats.agent_valid & (speed > 2.0) & jnp.all(log_valid, -1)
              & (feats.agent_types == ObjectType.VEHICLE))
    second = int(round(1.0 / cfg.kinematics.dt))
    speed_change = {k: jnp.sum(v[:, :second, 0], -1) * cfg.kinematics.dt for k, v in plans.items()}
    return {k: v[:, 0] for k, v in plans.items()}, speed_change, moving, speed

  firsts, changes, moving, speed = jax.jit(jax.vmap(one))(
      batch, jax.random.split(jax.random.PRNGKey(args.seed), num))
  moving = np.asarray(moving)
  rows = {}
  for name, a in firsts.items():
    a = np.asarray(a)[moving]
    rows[name] = dict(yaw_rate_mean=float(a[:, 1].mean()), yaw_rate_abs=float(np.abs(a[:, 1]).mean()),
                      accel_mean=float(a[:, 0].mean()), agents=int(len(a)))
    r = rows[name]
    print(f"| {name} | {r['yaw_rate_mean']:+.4f} | {r['yaw_rate_abs']:.4f} | {r['accel_mean']:+.3f} | "
          f"{r['agents']} |", flush=True)
  speed = np.asarray(speed)[moving]
  bins = list(zip(SPEED_BINS[:-1], SPEED_BINS[1:]))
  names = [f"{lo:.0f}-{hi:.0f}" if np.isfinite(hi) else f">= {lo:.0f}" for lo, hi in bins]
  print("\n| speed change over 1 s (m/s), by starting speed (m/s) | " + " | ".join(names) + " |")
  print("|" + "---|" * (len(names) + 1))
  for name, c in changes.items():
    c = np.asarray(c)[moving]
    by_speed = {n: _mean_or_nan(c, (speed >= lo) & (speed < hi)) for n, (lo, hi) in zip(names, bins)}
    rows[name]["speed_change_1s"] = by_speed
    print(f"| {name} | " + " | ".join(f"{v:+.2f}" for v in by_speed.values()) + " |", flush=True)
  rows["agents_by_speed"] = {n: int(((speed >= lo) & (speed < hi)).sum()) for n, (lo, hi) in zip(names, bins)}
  print("| agents | " + " | ".join(str(v) for v in rows["agents_by_speed"].values()) + " |")
  return rows


PARKED_PATH = 0.5   # m over the horizon: the log's parked vehicles


def parked(args, models, cfg, batch, num) -> dict:
  """End displacement (m) of open-loop plans for the log's parked vehicles."""
  horizon = cfg.encoder.horizon

  def one(state, rng):
    state = env.reset(state)
    feats = features_lib.scene_features(state, cfg.features)
    cond = planner.condition(models.encoder, models.stats, jax.tree_util.tree_map(lambda a: a[None], feats), cfg)
    tiled = planner.repeat_samples(cond, args.samples)                         # (S, A, ...)
    top = planner.centre_on_top_mode(tiled).mu                                 # (S, A, d)
    end = lambda y: jnp.linalg.norm(planner.decode_states(models.stats, tiled, y, cfg)[..., -1, :2], axis=-1)
    keys = jax.random.split(rng, 1 + len(args.warm_steps))
    ends = {"top1 proposal": end(top), "cold": end(planner.sample(models.denoiser, tiled, cfg, keys[0]))}
    for key, step in zip(keys[1:], args.warm_steps):
      y = planner.sample(models.denoiser, tiled, cfg, key, 1, 0.0, centre=top, start_step=step)
      ends[f"warm from top1 @{step}"] = end(y)
    log = jax.lax.dynamic_slice_in_dim(state.log_trajectory.xy, state.timestep, horizon + 1, 1)
    valid = jax.lax.dynamic_slice_in_dim(state.log_trajectory.valid, state.timestep, horizon + 1, 1)
    pairs = valid[:, 1:] & valid[:, :-1]
    path = jnp.sum(jnp.where(pairs, jnp.linalg.norm(jnp.diff(log, axis=1), axis=-1), 0.0), -1)
    seen = jnp.mean(valid, -1) >= 0.5
    still = (feats.agent_valid & (seen & (path < PARKED_PATH))[feats.agent_index]
             & (feats.agent_types == ObjectType.VEHICLE))
    return ends, still, jnp.max(cond.probs[0], -1)

  ends, still, top_p = jax.jit(jax.vmap(one))(batch, jax.random.split(jax.random.PRNGKey(args.seed), num))
  still = np.asarray(still)                                                    # (B, A)
  if not still.any():
    print("no vehicle parked in the log among the modelled agents")
    return {name: dict(agents=0) for name in ends}
  rows = {}
  for name, e in ends.items():
    e = np.moveaxis(np.asarray(e), 1, -1)[still]                               # (agents, S)
    rows[name] = dict(median_m=float(np.median(e)), over_1m=float(np.mean(e > 1.0)),
                      over_5m=float(np.mean(e > 5.0)), agents=int(still.sum()))
    r = rows[name]
    print(f"| {name} | {r['median_m']:.1f} | {r['over_1m']:.2f} | {r['over_5m']:.2f} | {r['agents']} |", flush=True)
  print(f"(their encoder's top probability: mean {float(np.asarray(top_p)[still].mean()):.3f})")
  return rows


def _diffusion_steps(text: str) -> tuple[int, ...]:
  """'30,90' -> (30, 90), each a diffusion step in [0, 99]."""
  try:
    steps = tuple(int(w) for w in text.split(","))
  except ValueError:
    raise argparse.ArgumentTypeError(f"{text!r}: comma-separated integers") from None
  if not all(0 <= w <= 99 for w in steps):
    raise argparse.ArgumentTypeError(f"{text!r}: steps in [0, 99]")
  return steps


def starters(args, models, cfg, batch, num) -> list[dict]:
  """Per slow starter of the log: its proposals' 8 s travel (m) and probabilities, the
  log's travel and the still gate's decision, at the rollout start."""
  pcfg = policy.PolicyConfig()
  horizon = cfg.encoder.horizon

  def one(state):
    start = env.simulated_start(state, evaluation.EvalConfig().init_steps)
    scene = policy.encode(models, start, cfg, pcfg, policy.reactive_set(start, cfg))
    cond, feats = scene.cond, scene.feats
    actions = dynamics.clip_action(latent.decode(cond.proposals, models.stats), cfg.kinematics)
    speed = jnp.broadcast_to(cond.speed[..., None], cond.proposals.shape[:-1])
    ends = dynamics.rollout(latent.initial_states(speed), actions, cfg.kinematics.dt)[..., -1, :2]
    log = jax.lax.dynamic_slice_in_dim(start.log_trajectory.xy, start.timestep, horizon + 1, 1)
    valid = jax.lax.dynamic_slice_in_dim(start.log_trajectory.valid, start.timestep, horizon + 1, 1)
    last = jnp.max(jnp.where(valid, jnp.arange(horizon + 1), 0), -1)                    # (O,)
    log_travel = jnp.linalg.norm(jnp.take_along_axis(log, last[:, None, None], 1)[:, 0] - log[:, 0], axis=-1)
    md = start.object_metadata
    evaluated = (md.is_modeled | md.is_sdc)[feats.agent_index] & feats.agent_valid
    hold = scene.hold if scene.hold is not None else jnp.zeros_like(evaluated)
    return (jnp.linalg.norm(ends, axis=-1)[0], cond.probs[0], cond.speed[0], hold,
            log_travel[feats.agent_index], evaluated, feats.agent_index)

  travel, probs, speed, hold, log_travel, evaluated, index = (
      np.asarray(a) for a in jax.jit(jax.vmap(one))(batch))
  rows = []
  for b, a in zip(*np.nonzero(evaluated & (np.abs(speed) < realism.STARTER_SPEED)
                          & (log_travel > realism.STARTER_TRAVEL))):
    order = np.argsort(-probs[b, a])
    expected = float(np.sum(probs[b, a] * travel[b, a]))
    rows.append(dict(scene=int(b), object=int(index[b, a]), speed=float(speed[b, a]),
                     log_travel=float(log_travel[b, a]), expected_travel=expected, held=bool(hold[b, a]),
                     proposals=[[float(travel[b, a, k]), float(probs[b, a, k])] for k in order]))
    print(f"| {b} | {index[b, a]} | {speed[b, a]:.2f} | {log_travel[b, a]:.1f} | {expected:.1f} | "
          f"{'yes' if hold[b, a] else 'no'} | "
          + " ".join(f"{travel[b, a, k]:.1f} @ {probs[b, a, k]:.2f}" for k in order) + " |")
  if rows:
    ratio = np.median([r["expected_travel"] / r["log_travel"] for r in rows])
    print(f"\n{len(rows)} slow starters; median expected proposal travel / log travel {ratio:.2f}; "
          f"held by the still gate {sum(r['held'] for r in rows)}")
  else:
    print("no evaluated agent starts slowly and pulls away in the log")
  return rows


def main(argv=None) -> None:
  p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--checkpoint", required=True, help="diffusion training workdir (e.g. runs/cpu)")
  p.add_argument("--scenarios", required=True, help="TFRecord of scenarios")
  p.add_argument("--num-scenes", type=int, default=6)
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--out", default=None, type=_args.output_file, help="write the rows as JSON here")
  sub = p.add_subparsers(dest="section", required=True)
  r = sub.add_parser("replay", help="open-loop execution of one plan per agent")
  r.add_argument("--plans", default=",".join(PLANS))
  d = sub.add_parser("drift", help="offset from the log in closed loop")
  d.add_argument("--method", default="pcdiff", choices=["pcdiff", "pcdiff-noprior", "simpl-ar", "idm", "cv"])
  d.add_argument("--replan-every", type=int, default=policy.PolicyConfig().replan_every)
  d.add_argument("--ddim-steps", type=int, default=5)
  d.add_argument("--consistent-noise", action="store_true")
  d.add_argument("--execute", default="actions", choices=["actions", "track"])
  d.add_argument("--warm-start", action=argparse.BooleanOptionalAction, default=True,
                 help="pcdiff: warm-started replanning (default) or cold plans")
  d.add_argument("--policy", nargs="+", default=[], metavar="FIELD=VALUE", type=_args.policy_item,
                 help="pcdiff: policy fields over the flags above, as experiments.rollout takes them")
  d.add_argument("--solo", action="store_true",
                 help="also simulate each moving evaluated agent alone (the others on their log)")
  f = sub.add_parser("first-action", help="first planned action against the log's")
  f.add_argument("--ddim-steps", type=int, default=5)
  f.add_argument("--no-prior", dest="prior", action="store_false")
  f.add_argument("--warm-steps", default=(60, 90), type=_diffusion_steps,
                 help="comma-separated diffusion steps (0-99) of warm replans from the log's plan")
  sub.add_parser("starters", help="the proposals of evaluated agents that start slowly and pull away in the log")
  k = sub.add_parser("parked", help="open-loop plans of the log's parked vehicles")
  k.add_argument("--samples", type=int, default=16)
  k.add_argument("--warm-steps", default=(30, 90), type=_diffusion_steps,
                 help="comma-separated diffusion steps (0-99) of the warm starts")
  args = p.parse_args(argv)
  if args.num_scenes < 1:
    p.error("--num-scenes must be >= 1")
  if args.section == "parked" and args.samples < 1:
    p.error("--samples must be >= 1")
  if args.section == "drift":
    try:
      _drift_policy(args)
    except (ValueError, TypeError) as err:
      p.error(f"--policy: {err}")
  if not os.path.exists(args.scenarios):
    p.error(f"--scenarios {args.scenarios}: no such file")

  from pcdiff_jax.training import diffusion_stage
  prior = getattr(args, "prior", getattr(args, "method", "pcdiff") != "pcdiff-noprior")
  try:
    models, cfg = diffusion_stage.load(args.checkpoint, use_prior=prior)
    batch, num = _scenes(args.scenarios, args.num_scenes)
  except (FileNotFoundError, ValueError) as err:
    p.error(str(err))
  headers = {"replay": "| plan | collision | off-road | realism W1 | minADE |",
             "drift": ("| time | lateral mean (m, left +) | lateral abs | longitudinal mean (m, ahead +) | "
                       "heading mean (rad) | heading abs | agents | speed - log's (m/s) | moving agents | "
                       "cruising: speed - log's | cruising agents |"
                       + (" solo: speed - log's | joint, same agents | solo agents |"
                          if getattr(args, "solo", False) else "")),
             "first-action": "| plan | yaw rate mean (rad/s) | yaw rate abs | accel mean (m/s^2) | agents |",
             "parked": "| plans of parked vehicles | median end (m) | share > 1 m | share > 5 m | agents |",
             "starters": ("| scene | object | speed (m/s) | log travel (m) | expected proposal travel (m) | "
                          "held | proposals: travel (m) @ probability |")}
  print(headers[args.section])
  print("|" + "---|" * (headers[args.section].count("|") - 1))
  if args.section == "replay":
    rows = replay(args, models, cfg, batch, num)
  elif args.section == "drift":
    rows = drift(args, models, cfg, batch, num)
  elif args.section == "parked":
    rows = parked(args, models, cfg, batch, num)
  elif args.section == "starters":
    rows = starters(args, models, cfg, batch, num)
  else:
    rows = first_action(args, models, cfg, batch, num)
  if args.out:
    with open(args.out, "w") as f:
      json.dump({"section": args.section, "num_scenes": num, "rows": rows}, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
  main()
