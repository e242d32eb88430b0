"""WOSAC: the messages' bytes, the submission rules, the export and the checker."""
from __future__ import annotations

import struct

import jax
import numpy as np
import pytest

from pcdiff_jax import wosac
from pcdiff_jax.data import submission, womd
from pcdiff_jax.data import waymo_protos as pb


def _varint(v: int) -> bytes:
  out = bytearray()
  while True:
    b, v = v & 0x7F, v >> 7
    out.append(b | (0x80 if v else 0))
    if not v:
      return bytes(out)


def _tag(number: int, wire: int) -> bytes:
  return _varint(number << 3 | wire)


def _len(number: int, payload: bytes) -> bytes:
  return _tag(number, 2) + _varint(len(payload)) + payload


def test_messages_serialize_to_the_public_wire_format():
  traj = pb.SimulatedTrajectory(center_x=[1.0, 2.0], center_y=[3.0], center_z=[0.5], heading=[-1.0], object_id=7)
  floats = lambda *v: struct.pack(f"<{len(v)}f", *v)
  expected = (_len(2, floats(1.0, 2.0)) + _len(3, floats(3.0)) + _len(4, floats(0.5)) + _len(5, floats(-1.0))
              + _tag(6, 0) + _varint(7))   # packed floats 2-5, object_id 6 (varint)
  assert traj.SerializeToString() == expected
  scene = pb.JointScene(simulated_trajectories=[traj])
  rollouts = pb.ScenarioRollouts(scenario_id="ab", joint_scenes=[scene])
  assert rollouts.SerializeToString() == _len(1, b"ab") + _len(2, _len(1, expected))
  sub = pb.SimAgentsChallengeSubmission(
      scenario_rollouts=[rollouts], submission_type=pb.SIM_AGENTS_SUBMISSION, account_name="a@b.c",
      unique_method_name="m", authors=["x"], uses_lidar_data=False, num_model_parameters="3M",
      public_model_names=["p"], acknowledge_complies_with_closed_loop_requirement=True)
  assert sub.SerializeToString() == (
      _len(1, rollouts.SerializeToString()) + _tag(2, 0) + b"\x01" + _len(3, b"a@b.c") + _len(4, b"m")
      + _len(5, b"x") + _tag(9, 0) + b"\x00" + _len(12, b"3M") + _len(13, b"p") + _tag(14, 0) + b"\x01")
  # Scenario side: doubles (wire type 1), floats (5), bools, nested tracks, unpacked repeated timestamps.
  state = pb.ObjectState(center_x=1.5, length=4.0, valid=True)
  assert state.SerializeToString() == _tag(2, 1) + struct.pack("<d", 1.5) + _tag(5, 5) + struct.pack("<f", 4.0) + _tag(11, 0) + b"\x01"
  scenario = pb.Scenario(scenario_id="s", timestamps_seconds=[0.0, 0.1], sdc_track_index=0, current_time_index=10)
  scenario.tracks.add(id=3, object_type=1).states.append(state)
  assert scenario.SerializeToString() == (
      _tag(1, 1) + struct.pack("<d", 0.0) + _tag(1, 1) + struct.pack("<d", 0.1)
      + _len(2, _tag(1, 0) + b"\x03" + _tag(2, 0) + b"\x01" + _len(3, state.SerializeToString()))
      + _len(5, b"s") + _tag(6, 0) + b"\x00" + _tag(10, 0) + b"\x0a")
  feature = pb.MapFeature(id=5)
  feature.road_edge.type = 1
  assert feature.SerializeToString() == _tag(1, 0) + b"\x05" + _len(5, _tag(1, 0) + b"\x01")


