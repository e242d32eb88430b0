"""WOSAC: the messages' bytes, the submission rules, the export and the checker."""
from __future__ import annotations

import json
import os
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


# --------------------------------------------------------------------------
# Scoring with Waymo's evaluator: the glue (a fake evaluator), then the real one
# --------------------------------------------------------------------------

FAKE_WORKER = r'''#!/bin/sh
# A stand-in for the evaluator venv's python: prints the worker's JSON lines.
index=0
while [ $# -gt 0 ]; do [ "$1" = "--index" ] && index=$2; shift; done
m='"metametric": MM, "min_average_displacement_error": 1.5, "linear_speed_likelihood": 0.25'
b='"realism_meta_metric": MM, "kinematic_metrics": 0.5, "interactive_metrics": 0.5, "map_based_metrics": 0.5, "min_ade": 1.5, "simulated_collision_rate": 0.1'
line() { echo "{\"scenario_id\": \"$1\", \"record\": \"f#0\", \"metrics\": {$(echo "$m" | sed s/MM/$2/)}, \"buckets\": {$(echo "$b" | sed s/MM/$2/)}, \"seconds\": 1.0}"; }
if [ "$index" = 0 ]; then
  line s0 0.5
  echo '{"scenario_id": "bad", "record": "f#1", "error": "ValueError: boom", "traceback": ""}'
else
  line s1 0.7
  echo '{"scenario_id": "s9", "record": "f#2", "missing": true}'
fi
echo '{"done": true, "submitted": ["bad", "s0", "s1", "zz"]}'
'''


def _fake_evaluator(tmp_path):
  venv = tmp_path / "fake-venv"
  (venv / "bin").mkdir(parents=True)
  python = venv / "bin" / "python"
  python.write_text(FAKE_WORKER)
  python.chmod(0o755)
  return str(venv)


def _submission(tmp_path, ids):
  path = str(tmp_path / "sub.binproto")
  with submission.SubmissionWriter(path, submission.Metadata(unique_method_name="m")) as writer:
    for sid in ids:
      writer.add(submission.scenario_rollouts(sid, [1], np.zeros((1, 1, 80, 4), np.float32)))
  return path


def test_score_collects_the_workers_aggregates_and_writes_tables(womd_path, tmp_path, monkeypatch, capsys):
  from experiments import wosac as cli
  from pcdiff_jax import wosac_scoring
  venv = _fake_evaluator(tmp_path)
  sub = _submission(tmp_path, ["s0", "s1", "bad", "zz"])
  result = wosac_scoring.score([sub], womd_path, workers=2, progress=False, venv=venv)
  assert sorted(result["scenarios"]) == ["s0", "s1"] and list(result["failed"]) == ["bad"]
  assert "ValueError: boom" in result["failed"]["bad"] and result["missing"] == ["s9"]
  assert result["unknown"] == ["zz"]
  agg = result["aggregate"]
  assert agg["num_scenarios"] == 2 and agg["buckets"]["realism_meta_metric"] == pytest.approx(0.6)
  assert agg["metrics"]["linear_speed_likelihood"] == pytest.approx(0.25)
  table = wosac_scoring.markdown(result)
  assert "| metametric | 0.6000 |" in table and "| s1 | 0.7000 |" in table and "failed: " in table
  assert "| linear_speed_likelihood | 0.2500 |" in table
  assert "| m | 2 | 0.6000 |" in wosac_scoring.compare({"m": result})
  # The CLI: JSON and markdown next to the submission, warnings for the scenes left out, exit 0.
  monkeypatch.setenv("WOSAC_VENV", venv)
  assert cli.main(["--score", sub, "--scenarios", womd_path, "--no-progress"]) == 0
  out = capsys.readouterr()
  assert "scenario bad could not be scored, skipped" in out.err and "not in --scenarios" in out.err
  saved = json.loads((tmp_path / "sub.wosac.json").read_text())
  assert saved["aggregate"] == agg and (tmp_path / "sub.wosac.md").read_text() == table


