"""Scene features: agents and map pieces, fixed-size, masked, frame-invariant."""
from __future__ import annotations

import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene, stack_states
from pcdiff_jax.config import get_config
from pcdiff_jax.model import features as F
from pcdiff_jax.sim import env, selection
from pcdiff_jax.sim.datatypes import Action

CFG = get_config("tiny").features
PAPER = get_config("paper").features
FEATURES = jax.jit(F.scene_features, static_argnums=1)


def rigid_transform(state, angle: float, shift=(0.0, 0.0)):
  """Rotates the whole world by `angle` about the origin, then shifts it."""
  c, s = np.cos(angle), np.sin(angle)
  tx, ty = shift

  def pos(x, y):
    return c * x - s * y + tx, s * x + c * y + ty

  def vec(x, y):
    return c * x - s * y, s * x + c * y

  def traj(t):
    x, y = pos(t.x, t.y)
    vx, vy = vec(t.vel_x, t.vel_y)
    return t.replace(x=x, y=y, vel_x=vx, vel_y=vy, yaw=t.yaw + angle)

  rg = state.roadgraph_points
  x, y = pos(rg.x, rg.y)
  dx, dy = vec(rg.dir_x, rg.dir_y)
  tl = state.log_traffic_light
  lx, ly = pos(tl.x, tl.y)
  return state.replace(
      sim_trajectory=traj(state.sim_trajectory), log_trajectory=traj(state.log_trajectory),
      roadgraph_points=rg.replace(x=x, y=y, dir_x=dx, dir_y=dy),
      log_traffic_light=tl.replace(x=lx, y=ly))


def assert_same_features(a, b, atol):
  for name in ("agent_valid", "agent_index", "agent_types", "agent_history_valid", "map_valid",
               "map_types", "map_kind", "map_traffic_light", "map_ids", "timestep"):
    np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
  for name in ("agent_history", "agent_center", "agent_dir", "map_points", "map_center",
               "map_dir"):
    np.testing.assert_allclose(getattr(a, name), getattr(b, name), atol=atol, err_msg=name)


def world_points(f, i):
  """(P, 2) world positions of piece i."""
  local = np.asarray(f.map_points[i])
  c, s = np.asarray(f.map_dir[i])
  scene = local @ np.array([[c, s], [-s, c]]) + np.asarray(f.map_center[i])
  cy, sy = np.cos(float(f.scene_yaw)), np.sin(float(f.scene_yaw))
  return scene @ np.array([[cy, sy], [-sy, cy]]) + np.asarray(f.scene_xy)


def distance_to_polyline(points, line):
  """(Q,) distance of points (Q, 2) to the polyline line (R, 2)."""
  if len(line) == 1:
    return np.linalg.norm(points - line[0], axis=-1)
  a, b = line[:-1], line[1:]
  ab = b - a
  t = np.clip(np.einsum("qrc,rc->qr", points[:, None] - a[None], ab)
              / np.maximum(np.sum(ab ** 2, -1), 1e-12), 0, 1)
  near = a[None] + t[..., None] * ab[None]
  return np.min(np.linalg.norm(points[:, None] - near, axis=-1), axis=1)


@pytest.fixture(scope="module")
def scene_state():
  return env.reset(make_scene(), init_steps=11)


@pytest.fixture(scope="module")
def real_reset(real_state):
  return env.reset(real_state)


def test_shapes_and_masks_on_make_scene(scene_state):
  f = FEATURES(scene_state, CFG)
  a, h, m, p = CFG.max_agents, CFG.history_steps, CFG.max_polylines, CFG.points_per_polyline
  chex.assert_shape(f.agent_history, (a, h, F.AGENT_DIM))
  chex.assert_shape([f.agent_center, f.agent_dir], (a, 2))
  chex.assert_shape(f.map_points, (m, p, 2))
  chex.assert_shape([f.map_center, f.map_dir], (m, 2))
  # 4 objects, 9 agent slots: the SDC (slot 0) first, then by distance.
  np.testing.assert_array_equal(f.agent_valid, [True] * 4 + [False] * (a - 4))
  np.testing.assert_array_equal(f.agent_index[:4], [0, 1, 2, 3])
  assert not np.asarray(f.agent_history[4:]).any()
  assert np.asarray(f.agent_history_valid[:4]).all()
  # Three 299.5 m polylines -> 15 pieces each, 45 > M: every slot is a real piece.
  assert np.asarray(f.map_valid).all()
  # The SDC sits at the scene origin, heading along x.
  np.testing.assert_allclose(f.agent_center[0], [0.0, 0.0], atol=1e-6)
  np.testing.assert_allclose(f.agent_dir[0], [1.0, 0.0], atol=1e-6)
  np.testing.assert_allclose(f.scene_xy, [10.0, -2.0], atol=1e-5)   # x = 10 m/s * 1.0 s
  # Unit directions; the lane goes along +x, edge 1 along -x.
  np.testing.assert_allclose(np.linalg.norm(f.map_dir, axis=-1), 1.0, atol=1e-5)
  lane = np.asarray(f.map_ids) == 2
  np.testing.assert_allclose(np.asarray(f.map_dir)[lane], [[1.0, 0.0]] * lane.sum(), atol=1e-5)
  np.testing.assert_allclose(np.asarray(f.map_dir)[np.asarray(f.map_ids) == 1][:, 0], -1.0,
                             atol=1e-5)
  # History of the SDC in its own frame: 11 steps of 1 m along x, ending at 0.
  hist = np.asarray(f.agent_history[0])
  np.testing.assert_allclose(hist[:, 0], np.arange(-10, 1, dtype=np.float32), atol=1e-5)
  np.testing.assert_allclose(hist[1:, 2], 1.0, atol=1e-5)     # dx
  np.testing.assert_allclose(hist[:, 6], 10.0, atol=1e-5)     # vel_x
  np.testing.assert_allclose(hist[:, 8:10], [[4.5, 2.0]] * 11)
  np.testing.assert_allclose(hist[:, 10:14], [[1, 0, 0, 1]] * 11)


