"""Test-time guidance in latent space: map and collision objectives, and
adversarial pursuit-evasion (iterated best response) against the ego.

At chosen (late) DDIM steps the sampler's y0 estimate (..., A, d) is decoded
into actions, rolled out with f and placed in the scene frame; a few
gradient steps y0 <- y0 - eta grad J edit it in latent space. The gradient
goes through decode + rollout only, never through the denoiser, and the
edit runs inside the sampler's `lax.scan` (`diffusion.ddim_sample`'s hook).

Costs (all per agent, padded agents contribute 0, finite gradients for
coincident agents and empty maps):

  J_map   vehicles' box corners against road edges (every `map_stride`-th
          step): mean of relu(signed distance + margin)^2; the signed
          distance is Waymax's off-road test (positive = off road), read
          from a grid computed once per scenario (`sim.road_field`).
  J_coll  3 circles per agent (rear, middle, front; radius width / 2) over
          the first `coll_horizon` steps: sum over other agents of
          relu(r_i + r_j + margin - distance)^2.
  J_pursue  soft minimum over the first `coll_horizon` steps of the
          pursuer-evader distance.

Adversarial mode: the SDC (agent slot 0) is the evader, one pursuer (an
object slot: the user's, or the most threatening agent at the rollout
start, `most_threatening`). Each of `ibr_rounds` rounds takes `inner_steps`
best-response steps for the pursuer on w_pursue J_pursue + w_map J_map,
then for the evader on -w_pursue J_pursue + J_obj, then objective steps for
everyone else, each decoding and rolling out before its gradient.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.sim import geometry, road_field
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState
from pcdiff_jax.sim.road_field import RoadField

MODES = ("none", "objective", "adversarial")
_EPS = 1e-6


@dataclasses.dataclass(frozen=True)
class GuidanceConfig:
  """mode: none | objective | adversarial. eta: latent step size; inner_steps
  gradient steps per guided DDIM step; guided_steps: the last k DDIM steps
  are guided; adversary: object slot of the pursuer (-1: most threatening).
  w_map, w_coll: weights of J_map and J_coll; None takes the mode's own
  (`map_weight`, `coll_weight`)."""
  mode: str = "none"
  w_map: Optional[float] = None
  w_coll: Optional[float] = None
  w_pursue: float = 10.0
  eta: float = 0.05
  max_step: float = 10.0           # latent units per agent and inner step (prior sigma norm ~ 9)
  inner_steps: int = 2
  guided_steps: int = 2
  ibr_rounds: int = 2
  coll_horizon: int = 30           # steps (3 s)
  coll_neighbors: int = 8          # agents each agent's J_coll looks at
  map_stride: int = 4
  map_margin: float = 0.3          # m
  coll_margin: float = 0.3         # m
  pursuit_temperature: float = 1.0  # m, of the soft minimum
  field_size: int = 256            # cells per side of the road field (+-255 m around the SDC;
                                   # 128 left the far agents of long roads without J_map)
  field_spacing: float = 2.0       # m; bilinear is exact across straight edges
  max_edge_points: int = 4096      # road-edge samples the field is built from
  adversary: int = -1

  @property
  def map_weight(self) -> float:
    """w_map, or the mode's default: 100 for objective guidance (chosen on the
    first 50 val scenes from 1-300 with the v5 model), 1 for
    the adversarial game (the weight Table III was measured with)."""
    if self.w_map is not None:
      return self.w_map
    return 100.0 if self.mode == "objective" else 1.0

  @property
  def coll_weight(self) -> float:
    """w_coll, or the mode's default: 10 for objective guidance (chosen on all
    200 val scenes from 1 / 3 / 10 by a rule fixed before the run, with 8
    samples per replan: docs/RESULTS.md, "Ablation: objective guidance's
    collision weight"), 1 for the adversarial game (the weight Table III was measured with)."""
    if self.w_coll is not None:
      return self.w_coll
    return 10.0 if self.mode == "objective" else 1.0

  def validate(self) -> None:
    if self.mode not in MODES:
      raise ValueError(f"guidance mode must be one of {MODES}, got {self.mode!r}")
    for name in ("inner_steps", "guided_steps", "ibr_rounds", "coll_horizon", "map_stride",
                 "max_edge_points", "field_size", "coll_neighbors"):
      if getattr(self, name) < 1:
        raise ValueError(f"guidance {name} must be >= 1, got {getattr(self, name)}")
    if self.field_spacing <= 0:
      raise ValueError(f"guidance field_spacing must be > 0, got {self.field_spacing}")
    if self.max_step <= 0:
      raise ValueError(f"guidance max_step must be > 0, got {self.max_step}")
    if self.w_map is not None and self.w_map < 0:
      raise ValueError(f"guidance w_map must be >= 0, got {self.w_map}")
    if self.w_coll is not None and self.w_coll < 0:
      raise ValueError(f"guidance w_coll must be >= 0, got {self.w_coll}")
    if self.eta < 0:
      raise ValueError(f"guidance eta must be >= 0, got {self.eta}")

  def guide_steps(self, num_sample_steps: int) -> np.ndarray:
    """(n,) bool: the last `guided_steps` of n DDIM steps."""
    return np.arange(num_sample_steps) >= num_sample_steps - self.guided_steps


