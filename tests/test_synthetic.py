"""The embedded synthetic dataset: schema parity with real WOMD, maps, behaviour, CLI."""
from __future__ import annotations

import json
import os

import numpy as np
import pytest

from pcdiff_jax.data import womd
from pcdiff_jax.data.synthetic import FAMILIES, SyntheticConfig, count_overlaps, generate_scene
from pcdiff_jax.data.synthetic.scene import DEFAULT_FAMILY_WEIGHTS
from pcdiff_jax.sim import geometry
from pcdiff_jax.sim.datatypes import ObjectType, is_lane_center, is_road_edge


def _only(family: str) -> SyntheticConfig:
  return SyntheticConfig(family_weights=((family, 1.0),))


@pytest.fixture(scope="module")
def scenes():
  """Two scenes of every family (numpy states)."""
  return {f: [generate_scene(7, i, _only(f)) for i in range(2)] for f in FAMILIES}


def _raw(tf, path):
  raw = next(iter(tf.data.TFRecordDataset(path))).numpy()
  ex = tf.train.Example.FromString(raw)
  return {k: (f.WhichOneof("kind"), len(getattr(f, f.WhichOneof("kind")).value))
          for k, f in ex.features.feature.items()}


def test_schema_parity_with_real_record(womd_path, scenes, tmp_path, tensorflow):
  """Same feature keys, kinds (dtypes) and lengths as the real WOMD record."""
  real = _raw(tensorflow, womd_path)
  for family, (scene, _) in scenes.items():
    path = str(tmp_path / f"{family}.tfrecord")
    womd.write(path, [(scene.state, scene.scenario_id)])
    ours = _raw(tensorflow, path)
    assert set(ours) == set(real), (family, set(ours) ^ set(real))
    diff = {k: (ours[k], real[k]) for k in real if ours[k] != real[k]}
    assert not diff, (family, diff)


def test_scenes_load_and_are_well_formed(scenes, tmp_path):
  path = str(tmp_path / "all.tfrecord")
  items = [(s.state, s.scenario_id) for group in scenes.values() for s in group]
  womd.write(path, items)
  loaded = list(womd.iterate(path, with_meta=True, to_jax=False))
  assert [m.scenario_id for _, m in loaded] == [sid for _, sid in items]
  for state, meta in loaded:
    state.validate()
    traj, md = state.log_trajectory, state.object_metadata
    valid = np.asarray(traj.valid)
    objects = np.asarray(md.is_valid)
    assert 5 <= objects.sum() <= 128, meta.scenario_id
    assert np.asarray(md.is_sdc).sum() == 1
    sdc = int(np.argmax(md.is_sdc))
    assert md.object_types[sdc] == ObjectType.VEHICLE and valid[sdc].all()  # SDC seen throughout
    assert valid.shape == (128, 91)
    assert len(set(np.asarray(md.ids)[objects])) == objects.sum()           # unique ids
    assert 1 <= np.asarray(md.is_modeled).sum() <= 8
    assert np.all(np.asarray(traj.timestamp_micros)[valid] % 100000 == 0)
    types = set(np.asarray(md.object_types)[objects].tolist())
    assert types <= {1, 2, 3}


def test_roadgraph_sampling_and_directions(scenes):
  types_seen = set()
  for group in scenes.values():
    for scene in group:
      rg = scene.state.roadgraph_points
      valid = np.asarray(rg.valid)
      xy = np.stack([rg.x, rg.y], -1)[valid]
      d = np.stack([rg.dir_x, rg.dir_y], -1)[valid]
      ids = np.asarray(rg.ids)[valid]
      types_seen |= set(np.asarray(rg.types)[valid].tolist())
      same = ids[1:] == ids[:-1]
      step = np.linalg.norm(np.diff(xy, axis=0), axis=-1)[same]
      assert 0.3 < np.median(step) < 0.55                       # WOMD-like 0.5 m samples
      norms = np.linalg.norm(d, axis=-1)
      last = np.append(~same, True)                              # last sample of each polyline
      np.testing.assert_allclose(norms[~last], 1.0, atol=1e-4)
      assert np.all(norms[last] == 0)
      # dir is the unit vector to the next sample.
      nxt = np.diff(xy, axis=0)[same] / np.maximum(step, 1e-6)[:, None]
      np.testing.assert_allclose(d[:-1][same], nxt, atol=2e-3)
  assert {1 if 1 in types_seen else 2, 2, 6, 7, 12, 15, 17, 18} <= types_seen, types_seen


