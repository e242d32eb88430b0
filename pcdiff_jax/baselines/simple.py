"""Rule-free baselines: log replay, expert (inverse dynamics), constant velocity."""
from __future__ import annotations

from typing import Any, Callable

import jax.numpy as jnp

from pcdiff_jax.sim import action_spaces
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, SimulatorState, slice_time
from pcdiff_jax.sim.dynamics import KinematicModel
from pcdiff_jax.sim.selection import nearest_to_sdc

ControlledFn = Callable[[SimulatorState], Any]


def reactive_agents(max_agents: int = 64) -> ControlledFn:
  """The default controlled set: up to `max_agents` nearest the SDC, SDC excluded."""
  return lambda state: nearest_to_sdc(state, max_agents)


def _fixed_set(controlled_fn: ControlledFn):
  """Actor init that fixes the controlled set at the start of the rollout."""
  def init(rng, state):
    del rng
    return controlled_fn(state)
  return init


def _zero_action(state: SimulatorState, action_dim: int) -> Action:
  shape = state.object_metadata.ids.shape
  return Action(data=jnp.zeros(shape + (action_dim,), jnp.float32), valid=jnp.zeros(shape + (1,), bool))


def log_replay() -> Actor:
  """Controls nothing: every object follows its log."""
  def select_action(params, state, actor_state, rng):
    del params, rng
    return ActorOutput(actor_state=actor_state, action=_zero_action(state, 2),
                       is_controlled=jnp.zeros(state.object_metadata.ids.shape, bool))
  return Actor(select_action=select_action, name="log")


def expert(dynamics: Any = KinematicModel(), controlled_fn: ControlledFn = reactive_agents()) -> Actor:
  """Controls objects with the dynamics' inverse towards their logged next step
  (a zero action where the log has none).

  The controlled set is fixed when the rollout starts (`init`). Objects move
  by the simulator's dynamics, so this measures how well that
  model can reproduce the log in closed loop.
  """
  def select_action(params, state, actor_state, rng):
    del params, rng
    current = state.current_sim_trajectory
    target = slice_time(state.log_trajectory, state.timestep + 1)
    action = dynamics.inverse(current, target)
    # Where the log has no next step the object holds its motion (zero
    # action) instead of vanishing: a controlled object stays alive.
    alive = current.valid & actor_state[..., None]                       # (..., O, 1)
    data = jnp.where(target.valid & alive, action.data, 0.0)
    return ActorOutput(actor_state=actor_state, action=Action(data=data, valid=alive),
                       is_controlled=actor_state)
  return Actor(select_action=select_action, init=_fixed_set(controlled_fn), name="expert",
               action_space=getattr(dynamics, "action_space", action_spaces.NATIVE))


def constant_velocity(controlled_fn: ControlledFn = reactive_agents()) -> Actor:
  """Keeps each controlled object's current speed and heading.

  The controlled set is fixed when the rollout starts (`init`). Emits the
  zero action [a, psi_dot] = 0 of the kinematic model (also constant
  velocity under Waymax's bicycle model).
  """
  def select_action(params, state, actor_state, rng):
    del params, rng
    controlled = actor_state
    action = Action(data=jnp.zeros(controlled.shape + (2,), jnp.float32),
                    valid=state.current_sim_trajectory.valid & controlled[..., None])
    return ActorOutput(actor_state=actor_state, action=action, is_controlled=controlled)
  return Actor(select_action=select_action, init=_fixed_set(controlled_fn), name="cv")


def waymax_actor(actor: Actor, dynamics_model: Any) -> Actor:
  """A baseline (native [a, psi_dot] actions: cv, idm, simpl_ar, expert with
  our KinematicModel) for an environment stepping `dynamics_model`: Waymax's
  InvertibleBicycleModel, DeltaLocal or DeltaGlobal, or their space names
  (`sim.action_spaces.adapt`)."""
  return action_spaces.adapt(actor, dynamics_model)