@struct.dataclass
class Agents:
  """What the costs need of the modelled agents (..., A): sizes, validity,
  which are vehicles, and the pursuer / evader slots (..., ) (-1: none)."""
  length: Array
  width: Array
  valid: Array
  vehicle: Array
  pursuer: Array
  evader: Array


# ----------------------------------------------------------------------------
# Costs: xy (..., A, T, 2), yaw (..., A, T) in the scene frame.


def map_cost(xy: Array, yaw: Array, agents: Agents, road: RoadField, cfg: GuidanceConfig) -> Array:
  """(..., A) mean squared excursion of the vehicles' box corners past the
  road edge; road: the scene's field, queried in the frame of xy."""
  excess = jnp.maximum(_corners_past_edge(xy, yaw, agents, road, cfg) + cfg.map_margin, 0.0)
  per_agent = jnp.mean(excess ** 2, axis=(-1, -2))
  return jnp.where(agents.valid & agents.vehicle, per_agent, 0.0)


def map_excursion(xy: Array, yaw: Array, agents: Agents, road: RoadField, cfg: GuidanceConfig) -> Array:
  """(..., A) the furthest any box corner of each vehicle gets past the road edge (m; < 0
  inside), over the steps map_cost reads; -inf for other agents."""
  furthest = jnp.max(_corners_past_edge(xy, yaw, agents, road, cfg), axis=(-1, -2))
  return jnp.where(agents.valid & agents.vehicle, furthest, -jnp.inf)


def _corners_past_edge(xy: Array, yaw: Array, agents: Agents, road: RoadField,
                       cfg: GuidanceConfig) -> Array:
  """(..., A, T', 4) signed distance of the box corners past the road edge (> 0 outside) at
  every map_stride-th step of xy (..., A, T, 2)."""
  xy, yaw = xy[..., ::cfg.map_stride, :], yaw[..., ::cfg.map_stride]
  corners = geometry.box_corners(xy[..., 0], xy[..., 1], yaw, agents.length[..., None],
                                 agents.width[..., None])                    # (..., A, T', 4, 2)
  shape = corners.shape
  flat = corners.reshape(shape[:-4] + (-1, 2))
  return road_field.lookup(road, flat).reshape(shape[:-1])


def _gather_agents(a: Array, index: Array) -> Array:
  """a (..., A, *rest) gathered at index (..., A, k) -> (..., A, k, *rest)."""
  batch = a.shape[:-4]
  flat_a = a.reshape((-1,) + a.shape[len(batch):])
  flat_i = index.reshape((-1,) + index.shape[len(batch):])
  out = jax.vmap(lambda x, i: x[i])(flat_a, flat_i)
  return out.reshape(batch + out.shape[1:])


