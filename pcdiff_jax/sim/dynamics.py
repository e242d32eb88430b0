"""Kinematic models: the paper's f, its inverse, and Waymax-compatible models.

The paper's model (`step`, `rollout`, `inverse`) works on plain arrays:
state (..., 4) = [x, y, psi, v] and action (..., 2) = [a, psi_dot], dt = 0.1 s.
It integrates with semi-implicit Euler,

    v'   = v + a dt,   psi' = psi + psi_dot dt,
    p'   = p + v' dt [cos psi', sin psi'],

so a position step determines the next heading and speed exactly, and the
inverse can track logged positions without accumulating drift.

For the simulator (`pcdiff_jax.sim.env.step`) three dynamics models map an
`Action` on the current (..., O, 1) trajectory to the next step:
`KinematicModel` (ours, D = 2), `BicycleModel` (Waymax's [accel, curvature],
D = 2) and `StateDynamics` (Waymax's next-state action, D = 5).
"""
from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from pcdiff_jax.config import KinematicsConfig
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Action, Array, Trajectory

X, Y, PSI, V = 0, 1, 2, 3


def clip_action(action: Array, cfg: KinematicsConfig) -> Array:
  """(..., 2) [a, psi_dot] clipped to the configured bounds."""
  return jnp.stack([jnp.clip(action[..., 0], -cfg.max_accel, cfg.max_accel),
                    jnp.clip(action[..., 1], -cfg.max_yaw_rate, cfg.max_yaw_rate)], -1)


def step(state: Array, action: Array, dt: float = 0.1) -> Array:
  """One step of f. state (..., 4), action (..., 2) -> (..., 4). Unbounded."""
  v = state[..., V] + action[..., 0] * dt
  psi = geometry.wrap_angle(state[..., PSI] + action[..., 1] * dt)
  x = state[..., X] + v * dt * jnp.cos(psi)
  y = state[..., Y] + v * dt * jnp.sin(psi)
  return jnp.stack([x, y, psi, v], axis=-1)


def rollout(initial: Array, actions: Array, dt: float = 0.1) -> Array:
  """Rolls actions out with f as a `lax.scan` over time.

  Args: initial (..., 4); actions (..., T, 2).
  Returns: states (..., T, 4), the state after each action (initial excluded).
  """
  def body(s, u):
    s = step(s, u, dt)
    return s, s
  _, states = jax.lax.scan(body, initial, jnp.moveaxis(actions, -2, 0))
  return jnp.moveaxis(states, 0, -2)


def _tracking_action(state: Array, target_xy: Array, cfg: KinematicsConfig) -> Array:
  """The action that takes `state` (..., 4) to `target_xy` (..., 2) in one step.

  Heading follows the displacement (reversed when the motion is backwards)
  except below `min_speed_for_heading`, where it is held; speed is the
  displacement projected on the new heading. Bounds are applied.
  """
  d = target_xy - state[..., :2]
  dist = jnp.sqrt(jnp.sum(d ** 2, -1) + 1e-12)
  heading = geometry.unit(state[..., PSI])
  backwards = jnp.sum(d * heading, -1) < 0
  motion_dir = jnp.arctan2(d[..., 1], d[..., 0])
  psi_des = jnp.where(backwards, geometry.wrap_angle(motion_dir + jnp.pi), motion_dir)
  moving = dist / cfg.dt > cfg.min_speed_for_heading
  psi_next = jnp.where(moving, psi_des, state[..., PSI])
  v_next = jnp.sum(d * geometry.unit(psi_next), -1) / cfg.dt
  action = jnp.stack([(v_next - state[..., V]) / cfg.dt,
                      geometry.wrap_angle(psi_next - state[..., PSI]) / cfg.dt], -1)
  return clip_action(action, cfg)


