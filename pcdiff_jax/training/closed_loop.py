"""On-policy recovery fine-tuning (CAT-K's idea, ../shared/REFERENCES.md, in our diffusion policy).

A policy trained on logged states meets its own states in closed loop: small
errors put agents beside their lane, and a model that never saw such a state
does not bring them back (covariate shift). CAT-K fine-tunes on the states
its own closed-loop rollouts visit, with the logged future as the target.
Our fused, jitted closed loop makes the rollouts cheap, so a round is:

1. `collect`: roll the current policy out (`evaluation.make_rollout_fn`, the
   SDC on its log, every other agent planned at 10 Hz) on training scenes and
   cut examples at the visited steps `times`: the scene features read the
   simulated history (the policy's own), and each agent's target
   (`on_policy_targets`) starts at its simulated pose and speed and re-joins
   its logged future;
2. `finetune_encoder` (optional): train the encoder's proposals on the same
   mixed batches, so the proposal prior and SIMPL-AR also learn to bring a
   drifted agent back;
3. `finetune`: train the denoiser (encoder and latent frozen) on batches that
   mix those on-policy examples with the logged ones (with the random
   recovery perturbations of `training.perturb`).

Rounds repeat it with the fine-tuned policy (DAgger).

The re-joining target, in the world frame, for the log state x(t + k dt):

  o(tau) = d0 h00(tau) + R dv h10(tau),   tau = k dt / R
  p = x_log + o,   velocity = v_log + do/dt,

where d0 and dv are the differences of position and velocity vector between
the simulated and the logged agent at t, and h00, h10 the cubic Hermite
bases (`perturb._hermite`), so the path leaves the simulated pose with the
simulated velocity and meets the log, position and velocity, at R; R grows
with the offset (`OnPolicyConfig.rejoin_seconds` + |d0| / `rejoin_speed`).
Heading and speed are those of the path's velocity (the log's below
1 m/s). Agents farther than `max_offset` or turned more than `max_heading`
from their log are not trained on (their target would be a stunt), nor is an
agent whose log is invalid at t. Past the end of the log (t + k > 90 in
WOMD) the future is the last logged state moved on at constant speed and
heading: the model needs full 8 s futures, and at 10 Hz only the start of a
plan is executed.
"""
from __future__ import annotations

import dataclasses
import logging
import os
from typing import Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pcdiff_jax.baselines import idm
from pcdiff_jax.config import Config, FeaturesConfig, TrainConfig
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model import guidance as guidance_lib
from pcdiff_jax.model import latent, planner
from pcdiff_jax.model.planner import Models
from pcdiff_jax.sim import dynamics, env, geometry
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState
from pcdiff_jax.training import data as data_lib
from pcdiff_jax.training import perturb, trainer
from pcdiff_jax.training.data import Example, Targets

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class OnPolicyConfig:
  """times: the visited steps cut into examples (the rollout starts at 10 and
  runs to max(times)); rejoin_seconds + offset / rejoin_speed: the time to
  re-join the log; max_offset (m), max_heading (rad): farther agents are not
  trained on; mix: the fraction of each fine-tuning batch drawn from the
  on-policy examples; lane_tail: a log is continued past its end along the
  lane centres (`lane_continuation`), else straight at constant speed (the
  targets of rounds 0-6 of pcdiff-cpu-v5); targets: "rejoin" (the
  simulated pose re-joins the log, `on_policy_targets`), "guided" (the
  policy's own plan at that state under objective guidance, `guided_targets`:
  guidance distilled into the unguided model) or "hybrid" (the re-joining
  target where it stays on the road and clear of the others, the guided one
  elsewhere: `clean_rejoin_or`, with rejoin_margin and rejoin_whole_logs);
  drop_log_overlaps: an agent whose
  log overlaps another box in the horizon is not trained on (`data.log_overlaps_ahead`);
  drop_log_offroad: nor a vehicle whose log leaves the mapped road (`data.log_leaves_road_ahead`)."""
  times: tuple[int, ...] = (20, 30, 40, 50)
  rejoin_seconds: float = 3.0
  rejoin_speed: float = 2.0
  max_offset: float = 8.0
  max_heading: float = 0.8
  mix: float = 0.5
  lane_tail: bool = True
  targets: str = "rejoin"
  drop_log_overlaps: bool = False
  drop_log_offroad: bool = False
  rejoin_margin: float = 0.3
  rejoin_whole_logs: bool = True