def test_a_stopped_scoring_resumes_from_its_journal(womd_path, tmp_path):
  """Each scored scene goes to the journal as it comes; a second run takes
  the journal's scenes as they are (the workers skip them) and scores the
  failed ones again; a journal of other submission bytes is not used."""
  from pcdiff_jax import wosac_scoring
  venv = _fake_evaluator(tmp_path)
  sub = _submission(tmp_path, ["s0", "s1", "bad", "zz"])
  journal = str(tmp_path / "out" / "sub.wosac.jsonl")
  wosac_scoring.score([sub], womd_path, workers=2, progress=False, venv=venv, journal=journal)
  lines = [json.loads(line) for line in open(journal)]
  assert "journal_of" in lines[0] and sorted(item["scenario_id"] for item in lines[1:]) == ["bad", "s0", "s1"]
  # As if s0 had been scored 0.9 before a stop that cut the last line short.
  marked = [json.dumps(item).replace('"realism_meta_metric": 0.5', '"realism_meta_metric": 0.9')
            for item in lines if item.get("scenario_id") != "s1"]
  with open(journal, "w") as f:
    f.write("\n".join(marked) + '\n{"scenario_id": "s1", "rec')
  result = wosac_scoring.score([sub], womd_path, workers=2, progress=False, venv=venv, journal=journal)
  assert result["scenarios"]["s0"]["buckets"]["realism_meta_metric"] == 0.9     # kept, not scored again
  assert sorted(result["scenarios"]) == ["s0", "s1"] and list(result["failed"]) == ["bad"]
  assert wosac_scoring.read_journal(journal, [sub]).keys() == {"s0", "s1"}
  _submission(tmp_path, ["s0", "s1", "bad", "zz", "new"])                      # other bytes: a fresh start
  assert wosac_scoring.read_journal(journal, [sub]) == {}
  result = wosac_scoring.score([sub], womd_path, workers=2, progress=False, venv=venv, journal=journal)
  assert result["scenarios"]["s0"]["buckets"]["realism_meta_metric"] == 0.5


HEADINGS_WORKER = r'''#!/bin/sh
# A stand-in evaluator that says it read the logs' headings in radians, unless --raw-headings.
flag=', "headings_from_degrees": true'
for a in "$@"; do [ "$a" = "--raw-headings" ] && flag=''; done
b='"realism_meta_metric": 0.5, "kinematic_metrics": 0.5, "interactive_metrics": 0.5, "map_based_metrics": 0.5'
for sid in s0 s1; do
  echo "{\"scenario_id\": \"$sid\", \"record\": \"f#0\", \"metrics\": {\"metametric\": 0.5}, \"buckets\": {$b}, \"seconds\": 1.0$flag}"
done
echo '{"done": true, "submitted": ["s0", "s1"]}'
'''


def test_logs_are_scored_with_headings_in_radians_unless_raw_headings(womd_path, tmp_path):
  """A scene the worker read in radians says so in its result; --raw-headings reaches the worker,
  and a journal written one way is not reused the other way."""
  from pcdiff_jax import wosac_scoring
  venv = _fake_evaluator(tmp_path)
  (tmp_path / "fake-venv" / "bin" / "python").write_text(HEADINGS_WORKER)
  sub = _submission(tmp_path, ["s0", "s1"])
  journal = str(tmp_path / "sub.wosac.jsonl")
  read = wosac_scoring.score([sub], womd_path, progress=False, venv=venv, journal=journal)
  assert sorted(read["scenarios"]) == ["s0", "s1"]
  assert all(s["headings_from_degrees"] for s in read["scenarios"].values())
  assert wosac_scoring.read_journal(journal, [sub], raw_headings=True) == {}
  raw = wosac_scoring.score([sub], womd_path, progress=False, venv=venv, journal=journal, raw_headings=True)
  assert sorted(raw["scenarios"]) == ["s0", "s1"]
  assert not any("headings_from_degrees" in s for s in raw["scenarios"].values())


def test_a_killed_worker_is_an_error_that_keeps_the_scored_scenes(womd_path, tmp_path, monkeypatch, capsys):
  from experiments import wosac as cli
  venv = _fake_evaluator(tmp_path)
  script = (tmp_path / "fake-venv" / "bin" / "python")
  script.write_text(FAKE_WORKER.replace("line s1 0.7", "line s1 0.7; kill -9 $$"))
  sub = _submission(tmp_path, ["s0", "s1", "bad", "zz"])
  monkeypatch.setenv("WOSAC_VENV", venv)
  assert cli.main(["--score", sub, "--scenarios", womd_path, "--no-progress", "--workers", "2"]) == 2
  err = capsys.readouterr().err
  assert "killed: out of memory? try fewer --workers" in err and "sub.wosac.jsonl" in err
  assert "Traceback" not in err and not (tmp_path / "sub.wosac.json").exists()
  from pcdiff_jax import wosac_scoring
  assert set(wosac_scoring.read_journal(str(tmp_path / "sub.wosac.jsonl"), [sub])) == {"s0", "s1"}


