"""The functional simulator: reset, step and a `lax.scan` rollout.

Every function is pure and works on any leading batch dims (one timestep per
scenario), so it can be jitted once and vmapped or batched over scenarios.
"""
from __future__ import annotations

import math
from typing import Any

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.actors import Actor
from pcdiff_jax.sim.datatypes import (Action, Array, SimulatorState, Trajectory, num_timesteps, slice_time,
                                      update_time)
from pcdiff_jax.sim.dynamics import KinematicModel

DEFAULT_DYNAMICS = KinematicModel()
WOMD_INIT_STEPS = 11  # 10 past steps + the current one


def reset(state: SimulatorState, init_steps: int = WOMD_INIT_STEPS) -> SimulatorState:
  """Prepares a loaded state for simulation, as Waymax's `env.reset`.

  timestep = init_steps - 1 (10 for WOMD: the current step); the sim
  trajectory equals the log up to it and, after it, is invalid with -1 in
  every float field and timestamp (Waymax's fill).
  """
  num_t = num_timesteps(state)
  if not 0 < init_steps <= num_t:
    raise ValueError(f"init_steps={init_steps} must be in [1, {num_t}]")
  keep = jnp.arange(num_t) < init_steps                      # (T,)
  fill = lambda x: jnp.zeros_like(x) if x.dtype == jnp.bool_ else jnp.full_like(x, -1)
  sim = jax.tree_util.tree_map(lambda x: jnp.where(keep, x, fill(x)), state.log_trajectory)
  return state.replace(sim_trajectory=sim,
                       timestep=jnp.full(state.shape, init_steps - 1, jnp.int32))


MOTION_HEADING_SPEED = 1.0          # m/s: slower objects keep their box heading (velocity noise)
MOTION_HEADING_ANGLE = math.pi / 6  # rad: within it of the motion (or of reversing) a heading is kept


def align_headings(state: SimulatorState, min_speed: float = MOTION_HEADING_SPEED,
                   max_angle: float = MOTION_HEADING_ANGLE) -> SimulatorState:
  """The state with the sim trajectory's box heading replaced by the direction of motion
  wherever an object moves at >= min_speed and its heading is more than max_angle off both
  that direction and its opposite (a car does not move sideways), at every step up to the
  current one; the log is left as it is.

  A guard against logs whose box headings are unrelated to the motion (as the shared real
  scenes stored in degrees looked when read as radians; the reader now converts those:
  docs/DEVELOPING.md, "Known limits"). The kinematic model moves a box along its heading and
  keeps only the velocity's part along it (`dynamics.states_from_trajectory`), so such a car
  would start standing and be held by the still gate; aligned, it drives on at its logged
  speed."""
  sim = state.sim_trajectory
  motion = jnp.arctan2(sim.vel_y, sim.vel_x)
  off = jnp.abs(geometry.wrap_angle(motion - sim.yaw))
  past = jnp.arange(sim.valid.shape[-1]) <= state.timestep[..., None, None]
  wrong = (sim.valid & past & (sim.speed >= min_speed)
           & (off > max_angle) & (off < math.pi - max_angle))
  return state.replace(sim_trajectory=sim.replace(yaw=jnp.where(wrong, motion, sim.yaw)))


SPEED_FIT_STEPS = 6        # the last 0.5 s of positions, current step included
SPEED_FIT_MAX_DIFF = 2.0   # m/s: a tracked velocity further than this from the positions' is replaced


def fit_current_velocity(state: SimulatorState, steps: int = SPEED_FIT_STEPS,
                         max_diff: float = SPEED_FIT_MAX_DIFF) -> SimulatorState:
  """The state with each object's current velocity in the sim trajectory replaced by the
  least-squares slope of its last `steps` positions where the two differ by more than max_diff
  m/s and all those positions are valid; earlier steps and the log are left as they are.

  The kinematic model starts from the current velocity, and a tracked one can contradict the
  positions it was tracked from (a young track, a long vehicle seen as two): one truck of the
  real val scenes starts at 39 m/s 4 m behind another at 30 m/s, though both cover 32 m in the
  next second, and no braking saves it. 6 of the 806 objects of the real val scenes with 0.5 s
  of history are replaced (docs/RESULTS.md, "Ablation: the start velocity from positions")."""
  sim, t = state.sim_trajectory, state.timestep[..., None, None]          # t (..., 1, 1)
  offsets = jnp.arange(steps) - (steps - 1)                                # (W,) -W+1 .. 0
  idx = jnp.clip(t + offsets, 0, sim.valid.shape[-1] - 1)                  # (..., 1, W)
  take = lambda a: jnp.take_along_axis(a, jnp.broadcast_to(idx, a.shape[:-1] + (steps,)), -1)
  seen = jnp.all(take(sim.valid), -1) & (t[..., 0] >= steps - 1)          # (..., O)
  dt = (offsets - offsets.mean()) * 0.1                                   # (W,) s at 10 Hz
  slope = lambda a: jnp.sum(dt * (take(a) - take(a).mean(-1, keepdims=True)), -1) / jnp.sum(dt ** 2)
  fit_x, fit_y = slope(sim.x)[..., None], slope(sim.y)[..., None]         # (..., O, 1)
  current = slice_time(sim, state.timestep)                               # (..., O, 1)
  replace = seen[..., None] & (jnp.hypot(current.vel_x - fit_x, current.vel_y - fit_y) > max_diff)
  fitted = current.replace(vel_x=jnp.where(replace, fit_x, current.vel_x),
                           vel_y=jnp.where(replace, fit_y, current.vel_y))
  return state.replace(sim_trajectory=update_time(sim, state.timestep, fitted))


