"""TFRecord files and tf.train.Example messages without TensorFlow.

`womd` reads and writes through TensorFlow when it is installed and through
this module otherwise (or when `PCDIFF_RECORD_IO=python`): a machine with JAX
but no TensorFlow (a GPU image, a slim install) still makes, reads and trains
on the same files. The bytes are TensorFlow's: a record is framed as

  uint64 length | uint32 masked crc32c(length) | data | uint32 masked crc32c(data)

(little-endian; `tensorflow/core/lib/io/record_writer.cc`), and the Example
messages are built from the public `tensorflow/core/example/{example,feature}.proto`
schema in a private descriptor pool (they never clash with TensorFlow's own).
CRC-32C comes from `google_crc32c` or `crc32c` when either is installed, else
from a table in numpy-free Python (about 0.1 s per MB: fine for tests and a
single record, slow for making a dataset).
"""
from __future__ import annotations

import os
import struct
from typing import BinaryIO, Iterator, Optional

import numpy as np
from google.protobuf import descriptor_pb2, descriptor_pool

try:  # protobuf >= 4.21
  from google.protobuf.message_factory import GetMessageClass as _message_class
except ImportError:  # pragma: no cover - older protobuf
  from google.protobuf import message_factory as _mf
  _message_class = _mf.MessageFactory().GetPrototype


# --------------------------------------------------------------------------
# CRC-32C (Castagnoli), masked as TFRecord does
# --------------------------------------------------------------------------

def _python_table() -> list[int]:
  table = []
  for n in range(256):
    c = n
    for _ in range(8):
      c = (c >> 1) ^ 0x82F63B78 if c & 1 else c >> 1
    table.append(c)
  return table


_TABLE = _python_table()


def _crc32c_python(data: bytes) -> int:
  crc = 0xFFFFFFFF
  table = _TABLE
  for byte in data:
    crc = table[(crc ^ byte) & 0xFF] ^ (crc >> 8)
  return crc ^ 0xFFFFFFFF


def _crc32c_impl():
  try:
    import google_crc32c
    if google_crc32c.implementation == "c":
      return google_crc32c.value, "google_crc32c"
  except (ImportError, AttributeError):
    pass
  try:
    import crc32c as crc_pkg
    return crc_pkg.crc32c, "crc32c"
  except ImportError:
    return _crc32c_python, "python"


crc32c, CRC_IMPLEMENTATION = _crc32c_impl()


def masked_crc32c(data: bytes) -> int:
  crc = crc32c(data)
  return (((crc >> 15) | (crc << 17)) + 0xA282EAD8) & 0xFFFFFFFF


# --------------------------------------------------------------------------
# Framing
# --------------------------------------------------------------------------

class RecordError(ValueError):
  """A TFRecord file is truncated or corrupted at record `index`."""

  def __init__(self, index: int, message: str):
    super().__init__(message)
    self.index = index


def read_records(path: str, start: int = 0, verify: bool = True) -> Iterator[bytes]:
  """The raw records of a TFRecord file (uncompressed), from record `start`.

  verify: check both CRCs (TensorFlow's reader does). A truncated or corrupted
  record raises RecordError after the good ones before it were yielded.
  """
  with open(path, "rb") as f:
    index = 0
    while True:
      header = f.read(12)
      if not header:
        return
      if len(header) < 12:
        raise RecordError(index, f"truncated record header ({len(header)} of 12 bytes)")
      length, length_crc = struct.unpack("<QI", header)
      if verify and masked_crc32c(header[:8]) != length_crc:
        raise RecordError(index, "corrupted record length (CRC mismatch)")
      if index < start:
        f.seek(length + 4, os.SEEK_CUR)
        index += 1
        continue
      data = f.read(length)
      footer = f.read(4)
      if len(data) < length or len(footer) < 4:
        raise RecordError(index, f"truncated record ({len(data)} of {length} bytes)")
      if verify and masked_crc32c(data) != struct.unpack("<I", footer)[0]:
        raise RecordError(index, "corrupted record data (CRC mismatch)")
      yield data
      index += 1


def count_records(path: str) -> int:
  """How many records a TFRecord file holds, from the headers alone (a truncated last record
  counts; `read_records` reports it)."""
  count, size = 0, os.path.getsize(path)
  with open(path, "rb") as f:
    while f.tell() < size:
      header = f.read(12)
      if len(header) < 12:
        break
      f.seek(struct.unpack("<Q", header[:8])[0] + 4, os.SEEK_CUR)
      count += 1
  return count


