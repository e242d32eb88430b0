"""WOMD Scenario protos: the real record round trip, the converter's rules, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from pcdiff_jax.data import scenario_proto, tfrecord, womd
from pcdiff_jax.data import waymo_protos as pb


def _fields(state):
  out = {}
  for group in ("log_trajectory", "object_metadata", "log_traffic_light", "roadgraph_points"):
    part = getattr(state, group)
    out.update({f"{group}.{k}": np.asarray(getattr(part, k)) for k in part.__dataclass_fields__})
  return out


def test_real_record_round_trips_through_a_scenario_proto(womd_path, tmp_path):
  state, meta = womd.load(womd_path, to_jax=False)
  path = str(tmp_path / "scenario.tfrecord")
  womd.write(path, [(state, meta.scenario_id)], record_format="scenario")
  assert womd.detect_format(open(path, "rb").read()[12:-4]) == "scenario"   # one record: 12-byte head, 4-byte crc
  back, back_meta = womd.load(path, to_jax=False)   # the flavour is read from the content
  assert back_meta.scenario_id == meta.scenario_id
  forced, _ = womd.load(path, to_jax=False, record_format="scenario")
  a, b, c = _fields(state), _fields(back), _fields(forced)
  directions = {f"roadgraph_points.dir_{k}" for k in "xyz"}
  for key in a:
    assert np.array_equal(b[key], c[key]), key
    if key not in directions:   # ids, types, every trajectory field, validity, lights, roadgraph points
      assert np.array_equal(a[key], b[key]), key
  # Directions are recomputed from the points (float32 in the record, so within 2e-4), except the last
  # point of the record: its polyline was cut by the record's 20000-point cap and its direction points
  # to a sample that is not there (ours: 0, the end of a polyline).
  d = np.stack([a[k] for k in sorted(directions)], -1)
  e = np.stack([b[k] for k in sorted(directions)], -1)
  err = np.abs(d - e).max(-1)
  last = int(np.nonzero(a["roadgraph_points.valid"])[0][-1])
  assert err[:last].max() < 2e-4 and np.all(e[last] == 0)
  # Roadgraph points per type, and one map feature per polyline.
  scenario = pb.Scenario.FromString(open(path, "rb").read()[12:-4])
  valid = a["roadgraph_points.valid"]
  assert len(scenario.map_features) == len(np.unique(a["roadgraph_points.ids"][valid]))
  assert len(scenario.tracks) == 128 and scenario.sdc_track_index == 8 and scenario.tracks[8].id == 336
  assert [t.track_index for t in scenario.tracks_to_predict] == list(range(8))


def _state(x, y, valid):
  return pb.ObjectState(center_x=x, center_y=y, center_z=0.5, length=4.0, width=2.0, height=1.5, heading=0.1,
                        velocity_x=1.0, velocity_y=0.0, valid=valid)


def _scenario(num_steps=11, num_tracks=3):
  """A hand-built test-split Scenario: num_steps states per track."""
  s = pb.Scenario(scenario_id="abc", current_time_index=10, sdc_track_index=0)
  s.timestamps_seconds.extend([0.1 * t for t in range(num_steps)])
  for i in range(num_tracks):
    track = s.tracks.add(id=100 + i, object_type=1 + (i % 3))
    for t in range(num_steps):
      track.states.append(_state(10.0 * i + t, 1.0, valid=not (i == 2 and t == 10)))
  s.tracks_to_predict.add(track_index=1)
  s.tracks_to_predict.add(track_index=2)   # not valid at step 10: not modeled (the converter's rule)
  s.objects_of_interest.append(101)
  for t in range(num_steps):
    s.dynamic_map_states.add().lane_states.add(lane=7, state=4 if t < 5 else 6,
                                               stop_point=pb.MapPoint(x=1.0, y=2.0, z=0.0))
  lane = s.map_features.add(id=7)
  lane.lane.type = 2
  lane.lane.polyline.extend([pb.MapPoint(x=0.5 * k, y=0.0, z=0.0) for k in range(5)])
  s.map_features.add(id=8).stop_sign.position.CopyFrom(pb.MapPoint(x=3.0, y=4.0, z=0.0))
  s.map_features.add(id=9).crosswalk.polygon.extend(
      [pb.MapPoint(x=x, y=y, z=0.0) for x, y in ((0, 0), (2, 0), (2, 0.5), (0, 0.5))])
  return s


def _write(path, records):
  with open(path, "wb") as f:
    for r in records:
      tfrecord.write_record(f, r if isinstance(r, bytes) else r.SerializeToString())


def test_scenario_reader_follows_the_converter(tmp_path):
  path = tmp_path / "test.tfrecord"
  _write(path, [_scenario()])
  state, meta = womd.load(str(path), to_jax=False, max_num_rg_points=64)
  md, log = state.object_metadata, state.log_trajectory
  assert meta.scenario_id == "abc"
  assert list(md.ids[:3]) == [100, 101, 102] and list(md.object_types[:3]) == [1, 2, 3]
  assert list(md.is_sdc[:4]) == [True, False, False, False]
  assert list(md.is_modeled[:3]) == [False, True, False] and list(md.is_valid[:4]) == [True, True, True, False]
  assert list(md.objects_of_interest[:3]) == [False, True, False]
  assert log.valid.shape == (128, 91) and not log.valid[:, 11:].any()          # the test split: history only
  assert log.valid[:2, :11].all() and not log.valid[2, 10] and log.x[2, 10] == -1
  assert log.x[1, 3] == 13.0 and log.timestamp_micros[0, 10] == 1_000_000 and log.timestamp_micros[0, 11] == -1
  tl = state.log_traffic_light
  assert list(tl.state[0, :11]) == [4] * 5 + [6] * 6 and tl.lane_ids[0, 0] == 7 and not tl.valid[:, 11:].any()
  rg = state.roadgraph_points
  n = int(rg.valid.sum())
  assert list(rg.types[:n]) == [2] * 5 + [17] + [18] * 11
  assert np.allclose(rg.x[:5], [0, 0.5, 1, 1.5, 2]) and np.allclose(rg.dir_x[:4], 1) and rg.dir_x[4] == 0
  # Crosswalk: sides sampled every 0.5 m (4 samples on a 2 m side, 1 on a 0.5 m one), closed with its
  # first corner.
  assert np.allclose(rg.x[6:17], [0, 0.5, 1, 1.5, 2, 2, 1.5, 1, 0.5, 0, 0])
  assert np.allclose(rg.y[6:17], [0, 0, 0, 0, 0, 0.5, 0.5, 0.5, 0.5, 0.5, 0])


def test_resampling_is_the_converters():
  line = np.stack([np.arange(6) * 0.5, np.zeros(6), np.zeros(6)], -1)
  assert np.array_equal(scenario_proto.resample_polyline(line), line)       # 0.5 m: every source point
  assert np.allclose(scenario_proto.resample_polyline(line, 1.0)[:, 0], [0, 1, 2, 2.5])
  curve = np.stack([np.arange(5.0), np.arange(5.0) ** 2, np.zeros(5)], -1)
  mid = scenario_proto.resample_polyline(curve, 0.75)[1]   # 0.75 m = source index 1.5: Catmull-Rom on points 0-3
  p0, p1, p2, p3 = curve[0:4]
  a = 0.5
  spline = p1 + a * (0.5 * (-p0 + p2) + a * (0.5 * (2 * p0 - 5 * p1 + 4 * p2 - p3) + a * 0.5 * (-p0 + 3 * p1 - 3 * p2 + p3)))
  assert np.allclose(mid, spline)
  assert scenario_proto.resample_polyline(line[:1]).shape == (1, 3)


def test_more_tracks_than_slots_keeps_the_sim_agents(tmp_path):
  s = _scenario(num_steps=91, num_tracks=6)
  s.sdc_track_index = 3
  s.tracks[5].states[10].valid = False
  ex = scenario_proto.scenario_to_example(s, max_objects=4)
  # The 4 tracks valid at step 10 (0, 1, 3, 4) do not fit in 3 slots: an error, not a dropped sim agent.
  with pytest.raises(scenario_proto.ScenarioFormatError, match="valid at the current step"):
    scenario_proto.scenario_to_example(s, max_objects=3)
  assert list(ex["state/id"]) == [100, 101, 103, 104]    # SDC, the required one, the nearest valid; Scenario order
  assert list(ex["state/is_sdc"]) == [0, 0, 1, 0]


def test_bad_scenarios_name_the_file_record_and_field(tmp_path):
  good = _scenario()
  no_sdc = _scenario()
  no_sdc.ClearField("sdc_track_index")
  short = _scenario()
  del short.tracks[1].states[3]
  path = tmp_path / "bad.tfrecord"
  _write(path, [good, b"\x08\x96\x01 garbage", no_sdc, short])
  with pytest.raises(womd.WomdFormatError, match=r"bad.tfrecord, record 1: not a Scenario proto"):
    list(womd.iterate(str(path), to_jax=False, record_format="scenario"))
  skipped = []
  states = list(womd.iterate(str(path), to_jax=False, on_error="skip", skipped=skipped))
  assert len(states) == 1 and [e.index for e in skipped] == [1, 2, 3]
  assert skipped[1].field == "sdc_track_index" and skipped[2].field == "tracks[1].states"
  assert "has 10 states, expected 11" in str(skipped[2])
  junk = tmp_path / "junk.tfrecord"
  _write(junk, [b"\xff\xff junk"])
  with pytest.raises(womd.WomdFormatError, match="neither a WOMD motion tf.Example nor a WOMD Scenario"):
    list(womd.iterate(str(junk)))


def test_history_only_drops_the_logged_future(womd_path):
  state, _ = womd.load(womd_path, to_jax=False, history_only=True)
  log = state.log_trajectory
  assert not log.valid[:, 11:].any() and np.all(log.x[:, 11:] == -1) and log.valid[:, 10].sum() == 73
  assert not state.log_traffic_light.valid[:, 11:].any() and state.log_traffic_light.valid[:, 10].any()


REAL_VAL = __import__("pathlib").Path(__file__).resolve().parents[2] / "shared" / "data" / "womd_real" / "val.scenario.tfrecord"


def _reference_resample(points, spacing, source_spacing=0.5):
  """The converter's loop as first written (count from 0, spline at every sample)."""
  n = len(points)
  count = 0
  while int(count * spacing / source_spacing) < n - 1:
    count += 1
  dist = np.arange(count) * spacing
  left = (dist / source_spacing).astype(np.int64)
  alpha = ((dist - left * source_spacing) / source_spacing)[:, None]
  out = points[left] + alpha * (points[np.minimum(left + 1, n - 1)] - points[left])
  spline = (left >= 1) & (left <= n - 3)
  if spline.any():
    i, a = left[spline], alpha[spline]
    q0, q1, q2, q3 = points[i - 1], points[i], points[i + 1], points[i + 2]
    out[spline] = q1 + a * (0.5 * (-q0 + q2) + a * (0.5 * (2.0 * q0 - 5.0 * q1 + 4.0 * q2 - q3)
                                                   + a * 0.5 * (-q0 + 3.0 * q1 - 3.0 * q2 + q3)))
  if count == 0 or np.sum((points[-1] - out[-1]) ** 2) > 0.01 ** 2:
    out = np.concatenate([out, points[-1:]], 0)
  return out


