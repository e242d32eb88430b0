"""Native [a, psi_dot] actions in Waymax's action spaces (sim/action_spaces.py).

The reference dynamics below are written here from the semantics Waymax
documents for its models (../shared/WAYMAX_API.md and their docstrings), not
from its code: the adapters must reproduce our own trajectory through them.
"""
from __future__ import annotations

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax import baselines
from pcdiff_jax.config import KinematicsConfig
from pcdiff_jax.sim import action_spaces, dynamics, env
from pcdiff_jax.sim.datatypes import Action, Trajectory

DT = 0.1
KIN = KinematicsConfig()
STEPS = 80  # 8 s


def _wrap(a):
  return (a + np.pi) % (2 * np.pi) - np.pi


# Reference dynamics, per object, on (x, y, yaw, vel_x, vel_y) float32 arrays.
def ref_bicycle(s, u):
  """Documented forward: x += vel_x t + a cos(yaw) t^2 / 2 (same for y);
  yaw += curvature (speed t + a t^2 / 2); speed += a t; velocity along the new yaw."""
  x, y, yaw, vx, vy = s
  a, k = jnp.clip(u[..., 0], -6, 6), jnp.clip(u[..., 1], -0.3, 0.3)
  speed = jnp.hypot(vx, vy)
  nx = x + vx * DT + 0.5 * a * jnp.cos(yaw) * DT ** 2
  ny = y + vy * DT + 0.5 * a * jnp.sin(yaw) * DT ** 2
  nyaw = _wrap(yaw + k * (speed * DT + 0.5 * a * DT ** 2))
  v = speed + a * DT
  return nx, ny, nyaw, v * jnp.cos(nyaw), v * jnp.sin(nyaw)


def ref_delta_global(s, u):
  """Documented: the pose moves by [dx, dy, dyaw] (world frame); velocity = displacement / dt."""
  x, y, yaw, _, _ = s
  return x + u[..., 0], y + u[..., 1], _wrap(yaw + u[..., 2]), u[..., 0] / DT, u[..., 1] / DT


def ref_delta_local(s, u):
  """Documented: [dx, dy] in the object's frame, rotated by its yaw into the world."""
  yaw = s[2]
  c, si = jnp.cos(yaw), jnp.sin(yaw)
  world = jnp.stack([c * u[..., 0] - si * u[..., 1], si * u[..., 0] + c * u[..., 1], u[..., 2]], -1)
  return ref_delta_global(s, world)


REFERENCE = {"bicycle": ref_bicycle, "delta_global": ref_delta_global, "delta_local": ref_delta_local}


def _traj(s) -> Trajectory:
  """(O, 1) Trajectory of reference state tuple s (each (O,))."""
  x, y, yaw, vx, vy = (jnp.asarray(a, jnp.float32)[:, None] for a in s)
  one = jnp.ones_like(x)
  return Trajectory(x=x, y=y, z=0 * one, vel_x=vx, vel_y=vy, yaw=yaw, valid=one > 0,
                    timestamp_micros=jnp.zeros(x.shape, jnp.int32), length=4.5 * one, width=2 * one,
                    height=1.5 * one)


def _plan(num=3):
  """(O, 80, 2) native plans: speed up + left turn, brake + right turn, creep from rest + turn."""
  t = np.arange(STEPS) * DT
  a = np.stack([np.where(t < 3, 1.5, -0.5), np.where(t < 4, -2.0, 1.0), np.where(t < 2, 0.8, 0.0)])
  w = np.stack([0.25 * np.sin(t / 2), -0.3 * (t > 2) * (t < 6), 0.2 * np.ones_like(t)])
  return jnp.asarray(np.stack([a, w], -1)[:num], jnp.float32)


START = (np.array([0.0, 50.0, -20.0]), np.array([0.0, 10.0, 5.0]), np.array([0.3, -2.9, 3.1]),
         np.array([10.0, 14.0, 0.0]), np.zeros(3))                          # x, y, yaw, speed, -


def _start():
  x, y, yaw, v, _ = START
  return x, y, yaw, v * np.cos(yaw), v * np.sin(yaw)


def _ours(plan):
  """(O, 80, 4) our f's trajectory of the plan (the env's KinematicModel)."""
  x, y, yaw, v, _ = START
  s0 = jnp.asarray(np.stack([x, y, yaw, v], -1), jnp.float32)
  return dynamics.rollout(s0, dynamics.clip_action(plan, KIN), DT)


def _run(space_name, plan, track: bool):
  """Steps the plan through the adapter and the reference dynamics: each step
  the native action is the plan's (open loop) or, with `track`, the action
  that takes the actual state to the plan's next position (what a policy
  replanning every step does). Returns (O, 80, 3) x, y, yaw."""
  space = action_spaces.resolve(space_name)
  ref = REFERENCE[space_name]
  targets = _ours(plan)

  def body(s, inputs):
    u, target = inputs
    cur = _traj(s)
    if track:
      goal = cur.replace(x=target[:, None, 0], y=target[:, None, 1])
      u = dynamics.KinematicModel(KIN).inverse(cur, goal).data
    data = action_spaces.from_native(space, cur, u, KIN)
    nxt = ref(s, data)
    return nxt, jnp.stack(nxt[:3], -1)

  s0 = tuple(jnp.asarray(a, jnp.float32) for a in _start())
  _, out = jax.lax.scan(body, s0, (jnp.moveaxis(plan, 1, 0), jnp.moveaxis(targets, 1, 0)))
  return jnp.moveaxis(out, 0, 1), targets


