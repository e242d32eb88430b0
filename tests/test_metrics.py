"""Collision and off-road events and rates: hand-built scenes and the real record."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from conftest import make_scene
from pcdiff_jax import baselines
from pcdiff_jax.sim import env, metrics
from pcdiff_jax.sim.datatypes import ObjectType
from pcdiff_jax.sim.selection import nearest_to_sdc


def _counts(state, sim, start=5, k=3):
  evaluated = nearest_to_sdc(state.replace(timestep=jnp.int32(start)), k, include_sdc=True)
  return metrics.event_counts(sim, state.log_trajectory, state.roadgraph_points,
                              state.object_metadata.object_types, evaluated, start)


def test_collision_and_offroad_on_a_hand_built_scene():
  # Agent 3 (behind the SDC in its lane at 5 m/s) is made to drive at 30 m/s:
  # it rear-ends the SDC. Agent 1 drifts off the road; agent 2 starts off it.
  s = make_scene()
  sim = s.log_trajectory
  t = jnp.arange(sim.num_timesteps)
  x3 = jnp.where(t > 5, sim.x[3, 5] + 30.0 * (t - 5) * 0.1, sim.x[3])
  y1 = jnp.where(t > 5, 2.0 + 0.6 * (t - 5) * 0.1 * 10, 2.0)
  sim = sim.replace(x=sim.x.at[3].set(x3), y=sim.y.at[1].set(y1))
  c = _counts(s, sim, k=4)
  assert int(c.num_evaluated) == 4 and int(c.num_vehicles) == 4
  assert int(c.collided) == 2  # the SDC and agent 3
  assert int(c.start_offroad) == 1 and int(c.became_offroad) == 1
  on_log = _counts(s, s.log_trajectory, k=4)
  assert int(on_log.collided) == 0 and int(on_log.became_offroad) == 0 and int(on_log.start_offroad) == 1
  r = c.rates()
  assert r["collision_rate"] == 0.5 and r["offroad_rate"] == 1 / 3
  assert int(c.offroad_past_log) == 0 and r["offroad_past_log_rate"] == 0.0
  # The same drift once agent 1's log has ended (step 6 on) counts as off-road past its log.
  ended = s.replace(log_trajectory=s.log_trajectory.replace(valid=s.log_trajectory.valid.at[1, 6:].set(False)))
  c2 = _counts(ended, sim, k=4)
  assert int(c2.became_offroad) == 1 and int(c2.offroad_past_log) == 1


def test_collisions_with_objects_replaying_their_log_are_counted_apart():
  """Agent 3 rear-ends the SDC. With the SDC replaying its log, agent 3's collision has a partner
  that replays its log and the SDC's does not (its partner, agent 3, is the method's)."""
  s = make_scene()
  sim = s.log_trajectory
  t = jnp.arange(sim.num_timesteps)
  sim = sim.replace(x=sim.x.at[3].set(jnp.where(t > 5, sim.x[3, 5] + 30.0 * (t - 5) * 0.1, sim.x[3])))
  evaluated = nearest_to_sdc(s.replace(timestep=jnp.int32(5)), 4, include_sdc=True)
  count = lambda replayed: metrics.event_counts(sim, s.log_trajectory, s.roadgraph_points,
                                                s.object_metadata.object_types, evaluated, 5,
                                                replayed=replayed)
  sdc_replayed = count(jnp.arange(4) == 0)
  assert int(sdc_replayed.collided) == 2 and int(sdc_replayed.collided_with_replayed) == 1
  assert sdc_replayed.rates()["collision_with_replayed_rate"] == 0.25
  assert int(count(None).collided_with_replayed) == 0
  assert int(count(jnp.arange(4) == 1).collided_with_replayed) == 0   # agent 1 is nobody's partner



def test_pedestrians_hit_by_a_vehicle_are_counted_apart_from_walkers_overlapping():
  """Agent 3 runs into the SDC from behind. As a pedestrian it is a walker overlapping a
  vehicle (the SDC's collision has no vehicle partner); with the SDC a pedestrian too, the two
  overlap as walkers in a group do, and no vehicle is involved."""
  s = make_scene()
  sim = s.log_trajectory
  t = jnp.arange(sim.num_timesteps)
  sim = sim.replace(x=sim.x.at[3].set(jnp.where(t > 5, sim.x[3, 5] + 30.0 * (t - 5) * 0.1, sim.x[3])))
  types = s.object_metadata.object_types
  walker = s.replace(object_metadata=s.object_metadata.replace(object_types=types.at[3].set(ObjectType.PEDESTRIAN)))
  c = _counts(walker, sim, k=4)
  assert int(c.collided) == 2 and int(c.vehicle_collided) == 0
  assert int(c.num_vrus) == 1 and int(c.vru_vehicle_collided) == 1
  assert c.rates()["vru_vehicle_collision_rate"] == 1.0
  group = s.replace(object_metadata=s.object_metadata.replace(
      object_types=types.at[0].set(ObjectType.PEDESTRIAN).at[3].set(ObjectType.PEDESTRIAN)))
  c = _counts(group, sim, k=4)
  assert int(c.collided) == 2 and int(c.num_vrus) == 2 and int(c.vru_vehicle_collided) == 0

def _two_roads(state, offset: float = 100.0):
  """The scene's roadgraph and a copy of it `offset` m to the left (+y): two parallel roads."""
  rg = state.roadgraph_points
  far = rg.replace(y=rg.y + offset, ids=rg.ids + 10)
  return jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), rg, far)