def _pair_overlaps(c: Array, near_c: Array, r: Array, near_r: Array, margin: float) -> Array:
  """(..., A, k) summed squared overlaps of each agent's circles c (..., A, H, 3, 2)
  with those of its k neighbours near_c (..., A, k, H, 3, 2)."""
  diff = c[..., :, None, :, :, None, :] - near_c[..., :, :, :, None, :, :]   # (..., A, k, H, 3, 3, 2)
  dist = jnp.sqrt(jnp.sum(diff ** 2, -1) + _EPS)
  reach = (r[..., :, None] + near_r + margin)[..., None, None, None]
  return jnp.sum(jnp.maximum(reach - dist, 0.0) ** 2, axis=(-1, -2, -3))


def _circles(xy: Array, yaw: Array, agents: Agents, cfg: GuidanceConfig) -> Array:
  """(..., A, H, 3, 2) circle centres over the first coll_horizon steps."""
  h = cfg.coll_horizon
  return geometry.box_circles(xy[..., :h, :], yaw[..., :h], agents.length[..., None],
                              agents.width[..., None])


def collision_cost(xy: Array, yaw: Array, agents: Agents, cfg: GuidanceConfig) -> Array:
  """(..., A) squared circle overlaps with the other valid agents over the near
  term. Only each agent's `coll_neighbors` nearest agents (closest approach
  of the box centres over the horizon, no gradient) are scored: O(A k), not
  O(A^2), and the same value whenever an agent touches at most k others."""
  c = _circles(xy, yaw, agents, cfg)                                       # (..., A, H, 3, 2)
  num = agents.valid.shape[-1]
  k = min(cfg.coll_neighbors, num - 1)
  if k < 1:
    return jnp.zeros_like(agents.length)
  centre = jax.lax.stop_gradient(c[..., 1, :])                             # (..., A, H, 2)
  closest = jnp.min(jnp.sum((centre[..., :, None, :, :] - centre[..., None, :, :, :]) ** 2, -1), -1)
  pair = agents.valid[..., :, None] & agents.valid[..., None, :] & ~jnp.eye(num, dtype=bool)
  _, near = jax.lax.top_k(-jnp.where(pair, closest, jnp.inf), k)           # (..., A, k)
  near_ok = jnp.take_along_axis(pair, near, axis=-1)
  near_c = _gather_agents(c, near)                                         # (..., A, k, H, 3, 2)
  r = agents.width / 2.0
  near_r = jnp.take_along_axis(r[..., None, :], near, axis=-1)             # (..., A, k)
  overlap = _pair_overlaps(c, near_c, r, near_r, cfg.coll_margin)          # (..., A, k)
  return jnp.sum(jnp.where(near_ok, overlap, 0.0), -1)


def _take(a: Array, slot: Array, axis_from_end: int) -> Array:
  """a[..., slot, <axis_from_end - 1 trailing dims>] keeping the slot axis (size 1)."""
  index = jnp.maximum(slot, 0).reshape(slot.shape + (1,) * axis_from_end)
  return jnp.take_along_axis(a, index, axis=-axis_from_end)