def test_shapes_masks_and_sdc_on_the_real_sample(real_reset):
  f = FEATURES(real_reset, CFG)
  assert int(f.agent_index[0]) == 8 and bool(f.agent_valid[0])   # the SDC, first
  assert np.asarray(f.agent_valid).all() and np.asarray(f.map_valid).all()
  assert len(set(np.asarray(f.agent_index).tolist())) == CFG.max_agents
  # The same set as the simulator's selection, nearest first.
  mask = selection.nearest_to_sdc(real_reset, CFG.max_agents, include_sdc=True)
  assert set(np.nonzero(np.asarray(mask))[0].tolist()) == set(np.asarray(f.agent_index).tolist())
  dist = np.linalg.norm(np.asarray(f.agent_center), axis=-1)
  assert np.all(np.diff(dist) >= 0)
  # History: the current step is the origin and valid.
  np.testing.assert_allclose(np.asarray(f.agent_history)[:, -1, :2], 0.0, atol=1e-6)
  assert np.asarray(f.agent_history_valid)[:, -1].all()
  # Pieces: in roadgraph order, of known kinds.
  ids = np.asarray(real_reset.roadgraph_points.ids)
  first_point = [np.nonzero(ids == i)[0][0] for i in np.asarray(f.map_ids)]
  assert np.all(np.diff(first_point) >= 0)
  assert set(np.asarray(f.map_kind).tolist()) <= {k.value for k in F.MapKind}
  assert np.isfinite(np.asarray(f.map_points)).all()


@pytest.mark.parametrize("angle, shift", [(0.7, (123.0, -45.0)), (-2.5, (-10.0, 300.0))])
def test_features_are_invariant_to_a_rigid_transform(scene_state, angle, shift):
  a = FEATURES(scene_state, CFG)
  b = FEATURES(rigid_transform(scene_state, angle, shift), CFG)
  assert_same_features(a, b, atol=1e-4)
  np.testing.assert_allclose(float(b.scene_yaw), angle, atol=1e-6)


def test_real_features_are_invariant_to_a_rigid_transform(real_reset):
  a = FEATURES(real_reset, PAPER)                   # 64 agents, 256 pieces
  b = FEATURES(rigid_transform(real_reset, -2.0, (1000.0, -3000.0)), PAPER)
  assert_same_features(a, b, atol=2e-3)   # world coordinates ~3 km: float32 rounding


def test_pieces_are_bounded_and_lie_on_their_polyline(real_reset):
  f = FEATURES(real_reset, PAPER)
  rg = real_reset.roadgraph_points
  ids, xy = np.asarray(rg.ids), np.asarray(rg.xy)
  assert np.asarray(f.map_valid).all()
  for i in range(PAPER.max_polylines):
    pts = world_points(f, i)
    length = np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=-1))
    assert length <= PAPER.segment_length + 1e-3
    line = xy[(ids == int(f.map_ids[i])) & np.asarray(rg.valid)]
    assert distance_to_polyline(pts, line).max() < 2e-3


