"""Motion statistics of trajectories: kinematic features, histograms, W1.

Shared by the synthetic-data realism report (generated scenes vs the real WOMD
sample) and the paper's realism metric (Wasserstein-1 between L1-normalised
histograms of longitudinal acceleration, lateral acceleration and jerk).

Layers, from jit-able to host-only:
  - `motion_features`, `histogram`, `wasserstein_1`: pure, written once for
    numpy *and* jax.numpy (the array module follows the inputs, so numpy in
    gives numpy out with no device transfer, and jnp/tracers work under jit).
  - `summarize`, `compare_markdown`, `plot_histograms`: host-side reports over
    many scenarios; outputs are JSON-serialisable.

Derivatives are **backward differences** throughout: the value at step t uses
steps t-1 and t (jerk: t-2, t-1, t), so step 0 (and step 1 for jerk) is never
valid. Shapes: O objects, T timesteps, any leading batch dims.
"""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from pcdiff_jax.data.womd import NUM_PAST
from pcdiff_jax.sim.datatypes import DT_SECONDS, Array, ObjectType, SimulatorState, Trajectory

QUANTITIES = ("speed", "lon_accel", "lat_accel", "jerk", "yaw_rate")
UNITS = {"speed": "m/s", "lon_accel": "m/s^2", "lat_accel": "m/s^2", "jerk": "m/s^3",
         "yaw_rate": "rad/s"}

# Fixed (lo, hi, step) per quantity, so histograms of any two runs share edges
# and their W1 is comparable across runs. Values outside are clipped into the
# end bins (so the end bins also hold the tails).
_EDGE_SPECS = {
    "speed": (0.0, 40.0, 1.0),
    "lon_accel": (-10.0, 10.0, 0.5),
    "lat_accel": (-10.0, 10.0, 0.5),
    "jerk": (-30.0, 30.0, 1.0),
    "yaw_rate": (-1.5, 1.5, 0.05),
}
FIXED_BIN_EDGES: dict[str, np.ndarray] = {
    # round() avoids 0.1-style float drift in the edges (e.g. 0.15000000000000002).
    k: np.round(np.linspace(lo, hi, int(round((hi - lo) / step)) + 1), 6).astype(np.float32)
    for k, (lo, hi, step) in _EDGE_SPECS.items()
}

# Fraction of valid samples with |x| > threshold, per quantity (summarize).
THRESHOLDS = {
    "speed": (0.5, 15.0, 30.0),      # moving at all; urban; highway
    "lon_accel": (3.0, 6.0),         # firm; emergency-level braking/accel
    "lat_accel": (3.0, 6.0),         # firm; near the tyre limit
    "jerk": (10.0, 20.0),
    "yaw_rate": (0.5, 1.0),
}
# Vehicle motion classes (`motion_classes`): still vehicles travel less than STILL_TRAVEL m in
# the whole future; starters are slower than STARTER_SPEED m/s at the current step and travel
# more than STARTER_TRAVEL m; movers are at STARTER_SPEED or faster.
STILL_TRAVEL, STARTER_SPEED, STARTER_TRAVEL = 1.0, 3.0, 5.0
MOTION_CLASSES = ("still", "starters", "movers")
STATISTICS = ("count", "mean", "std", "p1", "p5", "p50", "p95", "p99")
CURRENT_STEP = NUM_PAST  # WOMD: 10 past steps, then the current one


def _xp(*arrays):
  """numpy when every input is host data, else jax.numpy (jax arrays, tracers)."""
  host = (np.ndarray, np.generic, float, int, bool)
  return np if all(isinstance(a, host) for a in arrays) else jnp


def _wrap(angle):
  """Wraps to [-pi, pi)."""
  return (angle + math.pi) % (2 * math.pi) - math.pi


def _backward_diff(xp, a, valid, dt):
  """(..., T) -> ((a[t] - a[t-1]) / dt, valid[t] & valid[t-1]), step 0 invalid."""
  d = xp.concatenate([xp.zeros_like(a[..., :1]), (a[..., 1:] - a[..., :-1]) / dt], axis=-1)
  v = xp.concatenate([xp.zeros_like(valid[..., :1]), valid[..., 1:] & valid[..., :-1]], axis=-1)
  return d, v


