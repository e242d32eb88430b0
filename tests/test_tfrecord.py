"""The TensorFlow-free TFRecord / tf.Example path (`data/tfrecord.py`) against TensorFlow's."""
from __future__ import annotations

import jax
import numpy as np
import pytest

from pcdiff_jax.data import tfrecord, womd


def test_crc32c_known_values():
  # RFC 3720 (iSCSI) test vector and TFRecord's masking of it.
  for crc in (tfrecord.crc32c, tfrecord._crc32c_python):
    assert crc(b"123456789") == 0xE3069283
    assert crc(b"") == 0
  assert tfrecord.masked_crc32c(b"123456789") == \
      (((0xE3069283 >> 15) | (0xE3069283 << 17)) + 0xA282EAD8) & 0xFFFFFFFF


def test_record_io_choice(monkeypatch):
  monkeypatch.setenv(womd.RECORD_IO_ENV, "python")
  assert womd.record_io() == "python"
  monkeypatch.setenv(womd.RECORD_IO_ENV, "tf")
  assert womd.record_io() == "tf"
  monkeypatch.setenv(womd.RECORD_IO_ENV, "torch")
  with pytest.raises(ValueError, match="PCDIFF_RECORD_IO"):
    womd.record_io()


def test_real_record_parses_as_with_tensorflow(womd_path, monkeypatch, tensorflow):
  kinds = {k: womd.feature_kind(k) for k in womd.all_keys()}
  raw = next(tfrecord.read_records(womd_path))
  ours = tfrecord.parse_example(raw, kinds)
  monkeypatch.setenv(womd.RECORD_IO_ENV, "tf")
  theirs = womd._parse_raw([raw], womd_path, 0)[0]
  assert ours.keys() == theirs.keys()
  for k in ours:
    assert ours[k].dtype == theirs[k].dtype and ours[k].shape == theirs[k].shape, k
    np.testing.assert_array_equal(ours[k], theirs[k], err_msg=k)
  states = {}
  for io in ("tf", "python"):
    monkeypatch.setenv(womd.RECORD_IO_ENV, io)
    states[io] = womd.load(womd_path)[0]
  for a, b in zip(jax.tree_util.tree_leaves(states["tf"]), jax.tree_util.tree_leaves(states["python"])):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_writers_give_the_same_bytes(real_state, tmp_path, monkeypatch, tensorflow):
  items = [(real_state, "a3bb37c25ce56418"), (real_state, "second")]
  files = {}
  for io in ("tf", "python"):
    monkeypatch.setenv(womd.RECORD_IO_ENV, io)
    files[io] = tmp_path / f"{io}.tfrecord"
    assert womd.write(str(files[io]), items) == 2
  assert files["tf"].read_bytes() == files["python"].read_bytes()
  # TensorFlow's reader takes our file; ours reads it back record by record.
  assert len(list(tensorflow.data.TFRecordDataset(str(files["python"])))) == 2
  assert len(list(tfrecord.read_records(str(files["python"])))) == 2
  assert len(list(tfrecord.read_records(str(files["python"]), start=1))) == 1
  assert tfrecord.count_records(str(files["python"])) == 2


def test_parse_example_missing_and_mismatched_features():
  raw = tfrecord.make_example({"a": ("float", np.array([1.5, 2.0])), "b": ("int64", [3]),
                               "c": ("bytes", [b"x"])}).SerializeToString()
  out = tfrecord.parse_example(raw, {"a": "float", "b": "int64", "c": "bytes", "d": "float"})
  assert out["a"].dtype == np.float32 and out["a"].tolist() == [1.5, 2.0]
  assert out["b"].dtype == np.int64 and out["b"].tolist() == [3]
  assert out["c"].tolist() == [b"x"] and out["d"].shape == (0,)
  with pytest.raises(ValueError, match="'b' is a int64_list"):
    tfrecord.parse_example(raw, {"b": "float"})
  assert sorted(tfrecord.is_example(raw)) == ["a", "b", "c"] and tfrecord.is_example(b"\xff\x00junk") is None
