"""Choosing one candidate plan per agent so that the joint choice avoids collisions.

Shared by SIMPL-AR (candidates: an agent's K proposals, weighted by their
probabilities) and our policy's sample selection (candidates: S joint DDIM
samples, `PolicyConfig.select_samples`). The objective is

    sum_i unary_i(k_i) + weight * sum_{i<j} Coll_ij(k_i, k_j),

Coll_ij the number of (step, circle pair) overlaps between agent i's
candidate k_i and agent j's k_j (each agent covered by 3 circles of radius
width / 2 along its length; with `boxes`, plus one per step where the boxes
overlap, which catches the corners the circles leave out: docs/RESULTS.md,
"Ablation: box overlaps in the sample selection"), minimised approximately by iterated conditional
modes: start from each agent's best unary candidate, then `sweeps` passes over
the agents in a given order, each taking its best candidate given the others'
current choices (every update can only lower the objective).
"""
from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array


def collision_counts(xy: Array, yaw: Array, length: Array, width: Array, valid: Array,
                     boxes: bool = False) -> Array:
  """Pairwise overlap counts between every candidate pair.

  xy (A, K, L, 2), yaw (A, K, L) scene frame; length, width, valid (A,).
  Returns (A, K, A, K): circle-pair overlaps summed over the L steps (0 on
  the diagonal blocks and for padded agents); boxes: plus one per step where
  the boxes themselves overlap, so a corner the circles miss still counts.
  """
  num, k, steps = xy.shape[:3]
  c = geometry.box_circles(xy, yaw, length[:, None, None], width[:, None, None])       # (A, K, L, 3, 2)
  c = jnp.moveaxis(c, 2, 0).reshape(steps, num * k, 3, 2)                              # (L, P, 3, 2)
  r = jnp.repeat(width / 2.0, k)                                                       # (P,)
  rr2 = (r[:, None] + r[None, :]) ** 2                                                 # (P, P)
  # The box test's inputs only where it runs (None: an empty leaf of the scanned tuple).
  centre = jnp.moveaxis(xy, 2, 0).reshape(steps, num * k, 2) if boxes else None          # (L, P, 2)
  fwd = geometry.unit(jnp.moveaxis(yaw, 2, 0).reshape(steps, num * k)) if boxes else None  # (L, P, 2)
  half = jnp.repeat(jnp.stack([length, width], -1) / 2.0, k, axis=0)                   # (P, 2)

  def per_step(hits, step):
    ct, xyt, ft = step                                                     # (P, 3, 2), (P, 2), (P, 2)
    if boxes:
      hits = hits + geometry.boxes_overlap(xyt[:, None], ft[:, None], half[:, None],
                                           xyt[None], ft[None], half[None])
    # One (P, P) matrix per circle pair, squared distances as a matmul (|a|^2 + |b|^2 - 2 a.b):
    # a broadcast difference tensor was ~20x slower on CPU, one (3P, 3P) matrix reduced over
    # its circle axes 1.5x slower, and using (j, i) = (i, j)^T no faster.
    # Full float32 products: at a GPU's default (TF32) precision a.b is off by metres^2 here.
    sq = jnp.sum(ct ** 2, -1)                                              # (P, 3)
    for i in range(3):
      for j in range(3):
        dot = jnp.matmul(ct[:, i], ct[:, j].T, precision=jax.lax.Precision.HIGHEST)
        hits = hits + (sq[:, i, None] + sq[None, :, j] - 2.0 * dot < rr2)
    return hits, None

  hits, _ = jax.lax.scan(per_step, jnp.zeros((num * k, num * k), jnp.int32), (c, centre, fwd))
  hits = hits.reshape(num, k, num, k).astype(jnp.float32)
  pair = valid[:, None] & valid[None, :] & ~jnp.eye(valid.shape[0], dtype=bool)
  return jnp.where(pair[:, None, :, None], hits, 0.0)


def nearest_others(xy: Array, length: Array, width: Array, valid: Array, count: int,
                   boxes: bool = False) -> tuple[Array, Array]:
  """The `count` other agents whose candidates come closest to each agent's:
  the broad phase of `near_collision_counts`.

  xy (A, K, L, 2) candidate centres, length, width, valid (A,). At each step
  an agent's K candidates lie within R = max_k |xy_k - mean_k xy_k| +
  max(length, width) / 2 of their mean, and so do its 3 circles (boxes: the
  half diagonal, which reaches the corners); two agents' candidates can only
  overlap where their means are closer than R_i + R_j.
  Returns others (A, M), M = min(count, A - 1): agent indices, nearest
  (smallest min-over-steps gap |c_i - c_j| - R_i - R_j) first, and complete
  (A,): no agent outside an agent's list can overlap it (its gap is
  positive), so the near counts equal the dense ones for that agent. Padded
  and self entries sort last.
  """
  centre = jnp.mean(xy, axis=1)                                                    # (A, L, 2)
  extent = (jnp.hypot(length, width) if boxes else jnp.maximum(length, width))[:, None] / 2.0
  reach = jnp.max(jnp.linalg.norm(xy - centre[:, None], axis=-1), axis=1) + extent   # (A, L)
  dist = jnp.linalg.norm(centre[:, None] - centre[None, :], axis=-1)               # (A, A, L)
  gap = jnp.min(dist - reach[:, None] - reach[None, :], axis=-1)                  # (A, A)
  pair = valid[:, None] & valid[None, :] & ~jnp.eye(valid.shape[0], dtype=bool)
  gap = jnp.where(pair, gap, jnp.inf)
  num = valid.shape[0]
  count = min(count, num - 1)
  neg_gap, others = jax.lax.top_k(-gap, min(count + 1, num))                      # nearest first
  if count == num - 1:                                        # every other agent is in the list
    return others[:, :count], jnp.ones(num, bool)
  complete = -neg_gap[:, count] > 0.0                         # the first one left out cannot overlap
  return others[:, :count], complete


