"""Matplotlib rendering of a `SimulatorState`: scene PNGs, rollout GIFs, grids.

Host-side tools, not jitted: every function takes an *unbatched* state (object
fields (O, T), roadgraph (P,), lights (L, T), timestep ()) and converts it to
numpy first. Colours: the SDC red with a thick edge, controlled agents blue,
log-replayed agents grey; within a role pedestrians are a lighter and cyclists
a darker shade. Each box carries a dark triangle at its front.
"""
from __future__ import annotations

import math
from typing import Optional, Sequence

import jax
import matplotlib
import numpy as np
from PIL import Image

from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import DT_SECONDS, ObjectType, SimulatorState
from pcdiff_jax.sim.datatypes import RoadgraphType as R
from pcdiff_jax.sim.datatypes import TrafficLightState as TL

from matplotlib.backends.backend_agg import FigureCanvasAgg  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402
from matplotlib.colors import to_rgba, to_rgba_array  # noqa: E402
from matplotlib.figure import Figure  # noqa: E402

SDC_COLOR = "#ff2a1a"
SDC_EDGE = "#7a0000"
# Role -> face colours for (vehicle or other, pedestrian, cyclist).
ROLE_COLORS = {"log": ("#a9a9a9", "#dedede", "#6b6b6b"),
               "controlled": ("#3d7ee0", "#9cc3f5", "#1c4a96")}
LIGHT_COLORS = {TL.UNKNOWN: "#9e9e9e",
                TL.ARROW_STOP: "#d7191c", TL.STOP: "#d7191c", TL.FLASHING_STOP: "#d7191c",
                TL.ARROW_CAUTION: "#ffc107", TL.CAUTION: "#ffc107", TL.FLASHING_CAUTION: "#ffc107",
                TL.ARROW_GO: "#1a9641", TL.GO: "#1a9641"}
SPLIT_GAP_M = 2.0  # consecutive samples further apart than this start a new polyline

_BROKEN = (0, (4, 4))
# (roadgraph types, LineCollection style); drawn as polylines split per id.
_LINE_STYLES = (
    ((R.LANE_UNDEFINED, R.LANE_FREEWAY, R.LANE_SURFACE_STREET, R.LANE_BIKE_LANE),
     dict(colors="#cdcdcd", linewidths=0.6, linestyles=_BROKEN, zorder=1)),
    ((R.ROAD_LINE_BROKEN_SINGLE_WHITE,),
     dict(colors="#8f8f8f", linewidths=0.8, linestyles=_BROKEN, zorder=2)),
    ((R.ROAD_LINE_UNKNOWN, R.ROAD_LINE_SOLID_SINGLE_WHITE, R.ROAD_LINE_SOLID_DOUBLE_WHITE),
     dict(colors="#8f8f8f", linewidths=0.8, zorder=2)),
    ((R.ROAD_LINE_BROKEN_SINGLE_YELLOW, R.ROAD_LINE_BROKEN_DOUBLE_YELLOW),
     dict(colors="#e0a800", linewidths=1.0, linestyles=_BROKEN, zorder=2)),
    ((R.ROAD_LINE_SOLID_SINGLE_YELLOW, R.ROAD_LINE_SOLID_DOUBLE_YELLOW,
      R.ROAD_LINE_PASSING_DOUBLE_YELLOW),
     dict(colors="#e0a800", linewidths=1.0, zorder=2)),
    ((R.ROAD_EDGE_UNKNOWN, R.ROAD_EDGE_BOUNDARY, R.ROAD_EDGE_MEDIAN),
     dict(colors="#1e1e1e", linewidths=1.5, zorder=3)),
)
# (roadgraph types, PolyCollection style); one closed polygon per id.
_POLYGON_STYLES = (
    ((R.CROSSWALK,), dict(facecolors="#f2f2f2", edgecolors="#b5b5b5", hatch="////",
                          linewidths=0.5, zorder=0.5)),
    ((R.SPEED_BUMP,), dict(facecolors="#ffc27a", edgecolors="#f08a00", linewidths=2.0,
                           zorder=0.6)),
)


