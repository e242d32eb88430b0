"""Waymo Open Sim Agents Challenge (WOSAC) submissions: build, write, read, check.

The rules (`waymo_open_dataset/utils/sim_agents/submission_specs.py` and the
comments of `sim_agents_submission.proto`): per scenario one
`ScenarioRollouts` with its `scenario_id` and exactly 32 `JointScene`s; each
joint scene holds one `SimulatedTrajectory` per sim agent (every object valid
at step 10, the SDC included) and no other object, with `object_id` (the WOMD
track id) and 80 values each of `center_x`, `center_y`, `center_z`, `heading`
(steps 11-90, the scenario's global frame). A submission sets
`submission_type = SIM_AGENTS_SUBMISSION`, the account name, a unique method
name, and the now required `uses_lidar_data`, `uses_camera_data`,
`uses_public_model_pretraining`, `num_model_parameters` (an integer with an
optional K/M/B/T suffix) and `acknowledge_complies_with_closed_loop_requirement`.
The closed-loop rule (the challenge's page): a rollout is a sequence of inference
calls, each conditioned on the states simulated so far, at 1 Hz or more, the
10 Hz output filled in between (`MAX_STEPS_BETWEEN_CALLS`).
Large sets go in several files named `NAME.binproto-00000-of-00150`, packed
into one tar.gz for upload.
"""
from __future__ import annotations

import dataclasses
import os
import re
from typing import Iterable, Iterator, Optional, Sequence

import numpy as np

from pcdiff_jax.data import waymo_protos as pb

CURRENT_INDEX = 10
NUM_SIM_STEPS = 80
NUM_ROLLOUTS = 32
MAX_STEPS_BETWEEN_CALLS = 10   # the closed-loop rule: inference at 1 Hz or more, output at 10 Hz
FIELDS = ("center_x", "center_y", "center_z", "heading")
FILENAME_RE = re.compile(r".*\.binproto(-\d{5}-of-\d{5})?$")
PARAMS_RE = re.compile(r"^\d+[KMBT]?$")


@dataclasses.dataclass(frozen=True)
class Metadata:
  """The submission's fields besides the rollouts (sim_agents_submission.proto)."""
  account_name: str = ""
  unique_method_name: str = ""
  authors: tuple[str, ...] = ()
  affiliation: str = ""
  description: str = ""
  method_link: str = ""
  uses_lidar_data: bool = False
  uses_camera_data: bool = False
  uses_public_model_pretraining: bool = False
  public_model_names: tuple[str, ...] = ()
  num_model_parameters: str = "0"
  acknowledge_complies_with_closed_loop_requirement: bool = True

  def to_proto(self):
    """A SimAgentsChallengeSubmission with these fields and no rollouts."""
    sub = pb.SimAgentsChallengeSubmission(submission_type=pb.SIM_AGENTS_SUBMISSION)
    for field in dataclasses.fields(self):
      value = getattr(self, field.name)
      if isinstance(value, tuple):
        getattr(sub, field.name).extend(value)
      elif value != "":
        setattr(sub, field.name, value)
    return sub


def format_num_parameters(count: int) -> str:
  """A parameter count as the submission wants it, with two digits at least: '850', '27K', '2600K'."""
  for suffix, scale in (("T", 10 ** 12), ("B", 10 ** 9), ("M", 10 ** 6), ("K", 10 ** 3)):
    if count >= 10 * scale:   # at least two significant digits before the suffix
      return f"{round(count / scale)}{suffix}"
  return str(int(count))


def scenario_rollouts(scenario_id: str, object_ids: Sequence[int], trajectories: np.ndarray):
  """ScenarioRollouts from (R, A, 80, 4) [x, y, z, heading] of the A objects
  `object_ids`, one JointScene per rollout."""
  traj = np.asarray(trajectories, np.float32)
  ids = [int(i) for i in object_ids]
  if traj.ndim != 4 or traj.shape[1] != len(ids) or traj.shape[3] != 4:
    raise ValueError(f"trajectories must be (rollouts, {len(ids)} objects, steps, 4), got {traj.shape}")
  out = pb.ScenarioRollouts(scenario_id=scenario_id)
  for scene in traj:
    joint = out.joint_scenes.add()
    for object_id, states in zip(ids, scene):
      # Lists, not arrays: protobuf copies a list much faster than it iterates an array.
      joint.simulated_trajectories.add(center_x=states[:, 0].tolist(), center_y=states[:, 1].tolist(),
                                       center_z=states[:, 2].tolist(), heading=states[:, 3].tolist(),
                                       object_id=object_id)
  return out


