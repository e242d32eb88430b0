"""Planar polyline helpers for building maps (numpy, offline).

A polyline is an (n, 2) float64 array. Maps are sampled every ~0.5 m like
WOMD's roadgraph, and agents move along lanes by arc length s.
"""
from __future__ import annotations

import numpy as np

SPACING = 0.5  # m, WOMD's roadgraph sampling


def arclength(poly: np.ndarray) -> np.ndarray:
  """(n, 2) -> (n,) cumulative distance from the first point."""
  seg = np.hypot(*np.diff(poly, axis=0).T)
  return np.concatenate([[0.0], np.cumsum(seg)])


def resample(poly: np.ndarray, spacing: float = SPACING) -> np.ndarray:
  """Resamples to (nearly) equal spacing, keeping both end points."""
  s = arclength(poly)
  n = max(int(np.ceil(s[-1] / spacing)), 1) + 1
  q = np.linspace(0.0, s[-1], n)
  return np.stack([np.interp(q, s, poly[:, 0]), np.interp(q, s, poly[:, 1])], -1)


def tangents(poly: np.ndarray) -> np.ndarray:
  """(n, 2) unit tangents (central differences, one-sided at the ends)."""
  d = np.gradient(poly, axis=0)
  return d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)


def normals(poly: np.ndarray) -> np.ndarray:
  """(n, 2) unit left normals."""
  t = tangents(poly)
  return np.stack([-t[:, 1], t[:, 0]], -1)


def offset(poly: np.ndarray, lateral: float) -> np.ndarray:
  """Parallel curve `lateral` metres to the left (negative: right)."""
  return resample(poly + lateral * normals(poly))


def directions(poly: np.ndarray) -> np.ndarray:
  """WOMD `dir`: unit vector to the next sample; zero at the last point."""
  d = np.diff(poly, axis=0)
  d = d / np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-9)
  return np.concatenate([d, np.zeros((1, 2))], 0)


def quintic_hermite(p0, t0, p1, t1, scale: float = 1.0, num: int = 200) -> np.ndarray:
  """Curve from p0 (heading t0) to p1 (heading t1) with zero curvature at both ends.

  Zero second derivatives at the ends make curvature continuous where the
  curve joins straight lanes, so yaw rate has no steps at turn entry.
  `scale` multiplies the tangent length (chord length); larger hugs corners.
  """
  p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
  chord = np.linalg.norm(p1 - p0) * scale
  m0 = np.array([np.cos(t0), np.sin(t0)]) * chord
  m1 = np.array([np.cos(t1), np.sin(t1)]) * chord
  u = np.linspace(0.0, 1.0, num)[:, None]
  h00 = 1 - 10 * u**3 + 15 * u**4 - 6 * u**5
  h10 = u - 6 * u**3 + 8 * u**4 - 3 * u**5
  h01 = 10 * u**3 - 15 * u**4 + 6 * u**5
  h11 = -4 * u**3 + 7 * u**4 - 3 * u**5
  return resample(h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1)


def arc(center, radius: float, start: float, stop: float) -> np.ndarray:
  """Circular arc from angle `start` to `stop` (radians, either direction)."""
  n = max(int(abs(stop - start) * radius / SPACING) + 1, 2)
  a = np.linspace(start, stop, n)
  return np.asarray(center, float) + radius * np.stack([np.cos(a), np.sin(a)], -1)


def line(p0, p1) -> np.ndarray:
  return resample(np.stack([np.asarray(p0, float), np.asarray(p1, float)]))


def from_curvature(length: float, kappa_fn, start=(0.0, 0.0), heading: float = 0.0) -> np.ndarray:
  """Integrates a curvature profile kappa(s) into a polyline."""
  s = np.arange(0.0, length + SPACING, SPACING)
  h = heading + np.concatenate([[0.0], np.cumsum(kappa_fn(s[:-1]) * SPACING)])
  xy = np.stack([np.cos(h), np.sin(h)], -1) * SPACING
  return np.asarray(start, float) + np.concatenate([[[0.0, 0.0]], np.cumsum(xy[:-1], 0)])


def project(poly: np.ndarray, points: np.ndarray, coarse: int = 8) -> tuple[np.ndarray, np.ndarray]:
  """Nearest sample of `poly` for each point: (arc length, signed lateral offset).

  Coarse-to-fine: nearest of every `coarse`-th sample, then the exact nearest
  within that window, which is exact for the smooth lanes we build.
  """
  k0 = np.linalg.norm(points[:, None] - poly[None, ::coarse], axis=-1).argmin(1) * coarse
  window = np.clip(k0[:, None] + np.arange(-coarse, coarse + 1)[None], 0, len(poly) - 1)
  k = window[np.arange(len(points)), np.linalg.norm(points[:, None] - poly[window], axis=-1).argmin(1)]
  s = arclength(poly)
  rel = points - poly[k]
  lat = np.einsum("nd,nd->n", rel, normals(poly)[k])
  along = np.einsum("nd,nd->n", rel, tangents(poly)[k])
  return s[k] + along, lat


def interp(poly_s: np.ndarray, values: np.ndarray, s: np.ndarray) -> np.ndarray:
  """Linear interpolation of per-sample values (n, ...) at arc lengths s."""
  if values.ndim == 1:
    return np.interp(s, poly_s, values)
  return np.stack([np.interp(s, poly_s, values[:, k]) for k in range(values.shape[1])], -1)
