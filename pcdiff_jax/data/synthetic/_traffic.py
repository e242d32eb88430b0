"""The hidden traffic model that drives the synthetic scenes' "logs".

Deliberately NOT a policy: it reads the generator's private lane graph,
routes, light schedules and every driver's hidden parameters, never a
`SimulatorState`, so it cannot be plugged in as an actor to replay the logs.
The IDM baseline (pcdiff_jax.baselines) is a separate, simple rule.

Every agent moves along a route of lanes by arc length s with:
- heterogeneous drivers (desired-speed factor, headway, acceleration,
  comfortable braking, gap-acceptance margin, lateral-acceleration comfort,
  lane-change eagerness, a correlated acceleration noise);
- IDM-type car following over the nearest occupant ahead on the route;
- desired speed capped ahead of curves, lower limits and speed bumps;
- stop lines: red / yellow lights (stop if comfortably possible), stop
  signs (full stop, then go when right of way allows), dead ends;
- right of way in junction conflict zones: rank (major > minor, through >
  right > left, pedestrians first) and first-to-arrive among equals, with an
  agent that is inside a zone or cannot stop anymore always passing first;
- lane changes with gap acceptance (MOBIL-like incentive, mandatory at the end
  of an acceleration lane), executed as a smooth lateral move over distance;
- jerk-limited acceleration, so speeds and yaw rates stay within real ranges.

Numpy, vectorised over agents; a Python loop over time steps only.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from pcdiff_jax.data.synthetic import maps as maps_lib
from pcdiff_jax.data.synthetic import polyline as pl

DT = 0.1
VEHICLE, PEDESTRIAN, CYCLIST = 1, 2, 3  # WOMD object types
STOP_STATES = (1, 4, 7)                 # arrow stop, stop, flashing stop
CAUTION_STATES = (2, 5, 8)
STOP_LUT = np.isin(np.arange(-1, 9), STOP_STATES)        # indexed by state + 1
CAUTION_LUT = np.isin(np.arange(-1, 9), CAUTION_STATES)
MOVE_WEIGHT = {"through": 0.55, "left": 0.25, "right": 0.2, "lane": 1.0}
MAX_ROUTE = 6
LOOKAHEAD = 120.0
DECIDE_EVERY = 3     # steps between driver decisions (0.3 s reaction time)
sub_empty = np.zeros(0, int)


@dataclasses.dataclass
class LaneTable:
  """The lane graph packed into flat arrays (L lanes, P samples in all, C oriented conflicts)."""
  offsets: np.ndarray; count: np.ndarray; length: np.ndarray; spacing: np.ndarray
  xy: np.ndarray; tangent: np.ndarray; normal: np.ndarray
  left_s: np.ndarray; right_s: np.ndarray          # (P,) s on the neighbour lane, nan when none
  left: np.ndarray; right: np.ndarray              # (L,)
  v_limit: np.ndarray                              # (L,) speed limit
  v_curve_k: np.ndarray                            # (L,) max |curvature|
  user: np.ndarray                                 # (L,) 0 vehicle, 1 bike, 2 ped
  junction: np.ndarray; stop_sign: np.ndarray; dead_end: np.ndarray; entry: np.ndarray
  slow: np.ndarray                                 # (L, 3) s0, s1, speed
  successors: np.ndarray; succ_weight: np.ndarray  # (L, 3)
  siblings: np.ndarray                             # (L, 3) lanes starting at the same point
  sibling_len: np.ndarray                          # (L, 3) how far from the start they overlap
  signal: np.ndarray                               # (L, T) WOMD light state, -1 uncontrolled
  merge_target: np.ndarray                         # (L,) lanes that two or more lanes flow into
  crossing: np.ndarray                             # (L,) pedestrian crossings
  conflict_lanes: np.ndarray                       # lanes with a conflict zone
  c_a: np.ndarray; c_b: np.ndarray                 # (C,) lanes of each oriented conflict
  c_a_in: np.ndarray; c_a_out: np.ndarray; c_b_in: np.ndarray; c_b_out: np.ndarray
  c_rank_a: np.ndarray; c_rank_b: np.ndarray


USER_CODE = {"vehicle": 0, "bike": 1, "ped": 2, "parked": 3}


def _zone(a: np.ndarray, b: np.ndarray, threshold: float):
  """Arc-length ranges (+1 m) where lanes a and b come within `threshold`, or None."""
  if (a.min(0) - threshold > b.max(0)).any() or (b.min(0) - threshold > a.max(0)).any():
    return None
  diff = a[:, None] - b[None, ::2]  # every other sample of b: 1 m apart, well under the threshold
  d = np.einsum("ijk,ijk->ij", diff, diff) < threshold**2
  d = np.repeat(d, 2, axis=1)[:, :len(b)]
  if not d.any():
    return None
  ia, ib = np.nonzero(d.any(1))[0], np.nonzero(d.any(0))[0]
  sa, sb = pl.arclength(a), pl.arclength(b)
  return (max(sa[ia.min()] - 1.0, 0.0), min(sa[ia.max()] + 1.0, sa[-1]),
          max(sb[ib.min()] - 1.0, 0.0), min(sb[ib.max()] + 1.0, sb[-1]))


def _conflicts(lanes: list) -> list:
  """Oriented conflict zones (a, b, a_in, a_out, b_in, b_out) between lanes that cross or merge."""
  out = []
  veh = [i for i, l in enumerate(lanes) if l.user in ("vehicle", "bike")]
  junc = [i for i in veh if lanes[i].junction]
  cross = [i for i, l in enumerate(lanes) if l.crossing]
  pairs = [(a, b, 2.9) for n, a in enumerate(junc) for b in junc[n + 1:]
           if np.linalg.norm(lanes[a].xy[0] - lanes[b].xy[0]) > 0.5]
  pairs += [(a, b, 2.4) for a in cross for b in veh]
  for a, b, thr in pairs:
    z = _zone(lanes[a].xy, lanes[b].xy, thr)
    if z is not None:
      out.append((a, b) + z)
      out.append((b, a, z[2], z[3], z[0], z[1]))
  return out


def build_table(m: maps_lib.Map, num_steps: int) -> LaneTable:
  lanes = m.lanes
  L = len(lanes)
  count = np.array([len(l.xy) for l in lanes])
  offsets = np.concatenate([[0], np.cumsum(count)[:-1]])
  length = np.array([pl.arclength(l.xy)[-1] for l in lanes])
  xy = np.concatenate([l.xy for l in lanes])
  tangent = np.concatenate([pl.tangents(l.xy) for l in lanes])
  normal = np.stack([-tangent[:, 1], tangent[:, 0]], -1)

  def neighbour_s(side: str) -> np.ndarray:
    out = np.full(len(xy), np.nan)
    for i, l in enumerate(lanes):
      q = getattr(l, side)
      if q < 0:
        continue
      # Project every 4th sample and interpolate: the maps between parallel lanes are smooth.
      k = np.unique(np.append(np.arange(0, len(l.xy), 4), len(l.xy) - 1))
      s_k, lat_k = pl.project(lanes[q].xy, l.xy[k])
      idx = np.arange(len(l.xy))
      s, lat = np.interp(idx, k, s_k), np.interp(idx, k, lat_k)
      ok = (s > 0.5) & (s < length[q] - 0.5) & (np.abs(lat) < 5.0)
      out[offsets[i]:offsets[i] + count[i]] = np.where(ok, s, np.nan)
    return out

  succ = np.full((L, 3), -1)
  weight = np.zeros((L, 3))
  for i, l in enumerate(lanes):
    for k, j in enumerate(l.successors[:3]):
      succ[i, k], weight[i, k] = j, MOVE_WEIGHT[lanes[j].movement]
  siblings = np.full((L, 3), -1)
  sibling_len = np.zeros((L, 3))
  starts = np.stack([l.xy[0] for l in lanes])
  for i in range(L):
    same = np.nonzero((np.linalg.norm(starts - starts[i], axis=1) < 0.3) & (np.arange(L) != i))[0][:3]
    siblings[i, :len(same)] = same
    for k, q in enumerate(same):  # how far the two diverging lanes still overlap
      d = np.linalg.norm(lanes[i].xy[:, None] - lanes[q].xy[None, ::2], axis=-1).min(1)
      sibling_len[i, k] = pl.arclength(lanes[i].xy)[np.nonzero(d < 2.9)[0].max()] + 3.0
  signal = np.full((L, num_steps), -1, np.int32)
  for i, l in enumerate(lanes):
    if l.signal is not None and l.signal in m.light_states:
      signal[i] = m.light_states[l.signal][:num_steps]
  preds = np.zeros(L, int)
  for l in lanes:
    for j in l.successors:
      preds[j] += 1
  # Max |curvature| per lane from heading changes between consecutive samples.
  heading = np.arctan2(tangent[:, 1], tangent[:, 0])
  dh = np.abs(np.angle(np.exp(1j * np.diff(heading)))) / np.repeat(length / (count - 1), count)[1:]
  dh = np.append(dh, 0.0)
  dh[offsets + count - 1] = 0.0                       # no difference across lane boundaries
  kappa = np.maximum.reduceat(dh, offsets)
  conf = np.array(_conflicts(lanes), float).reshape(-1, 6)
  rank = np.array([l.rank for l in lanes])
  ca, cb = conf[:, 0].astype(int), conf[:, 1].astype(int)
  return LaneTable(
      offsets=offsets, count=count, length=length, spacing=length / (count - 1), xy=xy,
      tangent=tangent, normal=normal, left_s=neighbour_s("left"), right_s=neighbour_s("right"),
      left=np.array([l.left for l in lanes]), right=np.array([l.right for l in lanes]),
      v_limit=np.array([l.speed_limit for l in lanes]), v_curve_k=kappa,
      user=np.array([USER_CODE[l.user] for l in lanes]), junction=np.array([l.junction for l in lanes]),
      stop_sign=np.array([l.stop_sign for l in lanes]), dead_end=np.array([l.dead_end for l in lanes]),
      entry=np.array([l.entry for l in lanes]), slow=np.array([l.slow_zone for l in lanes], float),
      successors=succ, succ_weight=weight, siblings=siblings, sibling_len=sibling_len, signal=signal,
      merge_target=preds >= 2, crossing=np.array([l.crossing for l in lanes]),
      conflict_lanes=np.unique(ca),
      c_a=ca, c_b=cb, c_a_in=conf[:, 2], c_a_out=conf[:, 3], c_b_in=conf[:, 4], c_b_out=conf[:, 5],
      c_rank_a=rank[ca], c_rank_b=rank[cb])


def _interp_index(tab: LaneTable, lane: np.ndarray, s: np.ndarray):
  f = np.clip(s / tab.spacing[lane], 0.0, tab.count[lane] - 1 - 1e-6)
  i0 = np.floor(f).astype(int)
  return tab.offsets[lane] + i0, (f - i0)


def _at(values: np.ndarray, g0: np.ndarray, w: np.ndarray) -> np.ndarray:
  w = w.reshape(w.shape + (1,) * (values.ndim - 1))
  return values[g0] * (1 - w) + values[g0 + 1] * w


def _time_to_cover(d: np.ndarray, v: np.ndarray, accel: float, v_max: np.ndarray) -> np.ndarray:
  """Time to travel d from speed v, accelerating at `accel` up to v_max (at least v)."""
  d = np.maximum(d, 0.0)
  v_max = np.maximum(v_max, np.maximum(v, 0.5))
  t_acc = (v_max - v) / accel
  d_acc = 0.5 * (v + v_max) * t_acc
  t = (np.sqrt(v * v + 2 * accel * d) - v) / accel
  return np.where(d <= d_acc, t, t_acc + (d - d_acc) / v_max)


def _idm(v, v0, gap, dv, p):
  """IDM acceleration toward desired speed v0 behind an obstacle `gap` ahead closing at dv."""
  s_star = p["s0"] + np.maximum(0.0, v * p["T"] + v * dv / (2 * np.sqrt(p["a"] * p["b"])))
  return p["a"] * (1 - (v / np.maximum(v0, 0.1)) ** 4 - (s_star / np.maximum(gap, 0.1)) ** 2)


@dataclasses.dataclass
class Logs:
  """What the scene records: per slot (N) and recorded step (T)."""
  xy: np.ndarray; yaw: np.ndarray; vel: np.ndarray; active: np.ndarray
  length: np.ndarray; width: np.ndarray; height: np.ndarray; obj_type: np.ndarray
  yields: list          # (recorded step, yielding slot, slot it yielded to)
  lane: np.ndarray      # (N, T) lane index, for diagnostics


class _Sim:
  """Mutable simulation state; one instance per scene."""

  # Per-agent arrays grow by one entry per spawn (slots are never reused, so a
  # slot is one object for the whole log) and every step works on the N so far.
  FIELDS = {"active": (bool, False), "kind": (int, VEHICLE), "route_len": (float, 0.0), "s": (float, 0.0),
            "v": (float, 0.0), "a": (float, 0.0), "noise": (float, 0.0), "d0": (float, 0.0),
            "lc_len": (float, 1.0), "lc_prog": (float, 1.0), "lc_old": (int, -1), "cooldown": (int, 0),
            "stop_done": (int, -1), "length": (float, 4.5), "width": (float, 1.9), "height": (float, 1.6),
            "parked": (bool, False), "cmd": (float, 0.0), "dead": (bool, False)}
  PARAMS = ("v0f", "v0", "T", "a", "b", "s0", "margin", "alat", "lc_rate", "sigma")

  def __init__(self, tab: LaneTable, m: maps_lib.Map, rng: np.random.Generator, max_agents: int):
    self.tab, self.map, self.rng, self.capacity = tab, m, rng, max_agents
    for name, (dtype, _) in self.FIELDS.items():
      setattr(self, name, np.zeros(0, dtype))
    self.route = np.zeros((0, MAX_ROUTE), int)
    self.route_start = np.zeros((0, MAX_ROUTE))
    self.p = {k: np.zeros(0) for k in self.PARAMS}
    self.yields: list = []
    self.n_used = 0

  @property
  def N(self) -> int:
    return len(self.s)

  def _grow(self, k: int) -> None:
    """Adds k unused (inactive) slots; spawning fills them in order."""
    for name, (dtype, fill) in self.FIELDS.items():
      setattr(self, name, np.concatenate([getattr(self, name), np.full(k, fill, dtype)]))
    self.route = np.concatenate([self.route, np.full((k, MAX_ROUTE), -1)])
    self.route_start = np.concatenate([self.route_start, np.full((k, MAX_ROUTE), np.inf)])
    self.p = {name: np.concatenate([x, np.ones(k)]) for name, x in self.p.items()}

  # -- agents -------------------------------------------------------------------------------

  def _new_route(self, lane: int) -> list:
    out = [lane]
    while len(out) < MAX_ROUTE:
      succ, w = self.tab.successors[out[-1]], self.tab.succ_weight[out[-1]]
      ok = succ >= 0
      if not ok.any():
        break
      out.append(int(self.rng.choice(succ[ok], p=w[ok] / w[ok].sum())))
    return out

  def _set_route(self, i: int, lanes: list, s: float) -> None:
    self.route[i] = -1
    self.route_start[i] = np.inf
    self.route[i, :len(lanes)] = lanes
    starts = np.concatenate([[0.0], np.cumsum(self.tab.length[lanes])])
    self.route_start[i, :len(lanes)] = starts[:-1]
    self.route_len[i] = starts[-1]
    self.s[i] = s

  def spawn(self, lane: int, s: float, v: float, kind: int) -> int:
    if self.n_used >= self.capacity:
      return -1
    if self.n_used == self.N:
      self._grow(min(16, self.capacity - self.N))
    i = self.n_used
    self.n_used += 1
    rng, p = self.rng, self.p
    self.active[i] = True
    self.kind[i] = kind
    self._set_route(i, self._new_route(lane), s)
    if kind == VEHICLE:
      truck = rng.uniform() < 0.06
      self.length[i] = rng.uniform(7.5, 12.0) if truck else rng.normal(4.7, 0.35)
      self.width[i] = rng.uniform(2.4, 2.6) if truck else rng.uniform(1.75, 2.1)
      self.height[i] = rng.uniform(3.0, 3.8) if truck else rng.uniform(1.4, 2.0)
      vals = dict(v0f=np.clip(rng.normal(1.0, 0.1), 0.75, 1.3), v0=0.0, T=rng.uniform(0.9, 2.0),
                  a=rng.uniform(0.7, 1.2) if truck else rng.uniform(1.2, 2.6), b=rng.uniform(1.6, 3.0),
                  s0=rng.uniform(1.5, 3.0), margin=rng.uniform(1.0, 2.5), alat=rng.uniform(1.8, 3.2),
                  lc_rate=rng.uniform(0.05, 0.5), sigma=rng.uniform(0.05, 0.3))
    elif kind == CYCLIST:
      self.length[i], self.width[i], self.height[i] = rng.uniform(1.6, 1.95), rng.uniform(0.55, 0.8), 1.7
      vals = dict(v0f=0.0, v0=rng.uniform(3.5, 7.0), T=1.0, a=rng.uniform(0.8, 1.3), b=2.0, s0=1.5,
                  margin=rng.uniform(1.5, 2.5), alat=2.0, lc_rate=0.0, sigma=rng.uniform(0.05, 0.15))
    else:
      self.length[i] = self.width[i] = rng.uniform(0.55, 0.95)
      self.height[i] = rng.uniform(1.5, 1.9)
      vals = dict(v0f=0.0, v0=rng.uniform(0.9, 1.7), T=0.6, a=0.8, b=1.5, s0=0.8,
                  margin=rng.uniform(1.5, 3.0), alat=3.0, lc_rate=0.0, sigma=0.05)
    for k, x in vals.items():
      p[k][i] = x
    self.v[i], self.a[i], self.noise[i] = v, 0.0, 0.0
    self.d0[i], self.lc_prog[i], self.lc_old[i], self.cooldown[i], self.stop_done[i] = 0.0, 1.0, -1, 30, -1
    return i

  # -- per-step quantities ----------------------------------------------------------------

  def locate(self):
    idx = np.clip((self.route_start <= self.s[:, None]).sum(1) - 1, 0, MAX_ROUTE - 1)
    rows = np.arange(self.N)
    lane = np.maximum(self.route[rows, idx], 0)
    return lane, self.s - self.route_start[rows, idx]

  def distances(self) -> np.ndarray:
    """(N, L) distance from each agent's centre to the start of each lane on its route (inf off-route)."""
    D = np.full((self.N, len(self.tab.length)), np.inf)
    rows, cols = np.nonzero((self.route >= 0) & self.active[:, None])
    D[rows, self.route[rows, cols]] = self.route_start[rows, cols] - self.s[rows]
    return D

  def occupancy(self, lane, s_lane):
    """Flat (lane, s, owner) entries of what agents occupy: their own lane, their old
    lane mid-change, and lanes diverging from the start of theirs."""
    tab = self.tab
    occ_l = [lane]
    occ_s = [s_lane]
    back, mid_change = self.old_lane(lane, s_lane)
    occ_l.append(np.where(mid_change, self.lc_old, -1))
    occ_s.append(np.where(mid_change, back, 0.0))
    for k in range(3):
      sib = tab.siblings[lane, k]
      occ_l.append(np.where((s_lane < tab.sibling_len[lane, k]) & (sib >= 0), sib, -1))
      occ_s.append(s_lane)
    # Approaching a lane others also flow into: already occupy it (at a negative s) so that
    # traffic on the other branch follows in turn (zipper) rather than only yielding.
    k = np.clip((self.route_start <= self.s[:, None]).sum(1), 0, MAX_ROUTE - 1)
    nxt = self.route[np.arange(self.N), k]
    rem = tab.length[lane] - s_lane
    merging = (nxt >= 0) & tab.merge_target[nxt.clip(0)] & (rem < 25.0) & (k > 0)
    occ_l.append(np.where(merging, nxt, -1))
    occ_s.append(-rem)
    occ_l, occ_s = np.stack(occ_l, 1), np.stack(occ_s, 1)
    rows, k = np.nonzero((occ_l >= 0) & self.active[:, None])
    return occ_l[rows, k], occ_s[rows, k], rows

  def old_lane(self, lane, s_lane):
    """Position on the lane an agent is leaving, and whether its box still overlaps that lane."""
    tab = self.tab
    g0, w = _interp_index(tab, lane, s_lane)
    back = np.where(self.lc_old == tab.left[lane], _at(tab.left_s, g0, w), _at(tab.right_s, g0, w))
    return back, (self.lc_old >= 0) & (np.abs(self.d_now()) > 0.9) & np.isfinite(back)

  def d_now(self):
    p = self.lc_prog
    return self.d0 * (1 - (10 * p**3 - 15 * p**4 + 6 * p**5))

  def dd_ds(self):
    p = self.lc_prog
    return -self.d0 * (30 * p**2 - 60 * p**3 + 30 * p**4) / self.lc_len

  # -- one step -----------------------------------------------------------------------------

  def step(self, t: int, record_step: int) -> None:
    """Drivers decide every DECIDE_EVERY steps (a reaction time) and hold that command;
    the kinematics integrate every step."""
    if self.N == 0:
      return
    if t % DECIDE_EVERY == 0:
      self._decide(t, record_step)
    self._integrate()

  def _decide(self, t: int, record_step: int) -> None:
    tab, N, p, v = self.tab, self.N, self.p, self.v
    act = self.active
    lane, s_lane = self.locate()
    occ = self.occupancy(lane, s_lane)
    if self.lane_changes(lane, s_lane, *occ):
      lane, s_lane = self.locate()
      occ = self.occupancy(lane, s_lane)
    flat_l, flat_s, owner = occ
    D = self.distances()
    half = 0.5 * self.length
    rows = np.arange(N)

    # Leader: the nearest occupant ahead on the route.
    ahead = D[:, flat_l] + flat_s[None]                                   # (N, entries)
    ahead = np.where((owner[None] == rows[:, None]) | (ahead <= 0) | ~np.isfinite(ahead), np.inf, ahead)
    ahead = np.concatenate([ahead, np.full((N, 1), np.inf)], 1)
    jflat = ahead.argmin(1)
    lead = np.concatenate([owner, [0]])[jflat]
    gap_lead = ahead[rows, jflat] - half - half[lead]
    # Mid lane change, the box still overlaps the old lane: also follow whoever is ahead there.
    back, mid = self.old_lane(lane, s_lane)
    mi = np.nonzero(mid & act)[0]
    if mi.size and flat_l.size:
      rel = np.where((flat_l[None] == self.lc_old[mi, None]) & (owner[None] != mi[:, None]),
                     flat_s[None] - back[mi, None], np.inf)
      rel = np.where(rel > 0, rel, np.inf)
      jo = owner[rel.argmin(1)]
      gap_old = rel.min(1) - half[mi] - half[jo]
      closer = gap_old < gap_lead[mi]
      gap_lead[mi[closer]], lead[mi[closer]] = gap_old[closer], jo[closer]
    has_lead = np.isfinite(gap_lead) & (gap_lead < LOOKAHEAD)

    # Desired speed, capped ahead of curves, lower limits and slow zones.
    r_lane = np.maximum(self.route, 0)
    v0_lane = np.where((self.kind == VEHICLE)[:, None], tab.v_limit[r_lane] * p["v0f"][:, None], p["v0"][:, None])
    v0_lane = np.minimum(v0_lane, np.sqrt(p["alat"][:, None] / np.maximum(tab.v_curve_k[r_lane], 1e-4)))
    dist_start = np.maximum(self.route_start - self.s[:, None], 0.0)
    on_route = self.route >= 0
    cap = np.where(on_route, np.sqrt(v0_lane**2 + 2 * 1.5 * dist_start), np.inf)
    slow = tab.slow[r_lane]
    to_slow = self.route_start + slow[..., 0] - (self.s + half)[:, None]
    past_slow = self.route_start + slow[..., 1] - (self.s - half)[:, None] < 0
    cap_slow = np.where(on_route & np.isfinite(to_slow) & ~past_slow,
                        np.sqrt(slow[..., 2]**2 + 2 * 1.5 * np.maximum(to_slow, 0.0)), np.inf)
    v0 = np.maximum(np.minimum(cap.min(1), cap_slow.min(1)), 0.5)

    # Stop lines: red / yellow (if comfortably possible), stop signs, dead ends.
    front_to = self.route_start - (self.s + half)[:, None]             # front to each route lane start
    sig = tab.signal[r_lane, t]
    comfy = front_to > v[:, None] ** 2 / (2 * 3.0)
    must = STOP_LUT[sig + 1] | (CAUTION_LUT[sig + 1] & comfy)
    must |= tab.stop_sign[r_lane] & (self.stop_done[:, None] != r_lane)
    must &= on_route & (front_to > -0.3) & (front_to < LOOKAHEAD)
    stop_gap = np.where(must, front_to, np.inf).min(1)
    last = np.maximum((self.route >= 0).sum(1) - 1, 0)
    dead = tab.dead_end[np.maximum(self.route[rows, last], 0)]
    stop_gap = np.where(dead, np.minimum(stop_gap, self.route_len - self.s - half - 0.5), stop_gap)
    at_stop_sign = must & tab.stop_sign[r_lane] & (front_to < 2.5) & (v[:, None] < 0.3)
    done_lane = np.where(at_stop_sign.any(1), r_lane[rows, at_stop_sign.argmax(1)], -1)
    self.stop_done = np.where(done_lane >= 0, done_lane, self.stop_done)

    # Right of way in conflict zones.
    yield_gap = np.full(N, np.inf)
    # Only agents with a conflict lane within reach take part (rows of the (N, C) tables).
    sub = np.nonzero(act & (D[:, tab.conflict_lanes] < 75.0).any(1))[0] if tab.c_a.size else sub_empty
    if sub.size:
      self._right_of_way(t, record_step, sub, D[sub], lane[sub], half[sub], stop_gap[sub], v0[sub], yield_gap)
      yield_gap = self._clear_of_crosswalks(D, half, yield_gap)

    # Longitudinal command: IDM over leader / stop line / yield point.
    acc = _idm(v, v0, np.where(has_lead, gap_lead, np.inf), v - v[lead], p)
    self.cmd = np.minimum(acc, _idm(v, v0, np.minimum(stop_gap, yield_gap) - 0.3, v, p))
    self.dead = dead

  def _integrate(self) -> None:
    """Jerk-limited tracking of the command with correlated noise, then the kinematics."""
    N, p, v, act = self.N, self.p, self.v, self.active
    acc = self.cmd
    self.noise = self.noise * (1 - DT / 1.5) + p["sigma"] * np.sqrt(2 * DT / 1.5) * self.rng.standard_normal(N)
    acc = np.clip(acc + np.where(v > 1.0, self.noise, 0.0), -8.0, p["a"] * 1.2)
    jerk = np.where(acc < self.a - 2.0, 25.0, 8.0)
    a_new = self.a + np.clip((acc - self.a) * min(1.0, DT / 0.3), -jerk * DT, jerk * DT)
    v_new = np.where(self.parked, 0.0, np.maximum(v + a_new * DT, 0.0))
    a_new = (v_new - v) / DT
    self.a, self.v = np.where(act, a_new, 0.0), np.where(act, v_new, 0.0)
    self.s = self.s + self.v * DT
    self.lc_prog = np.minimum(self.lc_prog + self.v * DT / self.lc_len, 1.0)
    self.lc_old = np.where(self.lc_prog >= 1.0, -1, self.lc_old)
    self.cooldown = np.maximum(self.cooldown - 1, 0)

    # Leaving the map at the end of the route.
    done = act & ~self.dead & (self.s > self.route_len - 0.3)
    self.active = act & ~done

  def _right_of_way(self, t, record_step, sub, D, lane, half, stop_gap, v0, out) -> None:
    """Yield points in junction conflict zones for agents `sub`; writes out[sub] (front gap to stop).

    Agent i yields to j on a crossing/merging lane if j is inside the zone, cannot stop anymore,
    or is clearing the junction; or if j has the higher rank (major > minor, through > right >
    left, pedestrians first) and arrives before i could clear the zone plus i's margin; or has
    equal rank and arrives first.
    """
    tab, p = self.tab, {k: x[sub] for k, x in self.p.items()}
    v, N = self.v[sub], len(sub)
    rows = np.arange(N)
    Da, Db = D[:, tab.c_a], D[:, tab.c_b]
    fa = Da + tab.c_a_in[None] - half[:, None]
    ra = Da + tab.c_a_out[None] + half[:, None]
    fb = Db + tab.c_b_in[None] - half[:, None]
    rb = Db + tab.c_b_out[None] + half[:, None]
    near = lambda f, r, Dx: np.isfinite(Dx) & (r > 0) & (f < 70.0) & (f < stop_gap[:, None] + 0.5)
    ona, onb = near(fa, ra, Da), near(fb, rb, Db)
    cols = np.nonzero(ona.any(0) & onb.any(0))[0]
    if cols.size:
      fa, ra, fb, ona, onb = fa[:, cols], ra[:, cols], fb[:, cols], ona[:, cols], onb[:, cols]
      vv = v[:, None]
      tie = 1e-3 * rows[:, None] / N
      # Clearing the junction after the light changed, or too close to stop: passes first.
      clearing = tab.junction[lane] & STOP_LUT[tab.signal[lane, t] + 1]
      stuck_b = onb & ((fb <= 0) | ((fb < vv**2 / (2 * 3.5) + 1.0) & (vv > 1.0)) | clearing[:, None])
      vmax = v0[:, None]
      eta_b = np.where(fb <= 0, 0.0, _time_to_cover(fb, vv, 2.0, vmax)) + tie
      higher = tab.c_rank_b[cols] > tab.c_rank_a[cols]
      equal = tab.c_rank_b[cols] == tab.c_rank_a[cols]
      strong = np.where(onb & (stuck_b | higher[None]), eta_b, np.inf)
      peer = np.where(onb & equal[None], eta_b, np.inf)
      j_strong, j_peer = strong.argmin(0), peer.argmin(0)
      e_strong, e_peer = strong[j_strong, np.arange(cols.size)], peer[j_peer, np.arange(cols.size)]
      eta_a = _time_to_cover(fa, vv, 2.0, vmax) + tie
      clear_a = _time_to_cover(ra, vv, 1.5, vmax) + p["margin"][:, None]
      free_a = ona & (fa > 0) & ~((fa < vv**2 / (2 * 3.5) + 1.0) & (vv > 1.0)) & ~clearing[:, None]
      y_strong = free_a & (e_strong[None] < clear_a)
      y_peer = free_a & (e_peer[None] < eta_a) & (e_peer[None] < clear_a)
      must_yield = y_strong | y_peer
      # Vehicles stop short of the zone; pedestrians only ever wait at the kerb.
      kerb = D[:, tab.c_a[cols]] - half[:, None]
      ped = (self.kind[sub] == PEDESTRIAN)[:, None]
      stop_at = np.where(ped, np.where(kerb > -0.3, kerb, np.inf), fa - 1.0)
      out[sub] = np.where(must_yield, stop_at, np.inf).min(1)
      if record_step >= 0 and must_yield.any():
        for i, c in zip(*np.nonzero(must_yield)):
          j = j_strong[c] if y_strong[i, c] else j_peer[c]
          self.yields.append((record_step, int(sub[i]), int(sub[j])))

  def _clear_of_crosswalks(self, D, half, gap):
    """Moves a vehicle's waiting point back to before a crosswalk it would block."""
    tab = self.tab
    cw = np.nonzero(tab.crossing[tab.c_b] & ~tab.crossing[tab.c_a])[0]
    if cw.size == 0:
      return gap
    Da = D[:, tab.c_a[cw]]
    enter = Da + tab.c_a_in[cw][None] - half[:, None]                 # front reaches the crosswalk
    leave = Da + tab.c_a_out[cw][None] + half[:, None]                # rear clears it
    blocks = np.isfinite(Da) & (gap[:, None] > enter) & (gap[:, None] - 2 * half[:, None] < leave - 2 * half[:, None])
    blocks &= (enter > 0) & (self.kind == VEHICLE)[:, None]
    return np.minimum(gap, np.where(blocks, enter - 1.0, np.inf).min(1))

  def lane_changes(self, lane, s_lane, flat_l, flat_s, owner) -> bool:
    """MOBIL-like lane changes for the few agents that consider one this step; True if any."""
    tab, N, p = self.tab, self.N, self.p
    half = 0.5 * self.length
    mandatory = tab.dead_end[lane]
    cand = (self.active & (self.kind == VEHICLE) & (self.lc_prog >= 1.0) & (self.cooldown == 0)
            & ~tab.junction[lane] & ((self.v > 3.0) | mandatory))
    cand &= mandatory | (self.rng.uniform(size=N) < p["lc_rate"] * DT)
    ci = np.nonzero(cand)[0]
    if ci.size == 0:
      return False
    not_me = owner[None] != ci[:, None]
    lc, sc, v, vc, hc = lane[ci], s_lane[ci], self.v, self.v[ci], half[ci]
    pc = {k: x[ci] for k, x in p.items()}
    v0 = np.where(self.kind[ci] == VEHICLE, tab.v_limit[lc] * pc["v0f"], pc["v0"])
    g0, w = _interp_index(tab, lc, sc)
    # The current lane's leader, lane-local, for the incentive.
    rel_h = np.where((flat_l[None] == lc[:, None]) & not_me, flat_s[None] - sc[:, None], np.inf)
    rel_h = np.where(rel_h > 0, rel_h, np.inf)
    jh = owner[rel_h.argmin(1)]
    a_old = _idm(vc, v0, rel_h.min(1) - hc - half[jh], vc - v[jh], pc)
    best_gain = np.full(ci.size, 0.3)
    choice = np.full(ci.size, -1)
    choice_s = np.zeros(ci.size)
    for side, nb, nb_s, bias in (("left", tab.left, tab.left_s, -0.1), ("right", tab.right, tab.right_s, 0.15)):
      target = nb[lc]
      s_t = _at(nb_s, g0, w)
      ok = (target >= 0) & np.isfinite(s_t) & ~tab.dead_end[target]
      ok &= (tab.length[target] - s_t > 40.0) | ((tab.successors[target, 0] < 0) & ~tab.dead_end[target])
      if not ok.any():
        continue
      rel = np.where((flat_l[None] == target[:, None]) & not_me, flat_s[None] - s_t[:, None], np.nan)
      ahead = np.where(rel > 0, rel, np.inf)
      behind = np.where(rel <= 0, -rel, np.inf)
      ja, jb = owner[ahead.argmin(1)], owner[behind.argmin(1)]
      gap_a = ahead.min(1) - hc - half[ja]
      gap_b = behind.min(1) - hc - half[jb]
      a_new = _idm(vc, v0, gap_a, vc - v[ja], pc)
      pf = {k: x[jb] for k, x in p.items()}
      a_follow = np.where(np.isfinite(gap_b), _idm(v[jb], tab.v_limit[lc] * pf["v0f"], gap_b, v[jb] - vc, pf), 0.0)
      safe = (gap_a > np.maximum(2.0, 0.3 * vc)) & (gap_b > np.maximum(2.0, 0.5 * v[jb])) & (a_follow > -2.0)
      gain = a_new - a_old + bias + np.where(mandatory[ci] & (side == "left"), 10.0, 0.0)
      take = ok & safe & (gain > best_gain)
      best_gain = np.where(take, gain, best_gain)
      choice = np.where(take, target, choice)
      choice_s = np.where(take, s_t, choice_s)
    for k in np.nonzero(choice >= 0)[0]:
      i = int(ci[k])
      xy_old = self.position(np.array([i]))[0][0]
      tgt = int(choice[k])
      self.lc_old[i] = lane[i]
      self._set_route(i, self._new_route(tgt), float(choice_s[k]))
      gi, wi = _interp_index(tab, np.array([tgt]), np.array([choice_s[k]]))
      base, nrm = _at(tab.xy, gi, wi)[0], _at(tab.normal, gi, wi)[0]
      self.d0[i] = float(np.dot(xy_old - base, nrm))
      self.lc_len[i] = np.clip(max(self.v[i], 2.0) * self.rng.uniform(3.5, 5.5), 15.0, 90.0)
      self.lc_prog[i] = 0.0
      self.cooldown[i] = 50
    return bool((choice >= 0).any())

  def position(self, idx):
    """Centre xy, yaw and velocity of agents `idx`."""
    lane, s_lane = self.locate()
    return _poses(self.tab, lane[idx], s_lane[idx], self.d_now()[idx], self.dd_ds()[idx], self.v[idx])