TARGETS = ("rejoin", "guided", "hybrid")


def lane_continuation(state: SimulatorState, num_steps: int, dt: float,
                      max_lane_points: int = 4096, max_yaw_rate: float = 0.8) -> Array:
  """(O, num_steps, 4) [x, y, yaw, v]: each object's last logged state moved
  on at its last speed for num_steps steps, steered along the lane centres
  by pure pursuit (`baselines.idm.pursuit_yaw_rate`, a probe max(6 m, 0.6 s)
  ahead, lane samples at least 1 m ahead) and straight where no lane is in
  reach, or the object was stopped or reversing. This is where a vehicle
  whose synthetic log ends early would have driven: a straight tail left the
  road on every curve and taught the policy to leave it too (docs/RESULTS.md
  "Models v6")."""
  traj = state.log_trajectory
  states = dynamics.states_from_trajectory(traj)                               # (O, T, 4)
  last = jnp.max(jnp.where(traj.valid, jnp.arange(traj.num_timesteps), -1), axis=-1)
  end = jnp.take_along_axis(states, jnp.maximum(last, 0)[:, None, None], axis=1)[:, 0]   # (O, 4)
  lanes = idm.lane_samples(state, max_lane_points)

  def advance(s, _):
    speed = s[:, 3]
    rate, found = idm.pursuit_yaw_rate(s[:, :2], s[:, 2], speed, lanes,
                                       jnp.maximum(6.0, 0.6 * speed), min_ahead=1.0)
    rate = jnp.where(found & (speed > 0.5), jnp.clip(rate, -max_yaw_rate, max_yaw_rate), 0.0)
    nxt = dynamics.step(s, jnp.stack([jnp.zeros_like(speed), rate], -1), dt)
    return nxt, nxt
  _, path = jax.lax.scan(advance, end, None, length=num_steps)
  return jnp.moveaxis(path, 0, 1)


def _extended_log(state: SimulatorState, steps: Array, dt: float,
                  continuation: Optional[Array] = None) -> tuple[Array, Array]:
  """Log states (O, K, 4) [x, y, yaw, speed] and validity (O, K) at `steps`
  (K,), continued past each object's last valid step: past the end of the
  record, and past an earlier end (a synthetic vehicle's log ends where its
  route leaves the scene; without this, such an agent had no target once its
  log ended, and the policy planned for it unsupervised: half the off-road
  events, docs/RESULTS.md "Models v5"). The continuation: `continuation`
  (O, E, 4), the states 1..E steps after each object's last valid one
  (`lane_continuation`), or constant speed and heading when None."""
  traj = state.log_trajectory
  num_steps = traj.num_timesteps
  states = dynamics.states_from_trajectory(traj)                          # (O, T, 4)
  last = jnp.max(jnp.where(traj.valid, jnp.arange(num_steps), -1), axis=-1)   # (O,), -1: never valid
  end = jnp.take_along_axis(states, jnp.maximum(last, 0)[:, None, None], axis=1)[:, 0]   # (O, 4)
  past = steps[None, :] > last[:, None]                                      # (O, K)
  beyond = jnp.maximum(steps[None, :] - last[:, None], 0)                    # (O, K) steps
  if continuation is None:
    moved = end[:, None, :].repeat(steps.shape[0], axis=1)
    moved = moved.at[..., :2].add(end[:, None, 3:4] * (beyond * dt)[..., None]
                                  * geometry.unit(end[:, 2])[:, None, :])
  else:
    index = jnp.clip(beyond - 1, 0, continuation.shape[1] - 1)
    moved = jnp.take_along_axis(continuation, index[..., None], axis=1)
  at = jnp.where(past[..., None], moved, states[:, jnp.clip(steps, 0, num_steps - 1)])
  valid = jnp.where(past, (last >= 0)[:, None], traj.valid[:, jnp.clip(steps, 0, num_steps - 1)])
  return at, valid


