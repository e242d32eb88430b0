"""Our actors' actions in another dynamics model's action space.

Every actor of this package (the policy, the baselines) emits our NATIVE
action, [a, psi_dot] = [acceleration (m/s^2), yaw rate (rad/s)], shape
(..., O, 2), for `sim.dynamics.KinematicModel` (the paper's f). Waymax's
`InvertibleBicycleModel` also takes shape (..., O, 2) but means
[acceleration, steering curvature (1/m)]: fed a yaw rate it runs and steers
wrong. `adapt(actor, dynamics_model)` returns the same actor emitting actions
in `dynamics_model`'s space instead:

  space            action (per object)                     dynamics it drives
  accel_yaw_rate   [a, psi_dot] (native)                   sim.dynamics.KinematicModel
  bicycle          [accel, curvature], |.| <= [6, 0.3]     Waymax InvertibleBicycleModel, sim.dynamics.BicycleModel
  delta_local      [dx, dy, dyaw] in the object's frame    Waymax DeltaLocal
  delta_global     [dx, dy, dyaw] in the world frame       Waymax DeltaGlobal

Each conversion starts from the pose our f predicts for the next step (the
native action applied to the object's current simulated state):

- delta_local / delta_global: the displacement and heading change to that
  pose. Those models set the velocity to displacement / dt, which is f's
  new velocity exactly (f moves along its new heading at its new speed), so
  the trajectory is ours to float precision.
- bicycle: the acceleration, and the curvature that gives f's next heading
  under the bicycle's yaw update (yaw += curvature * (speed dt + a dt^2 / 2)),
  i.e. curvature = psi_dot / (speed + a dt / 2): heading and speed follow f
  exactly. Below `MIN_SPEED` (0.6 m/s, where Waymax's own inverse stops
  steering) the curvature is 0 (a yaw rate at a standstill has no curvature),
  and it is clipped to the model's bound, so it never blows up. The bicycle
  moves along its heading *before* the step, f along the one after it: the
  position lags by at most |v psi_dot| dt^2 per step (about 3 cm at 10 m/s
  and 0.3 rad/s), which a closed loop (the policy replans every step)
  corrects (tests/test_action_spaces.py measures it).

`dynamics_model` may be a space name, one of our models, or a Waymax model
(recognised by its class name; its `action_spec()` shape and bounds are
checked), so this module needs no Waymax import.
"""
from __future__ import annotations

import dataclasses
from typing import Any, Union

import jax.numpy as jnp
import numpy as np

from pcdiff_jax.config import KinematicsConfig
from pcdiff_jax.sim import dynamics, geometry
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, Array, Trajectory

NATIVE = "accel_yaw_rate"
MIN_SPEED = 0.6  # m/s: below it a bicycle action does not steer (as Waymax's inverse)


@dataclasses.dataclass(frozen=True)
class ActionSpace:
  """name; dim D; per-dimension bounds (None: unbounded)."""
  name: str
  dim: int
  minimum: tuple = None
  maximum: tuple = None


SPACES = {
    NATIVE: ActionSpace(NATIVE, 2),
    "bicycle": ActionSpace("bicycle", 2, (-6.0, -0.3), (6.0, 0.3)),
    "delta_local": ActionSpace("delta_local", 3, (-6.0, -6.0, -np.pi), (6.0, 6.0, np.pi)),
    "delta_global": ActionSpace("delta_global", 3, (-6.0, -6.0, -np.pi), (6.0, 6.0, np.pi)),
}

# Waymax's dynamics classes by name (no import of waymax needed).
_WAYMAX_MODELS = {"InvertibleBicycleModel": "bicycle", "DeltaLocal": "delta_local",
                  "DeltaGlobal": "delta_global"}


