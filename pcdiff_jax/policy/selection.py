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
from pcdiff_jax.model import joint_selection, latent, planner
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
                       policy.select_boxes, policy.select_map_spare)


def select_sample(y0: Array, models: Models, cond: planner.Conditioning, batched, cfg: Config,
                  lookahead: int, keep: Array, road: Optional[RoadField] = None,
                  map_weight: float = 0.0,
                  guidance: guidance_lib.GuidanceConfig = guidance_lib.GuidanceConfig(),
                  stride: int = 1, neighbours: int = 0, held: Optional[Array] = None,
                  boxes: bool = False, map_spare: tuple[float, float] = (0.0, 0.0)) -> Array:
  """(1, A, d): per agent, one of the S joint samples y0 (S, A, d) of one scene
  (cond, batched: that scene repeated S times) such that the chosen plans
  overlap least over their first `lookahead` steps, every `stride`-th (`PolicyConfig.select_samples`),
  plus map_weight x each sample's J_map on `road` (the scene's field in the
  scene frame) when map_weight > 0; agents where keep (A,) keep sample 0. neighbours > 0: overlaps against each
  agent's that many nearest agents only (`PolicyConfig.select_neighbours`). held (A,): agents
  the still gate stops, scored where they will be (standing at their start) in every sample.
  boxes: overlaps also count box against box (`joint_selection.collision_counts`).
  map_spare (probability, metres), unless (0, 0): J_map is charged only beyond the agent's
  likely proposals that leave the road (`proposal_map_allowance`)."""
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
    cost = guidance_lib.map_cost(xy, yaw, agents, road, guidance).T                   # (A, S)
    if any(map_spare):
      allowance = proposal_map_allowance(models, cond, feats, cfg, lookahead, stride, agents, road,
                                         guidance, *map_spare)
      cost = jnp.maximum(cost - allowance[:, None], 0.0)
    unary = map_weight * cost
  # ICM starts from each agent's best unary sample (sample 0 on ties) and never moves a kept
  # agent: a zero unary keeps it on sample 0.
  unary = jnp.where(keep[:, None], 0.0, unary)
  # Overlaps counted at every stride-th step weigh stride times: the same scale against J_map
  # (a mean over the steps) as with every step.
  choice = joint_selection.iterated_conditional_modes(
      unary, coll, feats.agent_valid & ~keep, float(stride), sweeps=2, order=jnp.arange(num), others=others)
  return jnp.take_along_axis(y0, choice[None, :, None], axis=0)



def proposal_map_allowance(models: Models, cond: planner.Conditioning, feats, cfg: Config,
                           lookahead: int, stride: int, agents: guidance_lib.Agents,
                           road: RoadField, guidance: guidance_lib.GuidanceConfig,
                           min_prob: float, min_excursion: float) -> Array:
  """(A,) the largest J_map among each agent's proposals of probability >= min_prob that
  take a box corner min_excursion metres or more past the road edge, over the selection's
  steps: how far the encoder itself expects the agent to leave the mapped road (0 where no
  such proposal; docs/RESULTS.md, "Ablation: the map spare"). cond: the S repeated copies
  (their first is read); feats: the unbatched scene."""
  states = latent.rollout(cond.proposals[0], cond.speed[0][:, None], models.stats, cfg.kinematics,
                          lookahead)[..., ::stride, :]                              # (A, K, L, 4)
  xy, yaw = planner.to_scene(states, feats)
  xy, yaw = jnp.moveaxis(xy, 1, 0), jnp.moveaxis(yaw, 1, 0)                         # (K, A, L, ...)
  cost = guidance_lib.map_cost(xy, yaw, agents, road, guidance)                     # (K, A)
  leaves = guidance_lib.map_excursion(xy, yaw, agents, road, guidance) >= min_excursion
  likely = jnp.moveaxis(cond.probs[0], 1, 0) >= min_prob
  return jnp.max(jnp.where(likely & leaves, cost, 0.0), axis=0)