def test_writer_streams_the_bytes_of_the_whole_message(tmp_path):
  meta = submission.Metadata(account_name="a@b.c", unique_method_name="m", num_model_parameters="409K")
  parts = [submission.scenario_rollouts(f"s{i}", [1, 2], np.full((2, 2, 80, 4), i, np.float32)) for i in range(3)]
  path = str(tmp_path / "sub.binproto")
  with submission.SubmissionWriter(path, meta) as writer:
    for p in parts:
      writer.add(p)
  whole = meta.to_proto()
  whole.scenario_rollouts.extend(parts)
  assert open(path, "rb").read() == whole.SerializeToString()
  assert submission.read(path) == whole
  assert submission.check_metadata(whole, path) == []
  assert [submission.format_num_parameters(n) for n in (0, 950, 12_345, 409_000, 2_600_000)] == \
      ["0", "950", "12K", "409K", "2600K"]


def _rollouts(agents, n=submission.NUM_ROLLOUTS, steps=80):
  return submission.scenario_rollouts("s", agents, np.zeros((n, len(agents), steps, 4), np.float32))


@pytest.mark.parametrize("break_it, message", [
    (lambda r: r.joint_scenes.pop(), "31 joint scenes, expected exactly 32"),
    (lambda r: r.joint_scenes[3].simulated_trajectories.pop(), "joint scene 3: sim agents missing: [3]"),
    (lambda r: r.joint_scenes[0].simulated_trajectories.add().CopyFrom(r.joint_scenes[0].simulated_trajectories[0]),
     "object 1 appears more than once"),
    (lambda r: r.joint_scenes[0].simulated_trajectories[1].heading.pop(), "heading has 79 values, expected 80"),
    (lambda r: r.joint_scenes[5].simulated_trajectories[0].center_y.__setitem__(4, float("nan")),
     "center_y has non-finite values"),
    (lambda r: setattr(r.joint_scenes[0].simulated_trajectories[0], "object_id", 9), "object 9 is not a sim agent"),
])
def test_check_rollouts_enforces_the_rules(break_it, message):
  good = _rollouts([1, 2, 3])
  assert submission.check_rollouts(good, [1, 2, 3]) == ([], [])
  break_it(good)
  errors, _ = submission.check_rollouts(good, [1, 2, 3])
  assert any(message in e for e in errors), errors


def test_bad_metadata_is_reported(tmp_path):
  sub = pb.SimAgentsChallengeSubmission(num_model_parameters="lots")
  problems = " ".join(submission.check_metadata(sub, str(tmp_path / "sub.pb")))
  for text in ("SIM_AGENTS_SUBMISSION", "file name", "account_name is empty", "uses_lidar_data is not set",
               "num_model_parameters 'lots'"):
    assert text in problems


def test_learned_methods_drive_the_sdc_and_idm_the_rest(tiny_models):
  from conftest import make_scene
  from pcdiff_jax import policy
  from pcdiff_jax.config import get_config
  from pcdiff_jax.sim import env
  import dataclasses
  cfg = get_config("tiny")
  cfg = dataclasses.replace(cfg, features=dataclasses.replace(cfg.features, max_agents=2))   # SDC + 1
  state = env.reset(make_scene(num_steps=91))
  actor, params = wosac.drive_all(policy.actor(cfg), tiny_models, learned=True)
  fallback, learned = actor.init(jax.random.PRNGKey(0), state)
  assert params[1] is tiny_models
  assert list(fallback[0]) == [True] * 4                       # IDM: every sim agent (the learned one wins)
  assert list(learned.controlled) == [True, True, False, False]   # the SDC and its nearest agent
  ego_actor, _ = wosac.drive_all(policy.actor(cfg), tiny_models, learned=True, ego="idm")
  _, learned, ego = ego_actor.init(jax.random.PRNGKey(0), state)
  assert list(learned.controlled) == [False, True, False, False] and list(ego[0]) == [True, False, False, False]