def _to_numpy(state: SimulatorState) -> SimulatorState:
  """The same state with numpy leaves; rejects batched states."""
  state = jax.tree_util.tree_map(np.asarray, state)
  if state.sim_trajectory.x.ndim != 2:
    raise ValueError(f"viz takes an unbatched state, got trajectories of shape "
                     f"{state.sim_trajectory.shape} (expected (O, T))")
  return state


def _polylines(xy: np.ndarray, ids: np.ndarray, gap: float) -> list[np.ndarray]:
  """Splits ordered (N, 2) points where `ids` change or samples are > `gap` m apart."""
  if len(xy) == 0:
    return []
  brk = (ids[1:] != ids[:-1]) | (np.linalg.norm(np.diff(xy, axis=0), axis=-1) > gap)
  return np.split(xy, np.flatnonzero(brk) + 1)


def _draw_roadgraph(ax, rg) -> None:
  """Draws the static map layer of numpy RoadgraphPoints (P,) onto `ax`."""
  xy = np.stack([rg.x, rg.y], -1)

  def select(types):
    keep = rg.valid & np.isin(rg.types, types)
    return xy[keep], rg.ids[keep]

  for types, style in _LINE_STYLES:
    lines = [p for p in _polylines(*select(types), SPLIT_GAP_M) if len(p) > 1]
    if lines:
      ax.add_collection(LineCollection(lines, capstyle="round", **style))
  for types, style in _POLYGON_STYLES:
    polys = [p for p in _polylines(*select(types), np.inf) if len(p) > 2]
    if polys:
      ax.add_collection(PolyCollection(polys, closed=True, **style))
  stops, _ = select((R.STOP_SIGN,))
  if len(stops):
    ax.scatter(stops[:, 0], stops[:, 1], marker="8", s=110, c="#c8102e", edgecolors="white",
               linewidths=1.0, zorder=4)


def _object_colors(meta, roles: np.ndarray) -> np.ndarray:
  """(O, 4) RGBA face colours by role (SDC, controlled, log) and object type."""
  kind = np.select([meta.object_types == ObjectType.PEDESTRIAN,
                    meta.object_types == ObjectType.CYCLIST], [1, 2], 0)
  table = to_rgba_array(ROLE_COLORS["log"] + ROLE_COLORS["controlled"])
  rgba = table[kind + 3 * roles.astype(int)]
  rgba[meta.is_sdc] = to_rgba(SDC_COLOR)
  return rgba


def _trails(traj, t: int, colors: np.ndarray, length: int) -> Optional[LineCollection]:
  """Fading segments over the last `length` steps of objects valid at `t`."""
  lo = max(t - length, 0)
  if t - lo < 1:
    return None
  xy = np.stack([traj.x[:, lo:t + 1], traj.y[:, lo:t + 1]], -1)   # (O, K, 2)
  valid = traj.valid[:, lo:t + 1]
  segs = np.stack([xy[:, :-1], xy[:, 1:]], axis=-2)                 # (O, K-1, 2, 2)
  ok = valid[:, :-1] & valid[:, 1:] & traj.valid[:, t:t + 1]
  rgba = np.repeat(colors[:, None], t - lo, axis=1)
  rgba[..., 3] = np.linspace(0.15, 0.8, t - lo)
  return LineCollection(segs[ok], colors=rgba[ok], linewidths=2.0, capstyle="round", zorder=5)


def _object_artists(traj, meta, roles: np.ndarray, t: int, trail: int) -> list:
  """Artists for the objects valid at step `t`: trails, oriented boxes, heading marks."""
  colors = _object_colors(meta, roles)
  idx = np.flatnonzero(traj.valid[:, t])
  idx = idx[np.argsort(meta.is_sdc[idx], kind="stable")]  # SDC drawn on top
  corners = np.asarray(geometry.box_corners(
      traj.x[:, t], traj.y[:, t], traj.yaw[:, t], traj.length[:, t], traj.width[:, t]))[idx]
  sdc = meta.is_sdc[idx]
  boxes = PolyCollection(corners, closed=True, facecolors=colors[idx],
                         edgecolors=np.where(sdc, SDC_EDGE, "#303030"),
                         linewidths=np.where(sdc, 2.0, 0.6), zorder=6)
  # Corners run front-left, rear-left, rear-right, front-right.
  f = 0.3
  tri = np.stack([(corners[:, 0] + corners[:, 3]) / 2,
                  corners[:, 0] + f * (corners[:, 1] - corners[:, 0]),
                  corners[:, 3] + f * (corners[:, 2] - corners[:, 3])], axis=1)
  heads = PolyCollection(tri, closed=True, facecolors=(0, 0, 0, 0.5), linewidths=0, zorder=7)
  trails = _trails(traj, t, colors, trail) if trail else None
  return [a for a in (trails, boxes, heads) if a is not None]


