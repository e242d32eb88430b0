"""Procedural map families for the synthetic WOMD-format scenes.

A `Map` is a lane graph (what the hidden traffic model drives on) plus the
painted features that go to the roadgraph (road lines, road edges,
crosswalks, stop signs, speed bumps) and the light schedules. Maps are built
in a canonical frame (junction at the origin); the scene applies a random
rigid transform at the end. Right-hand traffic; every road edge keeps the
road on its left, as WOMD's edges do and the off-road metric assumes.

Families: `straight` and `curved` multi-lane roads (1-4 lanes each way,
optional bike lanes, speed bumps and a mid-block crosswalk), `intersection`
(signalised 4-way with turn lanes, a light cycle with protected lefts and
crosswalks), `t_junction` (stop signs on the minor road), `merge` (an on-ramp
with an acceleration lane).
"""
from __future__ import annotations

import dataclasses
from typing import Optional

import numpy as np

from pcdiff_jax.data.synthetic import polyline as pl
from pcdiff_jax.sim.datatypes import RoadgraphType as RG
from pcdiff_jax.sim.datatypes import TrafficLightState as TL

FAMILIES = ("straight", "curved", "intersection", "t_junction", "merge")
DT = 0.1

# Right-of-way ranks inside junctions (higher goes first; ties: first to arrive).
RANK_PED = 10
RANK = {("major", "through"): 4, ("major", "right"): 3, ("major", "left"): 2,
        ("minor", "right"): 1, ("minor", "left"): 0,
        ("signal", "through"): 3, ("signal", "right"): 2, ("signal", "left"): 1}


@dataclasses.dataclass
class Lane:
  """One lane (or pedestrian path) of the lane graph, sampled every ~0.5 m."""
  xy: np.ndarray
  kind: int = int(RG.LANE_SURFACE_STREET)
  speed_limit: float = 13.0            # m/s
  user: str = "vehicle"                # vehicle | bike | ped | parked
  successors: list = dataclasses.field(default_factory=list)
  left: int = -1                       # same-direction neighbour lanes
  right: int = -1
  junction: bool = False               # inside an intersection box
  crossing: bool = False               # a pedestrian path across a road
  signal: Optional[str] = None         # light class controlling entry (stop line at the start)
  stop_sign: bool = False              # stop line at the start
  rank: int = 0
  entry: bool = False                  # traffic appears here
  dead_end: bool = False               # stop before the end (acceleration lane)
  write: bool = True                   # part of the roadgraph (pedestrian paths are not)
  slow_zone: tuple = (np.inf, np.inf, np.inf)  # (s0, s1, speed) e.g. a speed bump
  movement: str = "lane"               # through | left | right | lane


@dataclasses.dataclass
class Map:
  family: str
  lanes: list
  features: list                       # [(WOMD roadgraph type, (n, 2) polyline)]
  light_states: dict                   # light class -> (T,) WOMD states per simulated step
  focus: np.ndarray                    # where the interesting part is (SDC chosen near it)
  demand: float                        # 0..1, traffic density


def _add_lane(m: Map, lane: Lane) -> int:
  m.lanes.append(lane)
  return len(m.lanes) - 1


def _link_neighbours(m: Map, lanes_inner_to_outer: list) -> None:
  for a, b in zip(lanes_inner_to_outer[:-1], lanes_inner_to_outer[1:]):
    m.lanes[a].right, m.lanes[b].left = b, a


