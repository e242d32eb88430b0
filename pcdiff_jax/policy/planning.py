"""Planning: encode the scene -> sample joint latent plans with DDIM -> decode them into actions.

A plan covers the A agents the encoder models (the SDC in slot 0, then the controlled agents,
then the nearest others as context); `decode` scatters it back to the scene's O objects.
Sample selection (`policy.selection`) sits between `sample` and `decode`.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.config import Config, KinematicsConfig
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.model import guidance as guidance_lib
from pcdiff_jax.model import latent, planner
from pcdiff_jax.model.planner import Models
from pcdiff_jax.policy import selection
from pcdiff_jax.policy.config import PolicyConfig
from pcdiff_jax.sim import dynamics
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState
from pcdiff_jax.sim.road_field import RoadField

START_GATE_SPEED = 0.5   # m/s: below it an agent is starting (or stopping), not driving
STEADY_SPEED_TOLERANCE = 0.5   # m/s: a walker's tracked speed this far from its recent one is noise


@struct.dataclass
class Encoded:
  """One scene as the sampler sees it: feats the agents' and map's features (unbatched, A
  agents); batched the same repeated S = select_samples times (S, ...); cond the encoder's
  conditioning for them (S, ...), centred as policy.prior_centre says; hold (A,) the agents the
  still gate stops, or None without it."""
  feats: features_lib.SceneFeatures
  batched: features_lib.SceneFeatures
  cond: planner.Conditioning
  hold: Optional[Array]


@struct.dataclass
class WarmStart:
  """A previous plan to start from: actions (O, T, 2) already advanced to the
  current step (`advance_plan`) and which objects have one, has (O,)."""
  actions: Array
  has: Array


def recent_history(feats, steps: int):
  """feats (..., A, H, ...) with only the last `steps` history steps valid (0: all kept)."""
  return feats if steps <= 0 else features_lib.hide_history(feats, steps)


def encode(models: Models, state: SimulatorState, cfg: Config, policy: PolicyConfig,
           controlled: Optional[Array] = None) -> Encoded:
  """The scene at its current step, encoded: controlled (O,) objects are modelled first after
  the SDC, whatever their distance."""
  feats = features_lib.scene_features(state, cfg.features, keep=controlled)
  batched = jax.tree_util.tree_map(lambda a: a[None], feats)
  cond = planner.condition(models.encoder, models.stats, recent_history(batched, policy.encoder_history), cfg)
  hold = None
  if policy.still_gate[0] > 0:
    hold = still_agents(cond, models.stats, cfg, *policy.still_gate)[0]                  # (A,)
  if policy.prior_centre == "top1":
    cond = planner.centre_on_top_mode(cond)
  if policy.select_samples > 1:   # S candidate plans as a batch of S copies of the scene
    batched = jax.tree_util.tree_map(lambda a: jnp.repeat(a, policy.select_samples, axis=0), batched)
    cond = planner.repeat_samples(cond, policy.select_samples)
  return Encoded(feats=feats, batched=batched, cond=cond, hold=hold)


def sample(models: Models, scene: Encoded, cfg: Config, policy: PolicyConfig, rng: Array,
           adversary: Array, road: RoadField, noise: Optional[Array] = None,
           warm: Optional[WarmStart] = None) -> Array:
  """(S, A, d) joint latent plans, guided by policy.guidance (`adversary`: the pursuer's object
  slot under adversarial guidance; road: the scene's road field). noise (O, d): per-object
  initial noise (consistent_noise), default drawn from rng. warm: a previous plan to start from
  (warm_start), else the prior; the plan is cold when no modelled agent has a previous one.
  A denoiser with anchor inputs gets them here (`planner.draw_anchor`); pedestrians go on their
  proposals as policy.pedestrian_plan says and cyclists as policy.cyclist_plan says
  (`on_proposals`), unguided plans only."""
  feats, cond = scene.feats, scene.cond
  init_noise = None if noise is None else noise[feats.agent_index][None]   # (1, A, d)
  if init_noise is not None and policy.select_samples > 1:
    # Sample k starts from the consistent noise rolled by k over the agents: another
    # Gaussian draw per agent, still a function of the rollout's noise (not of rng).
    init_noise = jnp.concatenate([jnp.roll(init_noise, k, axis=1) for k in range(policy.select_samples)])
  k_anchor = jax.random.fold_in(rng, 1)   # rng itself untouched: models without anchors draw as before
  previous = has = None
  if warm is not None:
    previous = latent.encode(warm.actions[feats.agent_index], models.stats)[None]   # (1, A, d)
    has = warm.has[feats.agent_index] & feats.agent_valid
  cond = planner.draw_anchor(cond, cfg, k_anchor, previous, has, policy.anchor_tau,
                              policy.anchor_temperature)
  guide = _guide(models, scene.batched, cond, cfg, policy.guidance, jnp.asarray(adversary, jnp.int32), road)
  g = policy.guidance
  if warm is None:
    steps = g.guide_steps(policy.ddim_steps) if guide is not None else None
    y0 = planner.sample(models.denoiser, cond, cfg, rng, policy.ddim_steps, policy.eta,
                        prior_init=policy.prior_init, guide=guide, guide_steps=steps,
                        init_noise=init_noise)
  else:
    centre = warm_centres(cond, previous, has)
    y0 = planner.sample_cold_or_warm(
        models.denoiser, cond, cfg, rng, ~jnp.any(has), centre, policy.ddim_steps,
        policy.warm_ddim_steps, policy.warm_step, policy.eta, prior_init=policy.prior_init,
        guide=guide, cold_guide_steps=g.guide_steps(policy.ddim_steps) if guide is not None else None,
        warm_guide_steps=g.guide_steps(policy.warm_ddim_steps) if guide is not None else None,
        init_noise=init_noise)
  k_walk = jax.random.fold_in(rng, 2)   # rng itself untouched: "sample" draws as before
  # A proposal bypasses the guidance, so a guided plan keeps every agent's guided sample.
  walk = policy.pedestrian_plan if guide is None else "sample"
  ride = policy.cyclist_plan if guide is None else "sample"
  y0 = on_proposals(y0, cond, feats, walk, k_walk, previous, has, models.stats, cfg.kinematics,
                    policy.pedestrian_steady_travel)
  return on_proposals(y0, cond, feats, ride, jax.random.fold_in(rng, 3), previous, has, models.stats,
                      cfg.kinematics, kind=ObjectType.CYCLIST)


def on_proposals(y0: Array, cond: planner.Conditioning, feats, how: str, rng: Array,
                 previous: Optional[Array] = None, has: Optional[Array] = None,
                 stats: Optional[latent.LatentStats] = None,
                 kinematics: KinematicsConfig = KinematicsConfig(),
                 steady_travel: float = 0.0, kind: int = ObjectType.PEDESTRIAN) -> Array:
  """(S, A, d) the samples y0 with each agent of this `kind` (pedestrians by default, as
  `PolicyConfig.pedestrian_plan` says; cyclists as `cyclist_plan` says) on one of its
  proposals: "top", its likeliest in every sample; "drawn", in sample 0 its mode (the
  likeliest, or at a warm replan the one nearest its previous plan (1, A, d) where has (A,))
  and in each other sample one drawn by probability, for the selection to choose from;
  "mixed", so in the first half of the samples and the denoiser's in the rest, so the
  selection can still move an agent off proposals that all run into something; "steady" as
  "mixed" with the agent's steady plan (its speed and heading held: zero actions, encoded with
  stats) in sample 0 where it holds its pace (`holds_pace`, steady_travel its min_travel) and
  its mode in sample 1; "sample" keeps y0. docs/RESULTS.md, "Ablation: pedestrians on their
  proposals", "Ablation: a walker's steady plan" and "Ablation: a cyclist's steady plan"."""
  if how == "sample":
    return y0
  index = jnp.broadcast_to(jnp.argmax(cond.probs, -1), y0.shape[:-1])               # (S, A)
  if how in ("drawn", "mixed", "steady"):
    mode = index
    if previous is not None:
      mode = jnp.where(has[None], planner.nearest_proposal(cond, jnp.broadcast_to(previous, y0.shape)), index)
    drawn = jax.random.categorical(rng, jnp.log(jnp.maximum(cond.probs, 1e-9)))      # (S, A)
    on_mode = 2 if how == "steady" else 1   # the samples on the mode
    index = jnp.where((jnp.arange(y0.shape[0]) < on_mode)[:, None], mode, drawn)
  chosen = jnp.take_along_axis(jnp.broadcast_to(cond.proposals, y0.shape[:-1] + cond.proposals.shape[-2:]),
                               index[..., None, None], axis=-2)[..., 0, :]          # (S, A, d)
  if how == "steady":
    steady = latent.encode(jnp.zeros((stats.horizon, 2)), stats)                    # (d,)
    mode_plan = chosen[min(1, y0.shape[0] - 1)]                                      # (A, d)
    holds = holds_pace(mode_plan, cond.speed[0], feats, stats, kinematics, steady_travel)  # (A,)
    chosen = chosen.at[0].set(jnp.where(holds[:, None], steady, chosen[0]))
  walker = feats.agent_valid & (feats.agent_types == kind)                           # (A,)
  on_proposal = walker[None, :, None]
  if how in ("mixed", "steady"):
    on_proposal = on_proposal & (jnp.arange(y0.shape[0]) < max(y0.shape[0] // 2, 1))[:, None, None]
  return jnp.where(on_proposal, chosen, y0)


def holds_pace(mode: Array, speed: Array, feats, stats: latent.LatentStats,
               kinematics: KinematicsConfig, min_travel: float = 0.0) -> Array:
  """(A,) the agents a steady plan suits: the tracked speed (A,) is that of the last second of
  positions (`recent_speed`; a jittery track's is noise) and, with min_travel > 0, the mode
  (A, d), which reads the map and the lights, travels at least that share of the steady plan's
  distance (a walker that reaches the kerb to wait keeps its mode)."""
  ok = jnp.abs(jnp.abs(speed) - recent_speed(feats, kinematics.dt)) < STEADY_SPEED_TOLERANCE
  if min_travel > 0:
    end = latent.rollout(mode, speed, stats, kinematics)[..., -1, :2]               # (A, 2)
    ok &= jnp.linalg.norm(end, axis=-1) >= min_travel * jnp.abs(speed) * stats.horizon * kinematics.dt
  return ok


def recent_speed(feats, dt: float, seconds: float = 1.0) -> Array:
  """(A,) each agent's mean speed over its last `seconds` of history positions (as far back as
  it is valid; 0 with no earlier step)."""
  hist, valid = feats.agent_history[..., :2], feats.agent_history_valid            # (A, H, 2), (A, H)
  now = hist.shape[-2] - 1
  steps = jnp.arange(hist.shape[-2])
  earliest = jnp.min(jnp.where(valid & (steps >= now - round(seconds / dt)), steps, now), -1)  # (A,)
  back = jnp.take_along_axis(hist, earliest[:, None, None], axis=-2)[:, 0]        # (A, 2)
  span = jnp.maximum(now - earliest, 1) * dt
  return jnp.where(earliest < now, jnp.linalg.norm(hist[:, now] - back, axis=-1) / span, 0.0)


def decode(y0: Array, models: Models, scene: Encoded, state: SimulatorState, cfg: Config,
           policy: PolicyConfig) -> tuple[Array, Array, Array]:
  """The chosen plan y0 (1, A, d) per object: actions (O, T, 2) (zeros where not planned;
  the still gate's agents brake to a stop and hold), which objects got a plan (O,), and the
  planned positions (O, T, 2) in the world frame (zeros unless policy.execute is "track")."""
  feats, cond = scene.feats, scene.cond
  actions = dynamics.clip_action(latent.decode(y0[0], models.stats), cfg.kinematics)  # (A, T, 2)
  if scene.hold is not None:
    actions = jnp.where(scene.hold[:, None, None], stop_plan(cond.speed[0], actions.shape[1], cfg), actions)
  if policy.execute == "track":   # the world-frame path is only needed to track it
    states = dynamics.rollout(latent.initial_states(cond.speed[0]), actions, cfg.kinematics.dt)
    path, _ = features_lib.agent_to_world(states[..., :2], states[..., 2], feats)      # (A, T, 2)
  else:
    path = jnp.zeros_like(actions)
  num_objects = state.object_metadata.ids.shape[-1]
  per_object = features_lib.scatter_to_objects(actions, feats, num_objects)
  planned = features_lib.scatter_to_objects(feats.agent_valid, feats, num_objects, fill=False)
  return per_object, planned.astype(bool), features_lib.scatter_to_objects(path, feats, num_objects)


def plan_actions(models: Models, state: SimulatorState, cfg: Config, policy: PolicyConfig,
                 rng: Array, adversary: Array = -1, noise: Optional[Array] = None,
                 road: Optional[RoadField] = None, controlled: Optional[Array] = None,
                 warm: Optional[WarmStart] = None) -> tuple[Array, Array, Array]:
  """A joint plan for one scene at its current step: encode -> sample -> select -> decode.
  road: the scene's road field, default built here (a field per call); the other arguments as
  `encode` and `sample` take them. Returns `decode`'s actions (O, T, 2), planned (O,) and
  path (O, T, 2)."""
  if road is None:
    road = road_for(state, policy)
  scene = encode(models, state, cfg, policy, controlled)
  y0 = sample(models, scene, cfg, policy, rng, adversary, road, noise, warm)
  y0 = selection.select(y0, models, scene, cfg, policy, adversary, road)
  return decode(y0, models, scene, state, cfg, policy)


def _guide(models: Models, feats, cond: planner.Conditioning, cfg: Config,
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


def advance_plan(plan: Array, executed: Array) -> Array:
  """(O, T, 2) the plan without its first `executed` actions (a traced int),
  the freed tail holding the last state (zero actions)."""
  horizon = plan.shape[1]
  idx = executed + jnp.arange(horizon)                                       # (T,)
  shifted = jnp.take(plan, jnp.clip(idx, 0, horizon - 1), axis=1)
  return jnp.where((idx < horizon)[None, :, None], shifted, 0.0)


def warm_centres(cond: planner.Conditioning, previous: Array, has: Array) -> Array:
  """(S, A, d) where each of the S samples of a warm replan starts (before
  noising): the previous plan's latent previous (1, A, d) where an agent has
  one (has (A,)), else its prior centre (cond.mu (S, A, d))."""
  return jnp.broadcast_to(jnp.where(has[None, :, None], previous, cond.mu), cond.mu.shape)


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


def road_for(state: SimulatorState, policy: PolicyConfig) -> RoadField:
  """The scene's road field as the policy needs it: guidance's, or the one
  sample selection's map term reads (the same field), else a placeholder."""
  g = policy.guidance
  if g.mode == "none" and policy.select_samples > 1 and policy.select_map_weight > 0:
    g = dataclasses.replace(g, mode="objective")   # road_of builds the field for any guided mode
  return guidance_lib.road_of(state, g)


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