def near_collision_counts(xy: Array, yaw: Array, length: Array, width: Array, valid: Array,
                          count: int, boxes: bool = False) -> tuple[Array, Array, Array]:
  """`collision_counts` against each agent's `count` nearest others only
  (`nearest_others`): the same counts wherever `complete`, in count / A of
  the dense counts' work.

  xy (A, K, L, 2), yaw (A, K, L) scene frame; length, width, valid (A,).
  Returns coll (A, K, M, K), M = min(count, A - 1): overlaps of agent i's
  candidate k with others[i, m]'s candidate k' (0 for padded or self
  entries; boxes as in `collision_counts`); others (A, M); complete (A,).
  """
  num, k = xy.shape[:2]
  others, complete = nearest_others(xy, length, width, valid, count, boxes)
  c = geometry.box_circles(xy, yaw, length[:, None, None], width[:, None, None])      # (A, K, L, 3, 2)
  # x and y apart (L, A, K, 3): 2x faster on a CPU (docs/BENCHMARKS.md, "x and y apart").
  c = (jnp.moveaxis(c[..., 0], 2, 0), jnp.moveaxis(c[..., 1], 2, 0))
  r = width / 2.0
  rr2 = ((r[:, None] + r[others]) ** 2)[:, None, :, None]                            # (A, 1, M, 1)
  centre = (jnp.moveaxis(xy[..., 0], 2, 0), jnp.moveaxis(xy[..., 1], 2, 0)) if boxes else None  # (L, A, K) x 2
  fwd = (jnp.moveaxis(jnp.cos(yaw), 2, 0), jnp.moveaxis(jnp.sin(yaw), 2, 0)) if boxes else None
  half_l, half_w = length / 2.0, width / 2.0                                        # (A,)
  size_mine = lambda a: a[:, None, None, None]                                       # (A, 1, 1, 1)
  size_theirs = lambda a: a[others][:, None, :, None]                                # (A, 1, M, 1)

  def per_step(hits, step):
    (cx, cy), xyt, ft = step                                               # (A, K, 3) x 2, (A, K) x 2 x 2
    if boxes:
      mine, theirs = lambda a: a[:, :, None, None], lambda a: a[others][:, None]   # (A, K, 1, 1), (A, 1, M, K)
      hits = hits + geometry.boxes_overlap_xy(
          mine(xyt[0]) - theirs(xyt[0]), mine(xyt[1]) - theirs(xyt[1]), mine(ft[0]), mine(ft[1]),
          size_mine(half_l), size_mine(half_w), theirs(ft[0]), theirs(ft[1]), size_theirs(half_l), size_theirs(half_w))
    # Per step and circle pair one fused elementwise pass over (A, K, M, K): reducing a
    # broadcast (..., L, 3, 3) difference tensor instead was ~8x slower on a CPU.
    mine_x, mine_y = cx[:, :, None, None], cy[:, :, None, None]            # (A, K, 1, 1, 3)
    theirs_x, theirs_y = cx[others][:, None], cy[others][:, None]          # (A, 1, M, K, 3)
    for i in range(3):
      for j in range(3):
        dx, dy = mine_x[..., i] - theirs_x[..., j], mine_y[..., i] - theirs_y[..., j]
        hits = hits + (dx ** 2 + dy ** 2 < rr2)
    return hits, None

  hits, _ = jax.lax.scan(per_step, jnp.zeros((num, k, others.shape[1], k), jnp.int32), (c, centre, fwd))
  ok = valid[:, None] & valid[others] & (others != jnp.arange(valid.shape[0])[:, None])  # (A, M)
  return jnp.where(ok[:, None, :, None], hits, 0).astype(jnp.float32), others, complete


def iterated_conditional_modes(unary: Array, coll: Array, valid: Array, weight: float,
                               sweeps: int, order: Array, others: Optional[Array] = None) -> Array:
  """(A,) one candidate per agent. unary (A, K) each candidate's own cost;
  coll (A, K, M, K) the overlaps of agent i's candidates with those of agent
  others[i, m] (`near_collision_counts`), or (A, K, A, K) against every agent
  when others is None (`collision_counts`); valid (A,) agents that may
  change their choice; order (A,) the agents' update order within a sweep."""
  choice = jnp.argmin(unary, -1)
  num = unary.shape[0]
  if others is None:
    others = jnp.broadcast_to(jnp.arange(num), (num, num))

  def update(i, choice):
    theirs = coll[i][:, jnp.arange(others.shape[1]), choice[others[i]]]          # (K, M)
    cost = unary[i] + weight * jnp.sum(theirs, -1)
    return choice.at[i].set(jnp.where(valid[i], jnp.argmin(cost), choice[i]))

  return jax.lax.fori_loop(0, num * sweeps, lambda n, c: update(order[n % num], c), choice)