def pure_pursuit(target_xy: Array, before_xy: Array, speed: Array, steps: int, dt: float) -> Array:
  """[a, psi_dot] (..., 2) that follow a path from [0, 0, 0, speed]: reach the
  path's speed at its point `steps` ahead within those steps, and steer on the
  circle through the origin, tangent to the heading, that passes through it.

  target_xy (..., 2): the path's point `steps` ahead, in the agent's frame;
  before_xy (..., 2): the point one step before it (their gap sets the speed).
  Unclipped (see `clip_action`).
  """
  v_target = jnp.sqrt(jnp.sum((target_xy - before_xy) ** 2, -1) + 1e-12) / dt
  accel = (v_target - speed) / (steps * dt)
  dist2 = jnp.sum(target_xy ** 2, -1)
  curvature = 2.0 * target_xy[..., 1] / jnp.maximum(dist2, 1e-2)
  return jnp.stack([accel, jnp.maximum(speed, 0.0) * curvature], -1)


def inverse(states: Array, valid: Array, cfg: KinematicsConfig = KinematicsConfig()) -> tuple[Array, Array]:
  """Inverse dynamics: actions that make f track logged positions.

  The inverse runs closed loop (a `lax.scan`): each action is computed from
  the model's own state, not the log's, so clipping or noise at one step is
  corrected at the next instead of accumulating into drift. Steps whose
  target is invalid get a zero action (the model coasts) and are marked
  invalid; the first valid target after a gap catches up within bounds.

  Args:
    states: (..., T + 1, 4) logged [x, y, psi, v]; states[..., 0, :] is the
      initial state (its heading and speed seed the model).
    valid: (..., T + 1) bool.
  Returns:
    actions (..., T, 2) [a, psi_dot] within bounds, and their valid mask
    (..., T): both ends of the step valid.
  """
  targets = jnp.moveaxis(states[..., 1:, :2], -2, 0)       # (T, ..., 2)
  target_valid = jnp.moveaxis(valid[..., 1:], -1, 0)       # (T, ...)

  def body(s, inputs):
    target, ok = inputs
    u = jnp.where(ok[..., None], _tracking_action(s, target, cfg), 0.0)
    return step(s, u, cfg.dt), u

  _, actions = jax.lax.scan(body, states[..., 0, :], (targets, target_valid))
  action_valid = valid[..., 1:] & valid[..., :-1]
  return jnp.moveaxis(actions, 0, -2), action_valid


def states_from_trajectory(traj: Trajectory) -> Array:
  """(..., O, T, 4) kinematic states [x, y, yaw, v] of a trajectory.

  v is the velocity along the box heading (negative when reversing), the
  speed the planner's features read (`model.features`' agent-frame vx). A
  box whose heading disagrees with its motion (some converted real scenes
  have such headings) keeps only the part of its velocity along the
  heading: giving it the full speed with the projection's sign would start
  a car moving sideways in the log off in reverse at that speed.
  """
  heading = geometry.unit(traj.yaw)
  v = jnp.sum(traj.vel_xy * heading, -1)
  return jnp.stack([traj.x, traj.y, traj.yaw, v], axis=-1)


def to_bicycle_action(action: Array, speed: Array, dt: float = 0.1,
                      max_accel: float = 6.0, max_curvature: float = 0.3,
                      min_speed: float = 0.6) -> Array:
  """[a, psi_dot] -> Waymax bicycle [accel, steering curvature].

  Waymax integrates yaw += curvature (v dt + a dt^2 / 2), so the matching
  curvature is psi_dot / (v + a dt / 2); it is 0 below `min_speed` as in
  Waymax's own inverse. Clipped to Waymax's bounds. action (..., 2), speed (...).
  """
  a, yaw_rate = action[..., 0], action[..., 1]
  denom = speed + 0.5 * a * dt
  safe = jnp.abs(denom) > min_speed
  curvature = jnp.where(safe, yaw_rate / jnp.where(safe, denom, 1.0), 0.0)
  return jnp.stack([jnp.clip(a, -max_accel, max_accel),
                    jnp.clip(curvature, -max_curvature, max_curvature)], -1)


def from_bicycle_action(action: Array, speed: Array, dt: float = 0.1) -> Array:
  """Waymax bicycle [accel, curvature] -> [a, psi_dot] over one step."""
  a, curvature = action[..., 0], action[..., 1]
  return jnp.stack([a, curvature * (speed + 0.5 * a * dt)], -1)