FAKE_CEILING_WORKER = r'''#!/bin/sh
# A stand-in evaluator whose scored lines carry the scene's ceiling (s1's, an older journal's, none).
ceiling=no
for a in "$@"; do [ "$a" = "--ceiling" ] && ceiling=yes; done
c='"ceiling": {"metametric": 0.8, "kinematic_metrics": 0.6, "interactive_metrics": 0.8, "map_based_metrics": 0.9}'
if [ "$ceiling" = yes ]; then
  echo "{\"scenario_id\": \"s0\", \"record\": \"f#0\", $c}"
  echo '{"scenario_id": "bad", "record": "f#1", "error": "ValueError: boom"}'
else
  b='"buckets": {"realism_meta_metric": 0.5, "kinematic_metrics": 0.4, "interactive_metrics": 0.5, "map_based_metrics": 0.7}'
  echo "{\"scenario_id\": \"s0\", \"record\": \"f#0\", \"metrics\": {}, $b, \"seconds\": 1.0, $c}"
  echo "{\"scenario_id\": \"s1\", \"record\": \"f#1\", \"metrics\": {}, $b, \"seconds\": 1.0}"
fi
echo '{"done": true, "submitted": ["s0", "s1"]}'
'''


def test_the_ceiling_is_reported_beside_a_score_and_on_its_own(womd_path, tmp_path, monkeypatch, capsys):
  """A scored scene's ceiling goes into the aggregate (over the scenes that
  have one), the tables compare the submission with it on those scenes, and
  --ceiling writes it for the scenarios alone."""
  from experiments import wosac as cli
  from pcdiff_jax import wosac_scoring
  venv = _fake_evaluator(tmp_path)
  (tmp_path / "fake-venv" / "bin" / "python").write_text(FAKE_CEILING_WORKER)
  sub = _submission(tmp_path, ["s0", "s1"])
  result = wosac_scoring.score([sub], womd_path, workers=1, progress=False, venv=venv)
  top = result["aggregate"]["ceiling"]
  assert top["num_scenarios"] == 1 and top["metametric"] == pytest.approx(0.8)
  table = wosac_scoring.markdown(result)
  assert "| ceiling | 0.8000 | 0.6000 | 0.8000 | 0.9000 |" in table
  assert "| below the ceiling by | 0.3000 | 0.2000 | 0.3000 | 0.2000 |" in table
  assert "| ceiling (no submission scores above) | 1 | 0.8000 |" in wosac_scoring.compare({"m": result})
  monkeypatch.setenv("WOSAC_VENV", str(tmp_path / "nowhere"))
  assert cli.main(["--ceiling", "--scenarios", womd_path, "--no-progress"]) == 2
  assert "make wosac-env" in capsys.readouterr().err
  monkeypatch.setenv("WOSAC_VENV", venv)
  prefix = str(tmp_path / "out" / "val")
  assert cli.main(["--ceiling", "--scenarios", womd_path, "--score-out", prefix, "--no-progress"]) == 0
  err = capsys.readouterr().err
  assert "scenario bad has no ceiling, skipped" in err and "Traceback" not in err
  saved = json.loads(open(prefix + ".ceiling.json").read())
  assert saved["aggregate"]["metametric"] == pytest.approx(0.8) and list(saved["failed"]) == ["bad"]
  assert "| s0 | 0.8000 | 0.6000 | 0.8000 | 0.9000 |" in open(prefix + ".ceiling.md").read()
  with pytest.raises(SystemExit):
    cli.main(["--ceiling", "--score", sub, "--scenarios", womd_path])


def test_no_histogram_beats_the_logs_own_empirical_frequencies():
  """The ceiling of a time series feature: the mean log-likelihood of each
  agent's binned log values under its own bin frequencies, over the valid
  steps; any other histogram (the evaluator's: counts plus a pseudocount) gives
  less (Gibbs' inequality)."""
  from pcdiff_jax.wosac_worker import empirical_log_likelihood
  bins = np.array([[0, 0, 1, 1, 7], [2, 2, 2, 3, 3]])
  valid = np.array([[1, 1, 1, 1, 0], [1, 1, 1, 1, 1]], bool)
  expected = (4 * np.log(0.5) + 3 * np.log(0.6) + 2 * np.log(0.4)) / 9
  assert empirical_log_likelihood(bins, valid) == pytest.approx(expected)
  assert np.isnan(empirical_log_likelihood(bins, np.zeros_like(valid)))
  rng = np.random.default_rng(0)
  for _ in range(200):
    bins = rng.integers(0, 11, (3, 20))
    valid = rng.random((3, 20)) < 0.8
    counts = rng.integers(0, 40, (3, 11)) + 0.1
    probs = counts / counts.sum(1, keepdims=True)
    other = np.log(np.take_along_axis(probs, bins, 1))[valid].mean()
    assert other <= empirical_log_likelihood(bins, valid) + 1e-12