def test_lanes_lie_inside_the_road_edges(scenes):
  """Lane centres keep >= 1.1 m (a car's half width) inside the road edges, so the
  off-road metric is meaningful on these maps."""
  for family, group in scenes.items():
    for scene in group:
      rg = scene.state.roadgraph_points
      valid = np.asarray(rg.valid)
      types = np.asarray(rg.types)
      xy = np.stack([rg.x, rg.y], -1)
      edge = valid & np.asarray(is_road_edge(types))
      lane = valid & np.isin(types, (1, 2))
      sd = np.asarray(geometry.signed_distance_to_road_edges(
          xy[lane], xy[edge], np.stack([rg.dir_x, rg.dir_y], -1)[edge], np.asarray(rg.ids)[edge],
          np.ones(edge.sum(), bool)))
      assert sd.max() < -1.1, (family, scene.scenario_id, sd.max())


def test_lights_point_at_lanes(scenes):
  for scene in scenes["intersection"]:
    tl, rg = scene.state.log_traffic_light, scene.state.roadgraph_points
    valid = np.asarray(tl.valid)
    assert valid.any() and valid.shape == (16, 91)
    states = np.asarray(tl.state)[valid]
    assert set(states.tolist()) <= set(range(9)) and len(set(states.tolist())) >= 1
    ids, types = np.asarray(rg.ids), np.asarray(rg.types)
    for k in np.nonzero(valid.any(1))[0]:
      lane = np.asarray(tl.lane_ids)[k, 0]
      pts = np.nonzero(ids == lane)[0]
      assert pts.size and is_lane_center(types[pts[0]])
      np.testing.assert_allclose([rg.x[pts[0]], rg.y[pts[0]]], [tl.x[k, 0], tl.y[k, 0]], atol=1e-3)
  for scene in scenes["t_junction"]:
    assert not np.asarray(scene.state.log_traffic_light.valid).any()


def test_motion_is_smooth_and_collision_free(scenes):
  from pcdiff_jax.data import realism
  for family, group in scenes.items():
    for scene in group:
      traj = scene.state.log_trajectory
      f = realism.motion_features(traj)
      types = np.asarray(scene.state.object_metadata.object_types)[:, None]
      for q, bound in (("lon_accel", 8.5), ("lat_accel", 6.0), ("yaw_rate", 1.2)):
        x = np.asarray(f[q])[np.asarray(f[q + "_valid"]) & (types == 1)]
        assert np.abs(x).max() < bound, (family, q, np.abs(x).max())
      # No teleports: displacement per step agrees with the logged speed.
      xy, v = np.stack([traj.x, traj.y], -1), np.asarray(traj.valid)
      both = v[:, 1:] & v[:, :-1]
      step = np.linalg.norm(np.diff(xy, axis=1), axis=-1)[both]
      speed = np.hypot(traj.vel_x, traj.vel_y)[:, 1:][both]
      assert np.abs(step - speed * 0.1).max() < 0.1, family
      assert count_overlaps(xy, np.asarray(traj.yaw), np.asarray(traj.length)[:, 0],
                            np.asarray(traj.width)[:, 0], v) == 0
      assert scene.info["log_overlaps"] == 0


def test_project_metrics_on_logs(scenes):
  """The project's own collision / off-road metrics on log replay."""
  from experiments.realism_report import log_event_rates
  states = [group[0].state for group in scenes.values()]
  rates = log_event_rates(states, batch_size=len(states))
  assert rates["num_evaluated"] > 10, rates   # the logs were rolled out and scored
  assert rates["collision_rate"] == 0 and rates["offroad_rate"] == 0, rates


def test_deterministic_and_seed_dependent():
  a, b = generate_scene(3, 5), generate_scene(3, 5)
  c = generate_scene(4, 5)
  same = lambda x, y: all(np.array_equal(p, q) for p, q in zip(
      __import__("jax").tree_util.tree_leaves(x.state), __import__("jax").tree_util.tree_leaves(y.state)))
  assert same(a, b) and a.scenario_id == b.scenario_id
  assert not same(a, c)


@pytest.mark.parametrize("family", ["straight", "intersection", "merge"])
def test_surface_limit_stretch_widens_only_the_surface_limits(family):
  """The stretch maps the same draw to a higher limit, so the rest of the map is unchanged;
  stretch 1 is the benchmark's generator."""
  from pcdiff_jax.data.synthetic import maps
  from pcdiff_jax.sim.datatypes import RoadgraphType
  low = {"straight": 10.0, "intersection": 11.0, "merge": 12.0}[family]
  stretched = 0
  for seed in range(8):
    base = maps.build(family, np.random.default_rng(seed), 91)
    wide = maps.build(family, np.random.default_rng(seed), 91, surface_limit_stretch=2.0)
    assert [l.xy.tolist() for l in base.lanes] == [l.xy.tolist() for l in wide.lanes]
    assert [l.speed_limit for l in base.lanes if l.user != "vehicle"] == \
        [l.speed_limit for l in wide.lanes if l.user != "vehicle"]
    surface = [i for i, l in enumerate(base.lanes)
               if l.user == "vehicle" and l.kind == int(RoadgraphType.LANE_SURFACE_STREET)]
    if surface:   # the drawn limit is the map's highest surface limit
      drawn = max(base.lanes[i].speed_limit for i in surface)
      assert max(wide.lanes[i].speed_limit for i in surface) == pytest.approx(low + 2.0 * (drawn - low))
      stretched += 1
    else:         # a freeway keeps its limits
      assert [l.speed_limit for l in base.lanes] == [l.speed_limit for l in wide.lanes]
  assert stretched > 0