def on_policy_targets(state: SimulatorState, feats, horizon: int, cfg: OnPolicyConfig,
                      dt: float, continuation: Optional[Array] = None) -> Targets:
  """Targets (A, ...) of one rolled-out scene at t = state.timestep for the
  agents of `feats`: from each agent's simulated pose back onto its log
  (continued past its end by `continuation`, see `_extended_log`)."""
  t = state.timestep
  idx = feats.agent_index
  sim_now = dynamics.states_from_trajectory(state.sim_trajectory)[idx, t]   # (A, 4)
  log_now, log_valid_now = _extended_log(state, t[None], dt, continuation)
  log_now, log_valid_now = log_now[idx, 0], log_valid_now[idx, 0]            # (A, 4), (A,)
  fut, valid = _extended_log(state, t + 1 + jnp.arange(horizon), dt, continuation)
  fut, valid = fut[idx], valid[idx]                                          # (A, T, 4), (A, T)

  velocity = lambda s: s[..., 3:4] * geometry.unit(s[..., 2])
  d0 = sim_now[:, :2] - log_now[:, :2]                                       # (A, 2)
  dv = velocity(sim_now) - velocity(log_now)
  offset = jnp.linalg.norm(d0, axis=-1)
  rejoin = cfg.rejoin_seconds + offset / cfg.rejoin_speed                    # (A,)
  tau = dt * (1 + jnp.arange(horizon))[None] / rejoin[:, None]              # (A, T)
  h00, h10, d00, d10 = perturb._hermite(tau)
  o = d0[:, None] * h00[..., None] + (rejoin[:, None, None] * dv[:, None]) * h10[..., None]
  rate = (d0[:, None] * d00[..., None] + (rejoin[:, None, None] * dv[:, None]) * d10[..., None]) \
      / rejoin[:, None, None]                                                # (A, T, 2) do/dt
  xy = fut[..., :2] + o
  vel = velocity(fut) + rate
  speed = jnp.linalg.norm(vel, axis=-1)
  moving = speed > 1.0
  yaw = jnp.where(moving, jnp.arctan2(vel[..., 1], vel[..., 0]), fut[..., 2])
  # Signed speed along the heading (a reversing log stays negative).
  speed = jnp.where(moving, jnp.sum(vel * geometry.unit(yaw), -1), fut[..., 3])

  turned = jnp.abs(geometry.wrap_angle(sim_now[:, 2] - log_now[:, 2]))
  usable = feats.agent_valid & log_valid_now & (offset <= cfg.max_offset) & (turned <= cfg.max_heading)
  usable = usable & ~data_lib.dropped_labels(state, idx, horizon, cfg.drop_log_overlaps, cfg.drop_log_offroad)
  valid = valid & usable[:, None]
  origin, yaw0 = sim_now[:, None, :2], sim_now[:, None, 2]
  local_xy = geometry.to_local(xy, origin, yaw0)
  local_yaw = geometry.wrap_angle(yaw - yaw0)
  zero = lambda a: jnp.where(valid if a.ndim == 2 else valid[..., None], a, 0.0)
  return Targets(future_xy=zero(local_xy), future_yaw=zero(local_yaw), future_speed=zero(speed),
                 future_valid=valid, current_speed=jnp.where(feats.agent_valid, sim_now[:, 3], 0.0))