def _place_initial(sim: _Sim, m: maps_lib.Map, rng: np.random.Generator, budget: int) -> None:
  """Fills the lanes with traffic at a density drawn per scene."""
  tab = sim.tab
  mean_gap = np.interp(m.demand, [0.0, 1.0], [90.0, 12.0])
  order = rng.permutation(len(m.lanes))
  for li in order:
    lane = m.lanes[li]
    if lane.junction or lane.crossing:
      continue
    if lane.user == "ped":
      if rng.uniform() < 0.35 * m.demand:
        sim.spawn(li, rng.uniform(0, tab.length[li] * 0.8), rng.uniform(0.0, 1.4), PEDESTRIAN)
      continue
    if lane.user == "parked":  # parked cars: static for the whole log, like many WOMD vehicles
      s, occupancy = rng.uniform(0, 20), rng.uniform(0.2, 0.9)
      while s < tab.length[li] - 6.0 and sim.n_used < budget:
        if rng.uniform() < occupancy:
          s += 2.75
          i = sim.spawn(li, s, 0.0, VEHICLE)
          sim.parked[i] = True
          sim.length[i], sim.width[i] = min(sim.length[i], 5.5), min(sim.width[i], 2.1)
          s += 0.5 * sim.length[i] + 2.75 + rng.uniform(1.0, 3.0)
        else:
          s += rng.uniform(5.0, 12.0)
      continue
    gap_scale = mean_gap * (3.0 if lane.user == "bike" else 1.0)
    s = rng.exponential(gap_scale)
    placed = []
    while s < tab.length[li] - 8.0 and sim.n_used < budget:
      kind = CYCLIST if lane.user == "bike" else VEHICLE
      if kind == VEHICLE and lane.right < 0 and lane.kind == 2 and rng.uniform() < 0.03:
        kind = CYCLIST
      limit = lane.speed_limit if kind == VEHICLE else 5.0
      to_end = tab.length[li] - s
      v = min(limit * rng.uniform(0.6, 1.0), np.sqrt(2 * 1.5 * to_end) if lane.successors or lane.dead_end else limit)
      i = sim.spawn(li, s, v, kind)
      if i < 0:
        break
      placed.append(i)
      s += 0.5 * sim.length[i] + 7.0 + rng.exponential(gap_scale)  # clears the longest truck
    # Start everyone at a speed they can hold or comfortably brake from behind the one ahead.
    ahead_rear, ahead_v = np.inf, 0.0
    for i in placed[::-1]:
      gap = max(ahead_rear - sim.s[i] - 0.5 * sim.length[i] - sim.p["s0"][i], 0.0)
      sim.v[i] = min(sim.v[i], ahead_v + gap / sim.p["T"][i], np.sqrt(ahead_v**2 + 2 * 2.0 * gap))
      ahead_rear, ahead_v = sim.s[i] - 0.5 * sim.length[i], sim.v[i]


