"""IDM on each object's own logged path (Waymax's `IDMRoutePolicy` semantics).

Each controlled object (the reactive set, fixed at `init`):

- Route: its logged positions over the whole log (history and future, valid
  steps only, in time order), as a polyline with arclength; past its last
  logged point the route goes on straight along the last logged heading
  (Waymax extrapolates the same way by default). It reads the logged future,
  so WOSAC exports use the lane-following `idm.idm` instead.
- Still objects: an object slower than `static_speed` (1 m/s, Waymax's
  `_STATIC_SPEED_THRESHOLD`) at the start step is held at its start pose for
  the whole rollout. Waymax's constant is documented as "stationary objects
  are not updated"; in its code it only spares them from `invalidate_on_end`,
  and a parked car stays within about a metre because reaching its last
  waypoint freezes its velocity. We hold them exactly: parked cars stay parked.
- Speed: the IDM law along the route (a carried reference: arclength
  `progress`, speed `speed`). The leader is the nearest valid object (any:
  agents, the SDC, log-replayed ones) whose box reaches into the corridor of
  the follower's width along the route ahead, `lookahead` = clip(10 m + 4 s
  * v, 10, 80) m sampled at `num_samples` points (Waymax: boxes overlapping
  the follower's box moved up to 10 m ahead); the gap is bumper to bumper,
  the leader's speed its velocity along the route there (>= 0). The desired
  speed is the object's largest logged speed (Waymax: 30 m/s for every
  object, pedestrians included); `desired_speed` sets a fixed one.
- Action: the native [a, psi_dot] that takes the object to the route point
  `progress'` = progress + v' dt in one step (`KinematicModel.inverse`), so
  the object stays on its logged path to float precision unless a bound
  clips it (then it catches up along the route). Held objects brake to 0.

Pure jnp; one scenario per call (vmap for batches); no Python loop over
objects or time.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.baselines.idm import idm_acceleration
from pcdiff_jax.baselines.simple import ControlledFn, reactive_agents
from pcdiff_jax.config import KinematicsConfig
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, Array, SimulatorState, Trajectory
from pcdiff_jax.sim.dynamics import KinematicModel, states_from_trajectory


@dataclasses.dataclass(frozen=True)
class IDMRouteConfig:
  """IDM constants as Waymax's IDMRoutePolicy (s0 2 m, T 2 s, a 2, b 4 m/s^2,
  exponent 4) except the desired speed (None: each object's largest logged
  speed); the leader search; the still-object threshold."""
  desired_speed: Optional[float] = None   # m/s (v0); None: per object, its largest logged speed
  min_gap: float = 2.0                    # m (s0)
  headway: float = 2.0                    # s (T)
  max_accel: float = 2.0                  # m/s^2 (a_max)
  comfortable_decel: float = 4.0          # m/s^2 (b)
  exponent: float = 4.0
  max_brake: float = 8.0                  # m/s^2
  static_speed: float = 1.0               # m/s: slower at the start step -> held in place
  lookahead_min: float = 10.0             # m
  lookahead_time: float = 4.0             # s: the corridor reaches v * this beyond lookahead_min
  lookahead_max: float = 80.0             # m
  num_samples: int = 24                   # corridor samples along the route
  lateral_margin: float = 0.0             # m added to the corridor's half-width
  min_segment: float = 0.2                # m: shorter route segments take the logged yaw as heading
  kinematics: KinematicsConfig = KinematicsConfig()


@struct.dataclass
class Route:
  """Logged paths, one per object: xy (O, T, 2) and yaw (O, T) of the valid
  logged steps in time order (padded by repeating the last); s (O, T) the
  arclength at each point; last (O,) int32 the index of the last valid point."""
  xy: Array
  yaw: Array
  s: Array
  last: Array


@struct.dataclass
class RouteState:
  """The actor's carry: route; controlled, held (O,) bool (fixed at init);
  desired (O,) m/s; progress (O,) m along the route and speed (O,) m/s of
  each object's reference."""
  route: Route
  controlled: Array
  held: Array
  desired: Array
  progress: Array
  speed: Array


