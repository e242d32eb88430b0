"""Execution: from a plan to the action executed now, through the filters on it.

`execute` takes the plan's current step (or pure pursuit of its path), then, as PolicyConfig
turns them on, limits the jerk, keeps a wheeled agent ahead of a car on its log closing from
behind, keeps a fast vehicle on a free straight road from braking hard (the cruise hold), keeps
it able to stop behind the leader on its planned path, holds braking at standstill and bounds
the curvature; `ensemble_plans` blends
consecutive plans before that (temporal ensembling). The plan itself is never changed by a
filter: the next replan starts from the state the filtered action led to.
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp

from pcdiff_jax.config import Config
from pcdiff_jax.policy.config import PolicyConfig
from pcdiff_jax.policy.planning import advance_plan
from pcdiff_jax.sim import datatypes, dynamics, geometry
from pcdiff_jax.sim.datatypes import Action, Array, ObjectType, SimulatorState

STOPPED_REVERSE_SPEED = 0.1   # m/s: slower reversing is a stop (float error, log noise), not a manoeuvre
FOLLOW_MIN_GAP = 1.0          # m: bumper gap kept to a stopped leader
FOLLOW_MAX_BRAKE = 8.0        # m/s^2: the hardest braking the follow bound asks for
FOLLOW_STILL_SPEED = 1.0      # m/s: a slower object is an obstacle whatever its heading
FOLLOW_SIDE_MARGIN = 0.25     # m: a leader this close beside the path (box to box) is still ahead of it
FOLLOW_ALIGNED = 0.5          # cos 60 deg: a moving object heading within it of the path is a leader
FOLLOW_PATH_STRIDE = 5        # plan steps per segment of the path searched for leaders
FOLLOW_CROSSING_ALIGNED = 0.87  # cos 30 deg: an object heading further off the plan's heading (or its opposite) crosses it
FOLLOW_CROSSING_STEPS = 20    # plan steps (2 s) over which crossing objects are checked against the plan
FOLLOW_CROSSING_STRIDE = 2    # plan steps between those checks
FOLLOW_CROSSING_NEAREST = 16  # moving objects per follower (those that come closest to its plan) checked for a meeting
FOLLOW_LEADER_HALF_LENGTH = 3.0  # m: how far past the bumper gap the path is searched for a leader's centre
REAR_GUARD_MAX_ACCEL = 2.0   # m/s^2: the most the rear guard asks for
REAR_GUARD_HORIZON = 4.0     # s: a closing object that reaches the agent later is left alone
REAR_GUARD_QUEUE_GAP = 12.0  # m: a car of ours this close (bumper to bumper) behind in line passes its push on
REAR_GUARD_QUEUE_HOPS = 4    # cars up a queue a push is passed through


def execute(state: SimulatorState, plan: Array, path: Array, age, policy: PolicyConfig, cfg: Config,
            last_accel: Optional[Array] = None, followers: Optional[Array] = None) -> tuple[Array, Array]:
  """(O, 2) the actions executed now: the plan's (O, T, 2) step `age` (or pure pursuit of its
  path (O, T, 2), execute="track"), through the filters policy turns on; and (O,) the
  acceleration before the follow bound, the jerk limit's next reference (so that a braking the
  bound forced ends when the leader no longer asks for it, instead of easing off at the jerk
  limit for seconds). last_accel (O,): that reference from the previous step
  (`logged_accel` before the first), NaN where there is none (the jerk limit leaves those
  free); None reads it from the state (`executed_accel`, within the model's bounds).
  followers (O,): the objects whose actions are executed (at most cfg.features.max_agents), the
  only ones the follow bound is computed for; None: every object."""
  if policy.execute == "track":
    now = _track(state, path, age, policy.track_steps, cfg)
  else:
    now = jnp.take(plan, age, axis=1)
  if any(policy.jerk_limit):
    if last_accel is None:
      last_accel = jnp.clip(executed_accel(state, cfg.kinematics.dt), -cfg.kinematics.max_accel,
                            cfg.kinematics.max_accel)
    now = limit_jerk(now, last_accel, policy.jerk_limit, cfg.kinematics.dt)
  ahead = advance_plan(plan, age)
  bound = None
  if all(policy.follow) or policy.cruise_hold[0] > 0:
    # With the follow bound off, the cruise hold still tests the road ahead with its default.
    bound = follow_bound(state, ahead, policy.follow if all(policy.follow) else PolicyConfig.follow,
                         cfg.kinematics.dt, followers, cfg.features.max_agents, policy.follow_crossing)
  if policy.rear_guard and followers is not None:
    now = now.at[:, 0].set(jnp.maximum(now[:, 0], rear_guard(state, followers)))
  if policy.cruise_hold[0] > 0:
    now = now.at[:, 0].set(jnp.maximum(now[:, 0], cruise_floor(state, ahead, bound, policy.cruise_hold)))
  unbound = now
  if all(policy.follow):
    now = now.at[:, 0].set(jnp.minimum(now[:, 0], bound))
  if policy.stop_hold:
    now, unbound = (hold_at_stop(state, a, cfg.kinematics.dt) for a in (now, unbound))
  if policy.max_curvature > 0:
    now = limit_curvature(state, now, policy.max_curvature, cfg.kinematics.dt)
  return now, jnp.clip(unbound[:, 0], -cfg.kinematics.max_accel, cfg.kinematics.max_accel)


def controlled_action(state: SimulatorState, controlled: Array, planned: Array, now: Array) -> Action:
  """Action (O, 2): the plan's for planned agents; a controlled agent the plan
  missed (more controlled agents than the model's cap) keeps its speed and
  heading (zero action) rather than vanish. Valid for every controlled agent
  alive at this step."""
  valid = controlled & state.current_sim_trajectory.valid[..., 0]
  return Action(data=jnp.where((valid & planned)[:, None], now, 0.0), valid=valid[:, None])


def ensemble_plans(previous: Array, previous_valid: Array, executed: Array, plan: Array,
                   plan_valid: Array, weight) -> Array:
  """(O, T, 2) weight * previous + (1 - weight) * plan over the steps both
  cover, with `previous` advanced by the `executed` actions (a traced int);
  the new plan alone where the previous one has ended or an agent had none.
  weight: () or one per action channel (2,)."""
  horizon = plan.shape[1]
  both = ((jnp.arange(horizon) < horizon - executed)[None, :, None]
          & (previous_valid & plan_valid)[:, None, None])
  previous = advance_plan(previous, executed)
  weight = jnp.broadcast_to(jnp.asarray(weight, plan.dtype), plan.shape)
  blended = weight * previous + (1.0 - weight) * plan
  return jnp.where(both, blended, plan)


def _track(state: SimulatorState, path: Array, age: Array, steps: int, cfg: Config) -> Array:
  """(O, 2) pure-pursuit actions from each object's simulated state towards the
  plan's world-frame path (O, T, 2) `steps` points past step `age` (clamped
  to the plan's end)."""
  cur = state.current_sim_trajectory
  last = path.shape[1] - 1
  at = lambda k: jnp.take(path, jnp.clip(age + k, 0, last), axis=1)          # (O, 2)
  xy, yaw = cur.xy[:, 0], cur.yaw[:, 0]
  speed = jnp.sum(cur.vel_xy[:, 0] * geometry.unit(yaw), -1)
  local = lambda p: geometry.to_local(p, xy, yaw)
  action = dynamics.pure_pursuit(local(at(steps - 1)), local(at(steps - 2)), speed, steps, cfg.kinematics.dt)
  return dynamics.clip_action(action, cfg.kinematics)


def _mean_accel(state: SimulatorState, dt: float, steps: int) -> Array:
  """(O,) acceleration along the heading over the last `steps` steps (0 where either end is
  invalid or the trajectory is shorter)."""
  sim = state.sim_trajectory
  fields = (sim.vel_x, sim.vel_y, sim.yaw, sim.valid)      # only what the speeds need, not every field
  (vx, vy, yaw, ok), (vx0, vy0, yaw0, ok0) = (
      [a[..., 0] for a in datatypes.slice_time(fields, t)]
      for t in (state.timestep, jnp.maximum(state.timestep - steps, 0)))
  speed = lambda x, y, heading: x * jnp.cos(heading) + y * jnp.sin(heading)
  valid = ok & ok0 & (state.timestep >= steps)
  return jnp.where(valid, (speed(vx, vy, yaw) - speed(vx0, vy0, yaw0)) / (steps * dt), 0.0)


def executed_accel(state: SimulatorState, dt: float) -> Array:
  """(O,) each object's acceleration along its heading over the last step
  (0 at the first step of a log and where either step is invalid)."""
  return _mean_accel(state, dt, 1)


def logged_accel(state: SimulatorState, dt: float, steps: int = 10,
                 bound: float = PolicyConfig.jerk_start_bound) -> Array:
  """(O,) each object's mean acceleration along its heading over the last `steps` steps of its
  trajectory, within +-bound (0 where either end is invalid): the jerk limit's reference at a
  rollout's first step. A one-step difference of logged speeds is noise on real logs (tens of
  m/s^2); over a second it is the trend, and the bound (`PolicyConfig.jerk_start_bound`) keeps
  tracker noise from setting it."""
  return jnp.clip(_mean_accel(state, dt, steps), -bound, bound)


def limit_jerk(actions: Array, last: Array, limit, dt: float) -> Array:
  """(O, 2) actions whose acceleration is kept within [a - fall * dt,
  a + rise * dt] of the last executed one a = last (O,); NaN in `last` leaves
  that object free. limit (rise, fall) in m/s^3, 0 for no limit on that side.

  The reference is what the policy executed; at a rollout's first step it is
  `logged_accel`, never a one-step difference of the log: on real logs that
  reads as tens of m/s^2, which the limit would force on the agent for
  seconds (docs/RESULTS.md, "Table I (real WOMD val)")."""
  rise, fall = limit
  accel = actions[:, 0]
  free = jnp.isnan(last)
  if rise > 0:
    accel = jnp.where(free, accel, jnp.minimum(accel, last + rise * dt))
  if fall > 0:
    accel = jnp.where(free, accel, jnp.maximum(accel, last - fall * dt))
  return actions.at[:, 0].set(accel)


def hold_at_stop(state: SimulatorState, actions: Array, dt: float) -> Array:
  """(O, 2) actions whose braking stops at standstill: an agent moving forward
  or stopped (signed speed v > -STOPPED_REVERSE_SPEED) gets an acceleration
  of at least -v / dt, so it ends the step at v >= 0 instead of backing up;
  an agent reversing faster is left alone."""
  v = dynamics.states_from_trajectory(state.current_sim_trajectory)[:, 0, dynamics.V]
  accel = actions[:, 0]
  return actions.at[:, 0].set(jnp.where(v > -STOPPED_REVERSE_SPEED, jnp.maximum(accel, -v / dt), accel))


def limit_curvature(state: SimulatorState, actions: Array, max_curvature: float, dt: float) -> Array:
  """(O, 2) actions whose yaw rate a wheeled object can follow: a vehicle or
  cyclist turns only by moving, |psi_dot| <= max_curvature (1/m) x |its speed
  after this step's acceleration|. The kinematic model would otherwise spin a
  parked car in place, swinging its corners into its neighbours in a parking
  row. Pedestrians and other objects keep their yaw rate."""
  v = dynamics.states_from_trajectory(state.current_sim_trajectory)[:, 0, dynamics.V]
  speed = jnp.abs(v + actions[:, 0] * dt)
  types = state.object_metadata.object_types
  wheeled = (types == ObjectType.VEHICLE) | (types == ObjectType.CYCLIST)
  bound = jnp.where(wheeled, max_curvature * speed, jnp.inf)
  return actions.at[:, 1].set(jnp.clip(actions[:, 1], -bound, bound))


def planned_path(now: Array, states: Array, reach: Array, stride: int = FOLLOW_PATH_STRIDE) -> Array:
  """(F, K + 2, 2) where each follower's remaining plan, rolled out from its state now (F, 4)
  into states (F, T, 4), takes it in the world frame: its position now, every `stride`-th
  planned position, then `reach` (F,) metres straight on from the last one, so that a plan
  slower than the current speed is still searched as far as the agent needs to stop. A plan
  that brakes through zero speed ends where it stopped: execution holds a stop
  (`hold_at_stop`), and a path that doubled back would put a leader further along it than it is."""
  reversed_ = jnp.cumsum(states[..., dynamics.V] < 0.0, axis=1) > 0                      # (F, T)
  stop = jnp.take_along_axis(states, jnp.argmax(reversed_, 1)[:, None, None], 1)       # (F, 1, 4)
  states = jnp.where(reversed_[..., None], stop, states)
  points = states[:, stride - 1::stride]
  last = states[:, -1]
  beyond = last[:, :2] + reach[:, None] * geometry.unit(last[:, dynamics.PSI])
  return jnp.concatenate([now[:, None, :2], points[..., :2], beyond[:, None]], axis=1)


def _along_path(path: Array, xy: Array) -> tuple[Array, Array, Array]:
  """Each point xy (O, 2) projected on each path (F, K, 2): the distance along path i to the
  projection, the lateral distance (both (F, O)) and the path's direction there (F, O, 2)."""
  start = path[:, :-1]                                                                # (F, K-1, 2)
  seg = path[:, 1:] - start
  length = jnp.sqrt(jnp.sum(seg ** 2, -1) + 1e-12)                                    # (F, K-1)
  before = jnp.cumsum(length, -1) - length
  # x and y apart (F, O, K-1): 3x faster on a CPU (docs/BENCHMARKS.md, "x and y apart").
  rel_x, rel_y = (xy[None, :, None, i] - start[:, None, :, i] for i in (0, 1))
  seg_x, seg_y = seg[:, None, :, 0], seg[:, None, :, 1]
  t = jnp.clip((rel_x * seg_x + rel_y * seg_y) / length[:, None] ** 2, 0.0, 1.0)
  lateral = jnp.sqrt((rel_x - t * seg_x) ** 2 + (rel_y - t * seg_y) ** 2 + 1e-12)
  k = jnp.argmin(lateral, -1)                                                        # (F, O)
  pick = lambda a: jnp.take_along_axis(a, k[..., None], -1)[..., 0]
  along = pick(before[:, None] + t * length[:, None])
  direction = jnp.take_along_axis(seg / length[..., None], k[..., None], 1)           # (F, O, 2)
  return along, pick(lateral), direction


def crossing_gaps(states: Array, follower: Array, cur, moving: Array, reactive: Array, dt: float,
                  steps: int = FOLLOW_CROSSING_STEPS, stride: int = FOLLOW_CROSSING_STRIDE,
                  nearest: int = FOLLOW_CROSSING_NEAREST) -> Array:
  """(F, N) how far (m) each follower's plan takes its front before the near side of a crossing
  object it would run into; +inf for the objects it would not.

  states (F, T, 4): each follower's plan rolled out from now; follower (F,): their indices among
  the objects, whose current trajectory is cur (O, 1); moving (O,): the objects to check;
  reactive (O,): those that yield in turn (the others replay their log or ignore us). At
  every `stride`-th plan step within `steps` each of those is put where constant velocity takes
  it; the N = min(nearest, O) whose centres come closest to the follower's are checked. The
  pair meets at the first of those steps where their boxes, grown by FOLLOW_MIN_GAP along and
  FOLLOW_SIDE_MARGIN across each box's heading, overlap (a separating-axis test, so both agents
  of a pair see the same meeting). The follower yields where the object then heads across its
  planned heading (30 to 150 degrees) and stands further ahead of the follower than the
  follower stands ahead of it: the follower's front is at the object's side, not the other way
  round, so of two agents that meet only one yields. To an object that does not react the
  follower yields wherever the object is ahead of it."""
  num_objects = moving.shape[0]
  picked = jnp.arange(stride - 1, min(steps, states.shape[1]), stride)                # (J,)
  start = jnp.concatenate([cur.xy[follower, 0][:, None], states[:, :-1, :2]], 1)
  travelled = jnp.cumsum(jnp.sqrt(jnp.sum((states[..., :2] - start) ** 2, -1) + 1e-12), -1)[:, picked]
  # x and y apart: faster on a CPU (docs/BENCHMARKS.md, "x and y apart").
  at_x, at_y, at_yaw = (states[:, picked, i] for i in (dynamics.X, dynamics.Y, dynamics.PSI))  # (F, J)
  seconds = (picked + 1).astype(states.dtype) * dt                                    # (J,)
  where_x, where_y = (cur.xy[:, 0, i, None] + cur.vel_xy[:, 0, i, None] * seconds for i in (0, 1))  # (O, J)
  # The box test below costs followers x objects x times: keep the objects that come nearest.
  closest = jnp.min((where_x[None] - at_x[:, None]) ** 2 + (where_y[None] - at_y[:, None]) ** 2, -1)  # (F, O)
  candidate = moving[None] & (follower[:, None] != jnp.arange(num_objects)[None])
  _, near = jax.lax.top_k(jnp.where(candidate, -closest, -jnp.inf), min(nearest, num_objects))  # (F, N)
  candidate = jnp.take_along_axis(candidate, near, -1)
  rel_x, rel_y = where_x[near] - at_x[:, None], where_y[near] - at_y[:, None]         # (F, N, J)
  fx, fy = jnp.cos(at_yaw)[:, None], jnp.sin(at_yaw)[:, None]                         # (F, 1, J)
  ox, oy = jnp.cos(cur.yaw[near, 0])[..., None], jnp.sin(cur.yaw[near, 0])[..., None]  # (F, N, 1)
  ahead_of_f, beside_f = rel_x * fx + rel_y * fy, jnp.abs(rel_x * fy - rel_y * fx)    # (F, N, J)
  ahead_of_o, beside_o = -(rel_x * ox + rel_y * oy), jnp.abs(rel_x * oy - rel_y * ox)  # the follower in the object's frame
  cos = fx * ox + fy * oy
  sin = jnp.sqrt(jnp.maximum(1.0 - cos ** 2, 0.0))
  l_o, w_o = cur.length[near, 0][..., None], cur.width[near, 0][..., None]            # (F, N, 1)
  l_f, w_f = cur.length[follower, 0][:, None, None], cur.width[follower, 0][:, None, None]
  # Each box's half extents along and across the other's heading.
  o_along, o_across = 0.5 * (l_o * jnp.abs(cos) + w_o * sin), 0.5 * (l_o * sin + w_o * jnp.abs(cos))
  f_along, f_across = 0.5 * (l_f * jnp.abs(cos) + w_f * sin), 0.5 * (l_f * sin + w_f * jnp.abs(cos))
  meet = ((jnp.abs(ahead_of_f) < 0.5 * l_f + o_along + FOLLOW_MIN_GAP)
          & (beside_f < 0.5 * w_f + o_across + FOLLOW_SIDE_MARGIN)
          & (jnp.abs(ahead_of_o) < 0.5 * l_o + f_along + FOLLOW_MIN_GAP)
          & (beside_o < 0.5 * w_o + f_across + FOLLOW_SIDE_MARGIN))
  first = jnp.argmax(meet, -1)[..., None]                                             # (F, N, 1)
  pick = lambda a: jnp.take_along_axis(a, first, -1)[..., 0]
  gap = pick(ahead_of_f) - 0.5 * l_f[..., 0] - pick(o_along)
  yields = (jnp.any(meet, -1) & (jnp.abs(pick(cos)) <= FOLLOW_CROSSING_ALIGNED)
            & (pick(ahead_of_f) > 0) & ((pick(ahead_of_o) <= pick(ahead_of_f)) | ~reactive[near])
            & candidate)
  to_meeting = jnp.take_along_axis(jnp.broadcast_to(travelled[:, None], meet.shape), first, -1)[..., 0]
  return jnp.where(yields, to_meeting + gap, jnp.inf)


def rear_guard(state: SimulatorState, followers: Array) -> Array:
  """(O,) the least acceleration that keeps each follower (a vehicle or cyclist) ahead of an
  object closing on it in line from behind (for a follower faster than FOLLOW_STILL_SPEED the
  boxes overlap sideways, for a slower one the centres are within half the narrower width) that
  does not react (not among `followers`: it replays its log), -inf elsewhere: enough to reach
  the object's speed before the gap falls to FOLLOW_MIN_GAP, at most REAR_GUARD_MAX_ACCEL, for
  objects within REAR_GUARD_HORIZON of it;
  passed on to the follower ahead of a pushed one, up to REAR_GUARD_QUEUE_HOPS cars up a queue.
  A slow car of ours ahead of the SDC on its log was run into from behind (real val records 5
  and 13; docs/RESULTS.md, "Ablation: the rear guard")."""
  cur = state.current_sim_trajectory
  x, y, yaw, valid = cur.x[:, 0], cur.y[:, 0], cur.yaw[:, 0], cur.valid[:, 0]
  fx, fy = jnp.cos(yaw), jnp.sin(yaw)
  dx, dy = x[None] - x[:, None], y[None] - y[:, None]                                 # (O, O): j from i
  along = dx * fx[:, None] + dy * fy[:, None]
  beside = jnp.abs(dy * fx[:, None] - dx * fy[:, None])
  v = cur.vel_x[:, 0] * fx + cur.vel_y[:, 0] * fy                                     # (O,)
  u = cur.vel_x[None, :, 0] * fx[:, None] + cur.vel_y[None, :, 0] * fy[:, None]      # j's speed along i
  length, width = cur.length[:, 0], cur.width[:, 0]
  gap = -along - 0.5 * (length[:, None] + length[None])
  closing = u - v[:, None]
  aligned = fx[:, None] * fx[None] + fy[:, None] * fy[None] > FOLLOW_ALIGNED
  # In line: a moving car's box overlaps the closing one's sideways, so that driving on they meet
  # (real val record 13: 1 m to the side); a still car's centre is within half the narrower width
  # (drivers steer round parked cars; real val record 3).
  in_line = jnp.where(v[:, None] > FOLLOW_STILL_SPEED, 0.5 * (width[:, None] + width[None]),
                      0.5 * jnp.minimum(width[:, None], width[None]))
  in_line_behind = (along < 0) & (beside < in_line) & aligned & valid[None]
  behind = in_line_behind & (closing > 0) & (gap < closing * REAR_GUARD_HORIZON) & ~followers[None]
  need = jnp.minimum(closing ** 2 / (2.0 * jnp.maximum(gap - FOLLOW_MIN_GAP, 0.1)), REAR_GUARD_MAX_ACCEL)
  types = state.object_metadata.object_types
  wheeled = (types == ObjectType.VEHICLE) | (types == ObjectType.CYCLIST)
  pushed = followers & wheeled & valid
  own = jnp.where(pushed, jnp.max(jnp.where(behind, need, -jnp.inf), -1), -jnp.inf)
  # A push passes up a queue of ours: a car with a pushed car of ours close behind it in line
  # makes room as fast, or the follow bound holds the pushed one behind it (real val record 13).
  queue = in_line_behind & (gap < REAR_GUARD_QUEUE_GAP) & pushed[None] & pushed[:, None]
  passed_on = lambda _, a: jnp.maximum(a, jnp.max(jnp.where(queue, a[None], -jnp.inf), -1))
  return jax.lax.fori_loop(0, REAR_GUARD_QUEUE_HOPS, passed_on, own)


CRUISE_LOOKAHEAD = 30            # plan steps (3 s) whose turning the cruise hold reads
CRUISE_MAX_LATERAL = 1.5         # m/s^2: a plan that turns harder than this on average may slow for its turn


def cruise_floor(state: SimulatorState, plan: Array, bound: Array, hold) -> Array:
  """(O,) the least acceleration of a vehicle cruising on a free road: -hold[1] m/s^2 for a
  vehicle at hold[0] m/s or faster whose follow bound `bound` (O,) would not brake it (no
  leader or crossing object near on its path) and whose plan (O, T, 2 from now) turns less
  than CRUISE_MAX_LATERAL on average over the next CRUISE_LOOKAHEAD steps; -inf elsewhere.
  At highway speeds the plans brake where the logs keep their speed (docs/RESULTS.md,
  "Ablation: the cruise hold")."""
  min_speed, max_brake = hold
  cur = state.current_sim_trajectory
  speed = jnp.sqrt(jnp.sum(cur.vel_xy[:, 0] ** 2, -1))
  lateral = jnp.abs(jnp.mean(plan[:, :CRUISE_LOOKAHEAD, 1], -1)) * speed
  vehicle = state.object_metadata.object_types == ObjectType.VEHICLE
  free = vehicle & cur.valid[:, 0] & (speed >= min_speed) & (bound >= 0.0) & (lateral <= CRUISE_MAX_LATERAL)
  return jnp.where(free, -max_brake, -jnp.inf)


def safe_speed(gap: Array, lead_speed: Array, reaction: float, brake: float) -> Array:
  """The highest speed (...,) from which a follower that reacts after `reaction` s and then
  brakes at `brake` m/s^2 stops FOLLOW_MIN_GAP behind a leader `gap` m ahead (bumper to
  bumper) that brakes as hard from `lead_speed` (Gipps' safe speed); 0 where it cannot."""
  room = gap - FOLLOW_MIN_GAP + lead_speed ** 2 / (2.0 * brake)
  root = jnp.sqrt(jnp.maximum((brake * reaction) ** 2 + 2.0 * brake * room, 0.0))
  return jnp.where(room > 0, jnp.maximum(root - brake * reaction, 0.0), 0.0)


def follow_bound(state: SimulatorState, plan: Array, follow, dt: float,
                 followers: Optional[Array] = None, max_followers: Optional[int] = None,
                 crossing: bool = True) -> Array:
  """(O,) the highest acceleration that brings each vehicle or cyclist to its safe speed behind
  every leader on its planned path (O, T, 2 from now; `planned_path`) within the reaction
  time, and no harder than FOLLOW_MAX_BRAKE; +inf for other objects and where no leader is on the path.

  A leader is any valid object whose centre lies ahead on the path and whose box (as rotated
  against the path) comes within FOLLOW_SIDE_MARGIN of the follower's half width, that stands
  (below FOLLOW_STILL_SPEED) or heads within 60 degrees of the path. follow: (reaction s,
  braking m/s^2) of `safe_speed`. followers (O,): the objects to bound (+inf elsewhere), at
  most max_followers (static; any beyond are left unbound) of them; the search is followers x
  objects x path segments, so bounding only the executed agents halves it on a 128-object scene
  (docs/BENCHMARKS.md, "The follow bound for the executed agents only"). None: every object.
  crossing: a moving object crossing the path bounds too, as if standing where the plan would
  run into its side (`crossing_gaps`): the plans do not always see a slow crosser (real val: a
  car creeping at 1-2 m/s into the side of one passing in front of it; docs/RESULTS.md,
  "Ablation: crossing objects in the follow bound").
  The plans do not keep a follower behind a leader that brakes or starts more slowly than they
  expect: on real scenes ours' collisions were rear-end ones (docs/RESULTS.md, "Where ours
  collides")."""
  reaction, brake = follow
  cur = state.current_sim_trajectory
  num_objects = cur.xy.shape[0]
  if followers is None:
    index, chosen = jnp.arange(num_objects), jnp.ones((num_objects,), bool)
  else:
    size = min(num_objects, max_followers or num_objects)
    index = jnp.nonzero(followers, size=size, fill_value=0)[0]                        # (F,)
    chosen = jnp.arange(size) < jnp.sum(followers)
  now = dynamics.states_from_trajectory(cur)[:, 0]                                    # (O, 4)
  v = now[index, dynamics.V]                                                          # (F,)
  # Bumper to bumper: past the stopping distance the path must also reach the follower's front
  # and a leader's centre, or a plan that stops short misses the car it rolls into.
  reach = (jnp.maximum(v, 0.0) * reaction + jnp.maximum(v, 0.0) ** 2 / (2.0 * brake) + FOLLOW_MIN_GAP
           + 0.5 * cur.length[index, 0] + FOLLOW_LEADER_HALF_LENGTH)
  states = dynamics.rollout(now[index], plan[index], dt)                              # (F, T, 4)
  path = planned_path(now[index], states, reach)
  xy, yaw, valid = cur.xy[:, 0], cur.yaw[:, 0], cur.valid[:, 0]
  along, lateral, direction = _along_path(path, xy)                                   # (F, O)
  width, length = cur.width[:, 0], cur.length[:, 0]
  speed_along = jnp.sum(cur.vel_xy[None, :, 0] * direction, -1)                       # (F, O)
  heading_along = jnp.sum(geometry.unit(yaw)[None] * direction, -1)
  across = jnp.sqrt(jnp.maximum(1.0 - heading_along ** 2, 0.0))                         # |sin| to the path
  # The leader's box as the path sees it: a car standing at an angle reaches further across.
  half_across = 0.5 * (length[None] * across + width[None] * jnp.abs(heading_along))
  half_along = 0.5 * (length[None] * jnp.abs(heading_along) + width[None] * across)
  still = jnp.sqrt(jnp.sum(cur.vel_xy[:, 0] ** 2, -1)) < FOLLOW_STILL_SPEED
  leader = ((along > 0) & (lateral < 0.5 * width[index][:, None] + half_across + FOLLOW_SIDE_MARGIN)
            & (still[None] | (heading_along > FOLLOW_ALIGNED))
            & valid[None] & (index[:, None] != jnp.arange(num_objects)[None]))
  gap = along - 0.5 * length[index][:, None] - half_along
  v_safe = safe_speed(gap, jnp.maximum(speed_along, 0.0), reaction, brake)
  v_safe = jnp.min(jnp.where(leader, v_safe, jnp.inf), -1)                            # (F,)
  if crossing:
    reactive = jnp.ones((num_objects,), bool) if followers is None else followers
    across = crossing_gaps(states, index, cur, valid & ~still, reactive, dt)          # (F, N)
    v_safe = jnp.minimum(v_safe, jnp.min(safe_speed(across, 0.0, reaction, brake), -1))
  types = state.object_metadata.object_types[index]
  wheeled = (types == ObjectType.VEHICLE) | (types == ObjectType.CYCLIST)
  bound = jnp.maximum((v_safe - v) / reaction, -FOLLOW_MAX_BRAKE)   # Gipps: v_safe after the reaction time
  bound = jnp.where(chosen & wheeled & valid[index] & jnp.isfinite(v_safe), bound, jnp.inf)
  return jnp.full((num_objects,), jnp.inf).at[index].min(bound)
