"""Tests for pcdiff_jax.data.realism: kinematic features, histograms, W1, reports."""
from __future__ import annotations

import json
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from pcdiff_jax.data import realism
from pcdiff_jax.sim.datatypes import Trajectory

DT = 0.1


def make_traj(x, y, vel_x, vel_y, yaw, valid=None) -> Trajectory:
  """A numpy Trajectory from (..., O, T) arrays (positions are not used by the features)."""
  f = lambda a: np.ascontiguousarray(np.asarray(a, np.float32))
  x = f(x)
  shape = x.shape
  full = lambda v: np.full(shape, v, np.float32)
  return Trajectory(
      x=x, y=f(np.broadcast_to(y, shape)), z=full(0.0), vel_x=f(np.broadcast_to(vel_x, shape)),
      vel_y=f(np.broadcast_to(vel_y, shape)), yaw=f(np.broadcast_to(yaw, shape)),
      valid=np.ones(shape, bool) if valid is None else np.asarray(valid, bool),
      timestamp_micros=np.broadcast_to((np.arange(shape[-1]) * 100_000).astype(np.int32), shape).copy(),
      length=full(4.5), width=full(2.0), height=full(1.5))


def straight(speed=10.0, accel=0.0, heading=0.3, steps=30, objects=1):
  """Straight-line motion at constant acceleration along `heading`: (O, T)."""
  t = np.arange(steps) * DT
  v = np.tile(speed + accel * t, (objects, 1))
  s = np.tile(speed * t + 0.5 * accel * t ** 2, (objects, 1))
  c, sn = math.cos(heading), math.sin(heading)
  return make_traj(s * c, s * sn, v * c, v * sn, np.full(v.shape, heading))


def circle(speed=10.0, radius=50.0, steps=40):
  """Counter-clockwise uniform circular motion about the origin: (1, T)."""
  theta = speed / radius * np.arange(steps) * DT
  yaw = theta + np.pi / 2
  return make_traj(radius * np.cos(theta)[None], radius * np.sin(theta)[None],
                   speed * np.cos(yaw)[None], speed * np.sin(yaw)[None], yaw[None])


def test_constant_velocity_gives_zero_derivatives():
  feats = realism.motion_features(straight(speed=12.0, heading=2.5, objects=3), DT)
  for q in realism.QUANTITIES:
    assert feats[q].shape == (3, 30) and feats[q + "_valid"].shape == (3, 30)
    assert isinstance(feats[q], np.ndarray)  # numpy in, numpy out
  np.testing.assert_allclose(feats["speed"], 12.0, rtol=1e-6)
  for q in ("lon_accel", "lat_accel", "jerk", "yaw_rate"):
    np.testing.assert_allclose(feats[q][feats[q + "_valid"]], 0.0, atol=1e-4)
  # Backward differences: step 0 has no predecessor, jerk needs two.
  assert not feats["lon_accel_valid"][:, 0].any() and feats["lon_accel_valid"][:, 1:].all()
  assert not feats["jerk_valid"][:, :2].any() and feats["jerk_valid"][:, 2:].all()


@pytest.mark.parametrize("accel", [2.0, -4.5])
def test_constant_acceleration(accel):
  feats = realism.motion_features(straight(speed=15.0, accel=accel, heading=-1.0), DT)
  m = feats["lon_accel_valid"]
  np.testing.assert_allclose(feats["lon_accel"][m], accel, atol=1e-3)
  np.testing.assert_allclose(feats["lat_accel"][m], 0.0, atol=1e-3)
  np.testing.assert_allclose(feats["jerk"][feats["jerk_valid"]], 0.0, atol=0.05)


@pytest.mark.parametrize("speed,radius", [(10.0, 50.0), (5.0, 10.0)])
def test_uniform_circular_motion(speed, radius):
  feats = realism.motion_features(circle(speed, radius), DT)
  m = feats["lat_accel_valid"]
  # Counter-clockwise = turning left = positive lateral acceleration and yaw rate.
  np.testing.assert_allclose(feats["lat_accel"][m], speed ** 2 / radius, rtol=5e-3)
  np.testing.assert_allclose(feats["lon_accel"][m], 0.0, atol=1e-3)
  np.testing.assert_allclose(feats["yaw_rate"][m], speed / radius, rtol=1e-3)
  np.testing.assert_allclose(feats["speed"], speed, rtol=1e-5)


