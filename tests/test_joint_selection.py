"""Overlap counts between candidate plans: the dense counts and the near ones (a broad phase)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from pcdiff_jax.model import joint_selection


def _scene(num=12, k=3, steps=5, spread=40.0, seed=0):
  """Candidates of `num` agents scattered over `spread` metres, a few of them close."""
  rng = np.random.default_rng(seed)
  start = rng.uniform(0, spread, (num, 1, 1, 2))
  xy = start + np.cumsum(rng.normal(0, 0.8, (num, k, steps, 2)), 2)
  yaw = rng.uniform(-np.pi, np.pi, (num, k, steps))
  length, width = rng.uniform(4.0, 5.0, num), rng.uniform(1.8, 2.2, num)
  valid = np.ones(num, bool)
  valid[-1] = False
  return tuple(jnp.asarray(a, jnp.float32) for a in (xy, yaw, length, width)) + (jnp.asarray(valid),)


def _as_dense(near, others, num):
  """(A, K, A, K) from near counts (A, K, M, K) against others (A, M)."""
  near, others = np.asarray(near), np.asarray(others)
  dense = np.zeros((num, near.shape[1], num, near.shape[3]), np.float32)
  for i in range(num):
    for m, j in enumerate(others[i]):
      dense[i, :, j] += near[i, :, m]
  return dense


def test_near_counts_equal_the_dense_counts_where_complete():
  scene = _scene()
  dense = np.asarray(joint_selection.collision_counts(*scene))
  assert dense.sum() > 0                                     # some candidates do overlap
  near, others, complete = joint_selection.near_collision_counts(*scene, 4)
  assert near.shape == (12, 3, 4, 3) and others.shape == (12, 4)
  complete = np.asarray(complete)
  assert complete.sum() >= 6
  np.testing.assert_array_equal(_as_dense(near, others, 12)[complete], dense[complete])
  # Listed pairs count the same even where the list is not complete; self and padded entries 0.
  listed = _as_dense(near, others, 12)
  assert np.all(listed <= dense)
  assert np.all(listed[~np.asarray(scene[-1])] == 0) and np.all(listed[:, :, ~np.asarray(scene[-1])] == 0)


def test_near_counts_drop_a_crowd_beyond_the_list_and_say_so():
  # Agent 0's candidates overlap all 6 others (boxes 1 m apart along x at every step).
  num, k, steps = 7, 2, 3
  xy = jnp.zeros((num, k, steps, 2)).at[..., 0].set(jnp.arange(num, dtype=jnp.float32)[:, None, None] * 0.5)
  scene = (xy, jnp.zeros((num, k, steps)), jnp.full(num, 4.0), jnp.full(num, 2.0), jnp.ones(num, bool))
  dense = np.asarray(joint_selection.collision_counts(*scene))
  near, others, complete = joint_selection.near_collision_counts(*scene, 3)
  assert not bool(complete[0])
  assert _as_dense(near, others, num)[0].sum() < dense[0].sum()
  # A list as long as the other agents is the dense count.
  near, others, complete = joint_selection.near_collision_counts(*scene, 10)
  assert others.shape == (num, num - 1) and bool(jnp.all(complete))
  np.testing.assert_array_equal(_as_dense(near, others, num), dense)


def test_icm_on_near_counts_picks_what_it_picks_on_dense_counts():
  scene = _scene(num=10, k=4, spread=25.0, seed=0)
  dense = joint_selection.collision_counts(*scene)
  near, others, complete = joint_selection.near_collision_counts(*scene, 6)
  assert bool(jnp.all(complete))
  unary = jax.random.uniform(jax.random.key(0), (10, 4))
  valid, order = scene[-1], jnp.arange(10)
  a = joint_selection.iterated_conditional_modes(unary, dense, valid, 1.0, 2, order)
  b = joint_selection.iterated_conditional_modes(unary, near, valid, 1.0, 2, order, others=others)
  np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  assert np.any(np.asarray(a) != np.asarray(jnp.argmin(unary, -1)))   # the overlaps moved someone


def test_boxes_see_the_corner_of_a_turning_box_that_the_circles_miss():
  # Two 4.6 x 2 m cars in a staggered row, the second 4 m ahead and 2.1 m to the right (0.1 m
  # apart sideways). In candidate 1 the first has turned 0.1 rad to the right: its front-right
  # corner crosses into the second's box, while every circle pair (radius width / 2, centres
  # 1.3 m from the middle) stays apart.
  xy = jnp.array([[[[0.0, 0.0]]] * 2, [[[4.0, -2.1]]] * 2])                         # (2, 2, 1, 2)
  yaw = jnp.array([[[0.0], [-0.1]], [[0.0], [0.0]]])
  scene = (xy, yaw, jnp.full(2, 4.6), jnp.full(2, 2.0), jnp.ones(2, bool))
  circles = np.asarray(joint_selection.collision_counts(*scene))
  boxes = np.asarray(joint_selection.collision_counts(*scene, boxes=True))
  assert circles.sum() == 0
  assert boxes[0, 1, 1, 0] == 1 and boxes[0, 0, 1, 0] == 0 and boxes[1, 0, 0, 1] == 1
  near, others, complete = joint_selection.near_collision_counts(*scene, 1, boxes=True)
  assert bool(jnp.all(complete))
  np.testing.assert_array_equal(_as_dense(near, others, 2), boxes)


def test_near_counts_with_boxes_equal_the_dense_ones_where_complete():
  scene = _scene(seed=2)
  dense = np.asarray(joint_selection.collision_counts(*scene, boxes=True))
  assert dense.sum() > np.asarray(joint_selection.collision_counts(*scene)).sum()
  near, others, complete = joint_selection.near_collision_counts(*scene, 4, boxes=True)
  complete = np.asarray(complete)
  assert complete.sum() >= 6
  np.testing.assert_array_equal(_as_dense(near, others, 12)[complete], dense[complete])