def simulated_start(state: SimulatorState, init_steps: int, align: bool = True,
                    fit_velocity: bool = True) -> SimulatorState:
  """Where a simulated method's rollout starts: `reset` at init_steps, then, with fit_velocity,
  current velocities that contradict the positions replaced by theirs (`fit_current_velocity`),
  and, with align, box headings turned to the motion (`align_headings`). Evaluation, WOSAC
  exports and the on-policy rounds of fine-tuning all start here, so a round on real scenes
  rolls out what evaluation scores."""
  start = reset(state, init_steps)
  if fit_velocity:
    start = fit_current_velocity(start)
  return align_headings(start) if align else start


def step(state: SimulatorState, action: Action, controlled: Array,
         dynamics: Any = DEFAULT_DYNAMICS) -> SimulatorState:
  """Advances the sim trajectory by one step.

  Controlled objects (..., O) move by `dynamics.forward(current, action)`;
  a controlled object whose action is invalid becomes invalid. Every other
  object takes the logged next step. Sizes and z of controlled objects are
  carried from the current step; timestamps come from the log (or advance by
  0.1 s where the log has none).

  Args: state (...); action data (..., O, D), valid (..., O, 1);
    controlled (..., O) bool.
  Returns: the state at timestep + 1. Stepping past the last step is the
    caller's error (the scan lengths guard it).
  """
  dim = getattr(dynamics, "action_dim", None)
  if dim is not None and action.data.shape[-1] != dim:
    raise ValueError(f"action.data has shape {tuple(action.data.shape)}: {type(dynamics).__name__} takes "
                     f"{dim} numbers per object ({getattr(dynamics, 'action_space', '?')})")
  current = state.current_sim_trajectory                       # (..., O, 1)
  log_next = slice_time(state.log_trajectory, state.timestep + 1)
  moved = dynamics.forward(current, action)
  fallback_ts = jnp.where(log_next.valid, log_next.timestamp_micros, current.timestamp_micros + 100_000)
  moved = moved.replace(timestamp_micros=fallback_ts)
  ctrl = controlled[..., None]                                  # (..., O, 1)
  nxt = jax.tree_util.tree_map(lambda a, b: jnp.where(ctrl, a, b).astype(b.dtype), moved, log_next)
  sim = update_time(state.sim_trajectory, state.timestep + 1, nxt)
  md = state.object_metadata.replace(is_controlled=controlled)
  return state.replace(sim_trajectory=sim, timestep=state.timestep + 1, object_metadata=md)


@struct.dataclass
class RolloutCarry:
  """The scan carry of `rollout`."""
  state: SimulatorState
  actor_state: Any
  rng: Array


@struct.dataclass
class RolloutOutput:
  """final_state: after the rollout (its sim_trajectory holds every step);
  actions: data (S, ..., O, D), valid (S, ..., O, 1); is_controlled (S, ..., O)."""
  final_state: SimulatorState
  actions: Action
  is_controlled: Array

  @property
  def trajectory(self) -> Trajectory:
    """(..., O, T) the stacked simulated trajectory."""
    return self.final_state.sim_trajectory


def rollout(state: SimulatorState, actor: Actor, num_steps: int, rng: Array,
            params: Any = None, actor_state: Any = None,
            dynamics: Any = DEFAULT_DYNAMICS) -> RolloutOutput:
  """Runs `actor` in closed loop for `num_steps` steps as one `lax.scan`.

  Jit it with `num_steps` static (and the actor/dynamics closed over). The
  key for step k is `fold_in(rng, k)`, so results do not depend on how the
  loop is split.
  """
  space = getattr(dynamics, "action_space", None)
  if space is not None and actor.action_space != space:
    raise ValueError(f"actor {actor.name!r} emits {actor.action_space!r} actions but the dynamics model "
                     f"{type(dynamics).__name__} takes {space!r} ones (sim.action_spaces.adapt converts)")
  if actor_state is None:
    actor_state = actor.init(rng, state)

  def body(carry: RolloutCarry, k):
    out = actor.select_action(params, carry.state, carry.actor_state, jax.random.fold_in(carry.rng, k))
    new_state = step(carry.state, out.action, out.is_controlled, dynamics)
    return carry.replace(state=new_state, actor_state=out.actor_state), (out.action, out.is_controlled)

  carry, (actions, controlled) = jax.lax.scan(
      body, RolloutCarry(state=state, actor_state=actor_state, rng=rng), jnp.arange(num_steps))
  return RolloutOutput(final_state=carry.state, actions=actions, is_controlled=controlled)
