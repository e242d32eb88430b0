"""The WOMD loader and writer against the real record (values read independently)."""
from __future__ import annotations

import logging

import jax
import numpy as np
import pytest

from pcdiff_jax.data import tfrecord, womd

NUM_OBJ, T = 128, 91


def _raw_time(raw, name, dtype=np.float64):
  """(128, 91) from state/{past,current,future}/name of the raw example."""
  parts = [raw[f"state/{t}/{name}"].reshape(NUM_OBJ, -1) for t in ("past", "current", "future")]
  return np.concatenate(parts, axis=1).astype(dtype)


def test_real_record_values(real_state, raw_example):
  s, raw = real_state, raw_example
  s.validate()
  assert s.shape == () and s.sim_trajectory.shape == (NUM_OBJ, T)
  assert int(s.timestep) == 0
  # 73 objects are valid at the current step (index 10), the SDC is slot 8.
  assert int(np.asarray(s.log_trajectory.valid)[:, 10].sum()) == int(raw["state/current/valid"].sum()) == 73
  assert int(s.object_metadata.sdc_index) == int(np.argmax(raw["state/is_sdc"])) == 8
  valid = _raw_time(raw, "valid").astype(bool)
  np.testing.assert_array_equal(np.asarray(s.log_trajectory.valid), valid)
  # Exact positions, velocities (float32 as stored).
  for ours, theirs in [("x", "x"), ("y", "y"), ("z", "z"), ("vel_x", "velocity_x"),
                       ("vel_y", "velocity_y")]:
    np.testing.assert_array_equal(np.asarray(getattr(s.log_trajectory, ours)),
                                  _raw_time(raw, theirs, np.float32), err_msg=ours)
  # Yaw: wrapped into [-pi, pi) as Waymax's loader does (the record stores
  # 1406 valid entries unwrapped along time); else the stored value.
  yaw, stored = np.asarray(s.log_trajectory.yaw), _raw_time(raw, "bbox_yaw", np.float32)
  assert yaw.min() >= -np.pi and yaw.max() < np.pi
  turns = np.round((stored.astype(np.float64) - yaw) / (2 * np.pi))
  np.testing.assert_allclose(yaw + 2 * np.pi * turns, stored, atol=1e-6)
  assert int((turns[valid] != 0).sum()) == 1406
  # Waymax's loader: sim is the log at t = 0 only, zeros and invalid after.
  for field in ("x", "yaw", "valid", "timestamp_micros"):
    sim, log = np.asarray(getattr(s.sim_trajectory, field)), np.asarray(getattr(s.log_trajectory, field))
    np.testing.assert_array_equal(sim[:, 0], log[:, 0], err_msg=field)
    assert not sim[:, 1:].any(), field
  assert float(s.log_trajectory.x[8, 10]) == pytest.approx(float(raw["state/current/x"][8]))
  # Sizes: mean over valid steps (Waymax), constant over time.
  length = _raw_time(raw, "length")
  mean_len = (length * valid).sum(1) / np.maximum(valid.sum(1), 1)
  np.testing.assert_allclose(np.asarray(s.log_trajectory.length)[:, 0], mean_len, rtol=1e-6)
  np.testing.assert_array_equal(np.asarray(s.log_trajectory.timestamp_micros),
                                _raw_time(raw, "timestamp_micros", np.int32))
  # Metadata.
  np.testing.assert_array_equal(np.asarray(s.object_metadata.ids), raw["state/id"].astype(np.int32))
  np.testing.assert_array_equal(np.asarray(s.object_metadata.object_types), raw["state/type"].astype(np.int32))
  np.testing.assert_array_equal(np.asarray(s.object_metadata.is_modeled), raw["state/tracks_to_predict"] == 1)
  np.testing.assert_array_equal(np.asarray(s.object_metadata.objects_of_interest),
                                raw["state/objects_of_interest"] == 1)