def guided_targets(models: Models, state: SimulatorState, feats, model_cfg: Config, teacher,
                   rng: Array, road) -> Targets:
  """Targets (A, ...) of one rolled-out scene at t = state.timestep: the joint
  plan that `teacher` (a `policy.PolicyConfig` with objective guidance: the
  map and collision costs of `model.guidance`) samples there, cold, for the
  agents of `feats`, rolled out in each agent's frame.

  DAgger with a guided teacher: on the states the unguided policy visits, the
  label is what the same model does when guidance keeps its plan on the road
  and clear of the others, so the fine-tuned model learns to make that plan
  without guidance (its test-time cost unchanged). `road`: the scene's road
  field (`guidance.road_of`), built once per scene."""
  from pcdiff_jax import policy as policy_lib
  actions, planned, _ = policy_lib.plan_actions(models, state, model_cfg, teacher, rng, road=road)
  idx = feats.agent_index
  valid = planned[idx] & feats.agent_valid                                   # (A,)
  speed = jnp.where(valid, planner.agent_speed(feats), 0.0)                  # (A,)
  states = dynamics.rollout(latent.initial_states(speed), actions[idx], model_cfg.kinematics.dt)
  mask = jnp.broadcast_to(valid[:, None], states.shape[:2])
  zero = lambda a: jnp.where(mask if a.ndim == 2 else mask[..., None], a, 0.0)
  return Targets(future_xy=zero(states[..., :2]), future_yaw=zero(states[..., 2]),
                 future_speed=zero(states[..., 3]), future_valid=mask, current_speed=speed)


def clean_rejoin_or(state: SimulatorState, rejoin: Targets, guided: Targets, feats, road,
                    g: guidance_lib.GuidanceConfig, margin: float = 0.3, whole_logs: bool = True) -> Targets:
  """Targets (A, ...): each agent's re-joining target where it is usable, keeps
  every box corner of a vehicle `margin` m inside the road edge (or, for one
  nearer the edge now, no further out than now), and takes no agent's box
  into another's over the guidance's collision horizon (circles, no margin;
  the others on their chosen targets); with whole_logs, only for agents whose
  log lasts to the record's last step (a path past an early end is a guess).
  The guided target elsewhere: the log where the way back to it is safe
  (the recorded drivers' kinematics), the guided plan where it leaves the
  road or hits someone. `road`: the scene's field in the world frame
  (`guidance.road_of`)."""
  g = dataclasses.replace(g, map_margin=0.0, coll_margin=0.0)
  road = road.in_frame(feats.scene_xy, feats.scene_yaw)
  length, width = planner.agent_size(feats)
  vehicle = feats.agent_types == ObjectType.VEHICLE

  def scene_pose(t: Targets):
    states = jnp.concatenate([t.future_xy, t.future_yaw[..., None], t.future_speed[..., None]], -1)
    return planner.to_scene(states, feats)

  usable = feats.agent_valid & rejoin.future_valid.any(-1)
  if whole_logs:
    usable = usable & state.log_trajectory.valid[feats.agent_index, -1]
  agents = guidance_lib.Agents(length=length, width=width, valid=usable, vehicle=vehicle,
                               pursuer=jnp.int32(-1), evader=jnp.int32(-1))
  xy, yaw = scene_pose(rejoin)
  now_xy, now_yaw = features_lib.agent_to_scene(jnp.zeros_like(xy[:, :1]), jnp.zeros_like(yaw[:, :1]), feats)
  off_now = guidance_lib.map_excursion(now_xy, now_yaw, agents, road, g)
  off_path = guidance_lib.map_excursion(xy, yaw, agents, road, g)
  on_road = off_path <= jnp.maximum(off_now, -margin)                       # -inf for non-vehicles
  pick = lambda keep: jax.tree_util.tree_map(
      lambda r, q: jnp.where(keep.reshape(keep.shape + (1,) * (r.ndim - 1)), r, q), rejoin, guided)
  first = pick(usable & on_road)
  xy, yaw = scene_pose(first)
  clear = guidance_lib.collision_cost(xy, yaw, agents.replace(valid=feats.agent_valid), g) <= 0.0
  return pick(usable & on_road & clear)