def _road(m: Map, ref: np.ndarray, n_fwd: int, n_bwd: int, width: float, kind: int, limit: float,
          median: float = 0.0, bike: bool = False, parking: bool = False, edges: bool = True,
          entry_fwd: bool = True,
          entry_bwd: bool = True) -> tuple[list, list, dict]:
  """Adds a two-way road along `ref` (forward lanes on its right).

  Returns forward and backward lane indices (inner to outer) and the lateral
  half-widths {'fwd': W_r, 'bwd': W_l} of the paved area.
  """
  g = median / 2
  fwd = [_add_lane(m, Lane(pl.offset(ref, -(g + (k + 0.5) * width)), kind=kind, speed_limit=limit,
                           entry=entry_fwd)) for k in range(n_fwd)]
  bwd = [_add_lane(m, Lane(pl.offset(ref, g + (k + 0.5) * width)[::-1].copy(), kind=kind,
                           speed_limit=limit, entry=entry_bwd)) for k in range(n_bwd)]
  _link_neighbours(m, fwd)
  _link_neighbours(m, bwd)
  for k in range(1, n_fwd):
    m.features.append((int(RG.ROAD_LINE_BROKEN_SINGLE_WHITE), pl.offset(ref, -(g + k * width))))
  for k in range(1, n_bwd):
    m.features.append((int(RG.ROAD_LINE_BROKEN_SINGLE_WHITE), pl.offset(ref, g + k * width)[::-1].copy()))
  if median > 0:
    m.features.append((int(RG.ROAD_EDGE_MEDIAN), pl.offset(ref, -g)[::-1].copy()))
    m.features.append((int(RG.ROAD_EDGE_MEDIAN), pl.offset(ref, g)))
  elif n_fwd and n_bwd:
    m.features.append((int(RG.ROAD_LINE_SOLID_DOUBLE_YELLOW), ref.copy()))
  w_r, w_l = g + n_fwd * width, g + n_bwd * width
  if bike:
    for sign, lanes in ((-1, fwd), (1, bwd)):
      w = w_r if sign < 0 else w_l
      xy = pl.offset(ref, sign * (w + 0.8))
      idx = _add_lane(m, Lane(xy if sign < 0 else xy[::-1].copy(), kind=int(RG.LANE_BIKE_LANE),
                              speed_limit=6.0, user="bike", entry=True))
      lanes.append(idx)
      line = pl.offset(ref, sign * w)
      m.features.append((int(RG.ROAD_LINE_SOLID_SINGLE_WHITE), line if sign < 0 else line[::-1].copy()))
    w_r, w_l = w_r + 1.6, w_l + 1.6
  if parking:  # a kerbside strip of parked cars on each side, inside the road edges
    for sign in (-1, 1):
      w = w_r if sign < 0 else w_l
      _add_lane(m, Lane(pl.offset(ref, sign * (w + 1.2)), user="parked", write=False))
    w_r, w_l = w_r + 2.4, w_l + 2.4
  if edges:
    m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.offset(ref, -w_r)))
    m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.offset(ref, w_l)[::-1].copy()))
  return fwd, bwd, {"fwd": w_r, "bwd": w_l}


def _polygon(corners: np.ndarray) -> np.ndarray:
  return pl.resample(np.concatenate([corners, corners[:1]], 0))