# --------------------------------------------------------------------------
# Simulator dynamics models: Action on a (..., O, 1) trajectory -> next step.
# --------------------------------------------------------------------------

def _trajectory_step(current: Trajectory, x, y, yaw, vel_x, vel_y, valid) -> Trajectory:
  return current.replace(x=x, y=y, yaw=yaw, vel_x=vel_x, vel_y=vel_y, valid=valid)


@dataclasses.dataclass(frozen=True)
class KinematicModel:
  """The paper's f as a simulator dynamics model; action [a, psi_dot]."""
  config: KinematicsConfig = KinematicsConfig()
  action_dim: int = 2
  action_space: ClassVar[str] = "accel_yaw_rate"

  def forward(self, current: Trajectory, action: Action) -> Trajectory:
    """current (..., O, 1), action (..., O, 2) -> next (..., O, 1)."""
    s = states_from_trajectory(current)[..., 0, :]               # (..., O, 4)
    s = step(s, clip_action(action.data, self.config), self.config.dt)
    yaw, v = s[..., PSI], s[..., V]
    return _trajectory_step(current, s[..., X, None], s[..., Y, None], yaw[..., None],
                            (v * jnp.cos(yaw))[..., None], (v * jnp.sin(yaw))[..., None],
                            current.valid & action.valid)

  def inverse(self, current: Trajectory, target: Trajectory) -> Action:
    """The action taking current (..., O, 1) to target's position (..., O, 1)."""
    s = states_from_trajectory(current)[..., 0, :]
    u = _tracking_action(s, target.xy[..., 0, :], self.config)
    valid = current.valid & target.valid
    return Action(data=jnp.where(valid, u, 0.0).astype(jnp.float32), valid=valid)


@dataclasses.dataclass(frozen=True)
class BicycleModel:
  """Waymax's invertible bicycle model; action [accel, steering curvature]."""
  dt: float = 0.1
  max_accel: float = 6.0
  max_curvature: float = 0.3
  action_dim: int = 2
  action_space: ClassVar[str] = "bicycle"

  def forward(self, current: Trajectory, action: Action) -> Trajectory:
    accel = jnp.clip(action.data[..., 0:1], -self.max_accel, self.max_accel)
    curvature = jnp.clip(action.data[..., 1:2], -self.max_curvature, self.max_curvature)
    t = self.dt
    speed = current.speed
    x = current.x + current.vel_x * t + 0.5 * accel * jnp.cos(current.yaw) * t ** 2
    y = current.y + current.vel_y * t + 0.5 * accel * jnp.sin(current.yaw) * t ** 2
    yaw = geometry.wrap_angle(current.yaw + curvature * (speed * t + 0.5 * accel * t ** 2))
    v = speed + accel * t
    return _trajectory_step(current, x, y, yaw, v * jnp.cos(yaw), v * jnp.sin(yaw),
                            current.valid & action.valid)

  def inverse(self, current: Trajectory, target: Trajectory) -> Action:
    """Our tracking action towards target's position, as [accel, curvature]."""
    kinematic = KinematicModel(KinematicsConfig(dt=self.dt)).inverse(current, target)
    data = to_bicycle_action(kinematic.data, current.speed[..., 0], self.dt, self.max_accel, self.max_curvature)
    return kinematic.replace(data=jnp.where(kinematic.valid, data, 0.0).astype(jnp.float32))


@dataclasses.dataclass(frozen=True)
class StateDynamics:
  """Waymax's state dynamics: the action is the next [x, y, yaw, vel_x, vel_y]."""
  action_dim: int = 5
  action_space: ClassVar[str] = "state"

  def forward(self, current: Trajectory, action: Action) -> Trajectory:
    d = action.data[..., None, :]                                 # (..., O, 1, 5)
    return _trajectory_step(current, d[..., 0], d[..., 1], d[..., 2], d[..., 3], d[..., 4],
                            current.valid & action.valid)

  def inverse(self, current: Trajectory, target: Trajectory) -> Action:
    data = jnp.stack([target.x, target.y, target.yaw, target.vel_x, target.vel_y], -1)[..., 0, :]
    valid = current.valid & target.valid
    return Action(data=data.astype(jnp.float32), valid=valid)