@pytest.mark.parametrize("spacing", [0.5, 1.0, 0.3, 0.75, 2.0])
def test_fast_resampling_gives_the_loops_values(spacing):
  rng = np.random.default_rng(0)
  for n in (1, 2, 3, 4, 7, 40, 333):
    points = np.cumsum(rng.normal(size=(n, 3)) * 0.3, 0) + 1000.0
    got = scenario_proto.resample_polyline(points, spacing)
    assert np.array_equal(got, _reference_resample(points, spacing)), (n, spacing)


def test_directions_of_features_back_to_back():
  a = np.array([[0.0, 0, 0], [1, 0, 0], [1, 2, 0]])
  b = np.array([[5.0, 5, 0], [5, 6, 0]])
  both = scenario_proto.directions(np.concatenate([a, b]), ends=np.array([2, 4]))
  assert np.array_equal(both, np.concatenate([scenario_proto.directions(a), scenario_proto.directions(b)]))


@pytest.mark.skipif(not REAL_VAL.exists(), reason="../shared is absent (real WOMD val scenes)")
def test_real_val_scenes_read_to_the_same_bytes():
  """Digests of the reader's arrays for three real scenes, taken with the
  per-point reader this one replaced: the bulk conversion changes no bit."""
  import hashlib
  raws = list(tfrecord.read_records(str(REAL_VAL)))[:3]
  digests = []
  for raw in raws:
    ex = scenario_proto.scenario_to_example(raw)
    h = hashlib.sha256()
    for k in sorted(ex):
      h.update(k.encode())
      h.update(b"".join(ex[k]) if ex[k].dtype == object else ex[k].tobytes())
    digests.append(h.hexdigest()[:16])
  assert digests == ["f7ebb854dc8e836f", "dc719b3c690645c6", "9e4ceadf8babc353"]


