"""Choosing one candidate plan per agent so that the joint choice avoids collisions.

Shared by SIMPL-AR (candidates: an agent's K proposals, weighted by their
probabilities) and our policy's sample selection (candidates: S joint DDIM
samples, `PolicyConfig.select_samples`). The objective is

    sum_i unary_i(k_i) + weight * sum_{i<j} Coll_ij(k_i, k_j),

Coll_ij the number of (step, circle pair) overlaps between agent i's
candidate k_i and agent j's k_j (each agent covered by 3 circles of radius
width / 2 along its length), minimised approximately by iterated conditional
modes: start from each agent's best unary candidate, then `sweeps` passes over
the agents in a given order, each taking its best candidate given the others'
current choices (every update can only lower the objective).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array


def collision_counts(xy: Array, yaw: Array, length: Array, width: Array, valid: Array) -> Array:
  """Pairwise overlap counts between every candidate pair.

  xy (A, K, L, 2), yaw (A, K, L) scene frame; length, width, valid (A,).
  Returns (A, K, A, K): circle-pair overlaps summed over the L steps (0 on
  the diagonal blocks and for padded agents).
  """
  num, k, steps = xy.shape[:3]
  c = geometry.box_circles(xy, yaw, length[:, None, None], width[:, None, None])       # (A, K, L, 3, 2)
  c = jnp.moveaxis(c, 2, 0).reshape(steps, num * k, 3, 2)                              # (L, P, 3, 2)
  r = jnp.repeat(width / 2.0, k)                                                       # (P,)
  rr2 = (r[:, None] + r[None, :]) ** 2                                                 # (P, P)

  def per_step(hits, ct):                                                  # ct (P, 3, 2)
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

  hits, _ = jax.lax.scan(per_step, jnp.zeros((num * k, num * k), jnp.int32), c)
  hits = hits.reshape(num, k, num, k).astype(jnp.float32)
  pair = valid[:, None] & valid[None, :] & ~jnp.eye(valid.shape[0], dtype=bool)
  return jnp.where(pair[:, None, :, None], hits, 0.0)


def iterated_conditional_modes(unary: Array, coll: Array, valid: Array, weight: float,
                               sweeps: int, order: Array) -> Array:
  """(A,) one candidate per agent. unary (A, K) each candidate's own cost;
  coll (A, K, A, K) from `collision_counts`; valid (A,) agents that may
  change their choice; order (A,) the agents' update order within a sweep."""
  choice = jnp.argmin(unary, -1)
  num = unary.shape[0]

  def update(i, choice):
    others = coll[i][:, jnp.arange(num), choice]                             # (K, A)
    cost = unary[i] + weight * jnp.sum(others, -1)
    return choice.at[i].set(jnp.where(valid[i], jnp.argmin(cost), choice[i]))

  return jax.lax.fori_loop(0, num * sweeps, lambda n, c: update(order[n % num], c), choice)