def _light_artist(ax, lights, t: int):
  """Scatter of the traffic lights valid at step `t`, coloured by state."""
  on = lights.valid[:, t]
  colors = [LIGHT_COLORS.get(int(s), LIGHT_COLORS[TL.UNKNOWN]) for s in lights.state[on, t]]
  return ax.scatter(lights.x[on, t], lights.y[on, t], s=28, c=colors or "none",
                    edgecolors="black", linewidths=0.5, zorder=4)


def _center(traj, meta, rg, t: int) -> np.ndarray:
  """(2,) view centre: the SDC at (or nearest valid step to) `t`, else the objects' mean."""
  sdc = np.argmax(meta.is_sdc)
  steps = np.flatnonzero(traj.valid[sdc] & meta.is_sdc[sdc])
  if len(steps):
    s = steps[np.argmin(np.abs(steps - t))]
    return np.array([traj.x[sdc, s], traj.y[sdc, s]])
  for x, y, valid in ((traj.x[:, t], traj.y[:, t], traj.valid[:, t]), (rg.x, rg.y, rg.valid)):
    if valid.any():
      return np.array([x[valid].mean(), y[valid].mean()])
  return np.zeros(2)


def _draw_frame(ax, s: SimulatorState, t: int, trajectory: str = "sim", roles=None,
                view_radius: float = 60.0, center=None, title: Optional[str] = None,
                trail: int = 10) -> list:
  """Draws the dynamic layer of numpy state `s` at step `t`, sets the view; returns artists."""
  if trajectory not in ("sim", "log"):
    raise ValueError(f"trajectory must be 'sim' or 'log', got {trajectory!r}")
  traj = s.sim_trajectory if trajectory == "sim" else s.log_trajectory
  if not 0 <= t < traj.num_timesteps:
    raise ValueError(f"timestep {t} outside [0, {traj.num_timesteps})")
  meta = s.object_metadata
  roles = meta.is_controlled if roles is None else np.asarray(roles, bool)
  artists = [ax.add_collection(a) for a in _object_artists(traj, meta, roles, t, trail)]
  artists.append(_light_artist(ax, s.log_traffic_light, t))
  cx, cy = _center(traj, meta, s.roadgraph_points, t) if center is None else np.asarray(center)
  ax.set_xlim(cx - view_radius, cx + view_radius)
  ax.set_ylim(cy - view_radius, cy + view_radius)
  ax.set_aspect("equal", adjustable="box")
  ax.set_xticks([])
  ax.set_yticks([])
  ax.set_title(title or "", fontsize=10)
  return artists


def plot_scene(ax, state: SimulatorState, timestep=None, trajectory: str = "sim", roles=None,
               view_radius: float = 60.0, center=None, title: Optional[str] = None,
               trail: int = 10):
  """Draws one step of an unbatched state onto a matplotlib Axes and returns `ax`.

  Args:
    ax: matplotlib Axes.
    state: unbatched SimulatorState (objects (O, T), roadgraph (P,), lights (L, T)).
    timestep: step to draw, python int or 0-d array; default `state.timestep`.
    trajectory: "sim" (state.sim_trajectory) or "log" (state.log_trajectory).
    roles: (O,) bool, agents drawn as controlled (blue); default
      `object_metadata.is_controlled`. The SDC is always red.
    view_radius: half-width of the square view, m.
    center: (2,) view centre; default the SDC's position at `timestep`.
    title: optional axes title.
    trail: number of past steps drawn as a fading trail (0 for none).
  """
  s = _to_numpy(state)
  t = int(s.timestep if timestep is None else np.asarray(timestep))
  _draw_roadgraph(ax, s.roadgraph_points)
  _draw_frame(ax, s, t, trajectory, roles, view_radius, center, title, trail)
  return ax