def test_more_sim_agents_than_the_first_bucket_take_the_next(tmp_path):
  s = _scenario(num_steps=91, num_tracks=6)
  s.tracks[5].states[10].valid = False
  ex = scenario_proto.scenario_to_example(s, max_objects=(3, 5, 8))   # 4 sim agents: 3 is too small, 5 holds them
  assert list(ex["state/id"]) == [100, 101, 102, 103, 104]             # and one more track (most valid states)
  many = _scenario(num_steps=91, num_tracks=140)                      # 139 sim agents
  path = tmp_path / "many.tfrecord"
  _write(path, [many, _scenario(num_steps=91)])
  with pytest.raises(womd.WomdFormatError, match="more than max_num_objects=128"):
    list(womd.iterate(str(path), to_jax=False))
  big, small = womd.iterate(str(path), to_jax=False, max_num_objects=None)
  assert big.object_metadata.ids.shape == (256,) and small.object_metadata.ids.shape == (128,)
  assert big.log_trajectory.valid[:, 10].sum() == 139
  (batch,) = womd.iterate(str(path), to_jax=False, max_num_objects=None, batch_size=2)
  assert batch.log_trajectory.x.shape == (2, 256, 91)                # a batch takes its largest scene's size
  assert np.array_equal(batch.log_trajectory.x[1, :128], small.log_trajectory.x)
  assert not batch.object_metadata.is_valid[1, 128:].any() and np.all(batch.object_metadata.ids[1, 128:] == -1)


