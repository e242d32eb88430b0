"""The Waymax actor contract.

An actor has `init(rng, state) -> actor_state` and
`select_action(params, state, actor_state, rng) -> ActorOutput`, where the
output holds the new actor state, an `Action` (..., O, D) and the objects it
controls, `is_controlled` (..., O). Objects no actor controls follow the log.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Callable, Sequence

import jax.numpy as jnp
from flax import struct

from pcdiff_jax.sim.datatypes import Action, Array, SimulatorState


@struct.dataclass
class ActorOutput:
  actor_state: Any
  action: Action
  is_controlled: Array


def _no_state(rng, state):
  del rng, state
  return None


@dataclasses.dataclass(frozen=True)
class Actor:
  """A pure actor: two functions and a name (Waymax's WaymaxActorCore).

  action_space: what its actions mean. Every actor of this package emits
  "accel_yaw_rate", [a, psi_dot] for `dynamics.KinematicModel` (our native
  space); `sim.action_spaces.adapt` turns one into another space (Waymax's
  bicycle or delta models). `env.rollout` refuses an actor whose space is
  not its dynamics model's."""
  select_action: Callable[[Any, SimulatorState, Any, Array], ActorOutput]
  init: Callable[[Array, SimulatorState], Any] = _no_state
  name: str = "actor"
  action_space: str = "accel_yaw_rate"


def merge_outputs(outputs: Sequence[ActorOutput]) -> ActorOutput:
  """Combines actors that control disjoint objects (later ones win on overlap).

  Actions must share D. actor_state becomes a tuple of the actors' states.
  """
  data = outputs[0].action.data
  valid = outputs[0].action.valid
  controlled = outputs[0].is_controlled
  for out in outputs[1:]:
    mask = out.is_controlled[..., None]
    data = jnp.where(mask, out.action.data, data)
    valid = jnp.where(mask, out.action.valid, valid)
    controlled = controlled | out.is_controlled
  return ActorOutput(actor_state=tuple(o.actor_state for o in outputs),
                     action=Action(data=data, valid=valid), is_controlled=controlled)


def combine(actors: Sequence[Actor], name: str = "combined") -> Actor:
  """One actor running several, e.g. a fixed ego policy plus reactive agents."""
  def init(rng, state):
    return tuple(a.init(rng, state) for a in actors)

  def select_action(params, state, actor_state, rng):
    params = params if isinstance(params, tuple) else (params,) * len(actors)
    outs = [a.select_action(p, state, s, rng) for a, p, s in zip(actors, params, actor_state)]
    return merge_outputs(outs)

  spaces = {a.action_space for a in actors}
  if len(spaces) > 1:
    raise ValueError(f"actors emit different action spaces {sorted(spaces)}: adapt them to one")
  return Actor(select_action=select_action, init=init, name=name, action_space=spaces.pop())