def _crosswalk(m: Map, center: np.ndarray, along: np.ndarray, half_len: float, half_width: float,
               signal: Optional[str], sidewalk: float = 3.0) -> None:
  """A painted crosswalk across a road plus two pedestrian paths (one per direction).

  `along` is the unit direction in which pedestrians cross; the paths start
  and end `sidewalk` metres beyond the pavement, where pedestrians wait.
  """
  across = np.array([-along[1], along[0]])
  c = [center + sa * half_len * along + sw * half_width * across
       for sa, sw in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
  m.features.append((int(RG.CROSSWALK), _polygon(np.stack(c))))
  for direction, lat in ((1.0, -0.6), (-1.0, 0.6)):
    # People appear back from the kerb, wait at it (for the light or a gap), cross on
    # their own side of the crosswalk and walk straight on, so directions never share a path.
    p0 = center + lat * across - direction * (half_len + sidewalk) * along
    p1 = center + lat * across + direction * (half_len + sidewalk) * along
    ped = dict(kind=0, speed_limit=1.4, user="ped", write=False)
    k = _add_lane(m, Lane(pl.line(p0 - direction * 4.0 * along, p0), entry=True, **ped))
    x = _add_lane(m, Lane(pl.line(p0, p1), crossing=True, signal=signal, rank=RANK_PED, **ped))
    e = _add_lane(m, Lane(pl.line(p1, p1 + direction * 8.0 * along), **ped))
    m.lanes[k].successors, m.lanes[x].successors = [x], [e]


def _sidewalk(m: Map, ref: np.ndarray, lateral: float) -> None:
  """Pedestrians strolling along the road (off the pavement)."""
  for xy in (pl.offset(ref, lateral), pl.offset(ref, lateral - 1.6)[::-1].copy()):
    _add_lane(m, Lane(xy, kind=0, speed_limit=1.4, user="ped", write=False, entry=True))


def _curvature_fn(rng: np.random.Generator, amplitude: float):
  waves = [(rng.uniform(0.3, 1.0) * amplitude * rng.choice([-1, 1]), rng.uniform(150, 400),
            rng.uniform(0, 2 * np.pi)) for _ in range(2)]
  return lambda s: sum(a * np.sin(2 * np.pi * s / lam + ph) for a, lam, ph in waves)


# ----------------------------------------------------------------------------- roads


def _surface_limit(rng: np.random.Generator, low: float, high: float, stretch: float) -> float:
  """A surface street's speed limit (m/s), uniform on [low, low + stretch * (high - low)]; one draw
  whatever the stretch, so the rest of a scene is drawn the same; stretch 1 returns the draw itself,
  so the benchmark's scenes stay bit for bit."""
  drawn = rng.uniform(low, high)
  return drawn if stretch == 1.0 else low + stretch * (drawn - low)


def build_road(rng: np.random.Generator, curved: bool, num_steps: int,
               surface_limit_stretch: float = 1.0) -> Map:
  m = Map("curved" if curved else "straight", [], [], {}, np.zeros(2), rng.uniform(0.15, 1.0))
  length = 400.0
  amp = rng.uniform(1 / 250, 1 / 110) if curved else 0.0
  ref = pl.from_curvature(length, _curvature_fn(rng, amp), start=(-length / 2, 0.0))
  ref = ref - ref[len(ref) // 2]
  freeway = rng.uniform() < 0.35
  n_fwd, n_bwd = int(rng.integers(1, 5)), int(rng.integers(1, 5))
  if freeway:
    n_fwd, n_bwd = max(n_fwd, 2), max(n_bwd, 2)
    width, limit, kind = rng.uniform(3.5, 3.9), rng.uniform(24.0, 31.0), int(RG.LANE_FREEWAY)
    median = rng.uniform(2.0, 5.0)
  else:
    width = rng.uniform(3.0, 3.8)
    limit, kind = _surface_limit(rng, 10.0, 17.0, surface_limit_stretch), int(RG.LANE_SURFACE_STREET)
    median = 0.0
  bike = (not freeway) and rng.uniform() < 0.35
  parking = (not freeway) and rng.uniform() < 0.5
  fwd, bwd, half = _road(m, ref, n_fwd, n_bwd, width, kind, limit, median=median, bike=bike,
                         parking=parking)
  if not freeway and rng.uniform() < 0.3:  # speed bump across the whole road
    s_bump = rng.uniform(-60, 60) + length / 2
    k = int(s_bump / pl.SPACING)
    t, n = pl.tangents(ref)[k], pl.normals(ref)[k]
    c = ref[k]
    corners = np.stack([c - 0.5 * t - half["fwd"] * n, c + 0.5 * t - half["fwd"] * n,
                        c + 0.5 * t + half["bwd"] * n, c - 0.5 * t + half["bwd"] * n])
    m.features.append((int(RG.SPEED_BUMP), _polygon(corners)))
    for li in fwd + bwd:
      s_on, _ = pl.project(m.lanes[li].xy, c[None])
      m.lanes[li].slow_zone = (float(s_on[0]) - 6.0, float(s_on[0]) + 4.0, rng.uniform(2.5, 4.5))
  if not freeway:
    _sidewalk(m, ref, -half["fwd"] - 2.5)
    if rng.uniform() < 0.4:
      _sidewalk(m, ref, half["bwd"] + 3.3)
    if rng.uniform() < 0.35:  # mid-block crosswalk, pedestrians have priority
      k = int((length / 2 + rng.uniform(-50, 50)) / pl.SPACING)
      c = ref[k] + pl.normals(ref)[k] * (half["bwd"] - half["fwd"]) / 2
      _crosswalk(m, c, pl.normals(ref)[k], (half["fwd"] + half["bwd"]) / 2, 1.75, None)
  return m


# ----------------------------------------------------------------------------- junctions


def _light_schedule(rng: np.random.Generator, protected_left: bool, num_steps: int) -> dict:
  """WOMD light states per simulated step for the light classes of a 4-way junction.

  Groups A (arms 0, 2) and B (arms 1, 3) alternate: [protected left arrow,
  arrow caution], green (lefts permissive), yellow, all red. Pedestrians
  crossing parallel to a group walk during its green, except its last 6 s.
  """
  phases = []  # (duration s, {class: state})
  for g, other in (("A", "B"), ("B", "A")):
    red = {f"{other}_through": int(TL.STOP), f"{other}_left": int(TL.ARROW_STOP), f"walk_{other}": int(TL.STOP)}
    green = rng.uniform(10.0, 22.0)
    if protected_left:
      phases.append((rng.uniform(5.0, 8.0), {f"{g}_through": int(TL.STOP), f"{g}_left": int(TL.ARROW_GO),
                                             f"walk_{g}": int(TL.STOP), **red}))
      phases.append((2.0, {f"{g}_through": int(TL.STOP), f"{g}_left": int(TL.ARROW_CAUTION),
                           f"walk_{g}": int(TL.STOP), **red}))
    phases.append((green - 6.0, {f"{g}_through": int(TL.GO), f"{g}_left": int(TL.GO), f"walk_{g}": int(TL.GO), **red}))
    phases.append((6.0, {f"{g}_through": int(TL.GO), f"{g}_left": int(TL.GO), f"walk_{g}": int(TL.STOP), **red}))
    phases.append((3.0, {f"{g}_through": int(TL.CAUTION), f"{g}_left": int(TL.CAUTION),
                         f"walk_{g}": int(TL.STOP), **red}))
    phases.append((1.5, {f"{g}_through": int(TL.STOP), f"{g}_left": int(TL.ARROW_STOP),
                         f"walk_{g}": int(TL.STOP), **red}))
  bounds = np.cumsum([0.0] + [d for d, _ in phases])
  t = (np.arange(num_steps) * DT + rng.uniform(0, bounds[-1])) % bounds[-1]
  idx = np.searchsorted(bounds, t, side="right") - 1
  classes = phases[0][1].keys()
  return {c: np.array([phases[i][1][c] for i in idx], np.int32) for c in classes}


def build_junction(rng: np.random.Generator, num_steps: int, tee: bool,
                   surface_limit_stretch: float = 1.0) -> Map:
  """A 4-way signalised intersection, or a T-junction with stop signs on the minor arm.

  Arm k points along angle k*90 deg; its incoming lanes lie on its left
  (+n side, seen from the centre outwards), outgoing lanes on its right.
  """
  m = Map("t_junction" if tee else "intersection", [], [], {}, np.zeros(2), rng.uniform(0.3, 1.0))
  width = rng.uniform(3.1, 3.8)
  limit = _surface_limit(rng, 11.0, 16.0, surface_limit_stretch)
  arms = [0, 1, 2, 3]
  minor = None
  if tee:
    minor = int(rng.integers(0, 4))
    arms.remove((minor + 2) % 4)
  n_major = int(rng.integers(1, 3 if not tee else 4))
  n_minor = int(rng.integers(1, 3))
  n_lanes = {k: (n_minor if k % 2 == 1 else n_major) for k in arms}
  if tee:
    n_lanes = {k: (n_minor if k == minor else n_major) for k in arms}
  turn_lane = {k: (not tee) and n_lanes[k] >= 1 and rng.uniform() < 0.5 for k in arms}
  if not tee and rng.uniform() < 0.5:  # protected lefts need left-turn pockets on every arm
    turn_lane = {k: True for k in arms}
  protected = (not tee) and all(turn_lane.values())
  radius = rng.uniform(6.0, 10.0)
  w_in = {k: (n_lanes[k] + turn_lane[k]) * width for k in arms}   # +n side
  w_out = {k: n_lanes[(k + 2) % 4] * width if (k + 2) % 4 in arms else n_lanes[k] * width for k in arms}
  d_stop = max(max(w_in.values()), max(w_out.values())) + radius + 5.5
  arm_len = rng.uniform(110.0, 140.0)
  if not tee:
    m.light_states = _light_schedule(rng, protected, num_steps)

  u = {k: np.array([np.cos(k * np.pi / 2), np.sin(k * np.pi / 2)]) for k in range(4)}
  n = {k: np.array([-u[k][1], u[k][0]]) for k in range(4)}
  incoming, outgoing = {}, {}
  for k in arms:
    road_class = "minor" if k == minor else ("major" if tee else "signal")
    inc = []
    for j in range(n_lanes[k] + turn_lane[k]):
      lat = (j + 0.5) * width
      xy = pl.line(u[k] * (d_stop + arm_len) + n[k] * lat, u[k] * d_stop + n[k] * lat)
      inc.append(_add_lane(m, Lane(xy, speed_limit=limit, entry=True)))
    _link_neighbours(m, inc[1:] if turn_lane[k] else inc)  # no lane changes into the pocket
    out = []
    n_out = int(round(w_out[k] / width))
    for j in range(n_out):
      lat = -(j + 0.5) * width
      xy = pl.line(u[k] * d_stop + n[k] * lat, u[k] * (d_stop + arm_len) + n[k] * lat)
      out.append(_add_lane(m, Lane(xy, speed_limit=limit)))
    _link_neighbours(m, out)
    incoming[k], outgoing[k] = (inc, road_class), out
    # Painted lines: centre double yellow, broken white between lanes, solid white at the pocket.
    far, near = u[k] * (d_stop + arm_len), u[k] * d_stop
    m.features.append((int(RG.ROAD_LINE_SOLID_DOUBLE_YELLOW), pl.line(far, near)))
    for j in range(1, len(inc)):
      kind = RG.ROAD_LINE_SOLID_SINGLE_WHITE if (turn_lane[k] and j == 1) else RG.ROAD_LINE_BROKEN_SINGLE_WHITE
      start = near + u[k] * (25.0 if kind == RG.ROAD_LINE_SOLID_SINGLE_WHITE else 0.0)
      m.features.append((int(kind), pl.line(far + n[k] * j * width, start + n[k] * j * width)))
    for j in range(1, n_out):
      m.features.append((int(RG.ROAD_LINE_BROKEN_SINGLE_WHITE), pl.line(near - n[k] * j * width, far - n[k] * j * width)))

  # Road edges: one polyline per corner between consecutive present arms.
  for k in arms:
    nxt = (k + 1) % 4
    far = d_stop + arm_len
    if nxt in arms:
      c = u[k] * (w_out[nxt] + radius) + n[k] * (w_in[k] + radius)   # fillet centre
      leg1 = pl.line(u[k] * far + n[k] * w_in[k], u[k] * (w_out[nxt] + radius) + n[k] * w_in[k])
      a0 = np.arctan2(*(-n[k])[::-1])
      bend = pl.arc(c, radius, a0, a0 - np.pi / 2)
      leg2 = pl.line(n[k] * (w_in[k] + radius) + u[k] * w_out[nxt], u[nxt] * far - n[nxt] * w_out[nxt])
      m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.resample(np.concatenate([leg1, bend[1:-1], leg2]))))
    else:  # the minor arm is missing: straight edge along the major road
      opp = (k + 2) % 4
      m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.line(u[k] * far + n[k] * w_in[k],
                                                             u[opp] * far - n[opp] * w_out[opp])))

  # Connectors through the box.
  corner = {k: u[k] * (w_out[(k + 1) % 4] + radius) + n[k] * (w_in[k] + radius)
            for k in arms if (k + 1) % 4 in arms}
  for k in arms:
    inc, road_class = incoming[k]
    through = [j for j in range(len(inc)) if not (turn_lane[k] and j == 0)]
    for j, lane_idx in enumerate(inc):
      moves = []
      last = j == len(inc) - 1
      if (k + 2) % 4 in arms and j in through:
        moves.append(("through", (k + 2) % 4, min(through.index(j), len(outgoing[(k + 2) % 4]) - 1)))
      if (k - 1) % 4 in arms and (j == 0):
        moves.append(("left", (k - 1) % 4, 0))
      if (k + 1) % 4 in arms and last:
        moves.append(("right", (k + 1) % 4, len(outgoing[(k + 1) % 4]) - 1))
      p0 = m.lanes[lane_idx].xy[-1]
      for move, target, q in moves:
        out_idx = outgoing[target][q]
        p1 = m.lanes[out_idx].xy[0]
        xy = _connector(p0, np.arctan2(-u[k][1], -u[k][0]), p1, np.arctan2(u[target][1], u[target][0]),
                        corner[k] if move == "right" else None, radius)
        signal = None
        if not tee:
          group = "A" if k % 2 == 0 else "B"
          signal = f"{group}_left" if move == "left" else f"{group}_through"
        lane = Lane(xy, speed_limit=limit, junction=True, signal=signal, stop_sign=(k == minor),
                    rank=RANK[(road_class, move)], movement=move, successors=[out_idx])
        m.lanes[lane_idx].successors.append(_add_lane(m, lane))

  # Crosswalks on each arm, between the stop line and the box.
  for k in arms:
    if rng.uniform() < (0.85 if not tee else 0.5):
      center = u[k] * (d_stop - 2.75) + n[k] * (w_in[k] - w_out[k]) / 2
      signal = None if tee else f"walk_{'B' if k % 2 == 0 else 'A'}"
      _crosswalk(m, center, n[k], (w_in[k] + w_out[k]) / 2, 1.75, signal)
  if tee:
    k = minor
    m.features.append((int(RG.STOP_SIGN), (u[k] * (d_stop + 0.5) + n[k] * (w_in[k] + 1.0))[None]))
  return m