def on_policy_examples(final: SimulatorState, features: FeaturesConfig, horizon: int,
                       cfg: OnPolicyConfig, dt: float, label=None, choose=None) -> Example:
  """Examples (S, ...) of one rolled-out scene at each step of `cfg.times`.
  label: (state, feats, k) -> Targets of the k-th cut, for `cfg.targets`
  "guided" and "hybrid"; choose: (state, rejoin, guided, feats) -> Targets, for
  "hybrid" (`clean_rejoin_or`)."""
  tail = None
  if cfg.targets != "guided" and cfg.lane_tail:
    tail = lane_continuation(final, max(cfg.times) + horizon, dt)

  def at(k, t):
    state = final.replace(timestep=jnp.asarray(t, jnp.int32))
    feats = features_lib.scene_features(state, features)
    if cfg.targets == "rejoin":
      return Example(feats=feats, targets=on_policy_targets(state, feats, horizon, cfg, dt, tail))
    guided = label(state, feats, k)
    if cfg.targets == "hybrid":
      guided = choose(state, on_policy_targets(state, feats, horizon, cfg, dt, tail), guided, feats)
    return Example(feats=feats, targets=guided)
  exs = [at(k, t) for k, t in enumerate(cfg.times)]
  return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *exs)


def make_collect_fn(actor, model_cfg: Config, cfg: OnPolicyConfig, teacher=None):
  """jit(vmap): (states (B,), rngs (B,), models) -> Example (B, S, ...) of the
  policy's rollouts from WOMD's current step to max(times). teacher: the
  guided `policy.PolicyConfig` that labels the visited states when
  cfg.targets is "guided"."""
  init = env.WOMD_INIT_STEPS
  num_steps = max(cfg.times) - (init - 1)
  if min(cfg.times) < init:
    raise ValueError(f"on-policy times must be >= {init}, got {cfg.times}")
  if cfg.targets not in TARGETS:
    raise ValueError(f"on-policy targets must be one of {TARGETS}, got {cfg.targets!r}")
  if cfg.targets != "rejoin" and (teacher is None or teacher.guidance.mode != "objective"):
    raise ValueError(f"{cfg.targets} on-policy targets need a teacher PolicyConfig with objective guidance")

  def one(state, rng, models):
    k_roll, k_teach = jax.random.split(rng)
    start = env.simulated_start(state, init)   # as evaluation starts a simulated method
    final = env.rollout(start, actor, num_steps, k_roll, params=models).final_state
    label = choose = None
    if cfg.targets != "rejoin":
      road = guidance_lib.road_of(start, teacher.guidance)   # once per scene, around the SDC at t0
      label = lambda s, feats, k: guided_targets(models, s, feats, model_cfg, teacher,
                                                 jax.random.fold_in(k_teach, k), road)
      choose = lambda s, rejoin, guided, feats: clean_rejoin_or(
          s, rejoin, guided, feats, road, teacher.guidance, cfg.rejoin_margin, cfg.rejoin_whole_logs)
    return on_policy_examples(final, model_cfg.features, model_cfg.encoder.horizon, cfg,
                              model_cfg.kinematics.dt, label, choose)
  return jax.jit(jax.vmap(one, in_axes=(0, 0, None)))


