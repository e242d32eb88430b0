"""sim.waymax_interop: with Waymax importable, `policy.waymax_actor`'s output
goes straight into Waymax's own `agents.merge_actions`; without it the actor is
ours, unchanged. The leaves are the same either way."""
from __future__ import annotations

import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from conftest import make_scene
from pcdiff_jax import baselines, policy
from pcdiff_jax.config import get_config
from pcdiff_jax.sim import env, waymax_interop
from pcdiff_jax.sim.actors import ActorOutput

CFG = get_config("tiny")
PCFG = policy.PolicyConfig(ddim_steps=1, warm_start=False)
HAS_WAYMAX = waymax_interop.waymax_classes() is not None


@struct.dataclass
class _Output:   # stand-ins with Waymax's field names, another pytree class than ours
  actor_state: object
  action: object
  is_controlled: object


@struct.dataclass
class _Action:
  data: object
  valid: object


def test_without_waymax_the_actor_is_ours(monkeypatch):
  monkeypatch.setattr(waymax_interop, "waymax_classes", lambda: None)
  cv = baselines.constant_velocity(baselines.reactive_agents(3))
  assert waymax_interop.as_waymax_actor(cv) is cv


def test_outputs_are_rebuilt_as_the_given_classes_with_the_same_leaves(monkeypatch):
  monkeypatch.setattr(waymax_interop, "waymax_classes", lambda: (_Output, _Action))
  cv = baselines.constant_velocity(baselines.reactive_agents(3))
  wrapped = waymax_interop.as_waymax_actor(cv)
  assert (wrapped.name, wrapped.action_space, wrapped.init) == (cv.name, cv.action_space, cv.init)
  state = env.reset(make_scene(num_steps=91))
  key = jax.random.key(0)
  ours = cv.select_action(None, state, cv.init(key, state), key)
  theirs = jax.jit(wrapped.select_action)(None, state, cv.init(key, state), key)
  assert isinstance(ours, ActorOutput) and isinstance(theirs, _Output) and isinstance(theirs.action, _Action)
  for a, b in zip(jax.tree_util.tree_leaves(ours), jax.tree_util.tree_leaves(theirs)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


@pytest.mark.skipif(not HAS_WAYMAX, reason="waymax is not importable (it is not on the package registry: "
                                             "pip install git+https://github.com/waymo-research/waymax)")
def test_waymax_actor_output_goes_into_waymax_merge_actions(tiny_models):
  """Waymax's own merge_actions on [an expert-like output, ours]: no pytree
  error, and ours wins where it controls."""
  from waymax import agents, datatypes
  ours = policy.waymax_actor(CFG, PCFG, "bicycle")
  state = env.reset(make_scene(num_steps=91))
  key = jax.random.key(0)
  out = jax.jit(ours.select_action)(tiny_models, state, ours.init(key, state), key)
  assert isinstance(out, agents.WaymaxActorOutput) and isinstance(out.action, datatypes.Action)
  num_objects = out.is_controlled.shape[-1]
  expert = agents.WaymaxActorOutput(
      actor_state=None, is_controlled=~out.is_controlled,
      action=datatypes.Action(data=jnp.full((num_objects, 2), 7.0), valid=jnp.ones((num_objects, 1), bool)))
  merged = agents.merge_actions([expert, out])
  assert isinstance(merged, datatypes.Action)
  mine = np.asarray(out.is_controlled)
  assert mine.any() and not mine.all()
  np.testing.assert_array_equal(np.asarray(merged.data)[mine], np.asarray(out.action.data)[mine])
  np.testing.assert_array_equal(np.asarray(merged.data)[~mine], 7.0)