def agent_objective(xy: Array, yaw: Array, agents: Agents, road: RoadField, cfg: GuidanceConfig,
                    slot: Array) -> Array:
  """(...,) the objective of one agent slot (...,) alone: its J_map and its
  overlaps with every other valid agent. Equals objective(...)[..., slot]
  at O(A) instead of O(A^2) cost (the evader's best response)."""
  one = lambda a, k: _take(a, slot, k)
  mine = Agents(length=one(agents.length, 1), width=one(agents.width, 1), valid=one(agents.valid, 1),
                vehicle=one(agents.vehicle, 1), pursuer=agents.pursuer, evader=agents.evader)
  own_xy, own_yaw = one(xy, 3), one(yaw, 2)
  own_map = map_cost(own_xy, own_yaw, mine, road, cfg)[..., 0]
  c = _circles(xy, yaw, agents, cfg)
  overlap = _pair_overlaps(_circles(own_xy, own_yaw, mine, cfg), c[..., None, :, :, :, :],
                           mine.width / 2.0, agents.width[..., None, :] / 2.0, cfg.coll_margin)[..., 0, :]  # (..., A)
  others = agents.valid & (jnp.arange(agents.valid.shape[-1]) != slot[..., None]) & mine.valid
  own_coll = jnp.sum(jnp.where(others, overlap, 0.0), -1)
  return jnp.where((slot >= 0) & mine.valid[..., 0], cfg.map_weight * own_map + cfg.coll_weight * own_coll, 0.0)


def pursuit_cost(xy: Array, agents: Agents, cfg: GuidanceConfig) -> Array:
  """(...,) soft minimum over the near term of the pursuer-evader distance (0 without a pair)."""
  h = cfg.coll_horizon
  take = lambda slot: _take(xy[..., :h, :], slot, 3)[..., 0, :, :]          # (..., H, 2)
  dist = jnp.sqrt(jnp.sum((take(agents.pursuer) - take(agents.evader)) ** 2, -1) + _EPS)
  tau = cfg.pursuit_temperature
  soft_min = -tau * jax.nn.logsumexp(-dist / tau, axis=-1) + tau * jnp.log(dist.shape[-1])
  has_pair = (agents.pursuer >= 0) & (agents.evader >= 0) & (agents.pursuer != agents.evader)
  return jnp.where(has_pair, soft_min, 0.0)


def objective(xy: Array, yaw: Array, agents: Agents, road: RoadField, cfg: GuidanceConfig) -> Array:
  """(..., A) per-agent objective w_map J_map + w_coll J_coll."""
  return (cfg.map_weight * map_cost(xy, yaw, agents, road, cfg)
          + cfg.coll_weight * collision_cost(xy, yaw, agents, cfg))


# ----------------------------------------------------------------------------
# Guides for `diffusion.ddim_sample`.

PoseFn = Callable[[Array], tuple[Array, Array]]   # y0 (..., A, d) -> xy (..., A, T, 2), yaw


def _descend(cost: Callable[[Array], Array], y: Array, mask: Array, cfg: GuidanceConfig) -> Array:
  """`inner_steps` steps of y <- y - eta grad cost, on the agents of mask (..., A)
  only; each agent's step is clipped to norm max_step (a trust region: the
  squared overlaps of a deep collision have gradients hundreds of times those
  of a slight one, and an unclipped step would throw the agent far away)."""
  def body(y, _):
    g = jax.grad(cost)(y)
    g = jnp.where(jnp.isfinite(g), g, 0.0)
    step = cfg.eta * jnp.where(mask[..., None], g, 0.0)
    norm = jnp.sqrt(jnp.sum(step ** 2, -1, keepdims=True) + _EPS)
    return y - step * jnp.minimum(1.0, cfg.max_step / norm), None
  y, _ = jax.lax.scan(body, y, None, length=cfg.inner_steps)
  return y


def objective_guide(poses: PoseFn, agents: Agents, road: RoadField, cfg: GuidanceConfig):
  """guide(y0, y_s, s, i) -> y0 after objective steps for every valid agent."""
  def total(y):
    xy, yaw = poses(y)
    return jnp.sum(objective(xy, yaw, agents, road, cfg))

  def guide(y0, y_s, s, i):
    del y_s, s, i
    return _descend(total, y0, agents.valid, cfg)
  return guide


def _slot_mask(slot: Array, num: int) -> Array:
  """(..., A) one-hot of slot (...,) (all False for -1)."""
  return (jnp.arange(num) == slot[..., None]) & (slot[..., None] >= 0)


