"""Waymax's own pytree classes for an actor's output, so it mixes with Waymax's actors.

Waymax's `agents.merge_actions([expert_output, ours])` tree-maps the actions of
its inputs against each other, so every action must be the same pytree class,
`waymax.datatypes.Action`. Ours (`sim.datatypes.Action`) has the same fields
but is another class, and the merge raises a pytree-structure ValueError.

`as_waymax_actor(actor)` returns an actor whose `select_action` gives
`waymax.agents.WaymaxActorOutput(actor_state, action=waymax.datatypes.Action(
data, valid), is_controlled)` when Waymax is importable, and the actor
unchanged (our classes, the same fields) when it is not. The leaves, and so
every number, are the same either way.
"""
from __future__ import annotations

import importlib.util
from typing import Any, Optional

from pcdiff_jax.sim.actors import Actor


def waymax_classes() -> Optional[tuple[type, type]]:
  """(waymax.agents.WaymaxActorOutput, waymax.datatypes.Action), or None when
  Waymax is not installed or does not import (e.g. a missing dependency)."""
  if importlib.util.find_spec("waymax") is None:
    return None
  try:
    from waymax import agents, datatypes
  except ImportError:
    return None
  return agents.WaymaxActorOutput, datatypes.Action


def to_waymax_output(out: Any, classes: tuple[type, type]) -> Any:
  """An ActorOutput with fields actor_state, action (data, valid),
  is_controlled, rebuilt as Waymax's classes (`classes`: `waymax_classes()`)."""
  output_cls, action_cls = classes
  return output_cls(actor_state=out.actor_state, is_controlled=out.is_controlled,
                    action=action_cls(data=out.action.data, valid=out.action.valid))


def as_waymax_actor(actor: Actor) -> Actor:
  """`actor` emitting Waymax's WaymaxActorOutput / Action when Waymax is
  importable (for `waymax.agents.merge_actions`), else `actor` itself.
  Name, init and action_space are kept; the conversion is traced (no copy)."""
  classes = waymax_classes()
  if classes is None:
    return actor

  def select_action(params, state, actor_state, rng):
    return to_waymax_output(actor.select_action(params, state, actor_state, rng), classes)

  return Actor(select_action=select_action, init=actor.init, name=actor.name, action_space=actor.action_space)