def test_score_refuses_bad_inputs(womd_path, tmp_path, monkeypatch, capsys):
  from experiments import wosac as cli
  sub = _submission(tmp_path, ["s0"])
  monkeypatch.setenv("WOSAC_VENV", str(tmp_path / "nowhere"))
  assert cli.main(["--score", sub, "--scenarios", womd_path]) == 2
  err = capsys.readouterr().err
  assert "make wosac-env" in err and "Traceback" not in err
  monkeypatch.setenv("WOSAC_VENV", _fake_evaluator(tmp_path))
  (tmp_path / "junk.binproto").write_bytes(b"\xff\xff\xff")
  assert cli.main(["--score", str(tmp_path / "junk.binproto"), "--scenarios", womd_path]) == 2
  assert "junk.binproto: not a SimAgentsChallengeSubmission" in capsys.readouterr().err
  (tmp_path / "junk.tfrecord").write_bytes(b"\x00" * 40)
  assert cli.main(["--score", sub, "--scenarios", str(tmp_path / "junk.tfrecord")]) == 2
  assert "junk.tfrecord" in capsys.readouterr().err
  assert cli.main(["--score", str(tmp_path / "missing.binproto"), "--scenarios", womd_path]) == 2
  assert "missing.binproto" in capsys.readouterr().err


def test_log_replay_copies_the_logged_future(womd_path):
  state, _ = womd.load(womd_path, to_jax=False)
  result = wosac.Simulator(wosac.WosacConfig(eval=wosac.evaluation.EvalConfig(method="log"))).simulate(state, "x")
  now = np.asarray(state.log_trajectory.valid[:, 10])
  assert result.trajectories.shape == (32, int(now.sum()), 80, 4)
  assert np.array_equal(result.trajectories[0], result.trajectories[31])
  log_x = np.asarray(state.log_trajectory.x)[now, 11:]
  future = np.asarray(state.log_trajectory.valid)[now, 11:]
  assert np.array_equal(result.trajectories[0, ..., 0][future], log_x[future])
  with pytest.raises(ValueError, match="log replay has no actor"):
    wosac.make_actor(wosac.WosacConfig(eval=wosac.evaluation.EvalConfig(method="log")))


def test_log_replay_imputes_the_steps_the_log_leaves_invalid():
  """A gap between valid steps is interpolated (yaw the short way round through
  +-pi), the steps after the last valid one coast at its velocity, and an agent
  whose log is complete is copied unchanged: a held box would stand in the lane."""
  poses = np.zeros((2, 7, 4))
  poses[..., 0] = np.arange(7.0)
  poses[..., 1] = 2.0 * np.arange(7.0)
  poses[..., 3] = [3.0, 3.1, -3.1, -3.0, 0.2, 0.2, 0.2]
  valid = np.array([[1, 0, 1, 1, 0, 0, 0], [1] * 7], bool)
  corrupted = poses.copy()
  corrupted[0, 1] = corrupted[0, 4:] = 99.0                     # what an invalid step holds
  out = wosac.impute_log_gaps(corrupted, valid)
  np.testing.assert_allclose(out[0, :, :2], poses[0, :, :2], atol=1e-5)   # straight line, constant speed
  assert abs(abs(out[0, 1, 3]) - 3.1) < 0.2 and abs(out[0, 1, 3]) > 3.0   # through pi, not through 0
  np.testing.assert_allclose(out[0, 4:, 3], -3.0, atol=1e-6)               # yaw held after the log ends
  np.testing.assert_array_equal(out[1], poses[1].astype(np.float32))
  with pytest.raises(ValueError, match="current step"):
    wosac.impute_log_gaps(poses, np.array([[0, 1, 1, 1, 1, 1, 1], [1] * 7], bool))


@pytest.mark.skipif(not os.path.exists(os.path.join(os.path.dirname(__file__), "..", ".wosac-venv", "bin", "python")),
                    reason="Waymo's evaluator is not installed: run `make wosac-env`")
