"""The road signed-distance field agrees with the exact off-road test and is differentiable."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from pcdiff_jax.sim import geometry, road_field


def _bend():
  """One road edge that runs along +x then turns left (road on its left): a convex corner."""
  a = jnp.stack([jnp.linspace(-40.0, 0.0, 81), jnp.zeros(81)], -1)
  b = jnp.stack([jnp.zeros(80), jnp.linspace(0.5, 40.0, 80)], -1)
  xy = jnp.concatenate([a, b])
  d = jnp.concatenate([jnp.tile(jnp.array([[1.0, 0.0]]), (81, 1)), jnp.tile(jnp.array([[0.0, 1.0]]), (80, 1))])
  return xy, d, jnp.zeros(161, jnp.int32), jnp.ones(161, bool)


def _straight_road(half_width=4.0):
  """Two edges along x at y = -w (direction +x) and y = +w (direction -x): the road between them."""
  x = jnp.linspace(-60.0, 60.0, 241)
  xy = jnp.concatenate([jnp.stack([x, jnp.full_like(x, -half_width)], -1),
                        jnp.stack([x[::-1], jnp.full_like(x, half_width)], -1)])
  d = jnp.concatenate([jnp.tile(jnp.array([[1.0, 0.0]]), (241, 1)), jnp.tile(jnp.array([[-1.0, 0.0]]), (241, 1))])
  ids = jnp.concatenate([jnp.zeros(241, jnp.int32), jnp.ones(241, jnp.int32)])
  return xy, d, ids, jnp.ones(482, bool)


def _compare(edges, center, size, low, high):
  field = road_field.from_edges(*edges, jnp.asarray(center), size=size, spacing=1.0)
  query = jax.random.uniform(jax.random.PRNGKey(0), (1000, 2), minval=low, maxval=high)
  exact = geometry.signed_distance_to_road_edges(query, *edges)
  return np.abs(np.asarray(road_field.lookup(field, query) - exact)), np.asarray(exact)


def test_lookup_matches_the_exact_signed_distance_where_it_is_continuous():
  error, exact = _compare(_straight_road(), [0.0, 0.0], 81, -30.0, 30.0)
  # Bilinear on a 1 m grid: off by at most a quarter cell at the kink of |sd| on the centre line.
  assert error.max() < 0.3 and np.median(error) < 0.02, (error.max(), np.median(error))
  assert (exact > 0).any() and (exact < 0).any()


def test_lookup_near_a_corner():
  # Waymax's signed distance (the nearest sample's side) jumps where the
  # nearest sample switches between the two legs of a bend; bilinear
  # interpolation smooths that over one cell, so only most points are exact.
  error, _ = _compare(_bend(), [5.0, 5.0], 81, -30.0, 40.0)
  assert np.median(error) < 0.05 and np.quantile(error, 0.9) < 0.5, (np.median(error), np.quantile(error, 0.9))


def test_query_frame_and_gradient():
  edges = _bend()
  field = road_field.from_edges(*edges, jnp.zeros(2), size=101, spacing=1.0)
  point = jnp.array([[-10.0, -3.0]])                          # 3 m right of the edge: off road
  assert abs(float(road_field.lookup(field, point)[0]) - 3.0) < 1e-3
  # The same point seen from a frame at (-10, 0) heading +y: local (-3, 0).
  local = field.in_frame(jnp.array([-10.0, 0.0]), jnp.float32(np.pi / 2))
  assert abs(float(road_field.lookup(local, jnp.array([[-3.0, 0.0]]))[0]) - 3.0) < 1e-3
  grad = jax.grad(lambda p: road_field.lookup(field, p)[0])(point)
  np.testing.assert_allclose(np.asarray(grad[0]), [0.0, -1.0], atol=1e-3)   # away from the road: -y


def test_empty_map_is_on_road_everywhere_with_zero_gradient():
  xy, d, ids, _ = _bend()
  field = road_field.from_edges(xy, d, ids, jnp.zeros(161, bool), jnp.zeros(2), size=11, spacing=1.0)
  p = jnp.array([[1.0, 2.0], [100.0, -100.0]])
  assert bool(jnp.all(road_field.lookup(field, p) < -1e5))
  g = jax.grad(lambda q: jnp.sum(road_field.lookup(field, q)))(p)
  assert np.isfinite(np.asarray(g)).all() and float(jnp.abs(g).sum()) == 0.0


def test_grid_values_equal_the_exact_signed_distance():
  edges = _bend()
  field = road_field.from_edges(*edges, jnp.array([0.3, 0.7]), size=41, spacing=1.5)
  ticks = np.arange(41) * 1.5
  grid = np.stack(np.meshgrid(ticks, ticks, indexing="ij"), -1).reshape(-1, 2) + np.asarray(field.origin)
  exact = geometry.signed_distance_to_road_edges(jnp.asarray(grid, jnp.float32), *edges)
  np.testing.assert_allclose(np.asarray(field.values).reshape(-1), np.asarray(exact), atol=1e-4)


def test_tiles_against_their_nearest_samples_give_the_brute_force_field():
  # Each tile of cells is computed against the `candidates` samples nearest its centre;
  # `inexact_cells` counts the cells that choice cannot prove exact.
  edges, centre = _straight_road(), jnp.array([0.3, 0.7])
  brute = road_field.from_edges(*edges, centre, size=45, spacing=1.5)        # 482 samples < 1024: all
  tiled = lambda k: road_field.from_edges(*edges, centre, size=45, spacing=1.5, tile=4, candidates=k)
  unproven = lambda k: int(road_field.inexact_cells(*edges, centre, 45, 1.5, tile=4, candidates=k))
  assert unproven(128) == 0
  np.testing.assert_array_equal(np.asarray(tiled(128).values), np.asarray(brute.values))
  # Too few candidates: cells come out wrong, and the check counts at least those.
  wrong = int(np.sum(np.abs(np.asarray(tiled(16).values - brute.values)) > 1e-4))
  assert 0 < wrong <= unproven(16)