def test_offroad_finds_the_nearest_edge_of_objects_far_apart():
  """Three cars on one road and one on a parallel road 100 m away, each tested
  against only the 64 road-edge samples nearest it: none is off the road until
  the far one steers 6 m to the side, across its edge, and the flags equal those of a search
  of every sample. (A crop of the samples nearest the cars' centroid holds only
  the first road's edges, and judged the far car, beyond them, off the road.)"""
  state = make_scene(speeds=(5.0, 5.0, 5.0, 5.0), xs=(-20.0, 0.0, 10.0, 0.0), ys=(-2.0, 2.0, -2.0, 98.0))
  traj, rg = state.log_trajectory, _two_roads(state)
  off = metrics.offroad(traj, rg, max_edge_points=64)
  assert not bool(jnp.any(off))
  t = jnp.arange(traj.num_timesteps)
  swerve = traj.replace(y=traj.y.at[3].add(jnp.where(t >= 20, 6.0, 0.0)))
  off = metrics.offroad(swerve, rg, max_edge_points=64)
  assert off[3].tolist() == (t >= 20).tolist() and not bool(jnp.any(off[:3]))
  assert off.tolist() == metrics.offroad(swerve, rg, max_edge_points=rg.num_points).tolist()


def test_pairs_overlapping_at_start_are_not_collisions():
  s = make_scene(xs=(0.0, 0.0, 10.0, -2.0), speeds=(10.0, 8.0, 0.0, 10.0))  # 3 overlaps the SDC from the start
  c = _counts(s, s.log_trajectory, k=4)
  assert int(c.collided) == 0 and int(c.collided_any) == 2
  overlap = metrics.overlap(s.log_trajectory)
  assert overlap.shape == (4, 31) and bool(overlap[0].all())


def test_objects_entering_later_are_not_collision_partners():
  """Agent 2 is parked; its track ends at step 8 and object 3 (invisible until step 12: a new
  track, as after a tracker's re-identification) appears on it and drives off. Keeping agent 2
  in place is no collision with a sim agent; `collided_with_entering` still counts it."""
  s = make_scene(xs=(0.0, 20.0, 40.0, 40.0), ys=(-2.0, 2.0, -2.0, -2.0), speeds=(10.0, 8.0, 0.0, 5.0))
  log = s.log_trajectory
  t = jnp.arange(log.num_timesteps)
  valid = log.valid.at[3].set(t >= 12).at[2].set(t < 8)
  log = log.replace(valid=valid, x=log.x.at[3].set(jnp.where(t >= 12, 40.0 + 5.0 * (t - 12) * 0.1, 40.0)))
  s = s.replace(log_trajectory=log)
  sim = log.replace(valid=log.valid.at[2].set(True))             # the sim keeps agent 2 where it was
  c = _counts(s, sim, k=3)
  assert int(c.num_evaluated) == 3
  assert int(c.collided) == 0 and int(c.collided_with_entering) == 1
  assert c.rates()["collision_with_entering_rate"] == 1 / 3