def _connector(p0, h0, p1, h1, corner: Optional[np.ndarray], radius: float) -> np.ndarray:
  """A smooth path through the box; right turns are tightened until they clear the curb."""
  if corner is None:
    return pl.quintic_hermite(p0, h0, p1, h1, scale=1.0)
  best = None
  for scale in (1.0, 1.15, 1.3, 1.5, 1.75):
    xy = pl.quintic_hermite(p0, h0, p1, h1, scale=scale)
    clearance = np.linalg.norm(xy - corner, axis=1).min() - radius
    best = xy
    if clearance >= 1.9:
      break
  return best


# ----------------------------------------------------------------------------- merge


def build_merge(rng: np.random.Generator, num_steps: int, surface_limit_stretch: float = 1.0) -> Map:
  """A multi-lane road with an on-ramp: ramp -> acceleration lane -> merge by lane change."""
  m = Map("merge", [], [], {}, np.zeros(2), rng.uniform(0.3, 1.0))
  freeway = rng.uniform() < 0.6
  width = rng.uniform(3.4, 3.8)
  limit = rng.uniform(22.0, 30.0) if freeway else _surface_limit(rng, 12.0, 17.0, surface_limit_stretch)
  kind = int(RG.LANE_FREEWAY if freeway else RG.LANE_SURFACE_STREET)
  n_fwd, n_bwd = int(rng.integers(1, 4)), int(rng.integers(1, 4))
  length = 400.0
  ref = pl.line((-length / 2, 0.0), (length / 2, 0.0))
  median = rng.uniform(2.0, 4.0) if freeway else 0.0
  fwd, _, half = _road(m, ref, n_fwd, n_bwd, width, kind, limit, median=median, edges=False)
  w_r, w_l = half["fwd"], half["bwd"]
  m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.offset(ref, w_l)[::-1].copy()))
  x_a = rng.uniform(-40.0, 0.0)                    # acceleration lane starts
  x_b = x_a + rng.uniform(80.0, 140.0)             # and ends (dead end)
  y_acc = -(w_r + width / 2)
  angle = np.deg2rad(rng.uniform(10.0, 20.0))
  ramp_len = 130.0
  p_start = np.array([x_a - ramp_len * np.cos(angle), y_acc - ramp_len * np.sin(angle)])
  ramp = pl.quintic_hermite(p_start, angle, (x_a, y_acc), 0.0, scale=1.0)
  ramp_limit = min(limit, rng.uniform(14.0, 20.0))
  r_idx = _add_lane(m, Lane(ramp, kind=kind, speed_limit=ramp_limit, entry=True))
  acc = pl.line((x_a, y_acc), (x_b, y_acc))
  a_idx = _add_lane(m, Lane(acc, kind=kind, speed_limit=limit, dead_end=True))
  m.lanes[r_idx].successors = [a_idx]
  m.lanes[a_idx].left, m.lanes[fwd[-1]].right = fwd[-1], a_idx
  m.features.append((int(RG.ROAD_LINE_BROKEN_SINGLE_WHITE), pl.line((x_a, -w_r), (x_b, -w_r))))
  # Outer edge: ramp's right side, the acceleration lane, a taper, then the main road.
  taper = 40.0
  ramp_out = pl.offset(ramp, -width / 2)
  outer = np.concatenate([ramp_out, pl.line((x_a, -w_r - width), (x_b, -w_r - width))[1:],
                          pl.line((x_b, -w_r - width), (x_b + taper, -w_r))[1:],
                          pl.line((x_b + taper, -w_r), (length / 2, -w_r))[1:]])
  m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.resample(outer)))
  # Gore: the main road's right edge up to where the ramp's left side meets it, and back along the ramp.
  ramp_in = pl.offset(ramp, width / 2)
  tip = int(np.argmax(ramp_in[:, 1] >= -w_r - 0.05)) if (ramp_in[:, 1] >= -w_r - 0.05).any() else len(ramp_in) - 1
  x_tip = ramp_in[tip, 0]
  m.features.append((int(RG.ROAD_EDGE_BOUNDARY), pl.line((-length / 2, -w_r), (x_tip, -w_r))))
  m.features.append((int(RG.ROAD_EDGE_BOUNDARY), ramp_in[:tip + 1][::-1].copy()))
  m.focus = np.array([(x_a + x_b) / 2, 0.0])
  return m


def build(family: str, rng: np.random.Generator, num_steps: int, surface_limit_stretch: float = 1.0) -> Map:
  """The map of one scene of `family`. surface_limit_stretch widens the range of surface-street
  speed limits upwards (1: the benchmark's 10-17 m/s on roads; 2: 10-24 m/s)."""
  if family in ("straight", "curved"):
    m = build_road(rng, family == "curved", num_steps, surface_limit_stretch)
  elif family in ("intersection", "t_junction"):
    m = build_junction(rng, num_steps, family == "t_junction", surface_limit_stretch)
  elif family == "merge":
    m = build_merge(rng, num_steps, surface_limit_stretch)
  else:
    raise ValueError(f"unknown map family {family!r}; choose from {FAMILIES}")
  return m