def test_pieces_tile_a_polyline_in_equal_parts(scene_state):
  cfg = dataclasses.replace(CFG, max_polylines=64)   # all 45 pieces
  f = FEATURES(scene_state, cfg)
  valid = np.asarray(f.map_valid)
  assert valid.sum() == 45
  lane = valid & (np.asarray(f.map_ids) == 2)
  pts = np.stack([world_points(f, i) for i in np.nonzero(lane)[0]])   # (15, P, 2)
  np.testing.assert_allclose(pts[..., 1], 0.0, atol=1e-4)
  starts = np.sort(pts[:, 0, 0])
  np.testing.assert_allclose(starts, -100.0 + 299.5 / 15 * np.arange(15), atol=1e-3)
  np.testing.assert_allclose(np.sort(pts[:, -1, 0])[-1], 199.5, atol=1e-3)
  # Resampled evenly over arc length.
  np.testing.assert_allclose(np.diff(pts[..., 0], axis=1), 299.5 / 15 / (cfg.points_per_polyline - 1),
                             atol=1e-3)
  np.testing.assert_array_equal(np.asarray(f.map_kind)[lane], F.MapKind.LANE)
  assert set(np.asarray(f.map_kind)[valid & ~lane].tolist()) == {F.MapKind.ROAD_EDGE}


def test_traffic_light_is_attached_to_its_lane_at_time_t():
  base = make_scene()
  rg = base.roadgraph_points
  n = rg.num_points // 3
  # A second lane (id 3, at y = 2) replaces edge 1.
  ids = rg.ids.at[n:2 * n].set(3)
  types = rg.types.at[n:2 * n].set(1)
  ys = rg.y.at[n:2 * n].set(2.0)
  state = base.replace(roadgraph_points=rg.replace(ids=ids, types=types, y=ys))
  tsteps = base.log_traffic_light.num_timesteps
  # Slot 0 controls lane 3: red until step 14, then green. Slot 1 controls
  # lane 2 (flashing caution) until step 14, then a lane that is not mapped.
  lane_ids = np.stack([np.full(tsteps, 3), np.where(np.arange(tsteps) < 15, 2, 99)])
  states = np.stack([np.where(np.arange(tsteps) < 15, 4, 6), np.full(tsteps, 8)])
  lights = base.log_traffic_light.replace(
      lane_ids=jnp.asarray(lane_ids, jnp.int32), state=jnp.asarray(states, jnp.int32),
      valid=jnp.ones((2, tsteps), bool))
  state = state.replace(log_traffic_light=lights)
  cfg = dataclasses.replace(CFG, max_polylines=64)
  for t, lane2, lane3 in ((10, 1 + 8, 1 + 4), (20, 0, 1 + 6)):
    f = FEATURES(env.reset(state, init_steps=t + 1), cfg)
    mids, light, valid = (np.asarray(f.map_ids), np.asarray(f.map_traffic_light),
                          np.asarray(f.map_valid))
    assert (light[valid & (mids == 2)] == lane2).all()
    assert (light[valid & (mids == 3)] == lane3).all()
    assert (light[valid & (mids == 0)] == 0).all()     # the road edge has no light


def test_history_comes_from_the_sim_trajectory_at_t(scene_state):
  # Closed loop from step 10: object 1 brakes hard; the log keeps it at 8 m/s.
  s = scene_state
  controlled = jnp.array([False, True, False, False])
  action = Action(data=jnp.array([[0, 0], [-5.0, 0.3], [0, 0], [0, 0]], jnp.float32),
                  valid=jnp.ones((4, 1), bool))
  for _ in range(6):
    s = env.step(s, action, controlled)
  assert int(s.timestep) == 16
  f = FEATURES(s, CFG)
  assert int(f.timestep) == 16
  sim = s.sim_trajectory
  steps = np.arange(16 - CFG.history_steps + 1, 17)
  j = int(np.nonzero(np.asarray(f.agent_index) == 1)[0][0])
  xy = np.stack([np.asarray(sim.x)[1, steps], np.asarray(sim.y)[1, steps]], -1)
  yaw = float(sim.yaw[1, 16])
  rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
  expected = (xy - xy[-1]) @ rot
  np.testing.assert_allclose(np.asarray(f.agent_history)[j, :, :2], expected, atol=1e-4)
  # It differs from the log, and the future sim steps do not matter.
  log_xy = np.stack([np.asarray(s.log_trajectory.x)[1, steps],
                     np.asarray(s.log_trajectory.y)[1, steps]], -1)
  assert np.abs(log_xy - xy).max() > 0.5
  poisoned = s.replace(sim_trajectory=s.sim_trajectory.replace(
      x=s.sim_trajectory.x.at[:, 17:].set(1e4), valid=s.sim_trajectory.valid.at[:, 17:].set(True)))
  assert_same_features(f, FEATURES(poisoned, CFG), atol=0.0)


def test_jit_vmap_batch_without_retracing(scene_state):
  other = env.reset(make_scene(speeds=(5.0, 3.0, 1.0, 9.0), ys=(-2.0, 2.0, 2.0, -2.0)),
                    init_steps=11)
  batch = stack_states([scene_state, other])

  @jax.jit
  @chex.assert_max_traces(n=1)
  def fn(states):
    return F.scene_features(states, CFG)

  fa = fn(batch)
  fb = fn(stack_states([other, scene_state]))         # a different batch, same sizes
  chex.assert_shape(fa.map_points, (2, CFG.max_polylines, CFG.points_per_polyline, 2))
  for k, single in enumerate((scene_state, other)):
    one = FEATURES(single, CFG)
    assert_same_features(jax.tree_util.tree_map(lambda x: x[k], fa), one, atol=1e-5)
    assert_same_features(jax.tree_util.tree_map(lambda x: x[1 - k], fb), one, atol=1e-5)