def logged_route(log: Trajectory) -> Route:
  """The Route of every object of a (O, T) log (unbatched)."""
  order = jnp.argsort(~log.valid, axis=-1, stable=True)                   # (O, T) valid steps first
  take = lambda a: jnp.take_along_axis(a, order, axis=-1)
  n = jnp.sum(log.valid, -1)                                               # (O,)
  last = jnp.maximum(n - 1, 0).astype(jnp.int32)
  k = jnp.arange(log.valid.shape[-1])
  keep = jnp.minimum(k[None], last[:, None])                               # (O, T) repeat the last
  xy = jnp.take_along_axis(jnp.stack([take(log.x), take(log.y)], -1), keep[..., None], axis=1)
  yaw = jnp.take_along_axis(take(log.yaw), keep, axis=1)
  seg = jnp.linalg.norm(xy[:, 1:] - xy[:, :-1], axis=-1)                   # (O, T-1), 0 past the last
  s = jnp.concatenate([jnp.zeros_like(seg[:, :1]), jnp.cumsum(seg, -1)], -1)
  return Route(xy=xy, yaw=yaw, s=s, last=last)


def route_points(route: Route, query: Array, min_segment: float = 0.2) -> tuple[Array, Array]:
  """Points at arclengths `query` (O, K) along each object's route: xy
  (O, K, 2) and heading (O, K) (the segment's direction, or the logged yaw
  on segments shorter than `min_segment` and past the end)."""
  def one(xy, yaw, s, last, q):                                            # (T, 2), (T,), (T,), (), (K,)
    i = jnp.clip(jnp.searchsorted(s, q, side="right") - 1, 0, last)
    j = jnp.minimum(i + 1, last)
    seg = xy[j] - xy[i]                                                    # (K, 2)
    seg_len = s[j] - s[i]
    frac = jnp.where(seg_len > 0, (q - s[i]) / jnp.where(seg_len > 0, seg_len, 1.0), 0.0)
    end = i >= last
    past = jnp.maximum(q - s[last], 0.0)
    on_route = xy[i] + frac[:, None] * seg
    beyond = xy[last] + past[:, None] * geometry.unit(yaw[last])
    heading = jnp.where(end | (seg_len < min_segment), yaw[i], jnp.arctan2(seg[:, 1], seg[:, 0]))
    return jnp.where(end[:, None], beyond, on_route), heading
  return jax.vmap(one)(route.xy, route.yaw, route.s, route.last, query)


def route_leader(state: SimulatorState, rs: RouteState, cfg: IDMRouteConfig) -> tuple[Array, Array]:
  """Bumper gap (O,) from each object's reference to its leader on the route
  ahead (inf where none) and the leader's speed along the route (>= 0).

  A candidate j is in i's corridor at sample k when j's box, projected on
  the axes of the route there, overlaps the slab of length L/K and width
  w_i + 2 margin around the sample (a one-sided separating-axis test:
  conservative for rotated boxes).
  """
  cur = state.current_sim_trajectory
  xy, yaw, valid = cur.xy[:, 0], cur.yaw[:, 0], cur.valid[:, 0]           # (O, 2), (O,), (O,)
  length, width, vel = cur.length[:, 0], cur.width[:, 0], cur.vel_xy[:, 0]
  k = cfg.num_samples
  look = jnp.clip(cfg.lookahead_min + cfg.lookahead_time * rs.speed, cfg.lookahead_min, cfg.lookahead_max)
  step = look / k                                                          # (O,)
  dist = (jnp.arange(k) + 0.5)[None] * step[:, None]                       # (O, K) ahead of the reference
  pts, heading = route_points(rs.route, rs.progress[:, None] + dist, cfg.min_segment)
  rel = geometry.to_local(xy[None, None], pts[:, :, None], heading[:, :, None])   # (O, K, O, 2): j at i's k
  phi = yaw[None, None] - heading[:, :, None]                              # (O, K, O)
  c, s = jnp.abs(jnp.cos(phi)), jnp.abs(jnp.sin(phi))
  ex = 0.5 * (length[None, None] * c + width[None, None] * s)               # j's half extent along the route
  ey = 0.5 * (length[None, None] * s + width[None, None] * c)               # ... and across it
  along = dist[:, :, None] + rel[..., 0]                                   # j's centre ahead of i's reference
  num = xy.shape[0]
  hit = ((jnp.abs(rel[..., 0]) <= 0.5 * step[:, None, None] + ex)
         & (jnp.abs(rel[..., 1]) <= 0.5 * width[:, None, None] + cfg.lateral_margin + ey)
         & (along > 0) & valid[None, None] & ~jnp.eye(num, dtype=bool)[:, None])
  gap = jnp.where(hit, along - 0.5 * length[:, None, None] - ex, jnp.inf)    # (O, K, O)
  flat = gap.reshape(num, -1)                                              # (O, K*O)
  best = jnp.argmin(flat, axis=-1)
  lead_gap = jnp.take_along_axis(flat, best[:, None], -1)[:, 0]
  at_k, lead = best // num, best % num
  tangent = geometry.unit(jnp.take_along_axis(heading, at_k[:, None], -1)[:, 0])  # (O, 2)
  lead_speed = jnp.maximum(jnp.sum(vel[lead] * tangent, -1), 0.0)
  return lead_gap, lead_speed