def _figure(size_in: tuple[float, float], dpi: int) -> Figure:
  """A pyplot-free Agg figure (nothing to close, nothing leaks)."""
  fig = Figure(figsize=size_in, dpi=dpi)
  FigureCanvasAgg(fig)
  return fig


def render_scene_png(state: SimulatorState, path, figsize: float = 8.0, dpi: int = 100, **kw):
  """Writes one step of `state` to a PNG of (figsize*dpi)^2 px (800x800) and returns `path`.

  `kw` go to `plot_scene` (timestep, trajectory, roles, view_radius, center, title, trail).
  """
  fig = _figure((figsize, figsize), dpi)
  ax = fig.add_axes((0.02, 0.02, 0.96, 0.92 if kw.get("title") else 0.96))
  plot_scene(ax, state, **kw)
  fig.savefig(path, dpi=dpi)
  return path


def render_rollout_gif(state: SimulatorState, path, start: Optional[int] = None,
                       stop: Optional[int] = None, every: int = 1, fps: float = 10,
                       figsize: float = 6.0, dpi: int = 80, **kw):
  """Writes an animated GIF of `state.sim_trajectory` and returns `path`.

  One frame per `every` steps from `start` (default 10, WOMD's current step) to
  `stop` inclusive (default the last step); the view follows the SDC and the
  title reads "t = X.X s" (step * 0.1 s). The map is drawn once; only the
  objects and lights are redrawn per frame. Frames are (figsize*dpi)^2 px.
  `kw` go to `plot_scene` (trajectory, roles, view_radius, center, title, trail);
  a `title` is prefixed to the time.
  """
  s = _to_numpy(state)
  start = 10 if start is None else int(start)
  stop = s.sim_trajectory.num_timesteps - 1 if stop is None else int(stop)
  prefix = kw.pop("title", None)
  fig = _figure((figsize, figsize), dpi)
  ax = fig.add_axes((0.02, 0.02, 0.96, 0.92))
  _draw_roadgraph(ax, s.roadgraph_points)
  frames, dynamic = [], []
  for t in range(start, stop + 1, every):
    for artist in dynamic:
      artist.remove()
    clock = f"t = {t * DT_SECONDS:.1f} s"
    dynamic = _draw_frame(ax, s, t, title=f"{prefix}  {clock}" if prefix else clock, **kw)
    fig.canvas.draw()
    frames.append(Image.fromarray(np.array(fig.canvas.buffer_rgba())[..., :3]))
  if not frames:
    raise ValueError(f"no frames in range({start}, {stop + 1}, {every})")
  frames[0].save(path, save_all=True, append_images=frames[1:],
                 duration=int(round(1000 / fps)), loop=0)
  return path


def render_grid_png(states: Sequence[SimulatorState], path, ncols: int = 4,
                    titles: Optional[Sequence[str]] = None, panel_size: float = 4.0,
                    dpi: int = 100, **kw):
  """Writes a grid of scenes (a list of unbatched states) to one PNG and returns `path`.

  Each panel is `panel_size` inches square; `titles` (one per state) label the
  panels; `kw` go to `plot_scene` for every panel.
  """
  n = len(states)
  if n == 0:
    raise ValueError("render_grid_png needs at least one state")
  titles = list(titles) if titles is not None else [None] * n
  if len(titles) != n:
    raise ValueError(f"{len(titles)} titles for {n} states")
  ncols = min(ncols, n)
  nrows = math.ceil(n / ncols)
  fig = _figure((panel_size * ncols, panel_size * nrows), dpi)
  axes = fig.subplots(nrows, ncols, squeeze=False)
  fig.subplots_adjust(left=0.01, right=0.99, bottom=0.01, top=0.99 - 0.25 / (nrows * panel_size),
                      wspace=0.04, hspace=0.1)
  for ax, state, title in zip(axes.flat, states, titles):
    plot_scene(ax, state, title=title, **kw)
  for ax in axes.flat[n:]:
    ax.set_axis_off()
  fig.savefig(path, dpi=dpi)
  return path