def shard_path(out: str, index: Optional[int] = None, count: Optional[int] = None) -> str:
  """`out` or, for a shard, `out-00003-of-00150` (the official naming)."""
  if index is None:
    return out
  return f"{out}-{index:05d}-of-{count:05d}"


def _field_bytes(number: int, payload: bytes) -> bytes:
  """One length-delimited field: tag, varint length, payload."""
  head = bytearray()
  for value in ((number << 3) | 2, len(payload)):
    while True:
      byte = value & 0x7F
      value >>= 7
      head.append(byte | (0x80 if value else 0))
      if not value:
        break
  return bytes(head) + payload


def _read_varint(f) -> Optional[int]:
  """The next varint of a binary stream; None at its end or inside a cut-short varint."""
  value = shift = 0
  while True:
    byte = f.read(1)
    if not byte:
      return None
    value |= (byte[0] & 0x7F) << shift
    if byte[0] < 0x80:
      return value
    shift += 7


def iter_scenario_records(path: str, payloads: bool = True) -> Iterator[Optional[bytes]]:
  """The serialized ScenarioRollouts (field 1) of a submission file, or of a writer's `.tmp`
  stream, in order, one at a time (None for each with payloads=False: a count that seeks past
  them). A record cut short (a process killed while writing it) ends the stream; the other
  fields (the metadata) are skipped. A byte that starts no field is a ValueError naming the file."""
  with open(path, "rb") as f:
    while True:
      tag = _read_varint(f)
      if tag is None:
        return
      number, wire = tag >> 3, tag & 7
      if wire == 0:
        if _read_varint(f) is None:
          return
      elif wire in (1, 5):
        f.seek(8 if wire == 1 else 4, os.SEEK_CUR)
      elif wire == 2:
        length = _read_varint(f)
        if length is None:
          return
        if number == 1 and payloads:
          data = f.read(length)
          if len(data) < length:
            return
          yield data
          continue
        end = f.seek(length, os.SEEK_CUR)
        if end > os.fstat(f.fileno()).st_size:
          return
        if number == 1:
          yield None
      else:
        raise ValueError(f"{path}: not a SimAgentsChallengeSubmission stream (wire type {wire} at byte "
                         f"{f.tell()})")


def count_scenarios(path: str) -> int:
  """How many complete ScenarioRollouts `iter_scenario_records` would yield (0 for no file)."""
  return sum(1 for _ in iter_scenario_records(path, payloads=False)) if os.path.exists(path) else 0


class SubmissionWriter:
  """Writes a SimAgentsChallengeSubmission one ScenarioRollouts at a time, so
  a shard never sits whole in memory: the repeated field 1 streamed first, the
  metadata at `close()` (the bytes equal `SerializeToString()` of the whole
  message). Writes `path + '.tmp'` and renames it on close; `close_partial`
  keeps an interrupted run's scenarios as `path + '.partial'`."""

  def __init__(self, path: str, metadata: Metadata):
    self.path, self.metadata, self.count = path, metadata, 0
    self.scenario_ids: list[str] = []
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    self._file = open(f"{path}.tmp", "wb")

  def add(self, rollouts) -> None:
    self.add_serialized(rollouts.SerializeToString(), rollouts.scenario_id)

  def add_serialized(self, payload: bytes, scenario_id: str) -> None:
    """Appends one ScenarioRollouts already serialized (`iter_scenario_records`)."""
    self._file.write(_field_bytes(1, payload))
    self.scenario_ids.append(scenario_id)
    self.count += 1

  def flush(self) -> None:
    self._file.flush()

  def close(self, suffix: str = "") -> str:
    """Finishes the file as `path + suffix`; returns that path."""
    self._file.write(self.metadata.to_proto().SerializeToString())
    self._file.close()
    os.replace(f"{self.path}.tmp", self.path + suffix)
    return self.path + suffix

  def close_partial(self) -> str:
    """Finishes the scenarios written so far as a valid submission of them,
    `path + '.partial'` (never the final name: it is not the whole shard)."""
    return self.close(".partial")

  def abort(self) -> None:
    self._file.close()
    os.remove(f"{self.path}.tmp")

  def __enter__(self):
    return self

  def __exit__(self, exc_type, exc, tb):
    self.abort() if exc_type else self.close()


def read(path: str):
  """One submission file -> SimAgentsChallengeSubmission (ValueError naming it)."""
  with open(path, "rb") as f:
    raw = f.read()
  try:
    return pb.SimAgentsChallengeSubmission.FromString(raw)
  except Exception as err:
    raise ValueError(f"{path}: not a SimAgentsChallengeSubmission binproto ({err})") from None