def test_clockwise_circle_is_negative_and_yaw_wraps():
  tr = circle(10.0, 50.0, steps=400)  # several turns: yaw crosses +-pi
  # Mirror about the x axis; yaw stored wrapped to [-pi, pi), as logged headings are.
  cw = tr.replace(vel_y=-tr.vel_y, yaw=-((tr.yaw + np.pi) % (2 * np.pi) - np.pi))
  assert np.abs(np.diff(cw.yaw)).max() > 6  # the log does jump across +-pi
  feats = realism.motion_features(cw, DT)
  m = feats["yaw_rate_valid"]
  np.testing.assert_allclose(feats["yaw_rate"][m], -0.2, rtol=1e-3)
  np.testing.assert_allclose(feats["lat_accel"][m], -2.0, rtol=5e-3)


def test_validity_drops_differences_across_an_invalid_step():
  valid = np.ones((1, 30), bool)
  valid[0, 10] = False
  tr = straight(speed=10.0, accel=1.0)
  # Garbage at the invalid step, as WOMD's -1 fill: it must not leak into features.
  tr = tr.replace(valid=valid, vel_x=tr.vel_x.copy(), yaw=tr.yaw.copy())
  tr.vel_x[0, 10], tr.yaw[0, 10] = -1.0, -1.0
  feats = realism.motion_features(tr, DT)
  assert not feats["speed_valid"][0, 10] and feats["speed"][0, 10] == 0.0
  acc = feats["lon_accel_valid"][0]
  assert not acc[10] and not acc[11] and acc[9] and acc[12]
  jerk = feats["jerk_valid"][0]
  assert not jerk[10:13].any() and jerk[9] and jerk[13]
  np.testing.assert_allclose(feats["lon_accel"][0][acc], 1.0, atol=1e-3)
  np.testing.assert_allclose(feats["yaw_rate"][0][feats["yaw_rate_valid"][0]], 0.0, atol=1e-5)


def test_histogram_normalised_and_clipped():
  edges = realism.FIXED_BIN_EDGES["lon_accel"]
  values = np.array([0.1, 0.2, -50.0, 50.0, 3.3, 7.0], np.float32)
  valid = np.array([1, 1, 1, 1, 1, 0], bool)
  h = realism.histogram(values, valid, edges)
  assert h.shape == (edges.size - 1,)
  np.testing.assert_allclose(h.sum(), 1.0, rtol=1e-6)
  assert h[0] == pytest.approx(0.2) and h[-1] == pytest.approx(0.2)  # clipped into end bins
  assert h[np.searchsorted(edges, 7.0) - 1] == 0.0                   # invalid ignored
  np.testing.assert_array_equal(realism.histogram(values, np.zeros(6, bool), edges), 0.0)


def test_wasserstein():
  edges = realism.FIXED_BIN_EDGES["jerk"].astype(np.float64)
  k = edges.size - 1
  rng = np.random.default_rng(0)
  p = rng.random(k); p /= p.sum()
  q = rng.random(k); q /= q.sum()
  assert realism.wasserstein_1(p, p, edges) == pytest.approx(0.0, abs=1e-12)
  assert realism.wasserstein_1(p, q, edges) == pytest.approx(realism.wasserstein_1(q, p, edges))
  assert realism.wasserstein_1(p, q, edges) > 0
  a, b = np.zeros(k), np.zeros(k)
  a[3], b[40] = 1.0, 1.0
  centres = 0.5 * (edges[1:] + edges[:-1])
  assert realism.wasserstein_1(a, b, edges) == pytest.approx(centres[40] - centres[3])
  assert realism.wasserstein_1(a, b, edges) == pytest.approx(37.0)  # 1 m/s^3 bins


def test_bin_edges_are_as_stated():
  e = realism.FIXED_BIN_EDGES
  assert e["lon_accel"][0] == -10 and e["lon_accel"][-1] == 10 and np.allclose(np.diff(e["lon_accel"]), 0.5)
  assert e["jerk"].size == 61 and e["speed"].size == 41
  assert np.allclose(np.diff(e["yaw_rate"]), 0.05) and e["yaw_rate"][-1] == pytest.approx(1.5)


def test_jit_features_histogram_wasserstein_with_jnp():
  circ, line = circle(9.0, 36.0, steps=30), straight(speed=10.0, accel=0.0, steps=30)
  both = jax.tree_util.tree_map(lambda a, b: jnp.asarray(np.concatenate([a, b])), circ, line)
  edges = jnp.asarray(realism.FIXED_BIN_EDGES["lat_accel"])

  @jax.jit
  def lat_w1(traj):
    f = realism.motion_features(traj, DT)
    h_circ = realism.histogram(f["lat_accel"][0], f["lat_accel_valid"][0], edges)
    h_line = realism.histogram(f["lat_accel"][1], f["lat_accel_valid"][1], edges)
    return f, realism.wasserstein_1(h_circ, h_line, edges)

  feats, w1 = lat_w1(both)
  assert isinstance(w1, jax.Array)
  # Point masses in the bins holding 2.25 and 0.0 m/s^2: centres 2.25 and 0.25.
  assert float(w1) == pytest.approx(2.0, abs=1e-5)
  ref = realism.motion_features(jax.tree_util.tree_map(np.asarray, both), DT)
  for k in ref:
    np.testing.assert_allclose(np.asarray(feats[k]), ref[k], atol=1e-4)