def test_log_replay_rates_on_the_real_record(real_state):
  """Real WOMD, log replay over 8 s, the 64 agents nearest the SDC.

  Measured: off-road rate 0 (14 of 59 vehicles start off the road: parked
  cars); vehicle-vehicle collisions 0; collision rate 2/64, 5/64 with the
  objects that enter later as partners: the log's own pedestrian boxes
  (0.7 m) overlap inside a walking group and brush two parked cars (of the 5
  evaluated pedestrians, 1 overlaps a vehicle after the start). These are label
  overlaps, not simulator errors.
  """
  start = 10
  state = env.reset(real_state)
  out = jax.jit(lambda s: env.rollout(s, baselines.log_replay(), 80, jax.random.PRNGKey(0)))(state)
  evaluated = nearest_to_sdc(state, 64)
  c = metrics.event_counts(out.final_state.sim_trajectory, state.log_trajectory, state.roadgraph_points,
                           state.object_metadata.object_types, evaluated, start)
  assert int(c.num_evaluated) == 64 and int(c.num_vehicles) == 59
  assert int(c.became_offroad) == 0 and int(c.start_offroad) == 14
  assert int(c.vehicle_collided) == 0 and int(c.collided) == 2 and int(c.collided_with_entering) == 5
  assert int(c.num_vrus) == 5 and int(c.vru_vehicle_collided) == 1
  types = np.asarray(state.object_metadata.object_types)
  pairs = np.asarray(metrics.pairwise_overlap(state.log_trajectory))[11:]
  involved = np.nonzero(pairs.any(axis=(0, 2)) & np.asarray(evaluated))[0]
  # Every evaluated agent in a logged collision touches a pedestrian.
  for i in involved:
    partners = np.nonzero(pairs[:, i].any(0))[0]
    assert types[i] == 2 or (types[partners] == 2).all()


def test_offroad_on_the_evaluated_subset_matches_the_full_test(real_state):
  """`max_evaluated` (off-road only for the scored objects and the simulated
  steps, ~2x cheaper) gives the same counts as the test over all objects."""
  start = 10
  state = env.reset(real_state)
  cv = baselines.constant_velocity(baselines.reactive_agents(64))
  out = jax.jit(lambda s: env.rollout(s, cv, 80, jax.random.PRNGKey(0)))(state)
  evaluated = nearest_to_sdc(state, 64)
  args = (out.final_state.sim_trajectory, state.log_trajectory, state.roadgraph_points,
          state.object_metadata.object_types, evaluated, start)
  full = metrics.event_counts(*args)
  subset = metrics.event_counts(*args, max_evaluated=64)
  assert int(full.became_offroad) > 0                                  # CV leaves the road
  for name, value in vars(full).items():
    assert int(getattr(subset, name)) == int(value), name


def test_adversarial_scores_of_a_rear_end_pursuit():
  """Object 3 starts 30 m behind the SDC (10 m/s) and drives at 20 m/s: the
  boxes (4.5 m long) first touch at t = 2.6 s, relative speed 10 m/s."""
  from pcdiff_jax import metrics as metrics_lib
  state = make_scene(num_steps=91)
  t = np.arange(91) * 0.1
  sim = state.sim_trajectory
  sim = sim.replace(x=sim.x.at[3].set(jnp.asarray(-30.0 + 20.0 * t, jnp.float32)),
                    vel_x=sim.vel_x.at[3].set(20.0))
  final = state.replace(sim_trajectory=sim, timestep=jnp.int32(90))
  s = jax.jit(metrics_lib.adversarial_scores, static_argnums=(1, 3))(final, 10, jnp.int32(3), 512)
  assert bool(s.has_pair) and bool(s.collided) and not bool(s.became_offroad)
  assert float(s.impact_speed) == pytest.approx(10.0, abs=1e-3)
  assert float(s.min_distance) < 0.5
  none = metrics_lib.adversarial_scores(final, 10, jnp.int32(-1), 512)
  assert not bool(none.has_pair) and not bool(none.collided)
  agg = metrics_lib.aggregate_adversarial(jax.tree_util.tree_map(lambda a, b: jnp.stack([a, b]), s, none))
  assert agg["num_pairs"] == 1 and agg["ego_adv_collision_rate"] == 1.0
  assert agg["impact_speed"] == pytest.approx(10.0, abs=1e-3)


def test_still_moved_rate_counts_still_agents_driven_away():
  """Objects 2 and 3 stand still in the log; the rollout moves 2 by 3 m
  (counts) and 3 by 1.5 m (does not); the movers are not still. Log replay: 0."""
  from pcdiff_jax import metrics as metrics_lib
  state = make_scene(speeds=(10.0, 8.0, 0.0, 0.0), xs=(0.0, 0.0, 10.0, -30.0))
  t = jnp.arange(state.log_trajectory.num_timesteps)
  sim = state.log_trajectory
  sim = sim.replace(x=sim.x.at[2].add(jnp.where(t > 5, 3.0, 0.0)).at[3].add(jnp.where(t > 5, 1.5, 0.0)))
  start, steps = 5, 20
  final = state.replace(sim_trajectory=sim, timestep=jnp.int32(start + steps))
  evaluated = metrics_lib.evaluated_agents(final, start, 3)
  still, moved = metrics_lib.still_moved(final, start, steps, evaluated)
  assert still.tolist() == [False, False, True, True]
  assert moved.tolist() == [False, False, True, False]
  score = jax.jit(metrics_lib.score_rollout, static_argnums=(1, 2, 3, 4))
  batch = lambda s: jax.tree_util.tree_map(lambda a: np.asarray(a)[None, None], s)
  out = metrics_lib.aggregate(batch(score(final, start, steps, 3, 256)))
  assert out["num_still_agents"] == 2 and out["still_moved_rate"] == 0.5
  replay = state.replace(timestep=jnp.int32(start + steps))
  out = metrics_lib.aggregate(batch(score(replay, start, steps, 3, 256)))
  assert out["num_still_agents"] == 2 and out["still_moved_rate"] == 0.0