def sim_agent_ids(object_ids: np.ndarray, valid_now: np.ndarray) -> list[int]:
  """The sim agents of one scenario: the ids of the objects valid at step 10."""
  return [int(i) for i in np.asarray(object_ids)[np.asarray(valid_now, bool)]]


def check_rollouts(rollouts, agents: Iterable[int], num_rollouts: int = NUM_ROLLOUTS,
                   num_steps: int = NUM_SIM_STEPS, start_xy: Optional[dict] = None,
                   max_first_step: float = 10.0) -> tuple[list[str], list[str]]:
  """(errors, warnings) of one ScenarioRollouts against its scenario's sim
  agents: the official rules (errors) and sanity checks (warnings: a first
  simulated position more than `max_first_step` metres from the object's
  step-10 position in `start_xy` {id: (x, y)}, e.g. a local frame)."""
  errors, warnings = [], []
  sid = rollouts.scenario_id if rollouts.HasField("scenario_id") else None
  where = f"scenario {sid}"
  if sid is None:
    return ["a ScenarioRollouts has no scenario_id"], []
  if len(rollouts.joint_scenes) != num_rollouts:
    errors.append(f"{where}: {len(rollouts.joint_scenes)} joint scenes, expected exactly {num_rollouts}")
  expected = set(agents)
  far = 0
  for r, scene in enumerate(rollouts.joint_scenes):
    seen: set[int] = set()
    for traj in scene.simulated_trajectories:
      oid = traj.object_id
      if not traj.HasField("object_id"):
        errors.append(f"{where}, joint scene {r}: a trajectory has no object_id")
        continue
      if oid in seen:
        errors.append(f"{where}, joint scene {r}: object {oid} appears more than once")
      seen.add(oid)
      if oid not in expected:
        errors.append(f"{where}, joint scene {r}: object {oid} is not a sim agent (not valid at step 10)")
      for field in FIELDS:
        values = np.asarray(getattr(traj, field), np.float64)
        if len(values) != num_steps:
          errors.append(f"{where}, joint scene {r}, object {oid}: {field} has {len(values)} values, "
                        f"expected {num_steps}")
        elif not np.all(np.isfinite(values)):
          errors.append(f"{where}, joint scene {r}, object {oid}: {field} has non-finite values")
      for field in ("width", "length", "height", "valid"):
        n = len(getattr(traj, field))
        if n not in (0, num_steps):
          warnings.append(f"{where}, joint scene {r}, object {oid}: optional {field} has {n} values "
                          f"(empty or {num_steps}; ignored by the sim agents challenge)")
      if start_xy and oid in start_xy and len(traj.center_x) and len(traj.center_y):
        if np.hypot(traj.center_x[0] - start_xy[oid][0], traj.center_y[0] - start_xy[oid][1]) > max_first_step:
          far += 1
    missing = expected - seen
    if missing:
      errors.append(f"{where}, joint scene {r}: sim agents missing: {sorted(missing)}")
    if len(errors) > 20:
      errors.append(f"{where}: more errors not shown")
      break
  if far:
    warnings.append(f"{where}: {far} trajectories start more than {max_first_step:g} m from the object's "
                    "step-10 position (not in the scenario's global frame?)")
  return errors, warnings


def check_metadata(sub, path: str) -> list[str]:
  """Problems the server rejects a submission file for, besides its rollouts."""
  problems = []
  if sub.submission_type != pb.SIM_AGENTS_SUBMISSION:
    problems.append(f"{path}: submission_type is not SIM_AGENTS_SUBMISSION")
  if not FILENAME_RE.match(os.path.basename(path)):
    problems.append(f"{path}: the file name must match NAME.binproto or NAME.binproto-00000-of-00150")
  for field in ("account_name", "unique_method_name"):
    if not getattr(sub, field):
      problems.append(f"{path}: {field} is empty (required)")
  for field in ("uses_lidar_data", "uses_camera_data", "uses_public_model_pretraining",
                "acknowledge_complies_with_closed_loop_requirement"):
    if not sub.HasField(field):
      problems.append(f"{path}: {field} is not set (required)")
  if not sub.acknowledge_complies_with_closed_loop_requirement:
    problems.append(f"{path}: acknowledge_complies_with_closed_loop_requirement is false (the challenge "
                    "requires closed-loop simulation: inference at 1 Hz or more)")
  if not PARAMS_RE.match(sub.num_model_parameters):
    problems.append(f"{path}: num_model_parameters {sub.num_model_parameters!r} is not an integer with an "
                    "optional K/M/B/T suffix (required, e.g. '200K')")
  return problems