def test_headings_stored_in_degrees_read_in_radians(tmp_path):
  """Some public scenes converted back from JSON store box headings in degrees; the reader
  gives radians (the same values as the scene stored in radians, to float32), and leaves
  a scene in radians as it is."""
  radians = _scenario(num_steps=91)
  turns = np.linspace(-3.1, 3.1, 91)
  for i, track in enumerate(radians.tracks):
    for t, s in enumerate(track.states):
      s.heading = float(turns[(t + 30 * i) % 91])
  degrees = pb.Scenario.FromString(radians.SerializeToString())
  for track in degrees.tracks:
    for s in track.states:
      s.heading = float(np.degrees(s.heading))
  as_radians = scenario_proto.scenario_to_example(radians)
  as_degrees = scenario_proto.scenario_to_example(degrees)
  for part in ("past", "current", "future"):
    key = f"state/{part}/bbox_yaw"
    assert np.allclose(as_degrees[key], as_radians[key], atol=1e-6), key
  now = [tr.states[10].heading if tr.states[10].valid else -1.0 for tr in radians.tracks]
  assert np.array_equal(as_radians["state/current/bbox_yaw"].reshape(-1), np.float32(now))
  # The scorer's worker applies the same rule to the message (its own copy: it runs in the
  # evaluator's venv): the headings the reader gives, and a scene in radians left as it is.
  from pcdiff_jax import wosac_worker
  message = pb.Scenario.FromString(degrees.SerializeToString())
  assert wosac_worker.headings_in_radians(message) and not wosac_worker.headings_in_radians(radians)
  rewritten = scenario_proto.scenario_to_example(message)
  for part in ("past", "current", "future"):
    key = f"state/{part}/bbox_yaw"
    assert np.allclose(rewritten[key], as_degrees[key], atol=1e-6), key
  assert not wosac_worker.headings_in_radians(message)


@pytest.mark.skipif(not REAL_VAL.exists(), reason="../shared is absent (real WOMD val scenes)")
def test_real_val_scenes_in_degrees_are_the_thirteen_and_read_along_the_motion():
  """13 of the 36 real val scenes (records 3-15) store headings in degrees; read in radians,
  their movers' boxes point along their velocity, as in the other 23."""
  flagged = []
  for i, raw in enumerate(tfrecord.read_records(str(REAL_VAL))):
    scenario = scenario_proto.parse(raw)
    if scenario_proto.headings_in_degrees(np.array([s.heading for tr in scenario.tracks for s in tr.states
                                                    if s.valid])):
      flagged.append(i)
  assert flagged == list(range(3, 16))
  for index in (3, 9):
    state, _ = womd.load(str(REAL_VAL), index=index, to_jax=False, max_num_objects=None)
    log = state.log_trajectory
    moving = log.valid & (np.hypot(log.vel_x, log.vel_y) > 3)
    off = np.abs((log.yaw - np.arctan2(log.vel_y, log.vel_x) + np.pi) % (2 * np.pi) - np.pi)[moving]
    assert moving.sum() > 100 and np.median(off) < np.radians(3) and np.mean(off > np.pi / 2) < 0.01
