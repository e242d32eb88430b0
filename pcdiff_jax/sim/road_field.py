"""A road signed-distance field: Waymax's off-road test sampled on a grid.

Guidance evaluates the off-road cost at every gradient step on every box
corner of every agent; against E road-edge samples that is O(queries x E)
each time. The map is static, so the signed distance is computed once per
scenario on a square grid around the SDC and looked up with bilinear
interpolation (differentiable in the query point, O(1) per query). The
build itself goes by tiles of cells, each against the road-edge samples
nearest it (3x faster than every cell against every sample; equal to it on
every scene we checked, and `inexact_cells` counts what it cannot prove).

Outside the grid the value is clamped to its border (zero gradient there).
With no road edge the field is -1e6 everywhere (on road), as in
`geometry.signed_distance_to_road_edges`.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from flax import struct

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import Array, RoadgraphPoints
from pcdiff_jax.sim.metrics import road_edges


# Tiles of 16 x 16 cells against their 1024 nearest samples: 0.30 s per 256 x 256 field on
# 2 cores against 0.87 s brute force (8 x 8 / 512: 0.34 s; 8 x 8 / 256 was wrong by up to 4 m).
TILE = 16             # cells per side of a tile of `from_edges`
CANDIDATES = 1024     # road-edge samples each tile is computed against


@struct.dataclass
class RoadField:
  """values (..., G, G) signed distance (m, positive = off road) at world xy
  origin + spacing * (i, j) for values[..., i, j] (i along x); origin (..., 2),
  spacing (...). Queries are given in the frame at frame_xy (..., 2) heading
  frame_yaw (...) (the world frame by default)."""
  values: Array
  origin: Array
  spacing: Array
  frame_xy: Array
  frame_yaw: Array

  def in_frame(self, frame_xy: Array, frame_yaw: Array) -> "RoadField":
    """The same field, queried in the frame at frame_xy heading frame_yaw."""
    return self.replace(frame_xy=frame_xy, frame_yaw=frame_yaw)


def from_edges(edge_xy: Array, edge_dir: Array, edge_ids: Array, edge_valid: Array,
               center_xy: Array, size: int, spacing: float, tile: int = TILE,
               candidates: int = CANDIDATES) -> RoadField:
  """The field on a size x size grid of `spacing` m centred on center_xy (2,),
  from road-edge samples (E, 2) / (E,) in the world frame. One scene.

  The grid is computed in tiles of tile x tile cells, each against the
  `candidates` samples nearest its centre (all E when E <= candidates): that
  is the exact field wherever those include every sample within d + 2 r of the
  centre (d: its nearest sample's distance, r: the tile's half diagonal), and
  `inexact_cells` counts the cells where that is not proven. Memory stays O(tile^2 x candidates).
  """
  origin, ticks, pairs = _tile_layout(center_xy, size, spacing, tile)
  prior_dir = jnp.concatenate([edge_dir[:1], edge_dir[:-1]])
  same_line = jnp.concatenate([jnp.zeros((1,), bool), (edge_ids[1:] == edge_ids[:-1]) & edge_valid[:-1]])
  edges = (edge_xy, edge_dir, prior_dir, same_line, edge_valid)

  def tile_values(ij):
    xs, ys = ticks[ij[0]] + origin[0], ticks[ij[1]] + origin[1]
    query = jnp.stack(jnp.meshgrid(xs, ys, indexing="ij"), -1).reshape(-1, 2)   # (tile^2, 2)
    if candidates < edge_xy.shape[0]:
      _, near = _nearest_to_tile(xs, ys, edge_xy, edge_valid, candidates)
      sub = [a[near] for a in edges]
    else:
      sub = edges
    return _signed_distance(query, *sub).reshape(tile, tile)

  return RoadField(values=_untile(jax.lax.map(tile_values, pairs), size), origin=origin,
                   spacing=jnp.float32(spacing), frame_xy=jnp.zeros(2, jnp.float32), frame_yaw=jnp.float32(0.0))


def inexact_cells(edge_xy: Array, edge_dir: Array, edge_ids: Array, edge_valid: Array,
                  center_xy: Array, size: int, spacing: float, tile: int = TILE,
                  candidates: int = CANDIDATES) -> Array:
  """() int32: the cells of `from_edges`' grid whose value is not proven
  exact: a sample left out of the tile's `candidates` nearest could be
  nearer the cell than the ones kept (the K-th nearest sample's distance to
  the tile's centre, less the cell's, is below the cell's value). 0: the
  field equals the brute-force one (docs/BENCHMARKS.md counts them)."""
  if candidates >= edge_xy.shape[0]:
    return jnp.int32(0)
  field = from_edges(edge_xy, edge_dir, edge_ids, edge_valid, center_xy, size, spacing, tile, candidates)
  origin, ticks, pairs = _tile_layout(center_xy, size, spacing, tile)

  def bound(ij):
    xs, ys = ticks[ij[0]] + origin[0], ticks[ij[1]] + origin[1]
    kth_dist = _nearest_to_tile(xs, ys, edge_xy, edge_valid, candidates)[0][-1]
    off_centre = jnp.hypot((xs - jnp.mean(xs))[:, None], (ys - jnp.mean(ys))[None, :])
    return kth_dist - off_centre
  return jnp.sum(jnp.abs(field.values) > _untile(jax.lax.map(bound, pairs), size)).astype(jnp.int32)


def _tile_layout(center_xy: Array, size: int, spacing: float, tile: int):
  """The grid's origin (2,), each tile's cell offsets from it (n_tiles, tile)
  along one axis, and the tiles' (i, j) indices (n_tiles^2, 2)."""
  origin = center_xy - spacing * (size - 1) / 2.0
  n_tiles = -(-size // tile)
  ticks = (jnp.arange(n_tiles * tile, dtype=jnp.float32) * spacing).reshape(n_tiles, tile)
  pairs = jnp.stack(jnp.meshgrid(jnp.arange(n_tiles), jnp.arange(n_tiles), indexing="ij"), -1).reshape(-1, 2)
  return origin, ticks, pairs


def _nearest_to_tile(xs: Array, ys: Array, edge_xy: Array, edge_valid: Array, candidates: int):
  """Distances (candidates,), ascending, and indices of the samples nearest
  the centre of the tile with cell coordinates xs, ys (tile,)."""
  centre = jnp.stack([jnp.mean(xs), jnp.mean(ys)])
  neg_dist, near = jax.lax.top_k(-_distances(centre, edge_xy, edge_valid), candidates)
  return -neg_dist, near


def _untile(per_tile: Array, size: int) -> Array:
  """(n_tiles^2, tile, tile) tile-major values -> the (size, size) grid."""
  n_tiles, tile = int(round(per_tile.shape[0] ** 0.5)), per_tile.shape[-1]
  grid = per_tile.reshape(n_tiles, n_tiles, tile, tile).transpose(0, 2, 1, 3)
  return grid.reshape(n_tiles * tile, n_tiles * tile)[:size, :size]


def _distances(point: Array, edge_xy: Array, valid: Array) -> Array:
  """(E,) distance from point (2,) to each sample, inf where not valid."""
  return jnp.where(valid, jnp.linalg.norm(edge_xy - point, axis=-1), jnp.inf)


def _signed_distance(query: Array, edge_xy: Array, edge_dir: Array, prior_dir: Array, same_line: Array,
                     valid: Array) -> Array:
  """`geometry.signed_distance_to_road_edges` for queries (Q, 2) written with
  plain min / sum reductions instead of an argmin and gathers (several times
  faster on CPU): the side test is averaged over the samples at the minimum
  distance, which is the nearest sample's except on exact ties."""
  to_point = query[:, None, :] - edge_xy[None]                            # (Q, E, 2)
  sq = jnp.where(valid, jnp.sum(to_point ** 2, -1), jnp.inf)
  nearest_sq = jnp.min(sq, -1, keepdims=True)
  cross = lambda d: to_point[..., 0] * d[:, 1] - to_point[..., 1] * d[:, 0]
  c, c_prior = cross(edge_dir), cross(prior_dir)
  side = jnp.where(same_line & (c_prior < c), c_prior, c)
  at_min = (sq <= nearest_sq) & valid
  side = jnp.sum(jnp.where(at_min, side, 0.0), -1) / jnp.maximum(jnp.sum(at_min, -1), 1)
  dist = jnp.sqrt(nearest_sq[:, 0] + 1e-12)
  return jnp.where(jnp.any(valid), jnp.sign(side) * dist, -1e6)


def build(roadgraph: RoadgraphPoints, center_xy: Array, size: int = 128, spacing: float = 2.0,
          max_edge_points: int = 4096) -> RoadField:
  """The field of the `max_edge_points` road-edge samples nearest center_xy (2,). One scene."""
  xy, direction, ids, valid = road_edges(roadgraph, center_xy, max_edge_points)
  return from_edges(xy, direction, ids, valid, center_xy, size, spacing)


def lookup(field: RoadField, query_xy: Array) -> Array:
  """(..., Q) bilinear signed distance at query points (..., Q, 2) given in
  the field's query frame; ... is the field's batch shape."""
  world = geometry.from_local(query_xy, field.frame_xy[..., None, :], field.frame_yaw[..., None])
  size = field.values.shape[-1]
  grid = (world - field.origin[..., None, :]) / field.spacing[..., None, None]
  grid = jnp.clip(grid, 0.0, size - 1.0)
  low = jnp.clip(jnp.floor(grid), 0.0, size - 2.0)
  frac = grid - low
  i, j = low[..., 0].astype(jnp.int32), low[..., 1].astype(jnp.int32)
  flat = field.values.reshape(field.values.shape[:-2] + (-1,))

  def at(di, dj):
    return jnp.take_along_axis(flat, (i + di) * size + (j + dj), axis=-1)
  fx, fy = frac[..., 0], frac[..., 1]
  return ((1 - fx) * (1 - fy) * at(0, 0) + fx * (1 - fy) * at(1, 0)
          + (1 - fx) * fy * at(0, 1) + fx * fy * at(1, 1))
