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
          distance is Waymax's off-road test (positive = off road).
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
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array, ObjectType, SimulatorState
from pcdiff_jax.sim.metrics import road_edges

MODES = ("none", "objective", "adversarial")
_EPS = 1e-6


@dataclasses.dataclass(frozen=True)
class GuidanceConfig:
  """mode: none | objective | adversarial. eta: latent step size; inner_steps
  gradient steps per guided DDIM step; guided_steps: the last k DDIM steps
  are guided; adversary: object slot of the pursuer (-1: most threatening)."""
  mode: str = "none"
  w_map: float = 1.0
  w_coll: float = 1.0
  w_pursue: float = 10.0
  eta: float = 0.05
  inner_steps: int = 2
  guided_steps: int = 2
  ibr_rounds: int = 2
  coll_horizon: int = 30           # steps (3 s)
  map_stride: int = 4
  map_margin: float = 0.3          # m
  coll_margin: float = 0.3         # m
  pursuit_temperature: float = 1.0  # m, of the soft minimum
  max_edge_points: int = 1024
  adversary: int = -1

  def validate(self) -> None:
    if self.mode not in MODES:
      raise ValueError(f"guidance mode must be one of {MODES}, got {self.mode!r}")
    for name in ("inner_steps", "guided_steps", "ibr_rounds", "coll_horizon", "map_stride",
                 "max_edge_points"):
      if getattr(self, name) < 1:
        raise ValueError(f"guidance {name} must be >= 1, got {getattr(self, name)}")
    if self.eta < 0:
      raise ValueError(f"guidance eta must be >= 0, got {self.eta}")

  def guide_steps(self, num_sample_steps: int) -> np.ndarray:
    """(n,) bool: the last `guided_steps` of n DDIM steps."""
    return np.arange(num_sample_steps) >= num_sample_steps - self.guided_steps


@struct.dataclass
class Edges:
  """Road-edge samples in the scene frame: xy, dir (..., E, 2); ids, valid (..., E)."""
  xy: Array
  dir: Array
  ids: Array
  valid: Array


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


def scene_edges(state: SimulatorState, scene_xy: Array, scene_yaw: Array, max_points: int) -> Edges:
  """The `max_points` road-edge samples nearest the scene origin, in the scene
  frame. One scene."""
  xy, direction, ids, valid = road_edges(state.roadgraph_points, scene_xy, max_points)
  local = geometry.to_local(xy, scene_xy, scene_yaw)
  c, s = jnp.cos(scene_yaw), jnp.sin(scene_yaw)
  local_dir = jnp.stack([c * direction[..., 0] + s * direction[..., 1],
                         -s * direction[..., 0] + c * direction[..., 1]], -1)
  return Edges(xy=local, dir=local_dir, ids=ids, valid=valid)


# ----------------------------------------------------------------------------
# Costs: xy (..., A, T, 2), yaw (..., A, T) in the scene frame.


def map_cost(xy: Array, yaw: Array, agents: Agents, edges: Edges, cfg: GuidanceConfig) -> Array:
  """(..., A) mean squared excursion of the vehicles' box corners past the road edge."""
  xy, yaw = xy[..., ::cfg.map_stride, :], yaw[..., ::cfg.map_stride]
  corners = geometry.box_corners(xy[..., 0], xy[..., 1], yaw, agents.length[..., None],
                                 agents.width[..., None])                    # (..., A, T', 4, 2)
  shape = corners.shape
  flat = corners.reshape(shape[:-4] + (-1, 2))
  sd = geometry.signed_distance_to_road_edges(flat, edges.xy, edges.dir, edges.ids, edges.valid)
  excess = jnp.maximum(sd + cfg.map_margin, 0.0).reshape(shape[:-1])
  per_agent = jnp.mean(excess ** 2, axis=(-1, -2))
  return jnp.where(agents.valid & agents.vehicle, per_agent, 0.0)


def collision_cost(xy: Array, yaw: Array, agents: Agents, cfg: GuidanceConfig) -> Array:
  """(..., A) squared circle overlaps with every other valid agent over the near term."""
  h = cfg.coll_horizon
  c = geometry.box_circles(xy[..., :h, :], yaw[..., :h], agents.length[..., None],
                           agents.width[..., None])                       # (..., A, H, 3, 2)
  r = agents.width / 2.0
  diff = c[..., :, None, :, :, None, :] - c[..., None, :, :, None, :, :]   # (..., A, A, H, 3, 3, 2)
  dist = jnp.sqrt(jnp.sum(diff ** 2, -1) + _EPS)
  reach = (r[..., :, None] + r[..., None, :] + cfg.coll_margin)[..., None, None, None]
  overlap = jnp.sum(jnp.maximum(reach - dist, 0.0) ** 2, axis=(-1, -2, -3))  # (..., A, A)
  num = agents.valid.shape[-1]
  pair = agents.valid[..., :, None] & agents.valid[..., None, :] & ~jnp.eye(num, dtype=bool)
  return jnp.sum(jnp.where(pair, overlap, 0.0), -1)