def _spawn_entries(sim: _Sim, m: maps_lib.Map, rng: np.random.Generator) -> None:
  tab = sim.tab
  entries = np.nonzero(tab.entry)[0]
  rate = np.where(tab.user[entries] == 2, 0.03, np.where(tab.user[entries] == 1, 0.02, 0.25)) * m.demand
  fire = rng.uniform(size=entries.size) < rate * DT
  if not fire.any():
    return
  lane, s_lane = sim.locate()
  occ_l, occ_s, owner = sim.occupancy(lane, s_lane)
  for li in entries[fire]:
    if ((occ_l == li) & (occ_s < 20.0)).any():
      continue
    kind = {0: VEHICLE, 1: CYCLIST, 2: PEDESTRIAN}[int(tab.user[li])]
    v = tab.v_limit[li] * rng.uniform(0.7, 0.95) if kind == VEHICLE else (5.0 if kind == CYCLIST else 1.3)
    on_lane = occ_l == li
    if on_lane.any():  # enter no faster than can comfortably brake behind the one ahead
      j = np.argmin(np.where(on_lane, occ_s, np.inf))
      gap = max(occ_s[j] - 0.5 * sim.length[owner[j]] - 6.0, 0.0)
      v = min(v, np.sqrt(sim.v[owner[j]] ** 2 + 2 * 2.0 * gap))
    sim.spawn(int(li), 0.0, v, kind)


