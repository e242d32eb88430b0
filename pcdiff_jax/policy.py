"""The closed-loop policy: encode -> DDIM joint plan -> decode -> first action(s).

Two ways to use it from a Waymax-compatible loop:

  actor = policy.actor(cfg, PolicyConfig(ddim_steps=5))     # Actor contract
  out = sim.rollout(state, actor, 80, rng, params=models)   # one lax.scan

  action, controlled = policy.step(state, models, cfg, rng)  # one replanning

`models` (`planner.Models`) and `cfg` come from
`training.diffusion_stage.load(workdir)`. The actor controls the reactive
agents: the agents the encoder models at the start of the rollout (the SDC
and up to A - 1 nearest it, valid at that step), minus the SDC, which follows
its log (a fixed ego policy); every other object follows its log. The
controlled set is fixed at `init`, and every plan models it whole: the SDC,
every controlled agent still alive, then the nearest other objects as
context (`features.select_agents(keep=...)`), so a controlled agent is never
dropped for a newcomer and its action is valid at every step while it is
alive. Every `replan_every` steps the policy encodes the scene at the current
step (its simulated history), samples a joint plan for all A agents with DDIM
and decodes it into T actions [a, psi_dot] per agent; in between, it executes
the plan's next action. With `warm_start`, each plan after the first starts
from the previous one (advanced by the steps executed) instead of the
proposal prior.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.config import Config
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model import guidance as guidance_lib
from pcdiff_jax.model import joint_selection, latent, planner
from pcdiff_jax.model.planner import Models
from pcdiff_jax.sim import action_spaces, datatypes, dynamics, geometry
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, Array, ObjectType, SimulatorState
from pcdiff_jax.sim.road_field import RoadField


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
  """ddim_steps, eta: the sampler; prior_init False starts from N(0, I) (the
  no-prior model); replan_every: steps between plans (1 = 10 Hz); guidance:
  test-time guidance of every plan (`model.guidance`).

  consistent_noise: each object's initial DDIM noise is drawn once per rollout
  (at `init`) and reused by every replanning, so consecutive plans start from
  the same point of the prior and stay on the same mode. With fresh noise at
  every replan (the default, plain DDIM) an agent can switch modes every
  100 ms: measured in docs/RESULTS.md, consistent noise makes the motion far
  smoother (realism) but commits agents to a mode (minADE, collisions). It
  starts the cold chains only: a warm-started replan draws fresh noise.

  execute: "actions" runs the plan's decoded actions open loop until the next
  replan (the paper's policy); "track" instead steers each agent from its
  simulated state towards the plan's point `track_steps` ahead (pure pursuit,
  as SIMPL-AR executes its proposals), which ignores the noise of a plan's
  first action (docs/RESULTS.md: "The expected order does not hold").

  prior_centre: "mean" starts DDIM around the mean of each agent's K proposal
  latents (the paper's prior); "top1" around its most likely proposal's.

  warm_start: amortised replanning (SceneDiffuser's idea, in our latent): a
  replan after the first takes each agent's previous plan, drops the actions
  already executed, holds the last state for the freed tail (zero actions),
  encodes it, noises it to diffusion step `warm_step` and denoises it with
  `warm_ddim_steps` DDIM steps. Actions are [a, psi_dot], so the shifted
  plan needs no change of frame: it continues from the agent's new state.
  Agents without a previous plan start from the prior centre at the same
  noise level; the first plan of a rollout is the cold `ddim_steps` sampler.
  The default since models v3 (docs/RESULTS.md: on 50 val scenes at 10 Hz,
  fewer collisions, 3x better realism, 0.6 m better minADE than cold plans).
  Cold and warm chains are one while loop (`diffusion.ddim_sample_either`),
  so a vmapped batch pays the cold sampler only at its first replan.
  warm_ddim_steps: 1 since session 11 (2 before): with select_stride 3, what
  brings the default closed-loop step from 41.5 to 31.7 ms (65 agents, 2 CPU
  cores; docs/BENCHMARKS.md) at 3.96 / 1.96% collisions / off-road on the
  first 50 val scenes against 3.59 / 1.76 (docs/RESULTS.md, "Session 11").
  warm_step: 90 since session 13 (30 before): the previous plan keeps a
  weight sqrt(abar_90) = 0.36 in the start of the chain (0.89 at step 30),
  so each replan re-draws most of the plan from the current scene while
  starting near the last one. On the first 50 val scenes (3 seeds, with the
  jerk limit) collisions / off-road 3.19 / 1.50% -> 2.12 / 0.88% at realism
  W1 0.41 -> 0.56 and minADE 2.44 -> 2.58 m, at no extra cost (the same one
  DDIM step); steps 50 / 70 / 80 / 99 did less (docs/RESULTS.md, "Session 13").
  The temporal ensemble's weight (below) then wins the realism back.

  temporal_ensemble: (m_accel, m_yaw_rate), the weight of the earlier plans
  in the plan that is executed, per action channel (ACT's temporal ensembling
  of action chunks, with exponential weights): each replan keeps
  m * (previous plan, advanced) + (1 - m) * (new plan) where both exist, so an
  executed action averages every plan made for that step, the newest weighted
  (1 - m). Plans drawn afresh every 100 ms disagree by their sampling noise,
  and the executed accelerations inherit it as jerk; averaging removes most
  of it at a lag of about m / (1 - m) replans. The warm start then continues
  the ensembled plan. 0 is off for a channel. Default (0.3, 0) until session 12: on the first
  50 val scenes realism W1 1.09 -> 0.71 at the same collision and off-road
  rates; averaging the yaw rate too (0.5, 0.5) cost 4 points of each, as
  did a warm start closer to the previous plan (docs/RESULTS.md, "Models v5").
  (0.7, 0) since session 13, with warm_step 90: on the first 50 val scenes
  (3 seeds) 0.3 / 0.5 / 0.7 gave 2.12 / 1.93 / 2.45% collisions, 0.88 /
  0.95 / 1.08% off-road at realism W1 0.56 / 0.48 / 0.34 and minADE 2.58 /
  2.44 / 2.33 m (0.8: 2.85 / 1.03 / 0.27 / 2.32, 2 seeds); 0.7 is better than
  session 12's defaults (3.19 / 1.50 / 0.41 / 2.44) on every column.

  ensemble_brake_weight: None (the default) averages braking like any other
  acceleration; a weight in [0, 1) is used instead of m_accel at the steps
  where the new plan brakes harder than the previous one by more than
  ensemble_brake_margin (m/s^2), so a heavy ensemble smooths speeding up
  without delaying a stop. With no margin every small disagreement that slows
  down passes and the others are averaged: the agents drive slower.
  ensemble_pass: "brake" (the above) or "both": disagreements larger than the
  margin either way take ensemble_brake_weight, so big plan changes pass at
  once and the small ones (sampling noise) are averaged, without a speed
  bias. Session 14, v8, weight 0.3, margin 1: first 50 val scenes (3 seeds)
  2.05 / 0.95 / 0.41 / 2.38 against the defaults' 2.45 / 1.08 / 0.34 / 2.33;
  the real record 41.7% collisions against 45.3 (docs/RESULTS.md, "Session 14").

  select_samples: S > 1 draws S joint plans per replan (one batched chain)
  and keeps, per agent, the sample that collides least with the others'
  chosen samples over the first `select_lookahead` steps (iterated
  conditional modes, `model.joint_selection`: the mechanism SIMPL-AR uses
  over its proposals). Samples are equally likely, so an agent keeps sample 0
  (what S = 1 would have executed) unless another avoids an overlap; the SDC
  (slot 0, on its log) and an adversarial pursuer never change. No objective
  gradient: the S chains share the encoder and the denoiser's context, and
  cost 62 against 34 ms per cold 65-agent replan on 2 CPU cores
  (docs/BENCHMARKS.md). With consistent_noise,
  sample 0 starts from each object's fixed noise and sample k from the fixed
  noise of the agent k slots further (the plan stays a function of the
  scene). 4 from session 8 (docs/RESULTS.md, "Sample selection"): on the
  first 50 val scenes at 10 Hz, S = 1 / 2 / 4 / 8 gave 10.7 / 6.0 / 4.3 /
  4.3% collisions and 7.1 / 6.6 / 6.1 / 6.2% off-road at the same realism and
  minADE. Default 8 since session 18 (docs/RESULTS.md, "Session 18"): with
  today's map term and warm replans, v8, all 200 val scenes, 3 seeds, S = 4
  / 8 gave 2.71 / 2.39% collisions and 1.61 / 1.15% off-road, and the test
  split (first 100 scenes, 3 seeds) 2.76 / 2.47 and 2.19 / 1.45, same realism
  and minADE; about 25 against 30 ms per 65-agent closed-loop step on 2 CPU
  cores since session 19 (docs/BENCHMARKS.md, "Session 19").

  select_map_weight: with S > 1, each sample also costs this weight times its
  J_map over the lookahead (`guidance.map_cost`: mean squared excursion of the
  box corners past the road edge, m^2, on the same road field guidance uses),
  so an agent prefers a sample that stays on the road as it prefers one that
  does not collide. The field is built once per scenario (`road_for`, at the
  actor's init: about 1 s on 2 CPU cores); 0 turns the term off. Default 30
  since session 9 (docs/RESULTS.md, "Selection with a map term"): on the
  first 50 val scenes, weight 0 / 10 / 30 / 100 gave 6.1 / 2.9 / 2.6 / 2.7%
  off-road at 4.3 / 5.1 / 5.2 / 5.2% collisions, same realism.

  select_proposal_weight, select_proposal_scale (m): with S > 1, each sample
  also costs this weight times its `proposal_nll` over the lookahead: how
  unlikely the encoder's K proposals and their probabilities make it (a
  Gaussian mixture of this scale around the proposals), relative to the
  agent's likeliest sample. 0 (off) by default.

  select_stride: overlaps and J_map are scored at every N-th step of the
  lookahead only (overlap counts weighted N times, so the two terms keep
  their balance). Default 3 since session 11 (with warm_ddim_steps 1, above):
  the overlap counts were 7 of the 41 ms of a closed-loop step.

  select_neighbours: with S > 1, each agent's samples are checked for
  overlaps against those of its N nearest agents only
  (`joint_selection.near_collision_counts`: a broad phase on the bounding
  circles of each agent's S samples per step, then the circle tests), not
  against all of them; 0 checks every pair. The counts are the same as the
  dense ones for every agent whose (N+1)-th nearest agent cannot reach its
  samples within the lookahead (648 of 649 agents on the first plans of the
  real record and 30 val scenes; the real record's closed-loop metrics are
  identical), for N / A of the circle tests: a 65-agent closed-loop step at
  S = 8 on 2 CPU cores 28.7 against 30.2 ms. Default 16 since session 19
  (docs/RESULTS.md, "Session 19").

  jerk_limit: (rise, fall) in m/s^3: the executed acceleration moves from the
  one executed at the previous step (read from the simulated speeds) by at
  most rise * dt up and fall * dt down; the plan itself is not changed, and
  the next replan starts from the state this led to. 0 turns a side off.
  Plans drawn every 100 ms disagree in their first acceleration, which the
  log's drivers never do (|jerk| under 0.74 m/s^3 for 90% of the log's
  vehicle steps, 2.3 for 99%). Default (1.5, 5) since session 12
  (docs/RESULTS.md, "Session 12"): on the first 50 val scenes, v8, realism
  W1 0.70 -> 0.42 (jerk W1 1.93 -> 1.04) with collisions 3.96 -> 3.68,
  off-road 1.96 -> 1.66 and minADE 2.56 -> 2.44; a slower rise (1, 3 or 10)
  smooths more but collides more (4.4-4.9%).

  stop_hold: braking ends at standstill (`hold_at_stop`): an agent moving
  forward or stopped never backs up because its plan brakes. A plan drawn
  for a parked car has small accelerations of either sign (sampling noise in
  the latent), and the kinematic model integrates a brake at v = 0 into
  reversing: on the first 16 val scenes 53% of the steps of the parked cars
  (log path < 0.5 m) reversed faster than 0.05 m/s and they crept 1.7 m on
  average (SIMPL-AR: 0.17 m); with the hold none reversed. Default since
  session 15: collisions / off-road / realism W1 / minADE on the first 50
  val scenes (3 seeds) 1.93 / 0.98 / 0.33 / 2.25 against 2.45 / 1.08 / 0.34
  / 2.33 without it, on all 200 val scenes 2.64 / 1.60 / 0.33 / 2.35
  against 3.36 / 1.74 / 0.34 / 2.44 (docs/RESULTS.md, "Session 15").

  start_gate: (seconds, metres): an agent slower than START_GATE_SPEED
  starts moving only when the plan it executes would carry it at least
  `metres` within the next `seconds` (`gate_start`); otherwise it does not
  speed up, and one slower than STOPPED_REVERSE_SPEED stops. A plan drawn
  for a stopped car is a small noisy acceleration around 0; with stop_hold,
  only the forward part of that noise is executed, the agent creeps, and a
  creeping agent is encoded as a moving one at the next replan, whose
  proposals then move too. The gate asks a plan to commit to going. (0, 0)
  (off) is the default: session 16 (docs/RESULTS.md), v8, (2 s, 2 m) took
  the real record from 44.3 to 33.3% collisions but cost all 200 val scenes
  0.5 points (2.64 -> 3.15%: cars waiting at intersections start late);
  (2 s, 1 m) 39.6% there, level on val50.

  warm_proposals: with warm starts and S = select_samples > 1, samples
  1..n of a warm replan start from each agent's n most likely proposal
  latents (noised to warm_step like the previous plan) instead of from its
  previous plan, so the selection weighs continuing the plan (sample 0)
  against fresh alternatives anchored on the proposals: warm samples of one
  previous plan hardly differ, which left the selection little to choose
  from. 0 (off) to min(S - 1, K).
  """
  ddim_steps: int = 5
  eta: float = 0.0
  prior_init: bool = True
  replan_every: int = 1
  guidance: guidance_lib.GuidanceConfig = guidance_lib.GuidanceConfig()
  consistent_noise: bool = False
  execute: str = "actions"
  track_steps: int = 5
  prior_centre: str = "mean"
  warm_start: bool = True
  warm_step: int = 90
  warm_ddim_steps: int = 1
  temporal_ensemble: tuple[float, float] = (0.7, 0.0)
  ensemble_brake_weight: Optional[float] = None
  ensemble_brake_margin: float = 0.0
  ensemble_pass: str = "brake"
  select_samples: int = 8
  select_lookahead: int = 30
  select_map_weight: float = 30.0
  select_stride: int = 3
  select_neighbours: int = 16
  select_proposal_weight: float = 0.0
  select_proposal_scale: float = 1.0
  jerk_limit: tuple[float, float] = (1.5, 5.0)
  warm_proposals: int = 0
  stop_hold: bool = True
  start_gate: tuple[float, float] = (0.0, 0.0)
  max_curvature: float = 0.3
  still_gate: tuple[float, float] = (2.0, 1.0)


@struct.dataclass
class PlanState:
  """Actor state for one scenario: controlled (O,) fixed set; plan (O, T, 2)
  actions of the last plan; plan_valid (O,); age () steps since it was made;
  adversary () object slot of the pursuer under adversarial guidance (-1: none);
  noise (O, d) each object's initial DDIM noise (consistent_noise); road the
  scene's road signed-distance field for guidance, built once at `init`;
  path (O, T, 2) the last plan's positions in the world frame (execute="track")."""
  controlled: Array
  plan: Array
  path: Array
  plan_valid: Array
  age: Array
  adversary: Array
  noise: Array
  road: RoadField


def _guide(models: Models, state: SimulatorState, feats, cond: planner.Conditioning, cfg: Config,
           g: guidance_lib.GuidanceConfig, adversary: Array, road: RoadField):
  """The sampler's guide for one scene's batched feats / cond (None without guidance)."""
  if g.mode == "none":
    return None
  road = jax.tree_util.tree_map(lambda a: a[None], road.in_frame(feats.scene_xy[0], feats.scene_yaw[0]))
  length, width = planner.agent_size(feats)
  hit = (feats.agent_index[0] == adversary) & feats.agent_valid[0] & (adversary >= 0)
  pursuer = jnp.where(jnp.any(hit), jnp.argmax(hit), -1).astype(jnp.int32)
  evader = jnp.where(feats.agent_valid[0, 0], 0, -1).astype(jnp.int32)   # slot 0 is the SDC
  agents = guidance_lib.Agents(
      length=length, width=width, valid=feats.agent_valid,
      vehicle=feats.agent_types == ObjectType.VEHICLE, pursuer=pursuer[None], evader=evader[None])

  def poses(y):
    return planner.to_scene(planner.decode_states(models.stats, cond, y, cfg), feats)
  return guidance_lib.make_guide(poses, agents, road, g)


@struct.dataclass
class WarmStart:
  """A previous plan to start from: actions (O, T, 2) already advanced to the
  current step (`advance_plan`) and which objects have one, has (O,)."""
  actions: Array
  has: Array


def advance_plan(plan: Array, executed: Array) -> Array:
  """(O, T, 2) the plan without its first `executed` actions (a traced int),
  the freed tail holding the last state (zero actions)."""
  horizon = plan.shape[1]
  idx = executed + jnp.arange(horizon)                                       # (T,)
  shifted = jnp.take(plan, jnp.clip(idx, 0, horizon - 1), axis=1)
  return jnp.where((idx < horizon)[None, :, None], shifted, 0.0)


def plan_actions(models: Models, state: SimulatorState, cfg: Config, policy: PolicyConfig,
                 rng: Array, adversary: Array = -1, noise: Optional[Array] = None,
                 road: Optional[RoadField] = None, controlled: Optional[Array] = None,
                 warm: Optional[WarmStart] = None) -> tuple[Array, Array, Array]:
  """A joint plan for one scene at its current step (guided by policy.guidance;
  `adversary`: the pursuer's object slot under adversarial guidance; noise
  (O, d): per-object initial noise, default drawn from rng; road: the scene's
  road field, default built here, which costs a field per call; controlled
  (O,): objects modelled first after the SDC, whatever their distance; warm:
  a previous plan to start from (`PolicyConfig.warm_start`), else the prior;
  with `warm`, the plan is cold when no modelled agent has a previous plan).

  Returns actions (O, T, 2) per object (zeros where not planned), which
  objects got a plan (O,), and the planned positions (O, T, 2) in the world frame
  (zeros unless policy.execute is "track").
  """
  feats = features_lib.scene_features(state, cfg.features, keep=controlled)
  batched = jax.tree_util.tree_map(lambda a: a[None], feats)
  cond = planner.condition(models.encoder, models.stats, batched, cfg)
  hold = None
  if policy.still_gate[0] > 0:
    hold = still_agents(cond, models.stats, cfg, *policy.still_gate)[0]                  # (A,)
  if policy.prior_centre == "top1":
    cond = planner.centre_on_top_mode(cond)
  init_noise = None if noise is None else noise[feats.agent_index][None]   # (1, A, d)
  if policy.select_samples > 1:   # S candidate plans as a batch of S copies of the scene
    batched = jax.tree_util.tree_map(lambda a: jnp.repeat(a, policy.select_samples, axis=0), batched)
    cond = planner.repeat_samples(cond, policy.select_samples)
    if init_noise is not None:
      # Sample k starts from the consistent noise rolled by k over the agents: another
      # Gaussian draw per agent, still a function of the rollout's noise (not of rng).
      init_noise = jnp.concatenate([jnp.roll(init_noise, k, axis=1) for k in range(policy.select_samples)])
  if road is None:
    road = road_for(state, policy)
  guide = _guide(models, state, batched, cond, cfg, policy.guidance, jnp.asarray(adversary, jnp.int32), road)
  if warm is None:
    steps = policy.guidance.guide_steps(policy.ddim_steps) if guide is not None else None
    y0 = planner.sample(models.denoiser, cond, cfg, rng, policy.ddim_steps, policy.eta,
                        prior_init=policy.prior_init, guide=guide, guide_steps=steps,
                        init_noise=init_noise)
  else:   # the first plan of a rollout (no agent has a previous one) is cold
    previous = latent.encode(warm.actions[feats.agent_index], models.stats)[None]   # (1, A, d)
    has = warm.has[feats.agent_index] & feats.agent_valid
    centre = warm_centres(cond, previous, has, policy.warm_proposals)
    g = policy.guidance
    y0 = planner.sample_cold_or_warm(
        models.denoiser, cond, cfg, rng, ~jnp.any(has), centre, policy.ddim_steps,
        policy.warm_ddim_steps, policy.warm_step, policy.eta, prior_init=policy.prior_init,
        guide=guide, cold_guide_steps=g.guide_steps(policy.ddim_steps) if guide is not None else None,
        warm_guide_steps=g.guide_steps(policy.warm_ddim_steps) if guide is not None else None,
        init_noise=init_noise)
  if policy.select_samples > 1:   # the SDC (slot 0, on its log) and an adversarial pursuer keep sample 0
    pursuer = (feats.agent_index == adversary) & (adversary >= 0)
    keep = (jnp.arange(feats.agent_valid.shape[0]) == 0) | pursuer
    road_here = None
    if policy.select_map_weight > 0:
      road_here = road.in_frame(feats.scene_xy, feats.scene_yaw)
      road_here = jax.tree_util.tree_map(lambda a: a[None], road_here)   # a batch of 1 for map_cost
    y0 = select_sample(y0, models, cond, batched, cfg, policy.select_lookahead, keep,
                       road_here, policy.select_map_weight, policy.guidance, policy.select_stride,
                       policy.select_proposal_weight, policy.select_proposal_scale,
                       policy.select_neighbours)
  actions = dynamics.clip_action(latent.decode(y0[0], models.stats), cfg.kinematics)  # (A, T, 2)
  if hold is not None:
    actions = jnp.where(hold[:, None, None], stop_plan(cond.speed[0], actions.shape[1], cfg), actions)
  if policy.execute == "track":   # the world-frame path is only needed to track it
    states = dynamics.rollout(latent.initial_states(cond.speed[0]), actions, cfg.kinematics.dt)
    path, _ = features_lib.agent_to_world(states[..., :2], states[..., 2], feats)      # (A, T, 2)
  else:
    path = jnp.zeros_like(actions)
  num_objects = state.object_metadata.ids.shape[-1]
  per_object = features_lib.scatter_to_objects(actions, feats, num_objects)
  planned = features_lib.scatter_to_objects(feats.agent_valid, feats, num_objects, fill=False)
  return per_object, planned.astype(bool), features_lib.scatter_to_objects(path, feats, num_objects)


def still_agents(cond: planner.Conditioning, stats: latent.LatentStats, cfg: Config, seconds: float,
                 metres: float) -> Array:
  """(..., A) the agents the scene keeps still (`PolicyConfig.still_gate`): slower
  than START_GATE_SPEED and carried less than `metres` within `seconds` by their
  proposals, each proposal's distance weighted by its probability. The
  encoder's proposals read the map, the lights and the other agents, so a car
  queued at a light that turns green is let go while a parked one is not."""
  steps = max(1, min(round(seconds / cfg.kinematics.dt), cfg.encoder.horizon))
  actions = dynamics.clip_action(latent.decode(cond.proposals, stats)[..., :steps, :], cfg.kinematics)
  speed = jnp.broadcast_to(cond.speed[..., None], cond.proposals.shape[:-1])             # (..., A, K)
  states = dynamics.rollout(latent.initial_states(speed), actions, cfg.kinematics.dt)    # (..., A, K, steps, 4)
  travelled = jnp.max(jnp.hypot(states[..., 0], states[..., 1]), axis=-1)                # (..., A, K)
  expected = jnp.sum(cond.probs * travelled, axis=-1)
  return (jnp.abs(cond.speed) < START_GATE_SPEED) & (expected < metres)


def stop_plan(speed: Array, horizon: int, cfg: Config) -> Array:
  """(A, T, 2) plans that bring agents moving at `speed` (A,) to a stop in one
  step, within the braking bound, and then hold them: no yaw rate."""
  first = jnp.stack([-speed / cfg.kinematics.dt, jnp.zeros_like(speed)], -1)             # (A, 2)
  plan = jnp.zeros(speed.shape + (horizon, 2)).at[:, 0].set(first)
  return dynamics.clip_action(plan, cfg.kinematics)


def warm_centres(cond: planner.Conditioning, previous: Array, has: Array, proposals: int) -> Array:
  """(S, A, d) where each of the S samples of a warm replan starts (before
  noising): the previous plan's latent previous (1, A, d) where an agent has
  one (has (A,)), else its prior centre; samples 1..`proposals` from its
  most likely proposals instead (`PolicyConfig.warm_proposals`)."""
  centre = jnp.broadcast_to(jnp.where(has[None, :, None], previous, cond.mu), cond.mu.shape)
  if proposals == 0:
    return centre
  ranked = top_proposals(cond.proposals[0], cond.probs[0], proposals)           # (n, A, d)
  return centre.at[1:1 + proposals].set(ranked)


def top_proposals(proposals: Array, probs: Array, n: int) -> Array:
  """(n, A, d) each agent's n most likely of its proposal latents (A, K, d), by probs (A, K)."""
  order = jnp.argsort(-probs, axis=-1)[:, :n]                                   # (A, n)
  return jnp.moveaxis(jnp.take_along_axis(proposals, order[..., None], axis=1), 1, 0)


def select_sample(y0: Array, models: Models, cond: planner.Conditioning, batched, cfg: Config,
                  lookahead: int, keep: Array, road: Optional[RoadField] = None,
                  map_weight: float = 0.0,
                  guidance: guidance_lib.GuidanceConfig = guidance_lib.GuidanceConfig(),
                  stride: int = 1, proposal_weight: float = 0.0, proposal_scale: float = 1.0,
                  neighbours: int = 0) -> Array:
  """(1, A, d): per agent, one of the S joint samples y0 (S, A, d) of one scene
  (cond, batched: that scene repeated S times) such that the chosen plans
  overlap least over their first `lookahead` steps, every `stride`-th (`PolicyConfig.select_samples`),
  plus map_weight x each sample's J_map on `road` (the scene's field in the
  scene frame) when map_weight > 0, plus proposal_weight x its
  `proposal_nll` (scale `proposal_scale` m) when proposal_weight > 0; agents
  where keep (A,) keep sample 0. neighbours > 0: overlaps against each
  agent's that many nearest agents only (`PolicyConfig.select_neighbours`)."""
  states = planner.decode_states(models.stats, cond, y0, cfg)[..., :lookahead:stride, :]   # (S, A, L, 4)
  xy, yaw = planner.to_scene(states, batched)
  feats = jax.tree_util.tree_map(lambda a: a[0], batched)
  length, width = planner.agent_size(feats)
  xy_a, yaw_a = jnp.moveaxis(xy, 0, 1), jnp.moveaxis(yaw, 0, 1)                  # (A, S, L, ...)
  if neighbours > 0:
    coll, others, _ = joint_selection.near_collision_counts(xy_a, yaw_a, length, width,
                                                            feats.agent_valid, neighbours)   # (A, S, N, S)
  else:
    coll, others = joint_selection.collision_counts(xy_a, yaw_a, length, width, feats.agent_valid), None
  num = feats.agent_valid.shape[0]
  unary = jnp.zeros((num, y0.shape[0]))
  if map_weight > 0:
    agents = guidance_lib.Agents(length=length, width=width, valid=feats.agent_valid,
                                 vehicle=feats.agent_types == ObjectType.VEHICLE,
                                 pursuer=jnp.int32(-1), evader=jnp.int32(-1))
    unary = map_weight * guidance_lib.map_cost(xy, yaw, agents, road, guidance).T    # (A, S)
  if proposal_weight > 0:
    proposals = latent.rollout(jnp.moveaxis(cond.proposals[0], -2, 0), cond.speed[0], models.stats,
                               cfg.kinematics)[..., :lookahead:stride, :2]          # (K, A, L, 2)
    nll = proposal_nll(states[..., :2], proposals, cond.probs[0], proposal_scale)   # (S, A)
    unary = unary + proposal_weight * (nll - jnp.min(nll, axis=0)).T
  # ICM starts from each agent's best unary sample (sample 0 on ties) and never moves a kept
  # agent: a zero unary keeps it on sample 0.
  unary = jnp.where(keep[:, None], 0.0, unary)
  # Overlaps counted at every stride-th step weigh stride times: the same scale against J_map
  # (a mean over the steps) as with every step.
  choice = joint_selection.iterated_conditional_modes(
      unary, coll, feats.agent_valid & ~keep, float(stride), sweeps=2, order=jnp.arange(num), others=others)
  return jnp.take_along_axis(y0, choice[None, :, None], axis=0)


def proposal_nll(paths: Array, proposals: Array, probs: Array, scale: float) -> Array:
  """(S, A) -log sum_k p_k exp(-D_k / (2 scale^2)) of each sampled path
  (S, A, L, 2) under the encoder's proposals (K, A, L, 2) and their
  probabilities (A, K), D_k the mean squared distance to proposal k (agent
  frame, m^2): how unlikely the encoder finds a plan. A parked car whose
  encoder says 'stays' with p = 0.98 pays about 4 nats for a sample that
  pulls away along a 2% proposal; between likely modes the cost hardly differs."""
  dist = jnp.mean(jnp.sum(jnp.square(paths[:, None] - proposals[None]), -1), -1)   # (S, K, A)
  logp = jnp.log(jnp.maximum(probs.T, 1e-9))[None]                                   # (1, K, A)
  return -jax.nn.logsumexp(logp - dist / (2.0 * scale ** 2), axis=1)


def road_for(state: SimulatorState, policy: PolicyConfig) -> RoadField:
  """The scene's road field as the policy needs it: guidance's, or the one
  sample selection's map term reads (the same field), else a placeholder."""
  g = policy.guidance
  if g.mode == "none" and policy.select_samples > 1 and policy.select_map_weight > 0:
    g = dataclasses.replace(g, mode="objective")   # road_of builds the field for any guided mode
  return guidance_lib.road_of(state, g)


EXECUTE = ("actions", "track")


def _track(state: SimulatorState, path: Array, age: Array, steps: int, cfg: Config) -> Array:
  """(O, 2) pure-pursuit actions from each object's simulated state towards the
  plan's world-frame path (O, T, 2) `steps` points past step `age` (clamped
  to the plan's end)."""
  cur = state.current_sim_trajectory
  last = path.shape[1] - 1
  at = lambda k: jnp.take(path, jnp.clip(age + k, 0, last), axis=1)          # (O, 2)
  xy, yaw = cur.xy[:, 0], cur.yaw[:, 0]
  speed = jnp.sum(cur.vel_xy[:, 0] * geometry.unit(yaw), -1)
  local = lambda p: geometry.to_local(p, xy, yaw)
  action = dynamics.pure_pursuit(local(at(steps - 1)), local(at(steps - 2)), speed, steps, cfg.kinematics.dt)
  return dynamics.clip_action(action, cfg.kinematics)


def pursuer_of(state: SimulatorState, cfg: Config, g: guidance_lib.GuidanceConfig) -> Array:
  """() the pursuer's object slot: the user's, or the most threatening reactive
  vehicle at this step; -1 unless the guidance is adversarial."""
  if g.mode != "adversarial":
    return jnp.int32(-1)
  if g.adversary >= 0:
    return jnp.int32(g.adversary)
  return guidance_lib.most_threatening(state, reactive_set(state, cfg))


def reactive_set(state: SimulatorState, cfg: Config) -> Array:
  """(O,) the agents the encoder models at this step, minus the SDC."""
  index, valid = features_lib.select_agents(state, cfg.features.max_agents)
  num_objects = state.object_metadata.ids.shape[-1]
  chosen = jnp.zeros((num_objects,), bool).at[index].max(valid)
  return chosen & ~state.object_metadata.is_sdc


def ensemble_plans(previous: Array, previous_valid: Array, executed: Array, plan: Array,
                   plan_valid: Array, weight, brake_weight: Optional[float] = None,
                   brake_margin: float = 0.0, pass_both: bool = False) -> Array:
  """(O, T, 2) weight * previous + (1 - weight) * plan over the steps both
  cover, with `previous` advanced by the `executed` actions (a traced int);
  the new plan alone where the previous one has ended or an agent had none.
  weight: () or one per action channel (2,). brake_weight: the acceleration
  channel's weight where the new plan's acceleration is below the previous
  one's by more than brake_margin (pass_both: differs from it by more)."""
  horizon = plan.shape[1]
  both = ((jnp.arange(horizon) < horizon - executed)[None, :, None]
          & (previous_valid & plan_valid)[:, None, None])
  previous = advance_plan(previous, executed)
  weight = jnp.broadcast_to(jnp.asarray(weight, plan.dtype), plan.shape)
  if brake_weight is not None:
    gap = previous[..., 0] - plan[..., 0]
    brakes = (jnp.abs(gap) if pass_both else gap) > brake_margin
    weight = weight.at[..., 0].set(jnp.where(brakes, jnp.asarray(brake_weight, plan.dtype), weight[..., 0]))
  blended = weight * previous + (1.0 - weight) * plan
  return jnp.where(both, blended, plan)


def actor(cfg: Config, policy: PolicyConfig = PolicyConfig()) -> Actor:
  """The policy as an Actor (params = Models). One scenario per call: vmap
  the rollout for batches. Its actions are our native [a, psi_dot]
  (`action_space` "accel_yaw_rate", for `sim.dynamics.KinematicModel`); for
  a Waymax environment use `waymax_actor`."""
  validate(cfg, policy)

  def init(rng, state):
    num_objects = state.object_metadata.ids.shape[-1]
    return PlanState(controlled=reactive_set(state, cfg),
                     plan=jnp.zeros((num_objects, cfg.encoder.horizon, 2), jnp.float32),
                     path=jnp.zeros((num_objects, cfg.encoder.horizon, 2), jnp.float32),
                     plan_valid=jnp.zeros((num_objects,), bool),
                     age=jnp.asarray(policy.replan_every, jnp.int32),   # plan at the first call
                     adversary=pursuer_of(state, cfg, policy.guidance),
                     noise=jax.random.normal(jax.random.fold_in(rng, 1), (num_objects, cfg.diffusion.latent_dim)),
                     road=road_for(state, policy))

  def replan(models, state, ps: PlanState, rng):
    noise = ps.noise if policy.consistent_noise else None
    warm = None
    if policy.warm_start:
      warm = WarmStart(actions=advance_plan(ps.plan, ps.age), has=ps.plan_valid & ps.controlled)
    plan, plan_valid, path = plan_actions(models, state, cfg, policy, rng, ps.adversary, noise, ps.road,
                                          controlled=ps.controlled, warm=warm)
    if any(policy.temporal_ensemble):
      plan = ensemble_plans(ps.plan, ps.plan_valid, ps.age, plan, plan_valid, policy.temporal_ensemble,
                            policy.ensemble_brake_weight, policy.ensemble_brake_margin,
                            policy.ensemble_pass == "both")
    return plan, plan_valid, path

  def select_action(models, state, ps: PlanState, rng):
    due = ps.age >= policy.replan_every
    plan, plan_valid, path = jax.lax.cond(
        due, lambda: replan(models, state, ps, rng), lambda: (ps.plan, ps.plan_valid, ps.path))
    age = jnp.where(due, 0, ps.age)
    action = _controlled_action(state, ps.controlled, plan_valid, _execute(state, plan, path, age, policy, cfg))
    new = ps.replace(plan=plan, plan_valid=plan_valid, path=path, age=age + 1)
    return ActorOutput(actor_state=new, action=action, is_controlled=ps.controlled)

  name = "pcdiff" if policy.prior_init else "pcdiff-noprior"
  return Actor(select_action=select_action, init=init, name=name)


def waymax_actor(cfg: Config, policy: PolicyConfig, dynamics_model) -> Actor:
  """The policy as an actor for an environment stepping `dynamics_model`:
  Waymax's `InvertibleBicycleModel` ([accel, curvature]), `DeltaLocal`,
  `DeltaGlobal` (the model instance, or its space name "bicycle",
  "delta_local", "delta_global"), or our `KinematicModel` / "accel_yaw_rate"
  (then it is `actor`). Each step's planned action [a, psi_dot] is converted
  from the pose it leads to (`sim.action_spaces`); no argument defaults, so
  the action space is always chosen on purpose. With Waymax importable its
  output is Waymax's `WaymaxActorOutput` / `Action`, so it goes straight into
  `waymax.agents.merge_actions` (`sim.waymax_interop`)."""
  from pcdiff_jax.sim import waymax_interop
  return waymax_interop.as_waymax_actor(action_spaces.adapt(actor(cfg, policy), dynamics_model, cfg.kinematics))


def with_overrides(policy: PolicyConfig, overrides) -> PolicyConfig:
  """`policy` with fields replaced by (name, value) pairs, each value converted
  to the field's type (tuples element-wise); an unknown name is a ValueError
  that lists the fields."""
  fields = {f.name: f for f in dataclasses.fields(PolicyConfig)}
  changes = {}
  for name, value in overrides:
    if name not in fields or name == "guidance":
      raise ValueError(f"unknown policy field {name!r}; choose from {sorted(set(fields) - {'guidance'})}")
    default = getattr(PolicyConfig(), name)
    if isinstance(default, tuple):
      value = tuple(type(d)(v) for d, v in zip(default, value))
    elif isinstance(default, bool):
      value = value if isinstance(value, bool) else str(value).lower() in ("1", "true", "yes", "on")
    elif default is None:   # the optional floats (ensemble_brake_weight)
      value = None if str(value).lower() == "none" else float(value)
    else:
      value = type(default)(value)
    changes[name] = value
  return dataclasses.replace(policy, **changes)


def validate(cfg: Config, policy: PolicyConfig) -> None:
  """Raises ValueError naming the first PolicyConfig field out of range."""
  if policy.replan_every < 1 or policy.replan_every > cfg.encoder.horizon:
    raise ValueError(f"replan_every must be in [1, {cfg.encoder.horizon}], got {policy.replan_every}")
  if policy.prior_centre not in ("mean", "top1"):
    raise ValueError(f"prior_centre must be 'mean' or 'top1', got {policy.prior_centre!r}")
  if policy.execute not in EXECUTE:
    raise ValueError(f"execute must be one of {EXECUTE}, got {policy.execute!r}")
  if not 2 <= policy.track_steps <= cfg.encoder.horizon:
    raise ValueError(f"track_steps must be in [2, {cfg.encoder.horizon}], got {policy.track_steps}")
  if not 0 <= policy.warm_step < cfg.diffusion.num_steps:
    raise ValueError(f"warm_step must be in [0, {cfg.diffusion.num_steps - 1}], got {policy.warm_step}")
  if len(policy.temporal_ensemble) != 2 or not all(0.0 <= m < 1.0 for m in policy.temporal_ensemble):
    raise ValueError(f"temporal_ensemble must be two weights in [0, 1) (acceleration, yaw rate), "
                     f"got {policy.temporal_ensemble}")
  if policy.ensemble_pass not in ("brake", "both"):
    raise ValueError(f"ensemble_pass must be 'brake' or 'both', got {policy.ensemble_pass!r}")
  if policy.ensemble_brake_weight is not None and not 0.0 <= policy.ensemble_brake_weight < 1.0:
    raise ValueError(f"ensemble_brake_weight must be None or in [0, 1), got {policy.ensemble_brake_weight}")
  if not 1 <= policy.warm_ddim_steps <= policy.warm_step + 1:
    raise ValueError(f"warm_ddim_steps must be in [1, warm_step + 1 = {policy.warm_step + 1}], "
                     f"got {policy.warm_ddim_steps}")
  if not 1 <= policy.select_samples <= 64:
    raise ValueError(f"select_samples must be in [1, 64], got {policy.select_samples}")
  if not 1 <= policy.select_lookahead <= cfg.encoder.horizon:
    raise ValueError(f"select_lookahead must be in [1, {cfg.encoder.horizon}], got {policy.select_lookahead}")
  if len(policy.jerk_limit) != 2 or not all(j >= 0 for j in policy.jerk_limit):
    raise ValueError(f"jerk_limit must be two limits >= 0 in m/s^3 (rise, fall), got {policy.jerk_limit}")
  if not 1 <= policy.select_stride <= policy.select_lookahead:
    raise ValueError(f"select_stride must be in [1, select_lookahead], got {policy.select_stride}")
  if policy.select_neighbours < 0:
    raise ValueError(f"select_neighbours must be >= 0 (0: every pair), got {policy.select_neighbours}")
  if policy.select_map_weight < 0:
    raise ValueError(f"select_map_weight must be >= 0, got {policy.select_map_weight}")
  if policy.select_proposal_weight < 0:
    raise ValueError(f"select_proposal_weight must be >= 0, got {policy.select_proposal_weight}")
  if policy.select_proposal_scale <= 0:
    raise ValueError(f"select_proposal_scale must be > 0 (m), got {policy.select_proposal_scale}")
  if len(policy.start_gate) != 2 or not all(g >= 0 for g in policy.start_gate):
    raise ValueError(f"start_gate must be (seconds, metres) >= 0, got {policy.start_gate}")
  if len(policy.still_gate) != 2 or not all(g >= 0 for g in policy.still_gate):
    raise ValueError(f"still_gate must be (seconds, metres) >= 0, got {policy.still_gate}")
  if policy.max_curvature < 0:
    raise ValueError(f"max_curvature must be >= 0 (1/m; 0: off), got {policy.max_curvature}")
  most = min(policy.select_samples - 1, cfg.encoder.num_modes)
  if not 0 <= policy.warm_proposals <= most:
    raise ValueError(f"warm_proposals must be in [0, min(select_samples - 1, num_modes) = {most}], "
                     f"got {policy.warm_proposals}")
  policy.guidance.validate()


def controlled_or_default(state: SimulatorState, cfg: Config, controlled: Optional[Array] = None) -> Array:
  """(O,) the objects a stateless caller controls: `controlled` if given, else
  `state.object_metadata.is_controlled` where the caller set any, else the
  reactive set (`reactive_set`)."""
  if controlled is not None:
    return jnp.asarray(controlled, bool)
  marked = state.object_metadata.is_controlled
  return jnp.where(jnp.any(marked), marked, reactive_set(state, cfg))


def step(state: SimulatorState, models: Models, cfg: Config, rng: Array,
         policy: PolicyConfig = PolicyConfig(), road: Optional[RoadField] = None,
         controlled: Optional[Array] = None) -> tuple[Action, Array]:
  """One replanning for one scenario: the first planned action of the
  controlled agents (Action (O, 2), valid (O, 1)) and the controlled mask (O,).

  `step` keeps no memory between calls, so the caller says which agents it
  controls: `controlled` (O,) bool, by default `state.object_metadata.
  is_controlled` where any is set (as after `sim.step`), else the reactive set
  at this step. Those agents are modelled first (after the SDC), so a caller
  that passes the same mask at every step keeps the same agents; past the
  model's cap (`cfg.features.max_agents`, the SDC included) the farthest keep
  their speed and heading (zero action). Under guidance and with sample
  selection's map term (the default), pass road=`road_for(state, policy)`
  made once per scenario to avoid rebuilding the road field (about 1 s) at
  every call. A stateless call always
  plans cold (no warm start); the jerk limit applies (it reads the state)."""
  controlled = controlled_or_default(state, cfg, controlled)
  plan, planned, path = plan_actions(models, state, cfg, policy, rng,
                                     pursuer_of(state, cfg, policy.guidance), road=road,
                                     controlled=controlled)
  return _controlled_action(state, controlled, planned, _execute(state, plan, path, 0, policy, cfg)), controlled


def _execute(state: SimulatorState, plan: Array, path: Array, age, policy: PolicyConfig, cfg: Config) -> Array:
  """(O, 2) the actions executed now: the plan's step `age` (or pure pursuit
  of its path, execute="track"), within the jerk limit."""
  if policy.execute == "track":
    now = _track(state, path, age, policy.track_steps, cfg)
  else:
    now = jnp.take(plan, age, axis=1)
  if any(policy.jerk_limit):
    now = limit_jerk(state, now, policy.jerk_limit, cfg.kinematics.dt)
  if policy.stop_hold:
    now = hold_at_stop(state, now, cfg.kinematics.dt)
  if policy.start_gate[0] > 0:
    seconds, metres = policy.start_gate
    window = advance_plan(plan, age)[:, :max(1, round(seconds / cfg.kinematics.dt))]
    now = gate_start(state, now, window, metres, cfg.kinematics.dt)
  if policy.max_curvature > 0:
    now = limit_curvature(state, now, policy.max_curvature, cfg.kinematics.dt)
  return now


def limit_curvature(state: SimulatorState, actions: Array, max_curvature: float, dt: float) -> Array:
  """(O, 2) actions whose yaw rate a wheeled object can follow: a vehicle or
  cyclist turns only by moving, |psi_dot| <= max_curvature (1/m) x |its speed
  after this step's acceleration|. The kinematic model would otherwise spin a
  parked car in place, swinging its corners into its neighbours in a parking
  row. Pedestrians and other objects keep their yaw rate."""
  v = dynamics.states_from_trajectory(state.current_sim_trajectory)[:, 0, dynamics.V]
  speed = jnp.abs(v + actions[:, 0] * dt)
  types = state.object_metadata.object_types
  wheeled = (types == ObjectType.VEHICLE) | (types == ObjectType.CYCLIST)
  bound = jnp.where(wheeled, max_curvature * speed, jnp.inf)
  return actions.at[:, 1].set(jnp.clip(actions[:, 1], -bound, bound))


STOPPED_REVERSE_SPEED = 0.1   # m/s: slower reversing is a stop (float error, log noise), not a manoeuvre


def hold_at_stop(state: SimulatorState, actions: Array, dt: float) -> Array:
  """(O, 2) actions whose braking stops at standstill: an agent moving forward
  or stopped (signed speed v > -STOPPED_REVERSE_SPEED) gets an acceleration
  of at least -v / dt, so it ends the step at v >= 0 instead of backing up;
  an agent reversing faster is left alone."""
  v = dynamics.states_from_trajectory(state.current_sim_trajectory)[:, 0, dynamics.V]
  accel = actions[:, 0]
  return actions.at[:, 0].set(jnp.where(v > -STOPPED_REVERSE_SPEED, jnp.maximum(accel, -v / dt), accel))


START_GATE_SPEED = 0.5   # m/s: below it an agent is starting (or stopping), not driving


def gate_start(state: SimulatorState, actions: Array, window: Array, metres: float, dt: float) -> Array:
  """(O, 2) actions with the start gate (`PolicyConfig.start_gate`): an agent
  moving forward slower than START_GATE_SPEED (or stopped) whose plan window
  (O, H, 2) (its actions from now on) carries it less than `metres` (the
  speed floored at 0, as stop_hold does) does not speed up, and comes to a
  full stop below STOPPED_REVERSE_SPEED; faster or reversing agents keep
  their action. The yaw rate is untouched."""
  v = dynamics.states_from_trajectory(state.current_sim_trajectory)[:, 0, dynamics.V]
  speeds = jnp.maximum(v[:, None] + jnp.cumsum(window[..., 0], axis=1) * dt, 0.0)     # (O, H)
  slow = (v > -STOPPED_REVERSE_SPEED) & (v < START_GATE_SPEED)
  gated = slow & (jnp.sum(speeds, axis=1) * dt < metres)
  accel = jnp.where(v < STOPPED_REVERSE_SPEED, -v / dt, jnp.minimum(actions[:, 0], 0.0))
  return actions.at[:, 0].set(jnp.where(gated, accel, actions[:, 0]))


def executed_accel(state: SimulatorState, dt: float) -> Array:
  """(O,) each object's acceleration along its heading over the last step
  (0 at the first step of a log and where either step is invalid)."""
  sim = state.sim_trajectory
  fields = (sim.vel_x, sim.vel_y, sim.yaw, sim.valid)      # only what the speeds need, not every field
  (vx, vy, yaw, ok), (vx0, vy0, yaw0, ok0) = (
      [a[..., 0] for a in datatypes.slice_time(fields, t)]
      for t in (state.timestep, jnp.maximum(state.timestep - 1, 0)))
  speed = lambda x, y, heading: x * jnp.cos(heading) + y * jnp.sin(heading)
  valid = ok & ok0 & (state.timestep > 0)
  return jnp.where(valid, (speed(vx, vy, yaw) - speed(vx0, vy0, yaw0)) / dt, 0.0)


def limit_jerk(state: SimulatorState, actions: Array, limit, dt: float) -> Array:
  """(O, 2) actions whose acceleration is kept within [a - fall * dt,
  a + rise * dt] of the executed one a (`executed_accel`); limit (rise,
  fall) in m/s^3, 0 for no limit on that side."""
  rise, fall = limit
  accel, last = actions[:, 0], executed_accel(state, dt)
  if rise > 0:
    accel = jnp.minimum(accel, last + rise * dt)
  if fall > 0:
    accel = jnp.maximum(accel, last - fall * dt)
  return actions.at[:, 0].set(accel)


def _controlled_action(state: SimulatorState, controlled: Array, planned: Array, now: Array) -> Action:
  """Action (O, 2): the plan's for planned agents; a controlled agent the plan
  missed (more controlled agents than the model's cap) keeps its speed and
  heading (zero action) rather than vanish. Valid for every controlled agent
  alive at this step."""
  valid = controlled & state.current_sim_trajectory.valid[..., 0]
  return Action(data=jnp.where((valid & planned)[:, None], now, 0.0), valid=valid[:, None])
