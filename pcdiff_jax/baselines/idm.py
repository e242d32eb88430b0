"""IDM baseline `idm-lane`: lane following with the Intelligent Driver Model.

It reads no logged future (WOSAC exports use it); `route.idm_route` is the IDM on
each object's logged path that `experiments.rollout` calls `idm`.

Each controlled agent (the reactive set, fixed at `init`) at every step:

- Lane: the lane-centre sample (WOMD types 1-3) nearest to a point
  `lookahead` metres ahead of the agent among those whose direction is within
  45 degrees of the agent's heading; this follows its lane and, at the end of
  a lane, the connecting lane whose start lies ahead (WOMD records carry no
  explicit successors). Steering is pure pursuit towards that sample:
  psi_dot = v * 2 sin(alpha) / d, alpha the bearing of the sample.
  No lane sample in range: the heading is held. The candidate samples are
  the `max_lane_points` lane-centre samples nearest the SDC, fixed at `init`
  (a search over the whole roadgraph at every step cost ~75 ms per scenario
  step on CPU).
- Speed: IDM (Treiber et al.) with the leader the nearest valid object whose
  centre lies ahead in a corridor of half-width `corridor` around the
  heading line (all objects: other agents, the SDC, log-replayed ones):
  a = a_max [1 - (v / v0)^4 - (s* / s)^2],
  s* = s0 + v T + v dv / (2 sqrt(a_max b)), s = bumper gap.
  Traffic lights and stop signs are ignored (the paper's baseline: no
  map rules beyond the lane).

Emits [a, psi_dot] for the kinematic model. Pure jnp; one scenario per call.
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.baselines.simple import ControlledFn, reactive_agents
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.actors import Actor, ActorOutput
from pcdiff_jax.sim.datatypes import Action, Array, SimulatorState, is_lane_center


@dataclasses.dataclass(frozen=True)
class IDMConfig:
  desired_speed: float = 15.0      # m/s (v0); Waymax's own IDM uses 30 m/s on logged paths
  min_gap: float = 2.0             # m (s0)
  headway: float = 1.5             # s (T)
  max_accel: float = 2.0           # m/s^2 (a_max)
  comfortable_decel: float = 3.0   # m/s^2 (b)
  exponent: float = 4.0
  lookahead: float = 6.0           # m, pure-pursuit target distance
  corridor: float = 1.8            # m, half-width of the leader search
  max_brake: float = 8.0           # m/s^2
  max_lane_points: int = 4096      # lane-centre samples kept (nearest the SDC at init)


@struct.dataclass
class LaneSamples:
  """Lane-centre samples an IDM actor steers by: xy, dir (P, 2), valid (P,)."""
  xy: Array
  dir: Array
  valid: Array


def lane_samples(state: SimulatorState, max_points: int) -> LaneSamples:
  """The `max_points` lane-centre samples nearest the SDC at the current step."""
  rg = state.roadgraph_points
  lane = rg.valid & is_lane_center(rg.types)
  cur = state.current_sim_trajectory
  sdc_xy = jnp.sum(jnp.where(state.object_metadata.is_sdc[:, None], cur.xy[:, 0], 0.0), 0)
  d2 = jnp.where(lane, jnp.sum((rg.xy - sdc_xy) ** 2, -1), jnp.inf)
  k = min(max_points, d2.shape[0])
  neg, idx = jax.lax.top_k(-d2, k)
  return LaneSamples(xy=rg.xy[idx], dir=rg.dir_xy[idx], valid=jnp.isfinite(neg))


def _leader_gap(state: SimulatorState, cfg: IDMConfig) -> tuple[Array, Array]:
  """Bumper gap (O,) to the leader of each object and the leader's speed
  along the follower's heading (inf gap where none)."""
  cur = state.current_sim_trajectory
  xy, yaw, valid = cur.xy[:, 0], cur.yaw[:, 0], cur.valid[:, 0]
  length = cur.length[:, 0]
  vel = cur.vel_xy[:, 0]
  rel = geometry.to_local(xy[None, :, :], xy[:, None, :], yaw[:, None])     # (O, O, 2): j in i's frame
  ahead = (rel[..., 0] > 0) & (jnp.abs(rel[..., 1]) < cfg.corridor)
  ahead = ahead & valid[None, :] & ~jnp.eye(xy.shape[0], dtype=bool)
  gap = rel[..., 0] - 0.5 * (length[:, None] + length[None, :])
  gap = jnp.where(ahead, gap, jnp.inf)
  j = jnp.argmin(gap, axis=1)
  lead_gap = jnp.take_along_axis(gap, j[:, None], 1)[:, 0]
  lead_speed = jnp.sum(vel[j] * geometry.unit(yaw), -1)
  return lead_gap, lead_speed