def motion_features(traj: Trajectory, dt: float = DT_SECONDS) -> dict[str, Array]:
  """Kinematic features of every object at every step.

  Args:
    traj: fields (..., O, T), numpy or jax arrays (jit-able).
    dt: seconds between steps.
  Returns:
    {name: (..., O, T)} for name in QUANTITIES, each with `name + "_valid"`
    (bool (..., O, T)). Invalid entries hold 0. Backward differences:
    - speed[t] = |vel[t]|; valid at t.
    - lon_accel[t], lat_accel[t] = (vel[t] - vel[t-1]) / dt projected on the
      heading halfway between yaw[t-1] and yaw[t] and on its left normal
      (positive = accelerating / turning left); valid at t-1 and t.
    - jerk[t] = (lon_accel[t] - lon_accel[t-1]) / dt; valid at t-2..t.
    - yaw_rate[t] = wrap(yaw[t] - yaw[t-1]) / dt (positive = counter-clockwise).
  """
  xp = _xp(traj.vel_x, traj.vel_y, traj.yaw, traj.valid)
  valid = traj.valid
  # Logged velocities, not positions: in WOMD (and in our kinematics) vel[t] is
  # (p[t] - p[t-1]) / dt already (0.001 m/s apart on the real sample), so one
  # difference of it gives the same estimate as a second difference of
  # positions, needs one valid step fewer, and measures the velocity state a
  # generator or policy actually outputs.
  ax, acc_valid = _backward_diff(xp, traj.vel_x, valid, dt)
  ay, _ = _backward_diff(xp, traj.vel_y, valid, dt)
  dyaw = _wrap(traj.yaw - xp.concatenate([traj.yaw[..., :1], traj.yaw[..., :-1]], axis=-1))
  # The backward difference estimates the acceleration at t - 1/2, so project it
  # on the heading at t - 1/2: exact for uniform circular motion (no spurious
  # longitudinal component from the turn during the step).
  mid = traj.yaw - 0.5 * dyaw
  c, s = xp.cos(mid), xp.sin(mid)
  lon = xp.where(acc_valid, c * ax + s * ay, 0.0)
  lat = xp.where(acc_valid, -s * ax + c * ay, 0.0)
  jerk, jerk_valid = _backward_diff(xp, lon, acc_valid, dt)
  speed = xp.sqrt(traj.vel_x ** 2 + traj.vel_y ** 2)
  return {
      "speed": xp.where(valid, speed, 0.0), "speed_valid": valid,
      "lon_accel": lon, "lon_accel_valid": acc_valid,
      "lat_accel": lat, "lat_accel_valid": acc_valid,
      "jerk": xp.where(jerk_valid, jerk, 0.0), "jerk_valid": jerk_valid,
      "yaw_rate": xp.where(acc_valid, dyaw / dt, 0.0), "yaw_rate_valid": acc_valid,
  }


def histogram_counts(values: Array, valid: Array, edges: Array) -> Array:
  """(K,) counts of the valid `values` per bin (values outside are clipped into
  the end bins). Sum counts over scenarios, then normalise. Jit-able."""
  xp = _xp(values, valid, edges)
  k = edges.shape[0] - 1
  idx = xp.clip(xp.searchsorted(edges, values.reshape(-1), side="right") - 1, 0, k - 1)
  w = valid.reshape(-1).astype(values.dtype)
  return (np.bincount(idx, weights=w, minlength=k) if xp is np
          else jnp.bincount(idx, weights=w, length=k))


def histogram(values: Array, valid: Array, edges: Array) -> Array:
  """L1-normalised histogram of the valid `values`.

  Args:
    values, valid: (...) any shape, the same for both.
    edges: (K+1,) increasing bin edges; values outside are clipped into the
      end bins.
  Returns:
    (K,) that sums to 1, or all zeros if nothing is valid. Jit-able.
  """
  xp = _xp(values, valid, edges)
  counts = histogram_counts(values, valid, edges)
  return counts / xp.maximum(counts.sum(), 1.0)


def wasserstein_1(p: Array, q: Array, edges: Array) -> Array:
  """W1 distance between two normalised histograms (K,) on the same (K+1,) edges.

  The mass of a bin sits at its centre, so W1 = sum_i |CDF_p[i] - CDF_q[i]|
  * (centre[i+1] - centre[i]) (the bin width for uniform bins); two point
  masses are exactly their centres' distance apart. Symmetric, jit-able.
  """
  xp = _xp(p, q, edges)
  centres = 0.5 * (edges[1:] + edges[:-1])
  cdf_gap = xp.abs(xp.cumsum(p - q))[:-1]   # the last entry is 0 for normalised p, q
  return xp.sum(cdf_gap * (centres[1:] - centres[:-1]))


# --------------------------------------------------------------------------
# Host-side reports
# --------------------------------------------------------------------------