def resolve(dynamics_model: Union[str, Any]) -> ActionSpace:
  """The ActionSpace of a space name, one of our dynamics models, or a Waymax
  model. Raises ValueError naming what does not match."""
  if isinstance(dynamics_model, str):
    if dynamics_model not in SPACES:
      raise ValueError(f"dynamics_model: unknown action space {dynamics_model!r}; "
                       f"choose from {sorted(SPACES)} or pass a dynamics model")
    return SPACES[dynamics_model]
  if isinstance(dynamics_model, dynamics.KinematicModel):
    return SPACES[NATIVE]
  if isinstance(dynamics_model, dynamics.BicycleModel):
    space = SPACES["bicycle"]
    bounds = (dynamics_model.max_accel, dynamics_model.max_curvature)
    return dataclasses.replace(space, minimum=tuple(-b for b in bounds), maximum=bounds)
  name = type(dynamics_model).__name__
  if name not in _WAYMAX_MODELS:
    raise ValueError(f"dynamics_model: no adapter for {name} (supported: {sorted(_WAYMAX_MODELS)}, "
                     f"our KinematicModel / BicycleModel, or a name in {sorted(SPACES)}); "
                     f"StateDynamics takes the next state, not an action of ours")
  space = SPACES[_WAYMAX_MODELS[name]]
  spec = dynamics_model.action_spec()
  if tuple(spec.shape) != (space.dim,):
    raise ValueError(f"dynamics_model.action_spec().shape is {tuple(spec.shape)}, expected ({space.dim},) "
                     f"for {name}")
  lo, hi = tuple(float(v) for v in spec.minimum), tuple(float(v) for v in spec.maximum)
  if space.name == "bicycle" and (lo[0] != -hi[0] or lo[1] != -hi[1] or hi == (1.0, 1.0)):
    raise ValueError(f"dynamics_model.action_spec() bounds {lo}..{hi}: the adapter needs the "
                     f"unnormalised InvertibleBicycleModel (normalize_actions=False)")
  return dataclasses.replace(space, minimum=lo, maximum=hi)


def from_native(space: ActionSpace, current: Trajectory, action: Array,
                kinematics: KinematicsConfig = KinematicsConfig()) -> Array:
  """Native actions [a, psi_dot] (..., O, 2) from the current step (..., O, 1)
  -> actions (..., O, space.dim) in `space` (see the module docstring)."""
  if action.shape[-1] != 2:
    raise ValueError(f"action: native actions are [a, psi_dot] with last dim 2, got shape {action.shape}")
  action = dynamics.clip_action(action, kinematics)
  if space.name == NATIVE:
    return action
  dt = kinematics.dt
  now = dynamics.states_from_trajectory(current)[..., 0, :]                  # (..., O, 4)
  nxt = dynamics.step(now, action, dt)                                      # f's next pose
  yaw = now[..., dynamics.PSI]
  dyaw = geometry.wrap_angle(nxt[..., dynamics.PSI] - yaw)
  if space.name == "bicycle":
    a = jnp.clip(action[..., 0], space.minimum[0], space.maximum[0])
    speed = current.speed[..., 0]                                           # the bicycle's |v|
    travel = speed * dt + 0.5 * a * dt ** 2                                 # its arc length this step
    steer = speed > MIN_SPEED                                               # travel >= 0.03 m then
    curvature = jnp.where(steer, dyaw / jnp.where(steer, travel, 1.0), 0.0)
    return jnp.stack([a, jnp.clip(curvature, space.minimum[1], space.maximum[1])], -1)
  d = nxt[..., :2] - now[..., :2]                                           # (..., O, 2) world frame
  if space.name == "delta_local":
    d = geometry.to_local(nxt[..., :2], now[..., :2], yaw)
  return jnp.concatenate([d, dyaw[..., None]], -1)


def adapt(actor: Actor, dynamics_model: Union[str, Any],
          kinematics: KinematicsConfig = KinematicsConfig()) -> Actor:
  """`actor` (native [a, psi_dot] actions) emitting actions in the space of
  `dynamics_model` instead (`resolve`). Invalid actions stay invalid, with
  zero data. The conversion runs inside `select_action` (traced, no host
  transfer); any batch dims."""
  if actor.action_space != NATIVE:
    raise ValueError(f"actor {actor.name!r} already emits {actor.action_space!r} actions, not native ones")
  space = resolve(dynamics_model)
  if space.name == NATIVE:
    return actor

  def select_action(params, state, actor_state, rng):
    out = actor.select_action(params, state, actor_state, rng)
    data = from_native(space, state.current_sim_trajectory, out.action.data, kinematics)
    valid = out.action.valid
    return ActorOutput(actor_state=out.actor_state, is_controlled=out.is_controlled,
                       action=Action(data=jnp.where(valid, data, 0.0).astype(jnp.float32), valid=valid))

  return Actor(select_action=select_action, init=actor.init, name=f"{actor.name}[{space.name}]",
               action_space=space.name)