def collect(models: Models, model_cfg: Config, policy_cfg, paths: Sequence[str], cfg: OnPolicyConfig,
            first: int, count: int, batch_size: int = 4, seed: int = 0,
            progress: bool = True, teacher=None, actor=None) -> tuple[Example, dict]:
  """On-policy examples of training scenes [first, first + count) of `paths`.

  `model_cfg` is the config the policy runs with (its agent cap: the SDC and
  every evaluated agent, `evaluation.with_agent_cap`). Returns numpy
  Example (N, ...) and info {"scenes", "skipped", "usable_agents",
  "mean_offset"}. teacher: the guided policy of "guided" targets. actor: roll
  this Actor out instead of the diffusion policy (`models` are then its
  params, e.g. the SIMPL-AR baseline with its encoder's). A scenario that
  fails is skipped with a warning.
  """
  from tqdm.auto import tqdm
  from pcdiff_jax import evaluation, policy
  from pcdiff_jax.data import womd
  actor = actor if actor is not None else policy.actor(model_cfg, policy_cfg)
  fn = make_collect_fn(actor, model_cfg, cfg, teacher)
  chunks, skipped, done = [], [], 0
  batches = womd.iterate(paths, batch_size=batch_size, with_meta=True, on_error="skip",
                         skipped=skipped, max_scenarios=first + count)
  bar = tqdm(total=count, desc="on-policy rollouts", unit="scene", disable=not progress)
  seen = 0
  for index, (state, meta) in enumerate(batches):
    n = state.shape[0]
    seen += n
    if seen <= first:
      continue
    keep = slice(max(first - (seen - n), 0), n)
    try:
      rngs = jax.random.split(jax.random.fold_in(jax.random.key(seed), index), batch_size)
      padded = evaluation.pad_batch(state, batch_size)
      out = jax.device_get(fn(padded, rngs, models))
    except Exception as err:  # a bad scenario must not end a long job
      log.warning("skipping on-policy batch %s (%s): %s", index, meta.scenario_id, err)
      continue
    chunks.append(jax.tree_util.tree_map(lambda a: a[keep].reshape((-1,) + a.shape[2:]), out))
    done += n - keep.start
    bar.update(n - keep.start)
  bar.close()
  if not chunks:
    raise ValueError(f"no on-policy example could be collected from {list(paths)!r}")
  examples = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *chunks)
  full = examples.feats.agent_valid & examples.targets.future_valid.all(-1)
  info = {"scenes": done, "skipped": len(skipped), "examples": data_lib.num_examples(examples),
          "usable_agents": int(full.sum()), "modelled_agents": int(examples.feats.agent_valid.sum())}
  return examples, info


def mixed_batch_at(log_examples: Example, on_policy: Example, step: int, batch_size: int,
                   mix: float, seed: int, real: Optional[Example] = None,
                   real_share: float = 0.0) -> tuple[Example, Example]:
  """(log batch, on-policy batch) of global `step`: round(mix * batch_size)
  on-policy examples and the rest logged ones, of which round(real_share *
  their number) come from `real` (logged real scenes) when given; a pure
  function of (seed, step)."""
  n_on = int(round(mix * batch_size))
  n_log = batch_size - n_on
  n_real = int(round(real_share * n_log)) if real is not None else 0
  take = lambda ex, n, salt: data_lib.batch_at(ex, step, n, seed + salt) if n else \
      jax.tree_util.tree_map(lambda a: a[:0], ex)
  logged = take(log_examples, n_log - n_real, 0)
  if n_real:
    logged = jax.tree_util.tree_map(lambda a, b: np.concatenate([a, b]), logged, take(real, n_real, 104729))
  return logged, take(on_policy, n_on, 7919)


def _concat(a: Example, b: Example) -> Example:
  return jax.tree_util.tree_map(lambda x, y: jnp.concatenate([x, y], 0), a, b)