def test_the_official_evaluator_scores_log_replay_on_the_real_record(womd_path, tmp_path, capsys):
  from experiments import wosac as cli
  out = str(tmp_path / "log.binproto")
  assert cli.main(["--scenarios", womd_path, "--method", "log", "--out", out, "--no-progress"]) == 0
  assert cli.main(["--score", out, "--scenarios", womd_path, "--no-progress", "--workers", "1"]) == 0
  result = json.loads((tmp_path / "log.wosac.json").read_text())
  (scene,) = result["scenarios"].values()
  assert scene["metrics"]["min_average_displacement_error"] == pytest.approx(0.0, abs=1e-4)
  assert scene["buckets"]["realism_meta_metric"] == pytest.approx(0.636, abs=2e-3)   # measured once
  from pcdiff_jax import wosac_scoring
  assert set(wosac_scoring.LIKELIHOODS) <= set(scene["metrics"])
  # The ceiling: no likelihood of log replay above it; log replay's imputed boxes meet other agents.
  top = scene["ceiling"]
  assert top["metametric"] == pytest.approx(0.8248, abs=2e-3)   # measured once
  for key in wosac_scoring.LIKELIHOODS:
    assert scene["metrics"][key] <= top[key] + 1e-6, key
  # --kinematic: the same four likelihoods in a second; log replay visits every bin of its own.
  import subprocess
  env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
  run = subprocess.run([wosac_scoring.evaluator_python(), wosac_scoring.WORKER, "--kinematic",
                        "--submission", out, "--scenarios",
                        *wosac_scoring.scenario_files(womd_path, str(tmp_path))],
                       capture_output=True, text=True, env=env, cwd=wosac_scoring.REPO)
  assert run.returncode == 0, run.stderr[-2000:]
  kinematic = json.loads(run.stdout.splitlines()[0])["kinematic"]
  for name in ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration"):
    assert kinematic[f"{name}_likelihood"] == pytest.approx(scene["metrics"][f"{name}_likelihood"], abs=1e-5)
    assert kinematic[f"{name}_unvisited"] == 0.0
  agents = kinematic["agents"]   # per evaluated agent: its valid steps, none of them unvisited
  assert agents and all(sum(a["unvisited"].values()) == 0 and a["steps"]["linear_speed"] > 0 for a in agents)


def test_the_fallback_is_left_out_only_where_it_drives_nobody(tiny_models):
  """A scene whose sim agents the learned actor drives all of rolls out the
  same without the IDM fallback (every actor gets the same key), and with one
  copy of the scene for all rollouts, up to the rounding of a differently
  compiled program."""
  import dataclasses
  from conftest import make_scene
  from pcdiff_jax import evaluation, policy
  from pcdiff_jax.config import get_config
  cfg = get_config("tiny")
  state = make_scene(num_steps=91)
  one_plan = policy.PolicyConfig(ddim_steps=2, select_samples=1, warm_start=False)   # a smaller program
  ev = evaluation.EvalConfig(method="pcdiff", policy=one_plan, num_steps=20, init_steps=11)
  rngs = jax.random.split(jax.random.PRNGKey(3), 2)
  tiled = jax.tree_util.tree_map(lambda a: np.repeat(np.asarray(a)[None], 2, 0), state)
  for max_agents, expect_fallback in ((4, False), (2, True)):
    small = dataclasses.replace(cfg, features=dataclasses.replace(cfg.features, max_agents=max_agents))
    sim = wosac.Simulator.__new__(wosac.Simulator)
    sim.cfg, sim.learned = wosac.WosacConfig(eval=ev), wosac.with_sdc(policy.actor(small, one_plan))
    assert sim.needs_fallback(state) == expect_fallback
    if expect_fallback:
      continue
    runs = {}
    for fallback in (True, False):
      actor, params = wosac.drive_all(policy.actor(small, one_plan), tiny_models, learned=True, fallback=fallback)
      final = evaluation.make_rollout_fn(actor, ev)(tiled, rngs, params)
      runs[fallback] = np.asarray(final.sim_trajectory.x)
    assert np.allclose(runs[True], runs[False], atol=1e-3)   # two compiled programs: float rounding
    # The scene shared by the rollouts of a call (the export's default) instead of a copy each.
    shared = evaluation.make_rollout_fn(actor, ev, one_scene=True)(state, rngs, params)
    assert np.allclose(np.asarray(shared.sim_trajectory.x), runs[False], atol=1e-3)