def test_real_roadgraph_and_lights(real_state, raw_example):
  s, raw = real_state, raw_example
  rg = s.roadgraph_points
  assert rg.num_points == 30000  # padded to the default maximum
  raw_valid = raw["roadgraph_samples/valid"].astype(bool)
  assert int(np.asarray(rg.valid).sum()) == int(raw_valid.sum()) == 20000
  n = raw_valid.size
  xyz = raw["roadgraph_samples/xyz"].reshape(-1, 3).astype(np.float32)
  np.testing.assert_array_equal(np.asarray(rg.x)[:n], xyz[:, 0])
  np.testing.assert_array_equal(np.asarray(rg.dir_y)[:n], raw["roadgraph_samples/dir"].reshape(-1, 3)[:, 1].astype(np.float32))
  np.testing.assert_array_equal(np.asarray(rg.types)[:n], raw["roadgraph_samples/type"])
  types, counts = np.unique(np.asarray(rg.types)[np.asarray(rg.valid)], return_counts=True)
  assert dict(zip(types.tolist(), counts.tolist())) == {2: 6323, 3: 615, 6: 2462, 7: 2412, 11: 1260,
                                                        12: 167, 15: 4844, 16: 1917}
  assert not np.asarray(rg.valid)[n:].any()
  # Traffic lights: (L, T), slots as stored (time-major on disk).
  tl = s.log_traffic_light
  assert tl.shape == (16, T)
  for t, key, steps in [(0, "past", 10), (10, "current", 1), (11, "future", 80)]:
    raw_state = raw[f"traffic_light_state/{key}/state"].reshape(steps, 16).T
    raw_valid_tl = raw[f"traffic_light_state/{key}/valid"].reshape(steps, 16).T.astype(bool)
    raw_ids = raw[f"traffic_light_state/{key}/id"].reshape(steps, 16).T
    np.testing.assert_array_equal(np.asarray(tl.state)[:, t:t + steps], raw_state)
    np.testing.assert_array_equal(np.asarray(tl.valid)[:, t:t + steps], raw_valid_tl)
    np.testing.assert_array_equal(np.asarray(tl.lane_ids)[:, t:t + steps], raw_ids)
  assert np.asarray(tl.state)[:11, 10].tolist() == [0, 6, 6, 3, 3, 3, 6, 6, 0, 0, 0]


def test_round_trip_is_identical(real_state, womd_path, tmp_path, raw_example):
  out = str(tmp_path / "rt.tfrecord")
  assert womd.write(out, [(real_state, "a3bb37c25ce56418")]) == 1
  back, meta = womd.load(out)
  assert meta.scenario_id == "a3bb37c25ce56418"
  for path, a, b in zip(jax.tree_util.tree_leaves_with_path(real_state),
                        jax.tree_util.tree_leaves(real_state), jax.tree_util.tree_leaves(back)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=str(path[0]))
  # Schema parity: written at the record's own roadgraph size, every key and
  # length of the real record is reproduced.
  state20k, _ = womd.load(womd_path, max_num_rg_points=20000)
  ex = womd.state_to_example(state20k, "a3bb37c25ce56418")
  ours = {k: len(getattr(f, f.WhichOneof("kind")).value) for k, f in ex.features.feature.items()}
  theirs = {k: len(v) for k, v in raw_example.items()}
  assert ours == theirs
  kinds = {k: f.WhichOneof("kind") for k, f in ex.features.feature.items()}
  assert kinds["state/id"] == "float_list" and kinds["state/is_sdc"] == "int64_list"


def test_derived_speed_matches_record(womd_path, raw_example):
  state, _ = womd.load(womd_path, max_num_rg_points=20000)
  ex = womd.state_to_example(state, "x")
  ours = np.array(ex.features.feature["state/current/speed"].float_list.value)
  valid = raw_example["state/current/valid"] == 1
  np.testing.assert_allclose(ours[valid], raw_example["state/current/speed"][valid], rtol=1e-4, atol=1e-4)


def _write_variants(tmp_path, real_state, n=3):
  paths = []
  for k in range(2):
    p = str(tmp_path / f"part-{k}.tfrecord")
    womd.write(p, [(real_state, f"scene-{k}-{i}") for i in range(n - k)])
    paths.append(p)
  return paths


def test_glob_list_and_batches(real_state, tmp_path):
  paths = _write_variants(tmp_path, real_state)
  singles = list(womd.iterate(str(tmp_path / "part-*.tfrecord"), with_meta=True, max_num_rg_points=20000))
  assert [m.scenario_id for _, m in singles] == ["scene-0-0", "scene-0-1", "scene-0-2", "scene-1-0", "scene-1-1"]
  batches = list(womd.iterate(paths, batch_size=2, with_meta=True, max_num_rg_points=20000))
  assert [b.shape for b, _ in batches] == [(2,), (2,), (1,)]
  assert batches[0][0].sim_trajectory.shape == (2, 128, 91)
  assert batches[1][1].scenario_id == ("scene-0-2", "scene-1-0")
  assert batches[2][1].record_index == (1,)
  batches[0][0].validate()
  assert len(list(womd.iterate(paths, batch_size=2, drop_remainder=True, max_num_rg_points=20000))) == 2


def test_roadgraph_cap_keeps_points_nearest_sdc(real_state, womd_path):
  small, _ = womd.load(womd_path, max_num_rg_points=5000)
  rg = small.roadgraph_points
  assert rg.num_points == 5000 and bool(np.asarray(rg.valid).all())
  sdc = int(real_state.object_metadata.sdc_index)
  c = np.array([float(real_state.log_trajectory.x[sdc, 10]), float(real_state.log_trajectory.y[sdc, 10])])
  kept = np.linalg.norm(np.stack([rg.x, rg.y], -1) - c, axis=-1).max()
  full = real_state.roadgraph_points
  all_d = np.sort(np.linalg.norm(np.stack([full.x, full.y], -1)[np.asarray(full.valid)] - c, axis=-1))
  assert kept <= all_d[4999] + 1e-3