def write_record(f: BinaryIO, data: bytes) -> None:
  length = struct.pack("<Q", len(data))
  f.write(length)
  f.write(struct.pack("<I", masked_crc32c(length)))
  f.write(data)
  f.write(struct.pack("<I", masked_crc32c(data)))


# --------------------------------------------------------------------------
# tf.train.Example
# --------------------------------------------------------------------------

_F = descriptor_pb2.FieldDescriptorProto


def _example_file() -> descriptor_pb2.FileDescriptorProto:
  f = descriptor_pb2.FileDescriptorProto(name="pcdiff_jax/tf_example_subset.proto",
                                         package="tensorflow", syntax="proto3")
  for name, ftype in (("BytesList", _F.TYPE_BYTES), ("FloatList", _F.TYPE_FLOAT),
                      ("Int64List", _F.TYPE_INT64)):
    msg = f.message_type.add(name=name)
    field = msg.field.add(name="value", number=1, label=_F.LABEL_REPEATED, type=ftype)
    if ftype != _F.TYPE_BYTES:
      field.options.packed = True
  feature = f.message_type.add(name="Feature")
  feature.oneof_decl.add(name="kind")
  for number, name in enumerate(("bytes_list", "float_list", "int64_list"), start=1):
    type_name = ".tensorflow." + {"bytes_list": "BytesList", "float_list": "FloatList",
                                   "int64_list": "Int64List"}[name]
    feature.field.add(name=name, number=number, label=_F.LABEL_OPTIONAL, type=_F.TYPE_MESSAGE,
                      type_name=type_name, oneof_index=0)
  features = f.message_type.add(name="Features")
  entry = features.nested_type.add(name="FeatureEntry")
  entry.options.map_entry = True
  entry.field.add(name="key", number=1, label=_F.LABEL_OPTIONAL, type=_F.TYPE_STRING)
  entry.field.add(name="value", number=2, label=_F.LABEL_OPTIONAL, type=_F.TYPE_MESSAGE,
                  type_name=".tensorflow.Feature")
  features.field.add(name="feature", number=1, label=_F.LABEL_REPEATED, type=_F.TYPE_MESSAGE,
                     type_name=".tensorflow.Features.FeatureEntry")
  example = f.message_type.add(name="Example")
  example.field.add(name="features", number=1, label=_F.LABEL_OPTIONAL, type=_F.TYPE_MESSAGE,
                    type_name=".tensorflow.Features")
  return f


_POOL = descriptor_pool.DescriptorPool()
_POOL.Add(_example_file())
Example = _message_class(_POOL.FindMessageTypeByName("tensorflow.Example"))

_KINDS = {"float": ("float_list", np.float32), "int64": ("int64_list", np.int64),
          "bytes": ("bytes_list", object)}


def parse_example(raw: bytes, kinds: dict[str, str]) -> dict[str, np.ndarray]:
  """A serialized tf.train.Example -> {key: flat array} for the keys of `kinds`
  ({key: 'float' | 'int64' | 'bytes'}), as `tf.io.parse_example` with
  RaggedFeatures gives them: a missing key is an empty array; a key stored with
  another list type raises ValueError (TensorFlow raises InvalidArgumentError).
  Other keys are ignored. Raises google.protobuf's DecodeError on bytes that are
  not an Example."""
  features = Example.FromString(raw).features.feature
  out = {}
  for key, kind in kinds.items():
    field, dtype = _KINDS[kind]
    if key not in features:
      out[key] = np.zeros((0,), dtype)
      continue
    feature = features[key]
    stored = feature.WhichOneof("kind")
    if stored not in (None, field):
      raise ValueError(f"feature {key!r} is a {stored}, expected a {field}")
    values = getattr(feature, field).value
    if dtype is object:
      arr = np.empty((len(values),), object)
      arr[:] = list(values)
      out[key] = arr
    else:
      out[key] = np.fromiter(values, dtype, count=len(values))
  return out


def make_example(features: dict[str, tuple[str, np.ndarray]]):
  """{key: (kind, flat values)} -> an Example message (kinds as `parse_example`)."""
  ex = Example()
  feature_map = ex.features.feature
  for key, (kind, values) in features.items():
    field, dtype = _KINDS[kind]
    target = getattr(feature_map[key], field)
    if dtype is object:
      target.value.extend(list(values))
    else:
      # Lists, not arrays: protobuf copies a list ~10x faster than it iterates an array.
      target.value.extend(np.asarray(values, dtype).reshape(-1).tolist())
  return ex


def is_example(raw: bytes) -> Optional[list[str]]:
  """The feature keys of `raw` if it parses as an Example, else None."""
  try:
    return list(Example.FromString(raw).features.feature.keys())
  except Exception:  # DecodeError and friends: not an Example
    return None