def test_scores_of_scenes_with_different_object_counts_concatenate():
  """A file mixing scenes loaded at different object capacities (128 and 256 on
  real WOMD) aggregates: the per-object fields are zero-padded, and the pooled
  rates and means equal those counted scene by scene."""
  from pcdiff_jax import metrics as metrics_lib
  score = jax.jit(metrics_lib.score_rollout, static_argnums=(1, 2, 3, 4))
  batch = lambda s: jax.tree_util.tree_map(lambda a: np.asarray(a)[None, None], s)
  small = make_scene(speeds=(10.0, 8.0, 0.0, 0.0), xs=(0.0, 0.0, 10.0, -30.0))
  sim = small.log_trajectory
  small = small.replace(sim_trajectory=sim.replace(x=sim.x.at[2].add(3.0 * (jnp.arange(sim.num_timesteps) > 5))))
  big = make_scene(num_objects=6, speeds=(10.0, 8.0, 0.0, 0.0, 5.0, 0.0), ys=(-2.0, 2.0, -6.5, -2.0, 2.0, -2.0),
                   xs=(0.0, 0.0, 10.0, -30.0, 40.0, 60.0))
  parts = [batch(score(s.replace(timestep=jnp.int32(25)), 5, 20, 4, 256)) for s in (small, big)]
  assert parts[0].ade.shape[-1] == 4 and parts[1].ade.shape[-1] == 6
  out = metrics_lib.aggregate(metrics_lib.concatenate_scores(parts))
  alone = [metrics_lib.aggregate(p) for p in parts]
  assert out["num_still_agents"] == sum(a["num_still_agents"] for a in alone) == 4
  assert out["still_moved_rate"] == 0.25
  assert out["num_ade_agents"] == sum(a["num_ade_agents"] for a in alone)
  assert out["controlled_agents"] == sum(a["controlled_agents"] for a in alone)
  n = [a["num_ade_agents"] for a in alone]
  assert np.isclose(out["min_ade"], (alone[0]["min_ade"] * n[0] + alone[1]["min_ade"] * n[1]) / sum(n))


def test_min_ade_is_also_reported_per_kind():
  """Object 2, a pedestrian, is simulated 3 m off its log after the start: minADE per kind
  splits it from the vehicles (object 3 1.5 m off, object 1 on its log); no cyclist."""
  from pcdiff_jax import metrics as metrics_lib
  from pcdiff_jax.sim.datatypes import ObjectType
  state = make_scene(speeds=(10.0, 8.0, 0.0, 0.0), xs=(0.0, 0.0, 10.0, -30.0))
  md = state.object_metadata
  state = state.replace(object_metadata=md.replace(object_types=md.object_types.at[2].set(ObjectType.PEDESTRIAN)))
  t = jnp.arange(state.log_trajectory.num_timesteps)
  sim = state.log_trajectory
  sim = sim.replace(x=sim.x.at[2].add(jnp.where(t > 5, 3.0, 0.0)).at[3].add(jnp.where(t > 5, 1.5, 0.0)))
  final = state.replace(sim_trajectory=sim, timestep=jnp.int32(25))
  scores = metrics_lib.score_rollout(final, 5, 20, 4, 256)
  out = metrics_lib.aggregate(jax.tree_util.tree_map(lambda a: np.asarray(a)[None, None], scores))
  assert out["num_ade_pedestrian"] == 1 and np.isclose(out["min_ade_pedestrian"], 3.0)
  assert out["num_ade_vehicle"] == out["num_ade_agents"] - 1 == 2   # the SDC replays its log
  assert np.isclose(out["min_ade_vehicle"], 1.5 / 2)
  assert out["num_ade_cyclist"] == 0 and np.isnan(out["min_ade_cyclist"])