def _simulate_stopping_at(number: int, calls: list):
  """`Simulator.simulate` that records each scenario id in `calls` and raises
  KeyboardInterrupt (Ctrl-C) at call `number` (0: never)."""
  simulate = wosac.Simulator.simulate

  def run(self, state, scenario_id):
    calls.append(scenario_id)
    if len(calls) == number:
      raise KeyboardInterrupt
    return simulate(self, state, scenario_id)
  return run


def test_a_stopped_or_killed_export_goes_on_from_what_it_wrote(womd_path, tmp_path, monkeypatch, capsys):
  """Ctrl-C or SIGTERM (`timeout`, a batch system) after the first scenario: exit 130, no final
  file, and the finished scenario in a valid `.partial`. The same command after a stop or a kill
  (a `.tmp` whose last record is cut short) simulates only the scenarios left and writes the
  file one uninterrupted run writes; other settings are refused (exit 2) until --overwrite
  starts afresh; an interrupt in the first scenario goes on and leaves no file behind."""
  from experiments import wosac as cli
  state, _ = womd.load(womd_path, to_jax=False)
  scenarios = str(tmp_path / "scenario.tfrecord")
  womd.write(scenarios, [(state, f"scene-{i}") for i in range(3)], record_format="scenario")
  common = ["--scenarios", scenarios, "--method", "cv", "--num-rollouts", "2", "--no-progress"]
  whole, out = str(tmp_path / "whole.binproto"), str(tmp_path / "sub.binproto")
  assert cli.main(common + ["--out", whole]) == 0
  calls = []
  with monkeypatch.context() as m:
    m.setattr(wosac.Simulator, "simulate", _simulate_stopping_at(2, calls))
    assert cli.main(common + ["--out", out]) == 130
  assert "interrupted after 1 scenarios" in capsys.readouterr().err
  assert not os.path.exists(out) and not os.path.exists(out + ".tmp")
  sub = submission.read(out + ".partial")
  assert [r.scenario_id for r in sub.scenario_rollouts] == ["scene-0"] and sub.unique_method_name == "pcdiff_jax-cv"
  settings = open(wosac.run_record_path(out)).read()
  assert cli.main(common + ["--out", out, "--seed", "1"]) == 2
  assert "other settings (config differ)" in capsys.readouterr().err
  calls[:] = []
  with monkeypatch.context() as m:
    m.setattr(wosac.Simulator, "simulate", _simulate_stopping_at(0, calls))
    assert cli.main(common + ["--out", out]) == 0
  assert calls == ["scene-1", "scene-2"] and '"resumed_scenarios": 1' in capsys.readouterr().out
  assert (tmp_path / "sub.binproto").read_bytes() == (tmp_path / "whole.binproto").read_bytes()
  # Killed while the third scenario was written: its record is cut short and simulated again.
  records = list(submission.iter_scenario_records(whole))
  torn = b"".join(submission._field_bytes(1, r) for r in records[:2]) + submission._field_bytes(1, records[2])[:999]
  os.remove(out)
  (tmp_path / "sub.binproto.run.json").write_text(settings)   # as the killed run left it
  (tmp_path / "sub.binproto.tmp").write_bytes(torn)
  assert submission.count_scenarios(out + ".tmp") == 2
  calls[:] = []
  with monkeypatch.context() as m:
    m.setattr(wosac.Simulator, "simulate", _simulate_stopping_at(0, calls))
    assert cli.main(common + ["--out", out]) == 0 and calls == ["scene-2"]
  assert (tmp_path / "sub.binproto").read_bytes() == (tmp_path / "whole.binproto").read_bytes()
  assert sorted(os.listdir(tmp_path)) == ["scenario.tfrecord", "sub.binproto", "whole.binproto"]
  # Another export's leftovers: refused, then --overwrite starts afresh (stopped in its first scenario).
  (tmp_path / "sub.binproto.run.json").write_text(settings.replace("cv", "idm"))
  (tmp_path / "sub.binproto.tmp").write_bytes(torn)
  os.remove(out)
  assert cli.main(common + ["--out", out]) == 2
  calls[:] = []
  with monkeypatch.context() as m, pytest.raises(KeyboardInterrupt):
    m.setattr(wosac.Simulator, "simulate", _simulate_stopping_at(1, calls))
    cli.main(common + ["--out", out, "--overwrite"])
  assert sorted(os.listdir(tmp_path)) == ["scenario.tfrecord", "whole.binproto"]