def test_a_long_warm_up_queues_traffic_at_the_stop_lines():
  """The generator places traffic free-flowing; a 30 s warm-up lets queues form at red lights
  and stop signs before the log starts, so more of the scene's vehicles stand still or pull
  away from standing (docs/DATA.md, "Queued traffic")."""
  from pcdiff_jax.data import realism
  weights = (("intersection", 1.0), ("t_junction", 1.0))

  def counts(warmup_steps):
    cfg = SyntheticConfig(warmup_steps=warmup_steps, family_weights=weights)
    total = {k: 0 for k in realism.MOTION_CLASSES}
    for index in range(6):
      state = generate_scene(0, index, cfg).state
      for k, v in realism.motion_classes(state.log_trajectory, state.object_metadata.object_types).items():
        total[k] += int(v)
    return total

  short, long = counts(12), counts(300)
  assert long["still"] + long["starters"] > 2 * (short["still"] + short["starters"]), (short, long)
  assert long["movers"] < short["movers"], (short, long)


def test_family_weights_are_complete():
  assert {f for f, _ in DEFAULT_FAMILY_WEIGHTS} == set(FAMILIES)


@pytest.mark.slow
def test_make_data_cli_shards_resume_and_bytes(tmp_path):
  from experiments import make_data
  out1, out2 = str(tmp_path / "a"), str(tmp_path / "b")
  args = ["--num-train", "3", "--num-val", "2", "--seed", "5", "--shard-size", "2"]
  assert make_data.main(["--out", out1, "--workers", "1"] + args) == 0
  names = sorted(n for n in os.listdir(out1) if n.endswith(".tfrecord"))
  assert names == ["train-00000-of-00002.tfrecord", "train-00001-of-00002.tfrecord",
                   "val-00000-of-00001.tfrecord"]
  stats = json.load(open(os.path.join(out1, "stats.json")))
  assert stats["train"]["num_scenes"] == 3 and stats["val"]["num_scenes"] == 2
  assert stats["train"]["scenes_with_log_overlap"] == 0
  # Two processes write the same bytes.
  assert make_data.main(["--out", out2, "--workers", "2"] + args) == 0
  for n in names:
    assert open(os.path.join(out1, n), "rb").read() == open(os.path.join(out2, n), "rb").read(), n
  # Re-running keeps finished shards untouched.
  mtimes = {n: os.path.getmtime(os.path.join(out1, n)) for n in names}
  assert make_data.main(["--out", out1, "--workers", "1"] + args) == 0
  assert mtimes == {n: os.path.getmtime(os.path.join(out1, n)) for n in names}
  assert json.load(open(os.path.join(out1, "stats.json")))["shards_reused"] == 3
  # Another seed draws other scenes.
  out3 = str(tmp_path / "c")
  assert make_data.main(["--out", out3, "--workers", "1", "--num-train", "1", "--num-val", "0", "--seed", "6"]) == 0
  assert (open(os.path.join(out3, "train-00000-of-00001.tfrecord"), "rb").read()[:4000]
          != open(os.path.join(out1, names[0]), "rb").read()[:4000])


@pytest.mark.parametrize("argv", [[], ["--out", "x", "--num-train", "-1"], ["--out", "x", "--shard-size", "0"],
                                  ["--out", "x", "--families", "roundabout"],
                                  ["--out", "x", "--surface-limit-stretch", "0.5"],
                                  ["--out", "x", "--warmup-seconds", "-1"]])
def test_make_data_bad_arguments(argv):
  from experiments import make_data
  with pytest.raises(SystemExit) as e:
    make_data.parse_args(argv)
  assert e.value.code == 2


def test_stats_report(tmp_path, womd_path):
  from experiments import make_data
  out = str(tmp_path / "d")
  assert make_data.main(["--out", out, "--num-train", "0", "--num-val", "3", "--workers", "1"]) == 0
  assert make_data.main(["--stats", out, "--real", womd_path, "--num-scenes", "3", "--metric-scenes", "3"]) == 0
  report = json.load(open(os.path.join(out, "realism.json")))
  assert set(report["summaries"]) == {"synthetic", "real WOMD sample"}
  assert report["log_rates"]["synthetic"]["collision_rate"] == 0
  assert report["log_rates"]["synthetic"]["num_evaluated"] > 0
  assert report["log_rates"]["real WOMD sample"]["num_evaluated"] > 0
  for name in ("realism.md", "realism_hist.png", "examples.png"):
    assert os.path.getsize(os.path.join(out, name)) > 1000, name
  assert make_data.main(["--stats", str(tmp_path / "missing")]) == 2