def adversarial_guide(poses: PoseFn, agents: Agents, road: RoadField, cfg: GuidanceConfig):
  """guide(y0, ...) -> y0 after `ibr_rounds` rounds of pursuer, evader and
  objective best responses (each with its own decode + rollout)."""
  num = agents.valid.shape[-1]
  pursuer = _slot_mask(agents.pursuer, num) & agents.valid
  evader = _slot_mask(agents.evader, num) & agents.valid
  others = agents.valid & ~pursuer & ~evader

  # The pursuer keeps to the road (J_map, no collision term: it is meant to
  # hit the evader); the evader keeps its full objective.
  map_only = dataclasses.replace(cfg, w_coll=0.0)

  def pursue(y):
    xy, yaw = poses(y)
    own = agent_objective(xy, yaw, agents, road, map_only, agents.pursuer)
    return jnp.sum(cfg.w_pursue * pursuit_cost(xy, agents, cfg) + own)

  def evade(y):
    xy, yaw = poses(y)
    own = agent_objective(xy, yaw, agents, road, cfg, agents.evader)
    return jnp.sum(-cfg.w_pursue * pursuit_cost(xy, agents, cfg) + own)

  def rest(y):
    xy, yaw = poses(y)
    return jnp.sum(objective(xy, yaw, agents, road, cfg))

  def guide(y0, y_s, s, i):
    del y_s, s, i
    def round_(y, _):
      y = _descend(pursue, y, pursuer, cfg)
      y = _descend(evade, y, evader, cfg)
      return _descend(rest, y, others, cfg), None
    y0, _ = jax.lax.scan(round_, y0, None, length=cfg.ibr_rounds)
    return y0
  return guide


def make_guide(poses: PoseFn, agents: Agents, road: RoadField, cfg: GuidanceConfig):
  """The guide of cfg.mode (None for 'none')."""
  if cfg.mode == "objective":
    return objective_guide(poses, agents, road, cfg)
  if cfg.mode == "adversarial":
    return adversarial_guide(poses, agents, road, cfg)
  return None


def road_of(state: SimulatorState, cfg: GuidanceConfig) -> RoadField:
  """The scene's road field around the SDC at the current step (a 2 x 2
  placeholder without guidance, so the actor state keeps one structure)."""
  size = cfg.field_size if cfg.mode != "none" else 2
  sdc = jnp.argmax(state.object_metadata.is_sdc)
  center = state.current_sim_trajectory.xy[sdc, 0]
  if cfg.mode == "none":
    return road_field.from_edges(jnp.zeros((1, 2)), jnp.zeros((1, 2)), jnp.zeros((1,), jnp.int32),
                                 jnp.zeros((1,), bool), center, size, cfg.field_spacing)
  return road_field.build(state.roadgraph_points, center, size, cfg.field_spacing, cfg.max_edge_points)


def most_threatening(state: SimulatorState, candidates: Array, horizon_s: float = 3.0) -> Array:
  """() int32 object slot: the candidate (O,) vehicle whose constant-velocity
  extrapolation comes closest to the SDC's within `horizon_s` (-1: none)."""
  cur = state.current_sim_trajectory
  xy, vel = cur.xy[:, 0], cur.vel_xy[:, 0]
  sdc = jnp.argmax(state.object_metadata.is_sdc)
  t = jnp.linspace(0.0, horizon_s, 31)
  rel = (xy - xy[sdc])[:, None, :] + (vel - vel[sdc])[:, None, :] * t[None, :, None]  # (O, 31, 2)
  closest = jnp.min(jnp.sum(rel ** 2, -1), -1)
  ok = candidates & cur.valid[:, 0] & (state.object_metadata.object_types == ObjectType.VEHICLE)
  closest = jnp.where(ok, closest, jnp.inf)
  best = jnp.argmin(closest)
  return jnp.where(jnp.isfinite(closest[best]), best, -1).astype(jnp.int32)