def test_scenario_records_are_read_from_whole_files_and_cut_streams(tmp_path):
  path = str(tmp_path / "sub.binproto")
  traj = np.zeros((2, 1, 80, 4), np.float32)
  with submission.SubmissionWriter(path, submission.Metadata(unique_method_name="m")) as writer:
    for sid in ("a", "b"):
      writer.add(submission.scenario_rollouts(sid, [5], traj))
  raw = open(path, "rb").read()
  assert [pb.ScenarioRollouts.FromString(r).scenario_id for r in submission.iter_scenario_records(path)] == ["a", "b"]
  for cut, count in ((len(raw), 2), (len(raw) // 2 + 100, 1), (1, 0)):
    (tmp_path / "cut").write_bytes(raw[:cut])
    assert submission.count_scenarios(str(tmp_path / "cut")) == count
  assert submission.count_scenarios(str(tmp_path / "none")) == 0
  (tmp_path / "bad").write_bytes(b"\x0f\x00")
  with pytest.raises(ValueError, match="bad: not a SimAgentsChallengeSubmission stream"):
    submission.count_scenarios(str(tmp_path / "bad"))


def test_parts_merge_in_the_inputs_scenario_order(tmp_path):
  """Part j of n holds scenarios j, j + n, ...; the merged file lists them as the input did,
  with the parts' metadata, and an empty part (more jobs than scenarios) is allowed."""
  path = str(tmp_path / "sub.binproto")
  meta = submission.Metadata(account_name="me@example.com", unique_method_name="m", num_model_parameters="7")
  traj = np.zeros((2, 1, 80, 4), np.float32)
  for j, ids in enumerate([["s0", "s3"], ["s1"], ["s2"], []]):
    with submission.SubmissionWriter(wosac.part_path(path, j, 4), meta) as writer:
      for sid in ids:
        writer.add(submission.scenario_rollouts(sid, [5], traj))
  count, head = wosac.merge_parts(path, 4)
  sub = submission.read(path)
  assert count == 4 and [r.scenario_id for r in sub.scenario_rollouts] == ["s0", "s1", "s2", "s3"]
  assert sub.account_name == head.account_name == "me@example.com" and sub.num_model_parameters == "7"
  assert sorted(os.listdir(tmp_path)) == ["sub.binproto"]


@pytest.mark.slow
def test_jobs_write_the_file_one_process_writes(womd_path, tmp_path):
  """--jobs 2: two processes, each on its share of the cores, export every other scenario and
  the parts are merged: the same bytes as one process (cv is deterministic), nothing left over;
  --out may name a folder that does not exist yet."""
  from experiments import wosac as cli
  state, _ = womd.load(womd_path, to_jax=False)
  scenarios = str(tmp_path / "scenario.tfrecord")
  womd.write(scenarios, [(state, f"scene-{i}") for i in range(3)], record_format="scenario")
  common = ["--scenarios", scenarios, "--method", "cv", "--num-rollouts", "2", "--no-progress"]
  assert cli.main(common + ["--out", str(tmp_path / "one.binproto")]) == 0
  assert cli.main(common + ["--out", str(tmp_path / "new" / "two.binproto"), "--jobs", "2"]) == 0
  assert (tmp_path / "one.binproto").read_bytes() == (tmp_path / "new" / "two.binproto").read_bytes()
  assert sorted(os.listdir(tmp_path)) == ["new", "one.binproto", "scenario.tfrecord"]
  assert os.listdir(tmp_path / "new") == ["two.binproto"]


def test_plan_cap_is_the_first_bucket_that_holds_the_scene():
  assert [wosac.plan_cap(n, 64) for n in (0, 3, 15, 16, 31, 32, 63, 64, 200)] == [15, 15, 15, 31, 31, 63, 63, 64, 64]
  assert wosac.plan_cap(20, 24) == 24 and wosac.plan_cap(3, 8) == 8


def test_rollouts_per_call_default_to_one_wide_batch_on_an_accelerator_and_four_on_a_cpu():
  assert wosac.default_rollouts_per_call(32, "gpu") == 32
  assert wosac.default_rollouts_per_call(32, "cpu") == wosac.CPU_ROLLOUTS_PER_CALL == 4
  assert wosac.default_rollouts_per_call(2, "cpu") == 2
  with pytest.raises(ValueError, match="rollouts_per_call"):
    wosac.WosacConfig(rollouts_per_call=0).validate()


def test_more_plan_slots_leave_the_valid_agents_plans_as_they_are(tiny_models):
  """What sizing the plan to the scene rests on: the same scene (4 agents) in 4
  or 8 agent slots gives its agents the same prior and denoiser output (the
  padded slots' latents are junk), so a smaller plan changes only the random draws."""
  import dataclasses
  import functools
  import jax.numpy as jnp
  from conftest import make_scene
  from pcdiff_jax.config import get_config
  from pcdiff_jax.model import denoiser as denoiser_lib
  from pcdiff_jax.model import features as features_lib
  from pcdiff_jax.model import planner
  from pcdiff_jax.sim import env
  start = env.reset(make_scene(num_steps=91), init_steps=11)

  @functools.partial(jax.jit, static_argnums=2)
  def denoised(state, y, cfg):
    feats = jax.tree_util.tree_map(lambda a: a[None], features_lib.scene_features(state, cfg.features))
    cond = planner.condition(tiny_models.encoder, tiny_models.stats, feats, cfg)
    out = denoiser_lib.apply(tiny_models.denoiser, y[None], jnp.int32(40), cond.inputs, cfg.diffusion.denoiser)
    return feats.agent_valid[0], cond.mu[0], out[0]

  tiny = get_config("tiny")
  d = tiny.diffusion.latent_dim
  agents_y = jax.random.normal(jax.random.PRNGKey(1), (4, d))
  outs = {}
  for slots in (4, 8):
    cfg = dataclasses.replace(tiny, features=dataclasses.replace(tiny.features, max_agents=slots))
    junk = 40.0 * jax.random.normal(jax.random.PRNGKey(0), (slots - 4, d))
    outs[slots] = denoised(start, jnp.concatenate([agents_y, junk]), cfg)
  (valid4, mu4, out4), (valid8, mu8, out8) = outs[4], outs[8]
  assert bool(valid4.all()) and bool(valid8[:4].all()) and not bool(valid8[4:].any())
  np.testing.assert_allclose(np.asarray(mu8)[:4], np.asarray(mu4), atol=1e-4)
  np.testing.assert_allclose(np.asarray(out8)[:4], np.asarray(out4), atol=1e-4)


def test_a_learned_method_plans_each_scene_in_the_slots_it_needs(tiny_models, monkeypatch):
  """make_scene's 4 sim agents (the SDC among them): 16 slots and no IDM
  fallback under size_plans; the cap's own slots without it; a cap below the
  scene keeps the fallback."""
  from conftest import make_scene
  from pcdiff_jax import evaluation, policy
  from pcdiff_jax.config import MetricsConfig, get_config

  def tiny_actor(ev):
    return policy.actor(evaluation.with_agent_cap(get_config("tiny"), ev.metrics), ev.policy), tiny_models
  monkeypatch.setattr(wosac.evaluation, "make_actor", tiny_actor)
  state = wosac.hold_current_lights(make_scene(num_steps=91))
  for cap, size_plans, expect_cap, expect_fallback in ((64, True, 15, False), (64, False, 64, False),
                                                       (2, True, 2, True)):
    ev = evaluation.EvalConfig(method="pcdiff", checkpoint="unused", num_steps=80, init_steps=11,
                               metrics=MetricsConfig(max_reactive_agents=cap))
    sim = wosac.Simulator(wosac.WosacConfig(eval=ev, size_plans=size_plans))
    run, params, chosen = sim.learned_run(state)
    runs = sim._runs_at(chosen)
    assert chosen == expect_cap and (run is runs.run) == expect_fallback and (run is runs.run_alone) != expect_fallback
    assert params is (runs.params if expect_fallback else runs.params_alone)


def test_the_simulator_tells_the_scenes_that_compiled_a_program():
  """The export's steady per-scene figure leaves out the scenes that compiled:
  the first of each (closed loop, object bucket) pair; log replay compiles nothing."""
  from conftest import make_scene
  state = make_scene(num_steps=91)
  ev = wosac.evaluation.EvalConfig(method="cv", num_steps=80, init_steps=11)
  sim = wosac.Simulator(wosac.WosacConfig(eval=ev, num_rollouts=2))
  sim.simulate(state, "a")
  assert sim.compiled_last
  sim.simulate(state, "b")
  assert not sim.compiled_last
  log = wosac.Simulator(wosac.WosacConfig(eval=wosac.evaluation.EvalConfig(method="log")))
  log.simulate(state, "a")
  assert not log.compiled_last
