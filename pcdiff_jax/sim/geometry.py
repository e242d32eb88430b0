"""Planar geometry: angles, frames, oriented boxes, road-edge signed distance.

All functions are pure jnp, accept any leading batch dims and are jit/vmap/grad
friendly (no data-dependent shapes).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from jax import Array


def wrap_angle(angle: Array) -> Array:
  """Wraps to [-pi, pi)."""
  return (angle + jnp.pi) % (2 * jnp.pi) - jnp.pi


def unit(yaw: Array) -> Array:
  """(..., 2) unit vector of heading `yaw` (...)."""
  return jnp.stack([jnp.cos(yaw), jnp.sin(yaw)], axis=-1)


def to_local(points: Array, origin: Array, yaw: Array) -> Array:
  """Expresses (..., 2) `points` in the frame at `origin` (..., 2) heading `yaw` (...)."""
  d = points - origin
  c, s = jnp.cos(yaw)[..., None], jnp.sin(yaw)[..., None]
  return jnp.concatenate([c * d[..., :1] + s * d[..., 1:], -s * d[..., :1] + c * d[..., 1:]], -1)


def from_local(points: Array, origin: Array, yaw: Array) -> Array:
  """Inverse of `to_local`."""
  c, s = jnp.cos(yaw)[..., None], jnp.sin(yaw)[..., None]
  x, y = points[..., :1], points[..., 1:]
  return jnp.concatenate([c * x - s * y, s * x + c * y], -1) + origin


def box_corners(x: Array, y: Array, yaw: Array, length: Array, width: Array) -> Array:
  """(..., 4, 2) corners of boxes (...), counter-clockwise from front-left."""
  fwd = unit(yaw)                                   # (..., 2)
  left = jnp.stack([-fwd[..., 1], fwd[..., 0]], -1)  # (..., 2)
  centre = jnp.stack([x, y], -1)
  hl = (length / 2)[..., None]
  hw = (width / 2)[..., None]
  return jnp.stack([centre + hl * fwd + hw * left, centre - hl * fwd + hw * left,
                    centre - hl * fwd - hw * left, centre + hl * fwd - hw * left], axis=-2)


def box_circles(xy: Array, yaw: Array, length: Array, width: Array) -> Array:
  """(..., 3, 2) centres of 3 circles (radius width / 2) covering boxes at the
  rear, middle and front. xy (..., 2), yaw (...); sizes broadcast against yaw."""
  offset = jnp.maximum(length - width, 0.0)[..., None] / 2.0 * jnp.array([-1.0, 0.0, 1.0])
  return xy[..., None, :] + offset[..., None] * unit(yaw)[..., None, :]


def _box_axes(yaw: Array) -> Array:
  """(..., 2, 2) the two edge normals of a box of heading `yaw`."""
  fwd = unit(yaw)
  left = jnp.stack([-fwd[..., 1], fwd[..., 0]], -1)
  return jnp.stack([fwd, left], axis=-2)


def boxes_overlap(xy_a: Array, fwd_a: Array, half_a: Array, xy_b: Array, fwd_b: Array,
                  half_b: Array) -> Array:
  """Oriented-box overlap by the separating axis theorem in closed form, elementwise.

  xy (..., 2) centres, fwd (..., 2) unit headings, half (..., 2) [length, width] / 2; a's and
  b's arrays broadcast. Returns (...) bool. Cheaper than `pairwise_box_overlap`'s corner
  projections where a few pairs of many candidates are tested (`joint_selection`).
  """
  d = xy_a - xy_b
  return boxes_overlap_xy(d[..., 0], d[..., 1], fwd_a[..., 0], fwd_a[..., 1], half_a[..., 0], half_a[..., 1],
                          fwd_b[..., 0], fwd_b[..., 1], half_b[..., 0], half_b[..., 1])


def boxes_overlap_xy(dx: Array, dy: Array, ca: Array, sa: Array, la: Array, wa: Array,
                     cb: Array, sb: Array, lb: Array, wb: Array) -> Array:
  """`boxes_overlap` on components, all broadcasting (...): centre offset a - b (dx, dy),
  unit headings (ca, sa) and (cb, sb), half lengths la, lb and half widths wa, wb: XLA on a
  CPU is several times slower on arrays that end in a size-2 axis (docs/BENCHMARKS.md, "x and y apart")."""
  cos = jnp.abs(ca * cb + sa * sb)
  sin = jnp.abs(ca * sb - sa * cb)
  lon_b, lat_b = jnp.abs(dx * cb + dy * sb), jnp.abs(dy * cb - dx * sb)
  lon_a, lat_a = jnp.abs(dx * ca + dy * sa), jnp.abs(dy * ca - dx * sa)
  return ((lon_b < lb + la * cos + wa * sin) & (lat_b < wb + la * sin + wa * cos)
          & (lon_a < la + lb * cos + wb * sin) & (lat_a < wa + lb * sin + wb * cos))


def pairwise_box_overlap(x: Array, y: Array, yaw: Array, length: Array, width: Array) -> Array:
  """Exact oriented-box overlap by the separating axis theorem.

  Args: each (..., N). Returns (..., N, N) bool, symmetric, diagonal True.
  Boxes that only touch (zero-area contact) count as not overlapping.
  """
  corners = box_corners(x, y, yaw, length, width)      # (..., N, 4, 2)
  axes = _box_axes(yaw)                                # (..., N, 2, 2)
  n = x.shape[-1]
  batch = x.shape[:-1]
  # Candidate separating axes for pair (i, j): i's two normals and j's two.
  axes_ij = jnp.concatenate([
      jnp.broadcast_to(axes[..., :, None, :, :], batch + (n, n, 2, 2)),
      jnp.broadcast_to(axes[..., None, :, :, :], batch + (n, n, 2, 2)),
  ], axis=-2)                                          # (..., N, N, 4, 2)
  # Full float32 products: a GPU's default (TF32) matmul rounds these world-frame projections
  # by decimetres, which turned gaps between boxes into overlaps (45% collisions on val).
  exact = jax.lax.Precision.HIGHEST
  proj_i = jnp.einsum("...ijad,...icd->...ijac", axes_ij, corners, precision=exact)  # (..., N, N, 4, 4)
  proj_j = jnp.einsum("...ijad,...jcd->...ijac", axes_ij, corners, precision=exact)  # (..., N, N, 4, 4)
  separated = (proj_i.max(-1) <= proj_j.min(-1)) | (proj_j.max(-1) <= proj_i.min(-1))
  return ~jnp.any(separated, axis=-1)


def signed_distance_to_road_edges(
    query_xy: Array, edge_xy: Array, edge_dir: Array, edge_ids: Array, edge_valid: Array,
) -> Array:
  """Signed distance of query points to the nearest road-edge sample (Waymax semantics).

  Road edges are polylines oriented so that the road lies on their left; a
  positive value means the point is off the road. Where the nearest sample's
  predecessor lies on the same polyline, the smaller of the two half-plane
  tests is used so that convex corners are handled.

  Args:
    query_xy: (..., Q, 2).
    edge_xy, edge_dir: (..., E, 2) road-edge samples and their unit directions.
    edge_ids: (..., E) polyline ids. edge_valid: (..., E) bool.
  Returns:
    (..., Q) signed distance in metres; +inf-free: with no valid edge the
    result is -1e6 (on road), so empty maps never mark anything off road.
  """
  diff = edge_xy[..., None, :, :] - query_xy[..., :, None, :]        # (..., Q, E, 2)
  sq = jnp.sum(diff ** 2, axis=-1)                                    # (..., Q, E)
  sq = jnp.where(edge_valid[..., None, :], sq, jnp.inf)
  nearest = jnp.argmin(sq, axis=-1)                                   # (..., Q)
  prior = jnp.maximum(nearest - 1, 0)
  take = _gather_rows
  near_xy = take(edge_xy, nearest)                                    # (..., Q, 2)
  near_dir = take(edge_dir, nearest)
  prior_dir = take(edge_dir, prior)
  same_line = (take(edge_ids, nearest) == take(edge_ids, prior)) & take(edge_valid, prior)
  to_point = query_xy - near_xy
  cross = to_point[..., 0] * near_dir[..., 1] - to_point[..., 1] * near_dir[..., 0]
  cross_prior = to_point[..., 0] * prior_dir[..., 1] - to_point[..., 1] * prior_dir[..., 0]
  side = jnp.where(same_line & (cross_prior < cross), cross_prior, cross)
  dist = jnp.sqrt(jnp.sum(to_point ** 2, axis=-1) + 1e-12)
  any_edge = jnp.any(edge_valid, axis=-1)[..., None]
  return jnp.where(any_edge, jnp.sign(side) * dist, -1e6)


def _gather_rows(a: Array, idx: Array) -> Array:
  """a (..., E) or (..., E, C) gathered at idx (..., Q) -> (..., Q) or (..., Q, C)."""
  if a.ndim == idx.ndim:
    return jnp.take_along_axis(a, idx, axis=-1)
  full = jnp.broadcast_to(idx[..., None], idx.shape + a.shape[-1:])
  return jnp.take_along_axis(a, full, axis=-2)