def init_route_state(state: SimulatorState, controlled: Array, cfg: IDMRouteConfig) -> RouteState:
  """The carry at the current step of a reset state: each object's reference
  at its logged point of this step, at its current speed."""
  log = state.log_trajectory
  route = logged_route(log)
  t = state.timestep
  index = jnp.maximum(jnp.cumsum(log.valid, -1)[:, t] - 1, 0)               # (O,) its point in the route
  progress = jnp.take_along_axis(route.s, index[:, None], -1)[:, 0]
  speed = state.current_sim_trajectory.speed[:, 0]
  logged_max = jnp.max(jnp.where(log.valid, log.speed, 0.0), -1)
  desired = logged_max if cfg.desired_speed is None else jnp.full_like(speed, cfg.desired_speed)
  held = controlled & (speed < cfg.static_speed)
  return RouteState(route=route, controlled=controlled, held=held, desired=jnp.maximum(desired, 1e-3),
                    progress=progress, speed=speed)


def route_actions(state: SimulatorState, rs: RouteState, cfg: IDMRouteConfig) -> tuple[Array, RouteState]:
  """(O, 2) [a, psi_dot] of every object of one scenario and the advanced carry."""
  gap, lead_speed = route_leader(state, rs, cfg)
  accel = idm_acceleration(rs.speed, gap, lead_speed, cfg, desired_speed=rs.desired)
  dt = cfg.kinematics.dt
  speed = jnp.maximum(rs.speed + accel * dt, 0.0)
  progress = rs.progress + speed * dt
  target_xy, _ = route_points(rs.route, progress[:, None], cfg.min_segment)   # (O, 1, 2)
  cur = state.current_sim_trajectory
  target = cur.replace(x=target_xy[..., 0], y=target_xy[..., 1])
  follow = KinematicModel(cfg.kinematics).inverse(cur, target).data       # (O, 2)
  v = states_from_trajectory(cur)[:, 0, 3]                                 # signed speed
  hold = jnp.stack([-v / dt, jnp.zeros_like(v)], -1)
  data = jnp.where(rs.held[:, None], hold, follow)
  return data, rs.replace(progress=progress, speed=speed)


def idm_route(cfg: IDMRouteConfig = IDMRouteConfig(), controlled_fn: ControlledFn = reactive_agents(),
              name: str = "idm") -> Actor:
  """The route IDM as an Actor (controlled set, routes and held objects fixed
  at `init`; reads the whole logged trajectory)."""
  def init(rng, state):
    del rng
    return init_route_state(state, controlled_fn(state), cfg)

  def select_action(params, state, actor_state, rng):
    del params, rng
    data, actor_state = route_actions(state, actor_state, cfg)
    controlled = actor_state.controlled
    valid = state.current_sim_trajectory.valid[..., 0] & controlled
    data = jnp.where(valid[:, None], data, 0.0).astype(jnp.float32)
    return ActorOutput(actor_state=actor_state, action=Action(data=data, valid=valid[:, None]),
                       is_controlled=controlled)
  return Actor(select_action=select_action, init=init, name=name)
