"""On-policy targets: from the simulated pose back onto the log (training.closed_loop)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from conftest import make_scene
from pcdiff_jax.config import get_config
from pcdiff_jax.model import features as features_lib
from pcdiff_jax.sim import geometry
from pcdiff_jax.training import closed_loop
from pcdiff_jax.training import data as data_lib

CFG = get_config("tiny")
T, DT = 80, 0.1


def _drifted(t: int, shift, turn: float, obj: int = 1):
  """make_scene (91 steps) at step t with object `obj` moved by `shift` (m)
  and turned by `turn` (rad) in the simulation only; the log is unchanged."""
  state = make_scene(num_steps=91)
  sim = state.sim_trajectory
  sim = sim.replace(x=sim.x.at[obj, t].add(shift[0]), y=sim.y.at[obj, t].add(shift[1]),
                    yaw=sim.yaw.at[obj, t].add(turn))
  speed = sim.vel_x[obj, t]
  sim = sim.replace(vel_x=sim.vel_x.at[obj, t].set(speed * jnp.cos(turn)),
                    vel_y=sim.vel_y.at[obj, t].set(speed * jnp.sin(turn)))
  state = state.replace(sim_trajectory=sim, timestep=jnp.int32(t))
  return state, _features(state)


_features = jax.jit(lambda state: features_lib.scene_features(state, CFG.features))
_targets = jax.jit(lambda state, feats, cfg: closed_loop.on_policy_targets(state, feats, T, cfg, DT),
                   static_argnums=2)


def _slot(feats, obj):
  return int(np.flatnonzero(np.asarray(feats.agent_index) == obj)[0])


def test_agents_on_their_log_get_the_log_and_a_straight_tail_past_its_end():
  state, feats = _drifted(30, (0.0, 0.0), 0.0)
  cfg = closed_loop.OnPolicyConfig()
  got = _targets(state, feats, cfg)
  log = data_lib.targets_at(state, feats, T)
  inside = np.asarray(log.future_valid)                          # steps 31..90
  for field in ("future_xy", "future_yaw", "future_speed"):
    np.testing.assert_allclose(np.asarray(getattr(got, field))[inside],
                               np.asarray(getattr(log, field))[inside], atol=2e-3)
  # Past step 90 the log is continued at constant speed: make_scene drives straight.
  a = _slot(feats, 1)
  k = np.arange(1, T + 1)
  np.testing.assert_allclose(np.asarray(got.future_xy[a, :, 0]), 8.0 * DT * k, atol=2e-3)
  assert bool(got.future_valid[a].all())


def test_a_log_that_ends_early_continues_straight_and_its_agent_keeps_a_target():
  """A vehicle whose log ends at step 40 (a synthetic route leaving the map):
  before and after that step, its target is the log continued at constant
  speed, so the policy is never left without one."""
  cfg = closed_loop.OnPolicyConfig()
  k = np.arange(1, T + 1)
  for t in (30, 50):
    state, _ = _drifted(t, (0.0, 0.0), 0.0)
    log = state.log_trajectory
    state = state.replace(log_trajectory=log.replace(valid=log.valid.at[1, 41:].set(False)))
    feats = _features(state)
    got = _targets(state, feats, cfg)
    a = _slot(feats, 1)
    assert bool(got.future_valid[a].all())
    np.testing.assert_allclose(np.asarray(got.future_xy[a, :, 0]), 8.0 * DT * k, atol=2e-3)
    np.testing.assert_allclose(np.asarray(got.future_speed[a]), 8.0, atol=1e-3)


def test_a_drifted_agent_leaves_its_simulated_pose_and_rejoins_the_log():
  shift, turn = (0.0, 1.5), 0.1
  state, feats = _drifted(20, shift, turn)
  cfg = closed_loop.OnPolicyConfig(rejoin_seconds=3.0, rejoin_speed=2.0)
  got = _targets(state, feats, cfg)
  a = _slot(feats, 1)
  assert bool(got.future_valid[a].all())
  # The first step continues from the simulated pose, along its heading.
  np.testing.assert_allclose(np.asarray(got.future_xy[a, 0]), [8.0 * DT, 0.0], atol=0.05)
  assert abs(float(got.future_yaw[a, 0])) < 0.03
  # After R = 3 + 1.5 / 2 s it is the log, seen from the simulated frame.
  sim = state.sim_trajectory
  origin = jnp.stack([sim.x[1, 20], sim.y[1, 20]])
  log_xy = jnp.stack([state.log_trajectory.x[1, 21:91], state.log_trajectory.y[1, 21:91]], -1)
  log_local = geometry.to_local(log_xy, origin, sim.yaw[1, 20])
  after = int(np.ceil(3.75 / DT))
  np.testing.assert_allclose(np.asarray(got.future_xy[a, after:70]), np.asarray(log_local[after:70]), atol=1e-3)
  # Smooth: no step differs from the log's 0.8 m by more than a few cm.
  steps = np.linalg.norm(np.diff(np.asarray(got.future_xy[a]), axis=0), axis=-1)
  assert np.abs(steps - 0.8).max() < 0.08
  # Too far from the log: not trained on (future invalid), still in the scene.
  state, feats = _drifted(20, (0.0, 12.0), 0.0)
  far = _targets(state, feats, cfg)
  b = _slot(feats, 1)
  assert bool(feats.agent_valid[b]) and not bool(far.future_valid[b].any())


def test_mixed_batches_hold_the_asked_share_of_on_policy_examples():
  ex = jax.tree_util.tree_map(lambda a: np.arange(10)[:, None] + 0 * np.asarray(a)[None, :1], {"v": np.zeros(1)})
  on = jax.tree_util.tree_map(lambda a: 100 + a, ex)
  logged, visited = closed_loop.mixed_batch_at(ex, on, 3, 8, 0.25, 0)
  assert logged["v"].shape[0] == 6 and visited["v"].shape[0] == 2 and np.all(visited["v"] >= 100)
  again = closed_loop.mixed_batch_at(ex, on, 3, 8, 0.25, 0)
  np.testing.assert_array_equal(again[1]["v"], visited["v"])
  real = jax.tree_util.tree_map(lambda a: 1000 + a, ex)
  logged, visited = closed_loop.mixed_batch_at(ex, on, 3, 8, 0.25, 0, real=real, real_share=0.5)
  assert visited["v"].shape[0] == 2 and np.sum(logged["v"] >= 1000) == 3 and np.sum(logged["v"] < 100) == 3


def _with_left_curve(state, start=(32.0, 2.0), radius=60.0):
  """state with its lane centre replaced by a left-bending arc that starts at
  `start` heading +x (the straight lane before it kept up to there)."""
  rg = state.roadgraph_points
  lane = np.asarray(rg.types) == 2
  x0, y0 = start
  s = np.linspace(0.0, 120.0, int(lane.sum()))
  arc = np.stack([x0 + radius * np.sin(s / radius), y0 + radius * (1 - np.cos(s / radius))], -1)
  heading = s / radius
  f = lambda a: jnp.asarray(a, jnp.float32)
  return state.replace(roadgraph_points=rg.replace(
      x=rg.x.at[lane].set(f(arc[:, 0])), y=rg.y.at[lane].set(f(arc[:, 1])),
      dir_x=rg.dir_x.at[lane].set(f(np.cos(heading))), dir_y=rg.dir_y.at[lane].set(f(np.sin(heading))))), arc


def test_a_log_that_ends_early_is_continued_along_its_lane():
  """Object 1's log ends at step 40 where its lane starts a left curve: the
  continuation follows the curve (a straight tail would leave it by metres);
  an object with no lane in reach goes on straight."""
  state, arc = _with_left_curve(_drifted(50, (0.0, 0.0), 0.0)[0])
  log = state.log_trajectory
  state = state.replace(log_trajectory=log.replace(valid=log.valid.at[1, 41:].set(False)))
  tail = np.asarray(jax.jit(lambda s: closed_loop.lane_continuation(s, 40, DT))(state))   # (O, 40, 4)
  gap = np.min(np.linalg.norm(tail[1, :, None, :2] - arc[None], axis=-1), axis=-1)
  assert gap.max() < 0.3, gap
  assert tail[1, -1, 2] > 0.4                                         # turned with the lane
  np.testing.assert_allclose(tail[1, :, 3], 8.0, atol=1e-5)          # at its last speed
  # Object 2 is parked (speed 0): it stays where its log ended.
  np.testing.assert_allclose(tail[2, :, :2], np.repeat(tail[2, :1, :2], 40, 0), atol=1e-5)
  # Targets at step 50, past the end of the log, re-join the continuation
  # (0.5 m beside the straight-driving simulated agent) within 3.3 s and follow it.
  tail = jax.jit(lambda s: closed_loop.lane_continuation(s, 50 + T, DT))(state)
  feats = _features(state)
  got = closed_loop.on_policy_targets(state, feats, T, closed_loop.OnPolicyConfig(), DT, tail)
  a = _slot(feats, 1)
  sim = state.sim_trajectory
  world = geometry.from_local(got.future_xy[a], jnp.stack([sim.x[1, 50], sim.y[1, 50]]), sim.yaw[1, 50])
  gap = np.min(np.linalg.norm(np.asarray(world)[35:, None] - arc[None], axis=-1), axis=-1)
  assert bool(got.future_valid[a].all()) and gap.max() < 0.3, gap


def test_guided_targets_are_the_guided_plan_of_the_visited_state(tiny_models):
  """`targets="guided"`: each modelled agent's target is the teacher's
  (objective-guided) plan from its simulated pose: in the world frame it is
  the path the teacher planned; unmodelled slots are invalid and zero; a
  teacher without guidance is refused."""
  from pcdiff_jax import policy
  from pcdiff_jax.model import guidance, planner
  teacher = policy.PolicyConfig(ddim_steps=2, warm_start=False, execute="track", guidance=guidance.GuidanceConfig(
      mode="objective", guided_steps=1, inner_steps=1, field_size=64))
  t = 20
  state, feats = _drifted(t, (0.5, 1.0), 0.1)
  rng = jax.random.key(3)

  @jax.jit
  def run(state, feats):
    road = guidance.road_of(state, teacher.guidance)
    got = closed_loop.guided_targets(tiny_models, state, feats, CFG, teacher, rng, road)
    _, planned, path = policy.plan_actions(tiny_models, state, CFG, teacher, rng, road=road)
    return got, planned[feats.agent_index], path[feats.agent_index]
  got, planned, path = run(state, feats)
  modelled = np.asarray(feats.agent_valid & planned)
  assert modelled.sum() >= 3
  np.testing.assert_array_equal(np.asarray(got.future_valid), np.repeat(modelled[:, None], T, 1))
  np.testing.assert_allclose(np.asarray(got.current_speed)[modelled],
                             np.asarray(planner.agent_speed(feats))[modelled], atol=1e-5)
  sim = state.sim_trajectory
  for a in np.flatnonzero(modelled):
    o = int(feats.agent_index[a])
    world = geometry.from_local(got.future_xy[a], jnp.stack([sim.x[o, t], sim.y[o, t]]), sim.yaw[o, t])
    np.testing.assert_allclose(np.asarray(world), np.asarray(path[a]), atol=1e-2)
  assert not np.asarray(got.future_xy)[~modelled].any()
  import pytest
  with pytest.raises(ValueError, match="objective guidance"):
    closed_loop.make_collect_fn(None, CFG, closed_loop.OnPolicyConfig(targets="guided"), policy.PolicyConfig())
  with pytest.raises(ValueError, match="targets must be one of"):
    closed_loop.make_collect_fn(None, CFG, closed_loop.OnPolicyConfig(targets="log"))


def test_hybrid_targets_keep_the_log_where_its_way_back_is_on_the_road_and_clear():
  """`clean_rejoin_or`: on make_scene at step 20 (object 2 parked off the road),
  object 1's way back moved 3 m left (past the edge) and object 3's moved 40 m
  ahead (into object 0) take the guided target, and so does object 0 (it is
  hit); object 2 keeps its re-joining target (its path is no further off the
  road than it is now) unless its log ends before the record's."""
  from pcdiff_jax.model import guidance
  state = make_scene(num_steps=91).replace(timestep=jnp.int32(20))
  feats = _features(state)
  rejoin = _targets(state, feats, closed_loop.OnPolicyConfig())
  shift = {1: (0.0, 3.0), 3: (40.0, 0.0)}
  moved = rejoin.future_xy
  for obj, d in shift.items():
    moved = moved.at[_slot(feats, obj)].add(jnp.asarray(d))
  guided = rejoin.replace(future_speed=jnp.full_like(rejoin.future_speed, -1.0))
  g = guidance.GuidanceConfig(mode="objective", field_size=64)
  road = guidance.road_of(state, g)
  choose = jax.jit(lambda *a: closed_loop.clean_rejoin_or(state, *a, g))
  on_log = choose(rejoin, guided, feats, road)
  assert not bool(jnp.any((on_log.future_speed == -1.0) & on_log.future_valid))   # the log: all kept
  rejoin = rejoin.replace(future_xy=moved)
  guided = guided.replace(future_xy=moved)
  got = choose(rejoin, guided, feats, road)
  took_guided = {obj: bool(got.future_speed[_slot(feats, obj), 0] == -1.0) for obj in range(4)}
  assert took_guided == {0: True, 1: True, 2: False, 3: True}, took_guided
  np.testing.assert_array_equal(np.asarray(got.future_xy[_slot(feats, 2)]),
                                np.asarray(rejoin.future_xy[_slot(feats, 2)]))
  # A log that ends before the record does (object 2's last step) takes the guided target.
  log = state.log_trajectory
  ended = state.replace(log_trajectory=log.replace(valid=log.valid.at[2, -1].set(False)))
  got = jax.jit(lambda *a: closed_loop.clean_rejoin_or(ended, *a, g))(rejoin, guided, feats, road)
  assert bool(got.future_speed[_slot(feats, 2), 0] == -1.0)


def test_on_policy_agents_whose_log_overlaps_another_box_can_be_left_out():
  """The on-policy half of drop_log_overlaps: the scene of the training test (object 0 drives
  into object 2, standing 60 m ahead in its lane) rolled out on its log to step 10: with it, 0
  and 2 get no valid target step and the others keep theirs; without it all four keep theirs."""
  state = make_scene(num_steps=91, xs=(0.0, 0.0, 60.0, -30.0), ys=(-2.0, 2.0, -2.0, -2.0))
  state = state.replace(sim_trajectory=state.log_trajectory, timestep=jnp.int32(10))
  feats = _features(state)
  trained = lambda cfg: {int(o): bool(v.any()) for o, v, ok in zip(
      feats.agent_index, _targets(state, feats, cfg).future_valid, feats.agent_valid) if ok}
  assert trained(closed_loop.OnPolicyConfig()) == {0: True, 1: True, 2: True, 3: True}
  assert trained(closed_loop.OnPolicyConfig(drop_log_overlaps=True)) == {0: False, 1: True, 2: False, 3: True}