def _items(states_or_trajs, object_types):
  """Yields (numpy Trajectory (..., O, T), numpy object types (..., O))."""
  if isinstance(states_or_trajs, (SimulatorState, Trajectory)):
    states_or_trajs = [states_or_trajs]
    object_types = None if object_types is None else [object_types]
  types_iter = iter(object_types) if object_types is not None else None
  for item in states_or_trajs:
    if isinstance(item, SimulatorState):
      traj, types = item.log_trajectory, item.object_metadata.object_types
    elif types_iter is None:
      raise ValueError("summarize: Trajectory items need `object_types` ((..., O) per item)")
    else:
      traj, types = item, next(types_iter)
    # One transfer per scenario: everything below is plain numpy.
    yield jax.tree_util.tree_map(np.asarray, traj), np.asarray(types)


def _stats(x: np.ndarray, name: str, edges: np.ndarray) -> dict[str, Any]:
  """JSON-ready statistics of a 1-D sample (None where undefined)."""
  n = int(x.size)
  out: dict[str, Any] = {"count": n}
  x = x.astype(np.float64)
  pct = np.percentile(x, (1, 5, 50, 95, 99)) if n else [None] * 5
  out.update(mean=float(x.mean()) if n else None, std=float(x.std()) if n else None)
  out.update({f"p{p}": (None if v is None else float(v)) for p, v in zip((1, 5, 50, 95, 99), pct)})
  for thr in THRESHOLDS[name]:
    out[f"frac_abs_gt_{thr:g}"] = float(np.mean(np.abs(x) > thr)) if n else None
  out["hist"] = [float(v) for v in histogram(x, np.ones(n, bool), edges.astype(np.float64))]
  return out


def motion_classes(traj: Trajectory, object_types: Array, current: int = CURRENT_STEP) -> dict[str, np.ndarray]:
  """Per-scene counts of the vehicles valid at `current`, by how the log moves them.

  traj: numpy Trajectory (..., O, T); object_types (..., O). Returns {class: (...,) int
  counts} for MOTION_CLASSES, travel measured from `current` to the last valid step. Real
  scenes are mostly still vehicles, with starters (queues released, cars pulling out)
  among their movers; the synthetic generator makes queues only with a long warm-up
  (docs/DATA.md, "Queued traffic").
  """
  valid = np.asarray(traj.valid)[..., current:]
  xy = np.stack([np.asarray(traj.x), np.asarray(traj.y)], -1)[..., current:, :]
  last = np.max(np.where(valid, np.arange(valid.shape[-1]), 0), -1)                  # (..., O)
  end = np.take_along_axis(xy, last[..., None, None], -2)[..., 0, :]
  travel = np.linalg.norm(end - xy[..., 0, :], axis=-1)
  speed = np.hypot(np.asarray(traj.vel_x)[..., current], np.asarray(traj.vel_y)[..., current])
  vehicle = valid[..., 0] & (np.asarray(object_types) == ObjectType.VEHICLE)
  masks = {"still": travel < STILL_TRAVEL,
           "starters": (speed < STARTER_SPEED) & (travel > STARTER_TRAVEL),
           "movers": speed >= STARTER_SPEED}
  return {k: np.sum(vehicle & m, -1) for k, m in masks.items()}


def summarize(states_or_trajs, object_types=None, types: Sequence[int] = (ObjectType.VEHICLE,),
              dt: float = DT_SECONDS) -> dict[str, Any]:
  """Motion statistics pooled over many scenarios (host-side, numpy).

  Args:
    states_or_trajs: a SimulatorState or Trajectory (any batch dims), or an
      iterable of them; a state contributes its `log_trajectory` and its
      object types.
    object_types: for Trajectory items, their (..., O) WOMD type codes: one
      array, or an iterable parallel to `states_or_trajs`.
    types: the object types whose motion is pooled (default vehicles).
    dt: seconds between steps.
  Returns:
    {quantity: {count, mean, std, p1, p5, p50, p95, p99, frac_abs_gt_<thr>...,
    hist (on FIXED_BIN_EDGES[quantity])}} over the valid samples of the
    selected objects, plus `agents_per_scene` ({mean, min, max} of valid
    objects of any type at step CURRENT_STEP), `object_type_counts` ({type
    name: objects valid at that step}, all types), `vehicles_per_scene` (the mean count of
    each of MOTION_CLASSES), `num_scenes` and `types`.
    Only lists, floats, ints, strs and None (JSON-serialisable).
  """
  pooled: dict[str, list[np.ndarray]] = {q: [] for q in QUANTITIES}
  agents: list[int] = []
  type_counts = {t.name: 0 for t in ObjectType}
  classes: dict[str, list[np.ndarray]] = {k: [] for k in MOTION_CLASSES}
  for traj, obj_types in _items(states_or_trajs, object_types):
    if traj.num_timesteps > CURRENT_STEP:
      for k, v in motion_classes(traj, obj_types).items():
        classes[k].append(np.reshape(v, -1))
    feats = motion_features(traj, dt)
    selected = np.isin(obj_types, np.asarray(types))[..., None]            # (..., O, 1)
    for q in QUANTITIES:
      pooled[q].append(feats[q][feats[q + "_valid"] & selected])
    now = traj.valid[..., min(CURRENT_STEP, traj.num_timesteps - 1)]       # (..., O)
    agents.extend(now.reshape(-1, now.shape[-1]).sum(-1).tolist())         # one per scene
    for t in ObjectType:
      type_counts[t.name] += int(np.sum(now & (obj_types == t)))
  out: dict[str, Any] = {q: _stats(np.concatenate(pooled[q]), q, FIXED_BIN_EDGES[q])
                         for q in QUANTITIES}
  out["agents_per_scene"] = ({"mean": float(np.mean(agents)), "min": int(min(agents)),
                              "max": int(max(agents))} if agents else
                             {"mean": None, "min": None, "max": None})
  out["object_type_counts"] = type_counts
  out["vehicles_per_scene"] = {k: float(np.mean(np.concatenate(v))) if v else None for k, v in classes.items()}
  out["num_scenes"] = len(agents)
  out["types"] = [ObjectType(int(t)).name for t in types]
  return out