@pytest.mark.parametrize("space", ["delta_global", "delta_local"])
def test_delta_adapters_reproduce_our_trajectory(space):
  got, ours = _run(space, _plan(), track=False)
  err = np.linalg.norm(np.asarray(got[..., :2] - ours[..., :2]), axis=-1)
  # float32 only: a pose's velocity and heading agree to float rounding, and the speed is the
  # velocity along the heading, so a few micrometres per step accumulate (about 1 mm in 8 s).
  assert err.max() < 3e-3, err.max()
  np.testing.assert_allclose(np.asarray(_wrap(got[..., 2] - ours[..., 2])), 0.0, atol=1e-4)


def test_bicycle_adapter_follows_our_trajectory_within_centimetres():
  plan = _plan()
  # Open loop, each step's heading and speed are f's exactly; the position
  # lags (the bicycle moves along its heading before the step).
  got, ours = _run("bicycle", plan, track=False)
  np.testing.assert_allclose(np.asarray(_wrap(got[..., 2] - ours[..., 2]))[:2], 0.0, atol=1e-3)
  # Replanning every step (tracking the plan's next position): within a few cm over 8 s.
  got, ours = _run("bicycle", plan, track=True)
  err = np.linalg.norm(np.asarray(got[..., :2] - ours[..., :2]), axis=-1)
  moving = slice(0, 2)                        # the third starts at rest (no steering below 0.6 m/s)
  assert err[moving].max() < 0.08, err[moving].max(axis=-1)               # measured 0.058 m
  assert err[2].max() < 0.5, err[2].max()


def test_bicycle_curvature_at_low_speed_is_bounded():
  cur = _traj((np.zeros(4), np.zeros(4), np.zeros(4), np.array([0.0, 0.1, 0.6, 2.0]), np.zeros(4)))
  u = jnp.array([[0.0, 2.0], [-6.0, -2.0], [0.5, 1.0], [0.0, 1e-3]], jnp.float32)
  data = np.asarray(action_spaces.from_native(action_spaces.resolve("bicycle"), cur, u, KIN))
  assert np.isfinite(data).all()
  np.testing.assert_array_equal(data[:3, 1], 0.0)                          # at or below 0.6 m/s: no steer
  assert abs(data[3, 1] - 1e-3 / 2.0) < 1e-6 and np.abs(data[:, 1]).max() <= 0.3


def test_resolve_checks_the_model_and_its_spec():
  spec = lambda shape, lo, hi: types.SimpleNamespace(shape=shape, minimum=np.array(lo), maximum=np.array(hi))
  InvertibleBicycleModel = type("InvertibleBicycleModel", (), {})
  good = InvertibleBicycleModel()
  good.action_spec = lambda: spec((2,), [-6, -0.3], [6, 0.3])
  assert action_spaces.resolve(good).name == "bicycle"
  normalised = InvertibleBicycleModel()
  normalised.action_spec = lambda: spec((2,), [-1, -1], [1, 1])
  with pytest.raises(ValueError, match="normalize_actions"):
    action_spaces.resolve(normalised)
  DeltaLocal = type("DeltaLocal", (), {})
  wrong = DeltaLocal()
  wrong.action_spec = lambda: spec((2,), [-6, -6], [6, 6])
  with pytest.raises(ValueError, match=r"action_spec\(\).shape"):
    action_spaces.resolve(wrong)
  with pytest.raises(ValueError, match="StateDynamics"):
    action_spaces.resolve(type("StateDynamics", (), {})())
  with pytest.raises(ValueError, match="unknown action space"):
    action_spaces.resolve("yaw_rate")
  assert action_spaces.resolve(dynamics.KinematicModel()).name == action_spaces.NATIVE
  with pytest.raises(ValueError, match="last dim 2"):
    action_spaces.from_native(action_spaces.resolve("bicycle"), _traj(_start()), jnp.zeros((3, 3)), KIN)


def test_native_actions_are_not_mistaken_for_another_space():
  """A native actor cannot drive another model's env, nor an adapted one ours."""
  state = env.reset(make_scene(num_steps=31))
  cv = baselines.constant_velocity(baselines.reactive_agents(4))
  assert cv.action_space == "accel_yaw_rate"
  with pytest.raises(ValueError, match="emits 'accel_yaw_rate'"):
    env.rollout(state, cv, 2, jax.random.key(0), dynamics=dynamics.BicycleModel())
  bike = baselines.waymax_actor(cv, "bicycle")
  assert bike.action_space == "bicycle" and bike.name == "cv[bicycle]"
  with pytest.raises(ValueError, match="emits 'bicycle'"):
    env.rollout(state, bike, 2, jax.random.key(0))
  with pytest.raises(ValueError, match="already emits"):
    baselines.waymax_actor(bike, "delta_local")
  with pytest.raises(ValueError, match="action.data"):
    env.step(state, Action(data=jnp.zeros((4, 3)), valid=jnp.ones((4, 1), bool)), jnp.ones(4, bool))
  # Adapted to our own bicycle model it runs; the constant-velocity cars keep going straight.
  out = jax.jit(lambda s: env.rollout(s, bike, 5, jax.random.key(0), dynamics=dynamics.BicycleModel()))(state)
  np.testing.assert_allclose(np.asarray(out.final_state.sim_trajectory.y[1:, 11:16]),
                             np.asarray(state.log_trajectory.y[1:, 11:16]), atol=1e-4)
