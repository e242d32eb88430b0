"""Sample selection: per agent, one of a replan's S joint samples, the one that overlaps least
with the others' choices and stays on the road (docs/RESULTS.md, "Ablation: samples per replan").

Iterated conditional modes over the samples (`model.joint_selection`), the mechanism SIMPL-AR
uses over its proposals. Samples are equally likely, so an agent keeps sample 0 (what one sample
would have executed) unless another avoids an overlap.
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp

from pcdiff_jax.config import Config
from pcdiff_jax.model import guidance as guidance_lib
from pcdiff_jax.model import joint_selection, planner
from pcdiff_jax.model.planner import Models
from pcdiff_jax.policy.config import PolicyConfig
from pcdiff_jax.sim.datatypes import Array, ObjectType
from pcdiff_jax.sim.road_field import RoadField


def select(y0: Array, models: Models, scene, cfg: Config, policy: PolicyConfig, adversary: Array,
           road: RoadField) -> Array:
  """(1, A, d) the plan to execute from the S samples y0 (S, A, d) of `scene` (a
  `planning.Encoded`) as policy.select_* say; y0 itself when S = 1. The SDC (slot 0, on its
  log) and an adversarial pursuer keep sample 0. road: the scene's road field (world frame)."""
  if policy.select_samples == 1:
    return y0
  feats = scene.feats
  pursuer = (feats.agent_index == adversary) & (adversary >= 0)
  keep = (jnp.arange(feats.agent_valid.shape[0]) == 0) | pursuer
  road_here = None
  if policy.select_map_weight > 0:
    road_here = road.in_frame(feats.scene_xy, feats.scene_yaw)
    road_here = jax.tree_util.tree_map(lambda a: a[None], road_here)   # a batch of 1 for map_cost
  return select_sample(y0, models, scene.cond, scene.batched, cfg, policy.select_lookahead, keep,
                       road_here, policy.select_map_weight, policy.guidance, policy.select_stride,
                       policy.select_neighbours, scene.hold if policy.select_held_still else None,
                       policy.select_boxes)


def select_sample(y0: Array, models: Models, cond: planner.Conditioning, batched, cfg: Config,
                  lookahead: int, keep: Array, road: Optional[RoadField] = None,
                  map_weight: float = 0.0,
                  guidance: guidance_lib.GuidanceConfig = guidance_lib.GuidanceConfig(),
                  stride: int = 1, neighbours: int = 0, held: Optional[Array] = None,
                  boxes: bool = False) -> Array:
  """(1, A, d): per agent, one of the S joint samples y0 (S, A, d) of one scene
  (cond, batched: that scene repeated S times) such that the chosen plans
  overlap least over their first `lookahead` steps, every `stride`-th (`PolicyConfig.select_samples`),
  plus map_weight x each sample's J_map on `road` (the scene's field in the
  scene frame) when map_weight > 0; agents where keep (A,) keep sample 0. neighbours > 0: overlaps against each
  agent's that many nearest agents only (`PolicyConfig.select_neighbours`). held (A,): agents
  the still gate stops, scored where they will be (standing at their start) in every sample.
  boxes: overlaps also count box against box (`joint_selection.collision_counts`)."""
  states = planner.decode_states(models.stats, cond, y0, cfg, lookahead)[..., ::stride, :]   # (S, A, L, 4)
  if held is not None:
    states = jnp.where(held[None, :, None, None], 0.0, states)
  xy, yaw = planner.to_scene(states, batched)
  feats = jax.tree_util.tree_map(lambda a: a[0], batched)
  length, width = planner.agent_size(feats)
  xy_a, yaw_a = jnp.moveaxis(xy, 0, 1), jnp.moveaxis(yaw, 0, 1)                  # (A, S, L, ...)
  if neighbours > 0:
    coll, others, _ = joint_selection.near_collision_counts(xy_a, yaw_a, length, width,
                                                            feats.agent_valid, neighbours, boxes)   # (A, S, N, S)
  else:
    coll = joint_selection.collision_counts(xy_a, yaw_a, length, width, feats.agent_valid, boxes)
    others = None
  num = feats.agent_valid.shape[0]
  unary = jnp.zeros((num, y0.shape[0]))
  if map_weight > 0:
    agents = guidance_lib.Agents(length=length, width=width, valid=feats.agent_valid,
                                 vehicle=feats.agent_types == ObjectType.VEHICLE,
                                 pursuer=jnp.int32(-1), evader=jnp.int32(-1))
    unary = map_weight * guidance_lib.map_cost(xy, yaw, agents, road, guidance).T    # (A, S)
  # ICM starts from each agent's best unary sample (sample 0 on ties) and never moves a kept
  # agent: a zero unary keeps it on sample 0.
  unary = jnp.where(keep[:, None], 0.0, unary)
  # Overlaps counted at every stride-th step weigh stride times: the same scale against J_map
  # (a mean over the steps) as with every step.
  choice = joint_selection.iterated_conditional_modes(
      unary, coll, feats.agent_valid & ~keep, float(stride), sweeps=2, order=jnp.arange(num), others=others)
  return jnp.take_along_axis(y0, choice[None, :, None], axis=0)