def simulate(m: maps_lib.Map, rng: np.random.Generator, num_steps: int = 91, warmup: int = 40,
             max_agents: int = 128) -> Logs:
  """Runs the traffic model for `warmup` + `num_steps` steps; records the last `num_steps`."""
  tab = build_table(m, warmup + num_steps)
  sim = _Sim(tab, m, rng, max_agents)
  _place_initial(sim, m, rng, budget=int(max_agents * 0.8))
  N = max_agents
  rec = {k: np.zeros((N, num_steps)) for k in ("s", "d", "slope", "v")}
  active = np.zeros((N, num_steps), bool)
  lanes = np.zeros((N, num_steps), int)
  with np.errstate(invalid="ignore"):  # inactive slots hold inf positions, masked out
    for t in range(warmup + num_steps):
      r = t - warmup
      if r >= 0 and sim.N:
        n = sim.N
        lanes[:n, r], rec["s"][:n, r] = sim.locate()
        rec["d"][:n, r], rec["slope"][:n, r], rec["v"][:n, r] = sim.d_now(), sim.dd_ds(), sim.v
        active[:n, r] = sim.active
      sim.step(t, r)
      _spawn_entries(sim, m, rng)
    xy, yaw, vel = _poses(tab, lanes, np.where(active, rec["s"], 0.0), rec["d"], rec["slope"], rec["v"])
  pad = lambda a, fill: np.concatenate([a, np.full(N - sim.N, fill, a.dtype)])
  return Logs(xy=xy, yaw=yaw, vel=vel, active=active, length=pad(sim.length, 1.0),
              width=pad(sim.width, 1.0), height=pad(sim.height, 1.0), obj_type=pad(sim.kind, VEHICLE),
              yields=sim.yields, lane=np.where(active, lanes, -1))


def _poses(tab: LaneTable, lane, s, d, slope, speed):
  """Lane coordinates (any shape) -> centre xy, yaw, velocity: the lane point, offset by d
  along its normal, heading the lane tangent turned by atan(dd/ds)."""
  shape = lane.shape
  g0, w = _interp_index(tab, lane.reshape(-1), s.reshape(-1))
  base = _at(tab.xy, g0, w)
  tan = _at(tab.tangent, g0, w)
  nrm = np.stack([-tan[:, 1], tan[:, 0]], -1)
  yaw = np.arctan2(tan[:, 1], tan[:, 0]) + np.arctan(slope.reshape(-1))
  vel = speed.reshape(-1)[:, None] * np.stack([np.cos(yaw), np.sin(yaw)], -1)
  xy = base + d.reshape(-1)[:, None] * nrm
  return xy.reshape(shape + (2,)), yaw.reshape(shape), vel.reshape(shape + (2,))