def _fmt(v) -> str:
  if v is None:
    return "–"
  if isinstance(v, int):
    return str(v)
  return f"{v:.3g}"


def compare_markdown(summaries: Mapping[str, Mapping[str, Any]]) -> str:
  """A markdown table: one row per (quantity, statistic), one column per summary.

  `summaries` maps a name (e.g. "synthetic", "real WOMD sample") to a
  `summarize` output. For each quantity a `W1 to <first>` row gives the
  Wasserstein-1 distance of each histogram to the first summary's.
  """
  names = list(summaries)
  first = summaries[names[0]]
  rows = [f"| quantity | statistic | {' | '.join(names)} |",
          "|---|---|" + "---|" * len(names)]

  def row(q, stat, values):
    rows.append(f"| {q} | {stat} | {' | '.join(_fmt(v) for v in values)} |")

  for q in QUANTITIES:
    keys = list(STATISTICS) + [f"frac_abs_gt_{t:g}" for t in THRESHOLDS[q]]
    for key in keys:
      row(f"{q} ({UNITS[q]})", key, [s.get(q, {}).get(key) for s in summaries.values()])
    edges = FIXED_BIN_EDGES[q].astype(np.float64)
    w1 = []
    for s in summaries.values():
      p, p0 = s.get(q, {}).get("hist"), first.get(q, {}).get("hist")
      ok = p is not None and p0 is not None and sum(p) > 0 and sum(p0) > 0
      w1.append(float(wasserstein_1(np.asarray(p), np.asarray(p0), edges)) if ok else None)
    row(f"{q} ({UNITS[q]})", f"W1 to {names[0]}", w1)
  for key in ("mean", "min", "max"):
    row("agents_per_scene", key, [s.get("agents_per_scene", {}).get(key) for s in summaries.values()])
  for t in ObjectType:
    row("objects at current step", t.name.lower(),
        [s.get("object_type_counts", {}).get(t.name) for s in summaries.values()])
  for k in MOTION_CLASSES:
    row("vehicles per scene", k, [s.get("vehicles_per_scene", {}).get(k) for s in summaries.values()])
  row("scenes", "count", [s.get("num_scenes") for s in summaries.values()])
  return "\n".join(rows) + "\n"


def plot_histograms(summaries: Mapping[str, Mapping[str, Any]], path, dpi: int = 100):
  """Writes a PNG with one panel per quantity overlaying each summary's histogram.

  Log y-axis: the tails (hard braking, high jerk) are what tells scenes apart.
  Returns `path`.
  """
  from matplotlib.backends.backend_agg import FigureCanvasAgg
  from matplotlib.figure import Figure

  fig = Figure(figsize=(4.0 * len(QUANTITIES), 3.4), dpi=dpi)
  FigureCanvasAgg(fig)  # pyplot-free: nothing global to close
  axes = fig.subplots(1, len(QUANTITIES))
  for ax, q in zip(axes, QUANTITIES):
    edges = FIXED_BIN_EDGES[q]
    for name, s in summaries.items():
      hist = s.get(q, {}).get("hist")
      if hist is not None and sum(hist) > 0:
        ax.stairs(np.asarray(hist), edges, label=f"{name} (n={s[q]['count']})")
    ax.set_yscale("log")
    ax.set_xlabel(f"{q} ({UNITS[q]})")
    ax.set_ylabel("fraction")
    ax.legend(fontsize=7)
  fig.tight_layout()
  fig.savefig(path, dpi=dpi)
  return path
