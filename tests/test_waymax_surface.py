"""Every public entry point runs on states whose classes have exactly Waymax's
surface (../shared/WAYMAX_API.md: the fields, the listed properties,
`validate()` and `replace()`, nothing more), under jit and vmap; the loader
and reset fill states as Waymax's do; the Waymax example runs where Waymax is
installed.

The classes below are minimal stand-ins written from that table (not
Waymax's code): a property our library used that Waymax lacks (say
`current_traffic_light`) fails here with AttributeError.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import subprocess
import sys
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from conftest import ROOT, make_scene
from pcdiff_jax import baselines, metrics, policy, viz
from pcdiff_jax.baselines import idm, simpl_ar
from pcdiff_jax.config import get_config
from pcdiff_jax.model import features
from pcdiff_jax.sim import env, geometry
from pcdiff_jax.sim.datatypes import slice_time

CFG = get_config("tiny")
PCFG = policy.PolicyConfig(ddim_steps=1, warm_start=False)


@struct.dataclass
class Trajectory:
  x: Any
  y: Any
  z: Any
  vel_x: Any
  vel_y: Any
  yaw: Any
  valid: Any
  timestamp_micros: Any
  length: Any
  width: Any
  height: Any

  shape = property(lambda self: tuple(self.x.shape))
  num_objects = property(lambda self: self.x.shape[-2])
  num_timesteps = property(lambda self: self.x.shape[-1])
  xy = property(lambda self: jnp.stack([self.x, self.y], -1))
  xyz = property(lambda self: jnp.stack([self.x, self.y, self.z], -1))
  vel_xy = property(lambda self: jnp.stack([self.vel_x, self.vel_y], -1))
  speed = property(lambda self: jnp.hypot(self.vel_x, self.vel_y))
  vel_yaw = property(lambda self: jnp.arctan2(self.vel_y, self.vel_x))
  bbox_corners = property(lambda self: geometry.box_corners(self.x, self.y, self.yaw, self.length, self.width))

  def validate(self):
    pass


@struct.dataclass
class ObjectMetadata:
  ids: Any
  object_types: Any
  is_sdc: Any
  is_modeled: Any
  is_valid: Any
  objects_of_interest: Any
  is_controlled: Any

  shape = property(lambda self: tuple(self.ids.shape))
  num_objects = property(lambda self: self.ids.shape[-1])

  def validate(self):
    pass


@struct.dataclass
class RoadgraphPoints:
  x: Any
  y: Any
  z: Any
  dir_x: Any
  dir_y: Any
  dir_z: Any
  types: Any
  ids: Any
  valid: Any

  shape = property(lambda self: tuple(self.x.shape))
  num_points = property(lambda self: self.x.shape[-1])
  xy = property(lambda self: jnp.stack([self.x, self.y], -1))
  xyz = property(lambda self: jnp.stack([self.x, self.y, self.z], -1))
  dir_xy = property(lambda self: jnp.stack([self.dir_x, self.dir_y], -1))
  dir_xyz = property(lambda self: jnp.stack([self.dir_x, self.dir_y, self.dir_z], -1))

  def validate(self):
    pass


@struct.dataclass
class TrafficLights:
  x: Any
  y: Any
  z: Any
  state: Any
  lane_ids: Any
  valid: Any

  shape = property(lambda self: tuple(self.x.shape))
  num_timesteps = property(lambda self: self.x.shape[-1])
  num_traffic_lights = property(lambda self: self.x.shape[-2])
  xy = property(lambda self: jnp.stack([self.x, self.y], -1))

  def validate(self):
    pass


@struct.dataclass
class SimulatorState:
  sim_trajectory: Trajectory
  log_trajectory: Trajectory
  log_traffic_light: TrafficLights
  object_metadata: ObjectMetadata
  timestep: Any
  sdc_paths: Optional[Any] = None
  roadgraph_points: Optional[RoadgraphPoints] = None

  shape = property(lambda self: self.object_metadata.shape[:-1])
  batch_dims = property(lambda self: self.shape)
  num_objects = property(lambda self: self.object_metadata.num_objects)
  is_done = property(lambda self: self.timestep + 1 >= self.log_trajectory.num_timesteps)
  remaining_timesteps = property(lambda self: self.log_trajectory.num_timesteps - self.timestep - 1)
  current_sim_trajectory = property(lambda self: slice_time(self.sim_trajectory, self.timestep))
  current_log_trajectory = property(lambda self: slice_time(self.log_trajectory, self.timestep))

  def validate(self):
    pass


def surface_only(state) -> SimulatorState:
  """Our state (any batch dims) rebuilt with the minimal classes above."""
  def rebuild(cls, obj):
    return cls(**{f.name: getattr(obj, f.name) for f in dataclasses.fields(cls)})
  return SimulatorState(
      sim_trajectory=rebuild(Trajectory, state.sim_trajectory),
      log_trajectory=rebuild(Trajectory, state.log_trajectory),
      log_traffic_light=rebuild(TrafficLights, state.log_traffic_light),
      object_metadata=rebuild(ObjectMetadata, state.object_metadata),
      timestep=state.timestep, roadgraph_points=rebuild(RoadgraphPoints, state.roadgraph_points))


def test_the_stand_ins_have_no_more_than_waymax():
  extra = {"current_traffic_light", "total_timesteps", "sdc_index", "zeros", "FLOAT_FIELDS"}
  for cls in (Trajectory, ObjectMetadata, RoadgraphPoints, TrafficLights, SimulatorState):
    assert not extra & set(dir(cls)), cls
  with pytest.raises(AttributeError):
    surface_only(make_scene()).current_traffic_light   # noqa: B018


def _batch(states):
  return jax.tree_util.tree_map(lambda *xs: jnp.stack(xs), *states)


def test_entry_points_on_waymax_surface_jit_and_vmap(tiny_models, tmp_path):
  """reset, features, the policy's actor (through the Waymax bicycle adapter,
  which wraps `policy.actor`), every baseline and a step, jitted and vmapped
  over a batch of two surface-only scenes (one compile); viz on one of them."""
  loaded = _batch([make_scene(num_steps=91), make_scene(num_steps=91, speeds=(6.0, 7.0, 1.0, 3.0))])
  keys = jax.random.split(jax.random.key(0), 2)
  actors = {
      "pcdiff-bicycle": (policy.waymax_actor(CFG, PCFG, "bicycle"), tiny_models),
      "cv": (baselines.constant_velocity(baselines.reactive_agents(3)), None),
      "expert": (baselines.expert(controlled_fn=baselines.reactive_agents(3)), None),
      "log": (baselines.log_replay(), None),
      "idm": (idm.idm(controlled_fn=baselines.reactive_agents(3)), None),
      "simpl-ar": (simpl_ar.simpl_ar(CFG), tiny_models.encoder),
  }

  @jax.jit
  def run(loaded, keys):
    state = env.reset(loaded)                                                # batched (2,)
    feats = jax.vmap(lambda s: features.scene_features(s, CFG.features))(state)
    outs = {}
    for name, (actor, params) in actors.items():
      init = jax.vmap(actor.init)(keys, state)
      outs[name] = jax.vmap(actor.select_action, in_axes=(None, 0, 0, 0))(params, state, init, keys)
    return state, feats, outs, env.step(state, outs["idm"].action, outs["idm"].is_controlled)

  state, feats, outs, nxt = run(surface_only(loaded), keys)
  assert type(state).__name__ == "SimulatorState" and state.shape == (2,)
  assert feats.agent_valid.shape == (2, CFG.features.max_agents) and bool(feats.agent_valid[:, 0].all())
  for name, out in outs.items():
    assert bool(jnp.all(jnp.isfinite(out.action.data))), name
    assert out.action.valid.shape == (2, 4, 1), name
  assert outs["pcdiff-bicycle"].action.data.shape == (2, 4, 2)
  assert bool(outs["pcdiff-bicycle"].is_controlled[:, 1:].all())
  assert int(nxt.timestep[0]) == 11 and type(nxt).__name__ == "SimulatorState"
  one = jax.tree_util.tree_map(lambda a: a[0], nxt)
  assert viz.render_scene_png(one, tmp_path / "scene.png", timestep=11).exists()
  assert viz.render_rollout_gif(one, tmp_path / "roll.gif", start=10, stop=11).exists()


def test_entry_points_on_the_real_record(real_state, tiny_models):
  """The real record as a surface-only state: `policy.step` (jitted), a short
  closed loop (one lax.scan) and its scores."""
  state = surface_only(env.reset(real_state))
  action, controlled = jax.jit(lambda s, k: policy.step(s, tiny_models, CFG, k, PCFG))(state, jax.random.key(0))
  assert action.data.shape == (128, 2) and int(controlled.sum()) == CFG.features.max_agents - 1
  assert bool(jnp.all(jnp.isfinite(action.data)))

  @jax.jit
  def roll_and_score(s):
    final = env.rollout(s, baselines.constant_velocity(), 2, jax.random.key(1)).final_state
    return final, metrics.score_rollout(final, 10, 2, 64, 256)
  final, scores = roll_and_score(state)
  assert type(final).__name__ == "SimulatorState" and int(scores.lost.sum()) == 0


def test_a_simulated_start_on_waymax_surface():
  """`env.simulated_start` (reset, then the start velocity from positions and the headings) takes
  a surface-only state, as a Waymax rollout's reset state: object 1's tracked 14 m/s, which its
  positions (8 m/s) contradict, becomes 8."""
  loaded = make_scene(num_steps=91)
  log = loaded.log_trajectory
  loaded = loaded.replace(log_trajectory=log.replace(vel_x=log.vel_x.at[1, 10].set(14.0)))
  start = jax.jit(lambda s: env.simulated_start(s, 11))(surface_only(loaded))
  assert type(start).__name__ == "SimulatorState" and int(start.timestep) == 10
  np.testing.assert_allclose(float(start.sim_trajectory.vel_x[1, 10]), 8.0, atol=1e-3)


def test_reset_fills_like_waymax(real_state):
  """After reset: timestep 10, the log up to it; after it -1 in every float
  field and timestamp, invalid; is_controlled all False until a step sets it."""
  s = env.reset(real_state)
  assert int(s.timestep) == 10
  sim, log = s.sim_trajectory, s.log_trajectory
  for name in ("x", "y", "z", "vel_x", "vel_y", "yaw", "length", "width", "height", "timestamp_micros", "valid"):
    a, b = np.asarray(getattr(sim, name)), np.asarray(getattr(log, name))
    np.testing.assert_array_equal(a[:, :11], b[:, :11], err_msg=name)
    np.testing.assert_array_equal(a[:, 11:], False if name == "valid" else -1, err_msg=name)
  assert not np.asarray(s.object_metadata.is_controlled).any()


@pytest.mark.slow
@pytest.mark.skipif(importlib.util.find_spec("waymax") is None,
                    reason="waymax is not installed (it is not on the package registry: "
                           "pip install git+https://github.com/waymo-research/waymax to run this)")
def test_waymax_example_runs(womd_path):
  """examples/waymax_loop.py: our policy in Waymax's environment loop, on
  Waymax's dataloader's state, for each adapted action space."""
  for dynamics_name in ("bicycle", "delta_local"):
    run = subprocess.run([sys.executable, str(ROOT / "examples" / "waymax_loop.py"), "--record", womd_path,
                          "--steps", "3", "--dynamics", dynamics_name],
                         capture_output=True, text=True, cwd=ROOT, timeout=900)
    assert run.returncode == 0, run.stderr[-3000:]
    assert "waymax loop done" in run.stdout