def test_export_and_check_on_the_real_record(womd_path, tmp_path, capsys):
  from experiments import wosac as cli
  state, meta = womd.load(womd_path, to_jax=False)
  scenarios = str(tmp_path / "scenario.tfrecord")   # the Scenario-proto flavour of the real record
  womd.write(scenarios, [(state, meta.scenario_id)], record_format="scenario")
  out = str(tmp_path / "sub.binproto")
  assert cli.main(["--scenarios", scenarios, "--method", "cv", "--out", out, "--num-rollouts", "2",
                   "--no-progress", "--account-name", "me@example.com"]) == 0
  sub = submission.read(out)
  assert sub.submission_type == pb.SIM_AGENTS_SUBMISSION and sub.unique_method_name == "pcdiff_jax-cv"
  assert sub.account_name == "me@example.com" and sub.num_model_parameters == "0"
  (rollouts,) = sub.scenario_rollouts
  log = state.log_trajectory
  now = np.asarray(log.valid[:, 10])
  agents = np.asarray(state.object_metadata.ids)[now]
  assert rollouts.scenario_id == "a3bb37c25ce56418" and len(rollouts.joint_scenes) == 2 and len(agents) == 73
  sdc_id = int(np.asarray(state.object_metadata.ids)[np.asarray(state.object_metadata.is_sdc)][0])
  for scene in rollouts.joint_scenes:
    trajs = {t.object_id: t for t in scene.simulated_trajectories}
    assert sorted(trajs) == sorted(agents.tolist()) and sdc_id in trajs
    for t in trajs.values():
      values = np.array([t.center_x, t.center_y, t.center_z, t.heading])
      assert values.shape == (4, 80) and np.all(np.isfinite(values))
  # Constant velocity in the global frame: the SDC's first step is its step-10 pose moved 0.1 s on.
  sdc = int(np.argmax(np.asarray(state.object_metadata.is_sdc)))
  first = trajs[sdc_id]
  speed = np.hypot(log.vel_x[sdc, 10], log.vel_y[sdc, 10])
  step = np.hypot(first.center_x[0] - log.x[sdc, 10], first.center_y[0] - log.y[sdc, 10])
  assert abs(step - 0.1 * speed) < 0.05 and first.heading[0] == pytest.approx(float(log.yaw[sdc, 10]), abs=1e-5)
  capsys.readouterr()
  # The checker: valid with the test's rollout count, invalid for the challenge's 32 (exit 2, no traceback).
  assert cli.main(["--check", out, "--scenarios", womd_path, "--num-rollouts", "2"]) == 0
  assert "valid: 1 of 1 scenario(s)" in capsys.readouterr().out
  assert cli.main(["--check", out, "--scenarios", womd_path, "--strict"]) == 2
  err = capsys.readouterr().err
  assert "2 joint scenes, expected exactly 32" in err and "Traceback" not in err
  # A scenario the submission lacks, and a file that is not a submission.
  other = str(tmp_path / "other.tfrecord")
  womd.write(other, [(state, meta.scenario_id), (state, "another-scene")])
  assert cli.main(["--check", out, "--scenarios", other, "--num-rollouts", "2"]) == 2
  assert "1 scenario(s) of --scenarios have no rollouts: ['another-scene']" in capsys.readouterr().err
  (tmp_path / "junk.binproto").write_bytes(b"\xff\xff\xff")
  assert cli.main(["--check", str(tmp_path / "junk.binproto"), "--scenarios", womd_path]) == 2
  assert "not a SimAgentsChallengeSubmission" in capsys.readouterr().err


def test_cli_bad_input(tmp_path, capsys):
  from experiments import wosac as cli
  with pytest.raises(SystemExit) as err:
    cli.main(["--scenarios", "x", "--out", str(tmp_path / "s.binproto"), "--method", "pcdiff"])
  assert err.value.code == 2 and "--checkpoint" in capsys.readouterr().err
  with pytest.raises(SystemExit) as err:
    cli.main(["--scenarios", "x", "--out", str(tmp_path / "s.binproto"), "--shard", "3/2"])
  assert err.value.code == 2
  assert cli.main(["--scenarios", str(tmp_path / "missing.tfrecord"), "--method", "cv",
                   "--out", str(tmp_path / "s.binproto")]) == 2
  assert "missing.tfrecord" in capsys.readouterr().err