def idm_acceleration(speed: Array, gap: Array, lead_speed: Array, cfg: IDMConfig,
                     desired_speed: Optional[Array] = None) -> Array:
  """IDM acceleration (...,); an infinite gap is free driving. desired_speed
  (...,) overrides cfg.desired_speed (e.g. one per object)."""
  v0 = cfg.desired_speed if desired_speed is None else desired_speed
  dv = speed - lead_speed
  s_star = cfg.min_gap + jnp.maximum(speed * cfg.headway + speed * dv / (
      2.0 * jnp.sqrt(cfg.max_accel * cfg.comfortable_decel)), 0.0)
  free = 1.0 - (jnp.maximum(speed, 0.0) / v0) ** cfg.exponent
  finite = jnp.isfinite(gap)
  safe_gap = jnp.where(finite, jnp.maximum(gap, 0.1), 1.0)
  interaction = jnp.where(finite, (s_star / safe_gap) ** 2, 0.0)
  return jnp.clip(cfg.max_accel * (free - interaction), -cfg.max_brake, cfg.max_accel)


def pursuit_yaw_rate(xy: Array, yaw: Array, speed: Array, lanes: LaneSamples, lookahead: Array,
                     min_ahead: float = -jnp.inf) -> tuple[Array, Array]:
  """Pure pursuit of the lane-centre sample nearest a probe `lookahead` (m)
  ahead of each pose xy (N, 2), yaw, speed (N,), among samples within 45
  degrees of the heading (and at least `min_ahead` m ahead of the pose):
  (yaw rate (N,), whether a sample was found (N,); 0 where none)."""
  heading = geometry.unit(yaw)                                             # (N, 2)
  aligned = jnp.sum(lanes.dir[None] * heading[:, None], -1) > jnp.cos(jnp.pi / 4)
  rel = lanes.xy[None] - xy[:, None]                                        # (N, P, 2)
  ahead = jnp.sum(rel * heading[:, None], -1) >= min_ahead
  probe = jnp.broadcast_to(jnp.asarray(lookahead, xy.dtype), yaw.shape)[:, None, None] * heading[:, None]
  d2 = jnp.sum((rel - probe) ** 2, -1)                                      # (N, P)
  d2 = jnp.where(lanes.valid[None] & aligned & ahead, d2, jnp.inf)
  k = jnp.argmin(d2, axis=1)
  found = jnp.isfinite(jnp.take_along_axis(d2, k[:, None], 1)[:, 0])
  target = geometry.to_local(lanes.xy[k], xy, yaw)                          # (N, 2)
  dist2 = jnp.sum(target ** 2, -1) + 1e-6
  curvature = 2.0 * target[:, 1] / dist2                                    # 2 sin(alpha) / d
  return jnp.where(found, speed * curvature, 0.0), found


def _pursuit_yaw_rate(state: SimulatorState, lanes: LaneSamples, cfg: IDMConfig) -> Array:
  cur = state.current_sim_trajectory
  return pursuit_yaw_rate(cur.xy[:, 0], cur.yaw[:, 0], cur.speed[:, 0], lanes, cfg.lookahead)[0]


def idm_actions(state: SimulatorState, cfg: IDMConfig = IDMConfig(),
                lanes: Optional[LaneSamples] = None) -> Array:
  """(O, 2) [a, psi_dot] for every object of one scenario (lanes: the
  `lane_samples` of this state when None)."""
  cur = state.current_sim_trajectory
  lanes = lane_samples(state, cfg.max_lane_points) if lanes is None else lanes
  gap, lead_speed = _leader_gap(state, cfg)
  accel = idm_acceleration(cur.speed[:, 0], gap, lead_speed, cfg)
  return jnp.stack([accel, _pursuit_yaw_rate(state, lanes, cfg)], -1)


def sdc_only(state: SimulatorState) -> Array:
  """(O,) the SDC alone: a controlled set for an IDM ego."""
  return state.object_metadata.is_sdc & state.current_sim_trajectory.valid[..., 0]


def idm(cfg: IDMConfig = IDMConfig(), controlled_fn: ControlledFn = reactive_agents(),
        name: str = "idm-lane") -> Actor:
  """The IDM baseline as an Actor (controlled set and lane samples fixed at
  `init`). `controlled_fn=sdc_only` makes it the ego policy."""
  def init(rng, state):
    del rng
    return controlled_fn(state), lane_samples(state, cfg.max_lane_points)

  def select_action(params, state, actor_state, rng):
    del params, rng
    controlled, lanes = actor_state
    valid = state.current_sim_trajectory.valid[..., 0] & controlled
    data = jnp.where(valid[:, None], idm_actions(state, cfg, lanes), 0.0).astype(jnp.float32)
    return ActorOutput(actor_state=actor_state, action=Action(data=data, valid=valid[:, None]),
                       is_controlled=controlled)
  return Actor(select_action=select_action, init=init, name=name)