# ---------------------------------------------------------------- bad input

def _example_with(real_state, edit):
  ex = womd.state_to_example(real_state, "bad")
  edit(ex.features.feature)
  return ex.SerializeToString()


def _write_raw(path, records):
  with open(path, "wb") as f:   # TensorFlow's framing (tests/test_tfrecord.py), no TensorFlow needed
    for r in records:
      tfrecord.write_record(f, r)


@pytest.mark.parametrize("edit, field, message", [
    (lambda f: f.pop("state/current/x"), "state/current/x", "missing"),
    (lambda f: f["state/future/y"].float_list.value.pop(), "state/future/y", "expected 10240"),
    (lambda f: f["state/current/x"].float_list.value.__setitem__(8, float("nan")), "state/*/x", "non-finite"),
    (lambda f: f["state/current/valid"].int64_list.value.__setitem__(slice(None), [0] * 128),
     "state/current/valid", "no object is valid"),
    (lambda f: f["state/is_sdc"].int64_list.value.__setitem__(slice(None), [0] * 128), "state/is_sdc", "exactly one SDC"),
    (lambda f: f.pop("roadgraph_samples/xyz"), "roadgraph_samples/xyz", "missing"),
    (lambda f: f.pop("scenario/id"), "scenario/id", "missing"),
])
def test_bad_record_names_file_record_and_field(real_state, tmp_path, edit, field, message):
  path = tmp_path / "bad.tfrecord"
  _write_raw(path, [_example_with(real_state, edit)])
  with pytest.raises(womd.WomdFormatError) as err:
    list(womd.iterate(str(path)))
  text = str(err.value)
  assert str(path) in text and "record 0" in text and field in text and message in text


def test_too_many_objects(womd_path):
  with pytest.raises(womd.WomdFormatError, match="exceed max_num_objects=50"):
    list(womd.iterate(womd_path, max_num_objects=50))


@pytest.fixture(params=["tf", "python"])
def record_io(request, monkeypatch):
  """Runs a test with TensorFlow's TFRecord reader/writer and with ours (`tfrecord`)."""
  if request.param == "tf":
    request.getfixturevalue("tensorflow")   # skips without TensorFlow
  monkeypatch.setenv(womd.RECORD_IO_ENV, request.param)
  return request.param


def test_truncated_and_corrupt_files(real_state, tmp_path, record_io):
  good = tmp_path / "good.tfrecord"
  womd.write(str(good), [(real_state, "a"), (real_state, "b")])
  data = good.read_bytes()
  truncated = tmp_path / "truncated.tfrecord"
  truncated.write_bytes(data[: len(data) * 3 // 4])
  with pytest.raises(womd.WomdFormatError, match=r"truncated.tfrecord, record 1: corrupted or truncated"):
    list(womd.iterate(str(truncated)))
  corrupt = tmp_path / "corrupt.tfrecord"
  flipped = bytearray(data)
  flipped[100] ^= 0xFF
  corrupt.write_bytes(bytes(flipped))
  with pytest.raises(womd.WomdFormatError, match=r"corrupt.tfrecord, record 0"):
    list(womd.iterate(str(corrupt)))
  # Skipping keeps what was read before the damage.
  skipped = []
  ok = list(womd.iterate(str(truncated), on_error="skip", skipped=skipped, with_meta=True))
  assert [m.scenario_id for _, m in ok] == ["a"] and len(skipped) == 1


def test_not_an_example_and_skip_mode(real_state, tmp_path, caplog, record_io):
  path = tmp_path / "mixed.tfrecord"
  good = womd.state_to_example(real_state, "good").SerializeToString()
  _write_raw(path, [good, b"\x00garbage\xff" * 10, _example_with(real_state, lambda f: f.pop("state/id")), good])
  with pytest.raises(womd.WomdFormatError, match="record 1: not a tf.train.Example"):
    list(womd.iterate(str(path)))
  skipped = []
  with caplog.at_level(logging.WARNING):
    out = list(womd.iterate(str(path), on_error="skip", with_meta=True, skipped=skipped))
  assert [m.record_index for _, m in out] == [0, 3]
  assert [e.index for e in skipped] == [1, 2] and "state/id" in str(skipped[1])
  assert "skipping bad scenario" in caplog.text


def test_missing_files(tmp_path):
  with pytest.raises(FileNotFoundError, match="nope.tfrecord"):
    list(womd.iterate(str(tmp_path / "nope.tfrecord")))
  with pytest.raises(FileNotFoundError, match="no TFRecord matches"):
    list(womd.iterate(str(tmp_path / "*.tfrecord")))