def test_summarize_synthetic_and_report(tmp_path):
  tr = straight(speed=10.0, accel=2.0, objects=2)
  types = np.array([1, 2], np.int32)  # a vehicle and a pedestrian
  s = realism.summarize([tr, tr], object_types=[types, types])
  assert s["lon_accel"]["count"] == 2 * 29  # vehicles only, steps 1..29
  assert s["lon_accel"]["mean"] == pytest.approx(2.0, abs=1e-3)
  assert s["lon_accel"]["frac_abs_gt_3"] == 0.0
  assert s["agents_per_scene"] == {"mean": 2.0, "min": 2, "max": 2}
  assert s["object_type_counts"]["VEHICLE"] == 2 and s["object_type_counts"]["PEDESTRIAN"] == 2
  json.dumps(s, allow_nan=False)
  other = realism.summarize(straight(speed=10.0, accel=-1.0), object_types=np.array([1]))
  md = realism.compare_markdown({"a": s, "b": other})
  assert "| lon_accel (m/s^2) | W1 to a | 0 | 3 |" in md
  out = realism.plot_histograms({"a": s, "b": other}, tmp_path / "h.png")
  assert (tmp_path / "h.png").stat().st_size > 1000 and out == tmp_path / "h.png"


def test_motion_classes_counts_still_starting_and_moving_vehicles():
  steps = realism.CURRENT_STEP + 81
  still = straight(speed=0.0, steps=steps)                     # parked
  starter = straight(speed=0.0, accel=1.0, steps=steps)        # 0 m/s at the start, then away
  starter = make_traj(starter.x, starter.y, np.where(np.arange(steps) < realism.CURRENT_STEP, 0.0,
                                                     starter.vel_x), starter.vel_y, starter.yaw)
  mover = straight(speed=12.0, steps=steps)
  creeper = straight(speed=0.5, steps=steps)                   # 4 m in the 8 s of log: neither
  stack = lambda *ts: jax.tree_util.tree_map(lambda *a: np.concatenate(a), *ts)
  traj = stack(still, starter, mover, creeper, mover)
  types = np.array([1, 1, 1, 1, 2], np.int32)                  # the last is a pedestrian
  counts = realism.motion_classes(traj, types)
  assert {k: int(v) for k, v in counts.items()} == {"still": 1, "starters": 1, "movers": 1}
  batched = realism.motion_classes(jax.tree_util.tree_map(lambda a: np.stack([a, a]), traj),
                                   np.stack([types, types]))
  np.testing.assert_array_equal(batched["starters"], [1, 1])
  s = realism.summarize([traj], object_types=[types])
  assert s["vehicles_per_scene"] == {"still": 1.0, "starters": 1.0, "movers": 1.0}
  assert "| vehicles per scene | starters | 1 |" in realism.compare_markdown({"a": s})


def test_summarize_real_sample(real_state):
  s = realism.summarize(real_state)
  json.dumps(s, allow_nan=False)
  assert s["num_scenes"] == 1 and s["object_type_counts"]["VEHICLE"] > 0
  for q in realism.QUANTITIES:
    assert s[q]["count"] > 0
    for key in ("mean", "std", "p1", "p5", "p50", "p95", "p99"):
      assert math.isfinite(s[q][key]), (q, key)
    assert sum(s[q]["hist"]) == pytest.approx(1.0)
  assert s["object_type_counts"]["VEHICLE"] == 68 and s["agents_per_scene"]["mean"] == 73
  # Plausible traffic: urban speeds, no net (de)acceleration or turning bias,
  # typical yaw rates below 1 rad/s. (Raw 10 Hz differences are noisy: about 7%
  # of vehicle samples have |lon_accel| > 6 m/s^2, so no tighter tail bound.)
  assert 0 <= s["speed"]["p50"] < s["speed"]["p95"] < 30
  assert abs(s["lon_accel"]["mean"]) < 0.5 and abs(s["lat_accel"]["mean"]) < 0.5
  assert -1 < s["yaw_rate"]["p1"] < 0 < s["yaw_rate"]["p99"] < 1
  assert s["lat_accel"]["std"] < s["lon_accel"]["std"]