def test_empty_scene_gives_masked_finite_features(scene_state):
  s = scene_state
  empty = s.replace(
      sim_trajectory=s.sim_trajectory.replace(valid=jnp.zeros_like(s.sim_trajectory.valid)),
      roadgraph_points=s.roadgraph_points.replace(valid=jnp.zeros_like(s.roadgraph_points.valid)),
      log_traffic_light=s.log_traffic_light.replace(valid=jnp.zeros_like(s.log_traffic_light.valid)))
  f = FEATURES(empty, CFG)
  assert not np.asarray(f.agent_valid).any() and not np.asarray(f.map_valid).any()
  for leaf in jax.tree_util.tree_leaves(f):
    assert np.isfinite(np.asarray(leaf, np.float64)).all()
  assert not np.asarray(f.agent_history).any() and not np.asarray(f.map_points).any()


def test_scatter_and_frame_helpers(scene_state):
  f = FEATURES(scene_state, CFG)
  # The origin of each agent's frame is its world position at t.
  xy, yaw = F.agent_to_world(jnp.zeros((CFG.max_agents, 3, 2)), jnp.zeros((CFG.max_agents, 3)), f)
  cur = scene_state.current_sim_trajectory
  idx = np.asarray(f.agent_index)[:4]
  np.testing.assert_allclose(np.asarray(xy)[:4, 1], np.asarray(cur.xy)[idx, 0], atol=1e-5)
  np.testing.assert_allclose(np.asarray(yaw)[:4, 2], np.asarray(cur.yaw)[idx, 0], atol=1e-6)
  # A point 1 m ahead in the agent frame is 1 m along the heading (all yaw 0 here).
  ahead, _ = F.agent_to_world(jnp.ones((CFG.max_agents, 2)) * jnp.array([1.0, 0.0]),
                              jnp.zeros((CFG.max_agents,)), f)
  np.testing.assert_allclose(np.asarray(ahead)[:4] - np.asarray(cur.xy)[idx, 0], [[1.0, 0.0]] * 4,
                             atol=1e-5)
  per_object = F.scatter_to_objects(jnp.arange(CFG.max_agents, dtype=jnp.float32) + 1, f, 4, -1.0)
  np.testing.assert_array_equal(per_object[idx], np.arange(4) + 1)


def nearest_piece_distance(f, agent_xy):
  """(A,) distance of each agent (A, 2) world to the nearest point of a kept piece."""
  pts = np.concatenate([world_points(f, i) for i in np.nonzero(np.asarray(f.map_valid))[0]])
  return np.min(np.linalg.norm(agent_xy[:, None] - pts[None], axis=-1), axis=1)


def test_a_crop_anchored_on_the_agents_keeps_the_map_around_every_agent(real_reset):
  # A crop too small for the whole scene: anchored on the SDC it leaves the far
  # agents without a map; anchored on the agents it keeps each agent's surroundings.
  small = dataclasses.replace(PAPER, max_polylines=64)
  by_sdc = FEATURES(real_reset, small)
  by_agents = FEATURES(real_reset, dataclasses.replace(small, map_anchor="agents"))
  np.testing.assert_array_equal(by_sdc.agent_index, by_agents.agent_index)
  np.testing.assert_allclose(by_sdc.agent_history, by_agents.agent_history)
  assert np.asarray(by_agents.map_valid).all()
  valid = np.asarray(by_sdc.agent_valid)
  xy = np.asarray(real_reset.current_sim_trajectory.xy[:, 0])[np.asarray(by_sdc.agent_index)[valid]]
  rg = np.asarray(real_reset.roadgraph_points.xy)[np.asarray(real_reset.roadgraph_points.valid)]
  on_map = np.min(np.linalg.norm(xy[:, None] - rg[None], axis=-1), axis=1) < 5.0    # 48 of 65 agents
  near_sdc = nearest_piece_distance(by_sdc, xy)[on_map] < 5.0
  near_agents = nearest_piece_distance(by_agents, xy)[on_map] < 5.0
  assert near_sdc.mean() < 0.5               # 64 pieces around the SDC: 20 of the 48
  assert near_agents.mean() > 0.95           # around the agents: 47
  assert on_map[0] and near_agents[0]        # the SDC's own road is still there
  with pytest.raises(ValueError, match="map_anchor"):
    FEATURES(real_reset, dataclasses.replace(small, map_anchor="ego"))