def pursuit_cost(xy: Array, agents: Agents, cfg: GuidanceConfig) -> Array:
  """(...,) soft minimum over the near term of the pursuer-evader distance (0 without a pair)."""
  h = cfg.coll_horizon
  take = lambda slot: jnp.take_along_axis(xy[..., :h, :], jnp.maximum(slot, 0)[..., None, None, None],
                                          axis=-3)[..., 0, :, :]             # (..., H, 2)
  dist = jnp.sqrt(jnp.sum((take(agents.pursuer) - take(agents.evader)) ** 2, -1) + _EPS)
  tau = cfg.pursuit_temperature
  soft_min = -tau * jax.nn.logsumexp(-dist / tau, axis=-1) + tau * jnp.log(dist.shape[-1])
  has_pair = (agents.pursuer >= 0) & (agents.evader >= 0) & (agents.pursuer != agents.evader)
  return jnp.where(has_pair, soft_min, 0.0)


def objective(xy: Array, yaw: Array, agents: Agents, edges: Edges, cfg: GuidanceConfig) -> Array:
  """(..., A) per-agent objective w_map J_map + w_coll J_coll."""
  return (cfg.w_map * map_cost(xy, yaw, agents, edges, cfg)
          + cfg.w_coll * collision_cost(xy, yaw, agents, cfg))


# ----------------------------------------------------------------------------
# Guides for `diffusion.ddim_sample`.

PoseFn = Callable[[Array], tuple[Array, Array]]   # y0 (..., A, d) -> xy (..., A, T, 2), yaw


def _descend(cost: Callable[[Array], Array], y: Array, mask: Array, cfg: GuidanceConfig) -> Array:
  """`inner_steps` steps of y <- y - eta grad cost, on the agents of mask (..., A) only."""
  def body(y, _):
    g = jax.grad(cost)(y)
    g = jnp.where(jnp.isfinite(g), g, 0.0)
    return y - cfg.eta * jnp.where(mask[..., None], g, 0.0), None
  y, _ = jax.lax.scan(body, y, None, length=cfg.inner_steps)
  return y


def objective_guide(poses: PoseFn, agents: Agents, edges: Edges, cfg: GuidanceConfig):
  """guide(y0, y_s, s, i) -> y0 after objective steps for every valid agent."""
  def total(y):
    xy, yaw = poses(y)
    return jnp.sum(objective(xy, yaw, agents, edges, cfg))

  def guide(y0, y_s, s, i):
    del y_s, s, i
    return _descend(total, y0, agents.valid, cfg)
  return guide


def _slot_mask(slot: Array, num: int) -> Array:
  """(..., A) one-hot of slot (...,) (all False for -1)."""
  return (jnp.arange(num) == slot[..., None]) & (slot[..., None] >= 0)


def adversarial_guide(poses: PoseFn, agents: Agents, edges: Edges, cfg: GuidanceConfig):
  """guide(y0, ...) -> y0 after `ibr_rounds` rounds of pursuer, evader and
  objective best responses (each with its own decode + rollout)."""
  num = agents.valid.shape[-1]
  pursuer = _slot_mask(agents.pursuer, num) & agents.valid
  evader = _slot_mask(agents.evader, num) & agents.valid
  others = agents.valid & ~pursuer & ~evader

  def pursue(y):
    xy, yaw = poses(y)
    own_map = jnp.where(pursuer, map_cost(xy, yaw, agents, edges, cfg), 0.0)
    return jnp.sum(cfg.w_pursue * pursuit_cost(xy, agents, cfg)) + cfg.w_map * jnp.sum(own_map)

  def evade(y):
    xy, yaw = poses(y)
    own = jnp.where(evader, objective(xy, yaw, agents, edges, cfg), 0.0)
    return -jnp.sum(cfg.w_pursue * pursuit_cost(xy, agents, cfg)) + jnp.sum(own)

  def rest(y):
    xy, yaw = poses(y)
    return jnp.sum(objective(xy, yaw, agents, edges, cfg))

  def guide(y0, y_s, s, i):
    del y_s, s, i
    def round_(y, _):
      y = _descend(pursue, y, pursuer, cfg)
      y = _descend(evade, y, evader, cfg)
      return _descend(rest, y, others, cfg), None
    y0, _ = jax.lax.scan(round_, y0, None, length=cfg.ibr_rounds)
    return y0
  return guide


def make_guide(poses: PoseFn, agents: Agents, edges: Edges, cfg: GuidanceConfig):
  """The guide of cfg.mode (None for 'none')."""
  if cfg.mode == "objective":
    return objective_guide(poses, agents, edges, cfg)
  if cfg.mode == "adversarial":
    return adversarial_guide(poses, agents, edges, cfg)
  return None


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
