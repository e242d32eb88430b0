"""The policy as Waymax-style actors, and `step`, one stateless replanning.

Each reads as the recipe: encode -> sample -> select -> decode (`planning`, `selection`), then
the filters on the executed action (`execution`).
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.config import Config
from pcdiff_jax.model.planner import Models
from pcdiff_jax.policy import execution, planning, selection
from pcdiff_jax.policy.config import PolicyConfig, validate
from pcdiff_jax.policy.planning import reactive_set
from pcdiff_jax.sim import action_spaces
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, Array, SimulatorState
from pcdiff_jax.sim.road_field import RoadField


@struct.dataclass
class PlanState:
  """Actor state for one scenario: controlled (O,) fixed set; plan (O, T, 2)
  actions of the last plan; plan_valid (O,); age () steps since it was made;
  adversary () object slot of the pursuer under adversarial guidance (-1: none);
  noise (O, d) each object's initial DDIM noise (consistent_noise); road the
  scene's road signed-distance field for guidance, built once at `init`;
  path (O, T, 2) the last plan's positions in the world frame (execute="track"); accel (O,)
  the acceleration executed at the last step before the follow bound, before the first step
  the log's trend (`execution.logged_accel`): the jerk limit's reference."""
  controlled: Array
  plan: Array
  path: Array
  plan_valid: Array
  age: Array
  adversary: Array
  noise: Array
  road: RoadField
  accel: Array


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
  every call. A stateless call always plans cold (no warm start); the filters
  on the executed action apply (they read the state)."""
  controlled = controlled_or_default(state, cfg, controlled)
  road = planning.road_for(state, policy) if road is None else road
  adversary = planning.pursuer_of(state, cfg, policy.guidance)
  scene = planning.encode(models, state, cfg, policy, controlled)
  y0 = planning.sample(models, scene, cfg, policy, rng, adversary, road)               # (S, A, d)
  y0 = selection.select(y0, models, scene, cfg, policy, adversary, road)               # (1, A, d)
  plan, planned, path = planning.decode(y0, models, scene, state, cfg, policy)         # (O, T, 2)
  now, _ = execution.execute(state, plan, path, 0, policy, cfg, followers=controlled & planned)   # (O, 2)
  return execution.controlled_action(state, controlled, planned, now), controlled


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
                     adversary=planning.pursuer_of(state, cfg, policy.guidance),
                     noise=jax.random.normal(jax.random.fold_in(rng, 1), (num_objects, cfg.diffusion.latent_dim)),
                     road=planning.road_for(state, policy),
                     accel=execution.logged_accel(state, cfg.kinematics.dt, bound=policy.jerk_start_bound))

  def replan(models, state, ps: PlanState, rng):
    """A new plan (O, T, 2), which objects have one (O,) and its path (O, T, 2), blended with
    the last plan (temporal ensemble)."""
    noise = ps.noise if policy.consistent_noise else None
    warm = _warm_start(ps) if policy.warm_start else None
    scene = planning.encode(models, state, cfg, policy, ps.controlled)
    y0 = planning.sample(models, scene, cfg, policy, rng, ps.adversary, ps.road, noise, warm)   # (S, A, d)
    y0 = selection.select(y0, models, scene, cfg, policy, ps.adversary, ps.road)               # (1, A, d)
    plan, plan_valid, path = planning.decode(y0, models, scene, state, cfg, policy)
    if any(policy.temporal_ensemble):
      plan = execution.ensemble_plans(ps.plan, ps.plan_valid, ps.age, plan, plan_valid, policy.temporal_ensemble)
    return plan, plan_valid, path

  def select_action(models, state, ps: PlanState, rng):
    due = ps.age >= policy.replan_every
    plan, plan_valid, path = jax.lax.cond(
        due, lambda: replan(models, state, ps, rng), lambda: (ps.plan, ps.plan_valid, ps.path))
    age = jnp.where(due, 0, ps.age)
    now, reference = execution.execute(state, plan, path, age, policy, cfg, ps.accel,
                                       ps.controlled & plan_valid)                          # (O, 2), (O,)
    action = execution.controlled_action(state, ps.controlled, plan_valid, now)
    accel = jnp.where(action.valid[:, 0], reference, jnp.nan)
    new = ps.replace(plan=plan, plan_valid=plan_valid, path=path, age=age + 1, accel=accel)
    return ActorOutput(actor_state=new, action=action, is_controlled=ps.controlled)

  name = "pcdiff" if policy.prior_init else "pcdiff-noprior"
  return Actor(select_action=select_action, init=init, name=name)


def _warm_start(ps: PlanState) -> planning.WarmStart:
  """The last plan advanced by the steps executed since, for the controlled agents that have one."""
  return planning.WarmStart(actions=planning.advance_plan(ps.plan, ps.age), has=ps.plan_valid & ps.controlled)


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


def controlled_or_default(state: SimulatorState, cfg: Config, controlled: Optional[Array] = None) -> Array:
  """(O,) the objects a stateless caller controls: `controlled` if given, else
  `state.object_metadata.is_controlled` where the caller set any, else the
  reactive set (`reactive_set`)."""
  if controlled is not None:
    return jnp.asarray(controlled, bool)
  marked = state.object_metadata.is_controlled
  return jnp.where(jnp.any(marked), marked, reactive_set(state, cfg))