def finetune_encoder(encoder_params, model_cfg: Config, log_examples: Example, on_policy: Example,
                     workdir: str, train_cfg: TrainConfig, cfg: OnPolicyConfig,
                     max_minutes: Optional[float] = None, progress: bool = True,
                     real: Optional[Example] = None, real_share: float = 0.0):
  """Fine-tunes the encoder in WORKDIR/encoder (resumable) on mixed batches
  (`mixed_batch_at`) with stage 1's loss and `train_cfg.history_dropout`.
  Returns (state, {})."""
  from pcdiff_jax import config as config_lib
  from pcdiff_jax.model import encoder
  from pcdiff_jax.training import encoder_loss, encoder_stage
  cfg_ft = dataclasses.replace(model_cfg, encoder_train=train_cfg)
  tx = trainer.make_optimizer(train_cfg)
  state = trainer.create_state(encoder_params, tx, train_cfg.seed)

  def loss_fn(params, batch, rng):
    logged, visited = batch
    rng, k_perturb = jax.random.split(rng)
    logged = perturb.perturb(logged, k_perturb, train_cfg.perturb, model_cfg.kinematics.dt)
    # Its own key folded off, so runs without dropout draw as before it existed.
    both = perturb.drop_history(_concat(logged, visited), jax.random.fold_in(k_perturb, 1),
                                train_cfg.history_dropout)
    out = encoder.apply(params, both.feats, model_cfg.encoder, rng=rng)
    return encoder_loss.proposal_loss(out, both.targets, cls_weight=train_cfg.cls_weight)
  step_fn = trainer.make_train_step(loss_fn, tx)
  batch_at = lambda step: mixed_batch_at(log_examples, on_policy, step, train_cfg.batch_size,
                                         cfg.mix, train_cfg.seed, real, real_share)
  return trainer.fit(state, step_fn, batch_at, None, train_cfg,
                     os.path.join(workdir, encoder_stage.STAGE_DIR), config_lib.to_dict(cfg_ft),
                     desc="on-policy encoder", max_minutes=max_minutes, progress=progress,
                     schedule=trainer.learning_rate_schedule(train_cfg),
                     compare=encoder_stage.CONFIG_SECTIONS)


def finetune(models: Models, model_cfg: Config, log_examples: Example, on_policy: Example,
             workdir: str, train_cfg: TrainConfig, cfg: OnPolicyConfig,
             val_examples: Optional[Example] = None, max_minutes: Optional[float] = None,
             progress: bool = True, real: Optional[Example] = None, real_share: float = 0.0):
  """Fine-tunes the denoiser in WORKDIR/diffusion (resumable) from `models`
  on mixed batches (`mixed_batch_at`: logged, logged real, on-policy).

  The latent statistics and the encoder stay frozen; the saved checkpoint
  has stage 2's layout (`diffusion_stage.load(workdir)` reads it). Returns
  (state, last validation metrics)."""
  from pcdiff_jax import config as config_lib
  from pcdiff_jax.training import diffusion_stage
  cfg_ft = dataclasses.replace(model_cfg, diffusion_train=train_cfg)
  log_examples = diffusion_stage.full_future_examples(log_examples)
  on_policy = diffusion_stage.full_future_examples(on_policy)
  if real is not None:
    real = diffusion_stage.full_future_examples(real)
  extra = {"encoder": models.encoder, "stats": models.stats}
  tx = trainer.make_optimizer(train_cfg)
  state = trainer.create_state(models.denoiser, tx, train_cfg.seed, extra=extra)

  def loss_fn(params, extra, batch, rng):
    logged, visited = batch
    rng, k_perturb = jax.random.split(rng)
    logged = perturb.perturb(logged, k_perturb, train_cfg.perturb, model_cfg.kinematics.dt)
    return diffusion_stage.diffusion_loss(params, extra, _concat(logged, visited), rng, cfg_ft)
  step_fn = trainer.make_train_step(loss_fn, tx, with_extra=True)
  evaluate = None
  if val_examples is not None:
    ev = diffusion_stage.make_evaluate(cfg_ft, diffusion_stage.full_future_examples(val_examples),
                                       train_cfg.eval_batch_size)
    evaluate = lambda st: ev(st.params, st.extra)
  batch_at = lambda step: mixed_batch_at(log_examples, on_policy, step, train_cfg.batch_size,
                                         cfg.mix, train_cfg.seed, real, real_share)
  return trainer.fit(state, step_fn, batch_at, evaluate, train_cfg, os.path.join(workdir, "diffusion"),
                     config_lib.to_dict(cfg_ft), desc="on-policy fine-tune", max_minutes=max_minutes,
                     progress=progress, schedule=trainer.learning_rate_schedule(train_cfg),
                     compare=diffusion_stage.CONFIG_SECTIONS, evaluate_state=True)

