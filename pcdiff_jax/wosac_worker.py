"""Scores sim agents submissions with Waymo's official evaluator (2025 config).

Runs inside the evaluator's own venv (`make wosac-env`: Python 3.10,
`waymo-open-dataset-tf-2-12-0`), started by `pcdiff_jax.wosac_scoring` as a
script, never imported by pcdiff_jax: it imports only that venv's packages.

  .wosac-venv/bin/python pcdiff_jax/wosac_worker.py --submission S... \
      --scenarios F... [--index K --count N]

Reads every Scenario proto of --scenarios (full logs) and every rollout of
--submission, scores the scenarios whose position in the files is K modulo N,
and prints one JSON line per scenario on stdout: {"scenario_id", "record",
"metrics": {field: value}, "buckets": {...}, "seconds"}, {"scenario_id",
"error"} when scoring raised, or {"scenario_id", "missing": true} when the
submission holds no rollouts for it. A final {"done": true, "submitted": [ids]}
lists every scenario id of the submission.

--kinematic scores only the four kinematic likelihoods (a second per scene
instead of minutes), with Waymo's own features and estimator, and beside each
the share of the log's steps whose bin no rollout visits ("unvisited": each
such step costs log(0.1 / (rollouts x steps))), and per evaluated agent its valid and unvisited
steps of each (which agents the rollouts never reproduce): {"scenario_id", "record",
"kinematic": {..., "agents": [{"object_id", "steps", "unvisited"}]}, "seconds"}.

Every scored line also holds "ceiling": the most any submission can score on
that scene (`ceiling_likelihoods`); --ceiling computes only that, from the
logs alone (no --submission; seconds per scene).
"""
import argparse
import json
import os
import sys
import time
import traceback

os.environ.setdefault("TF_CPP_MIN_LOG_LEVEL", "2")
CONFIG = "challenge_2025_sim_agents_config.textproto"


def _metrics_dict(message) -> dict:
  """Every scalar field of a metrics proto, by name (fields left unset read 0)."""
  return {f.name: float(getattr(message, f.name)) for f in message.DESCRIPTOR.fields
          if f.type in (f.TYPE_FLOAT, f.TYPE_DOUBLE)}


def load_config(metrics):
  """The 2025 challenge config (`load_metrics_config(SIM_AGENTS)` opens it by a
  path relative to site-packages, so it only works from there: same file, by
  its absolute path)."""
  from google.protobuf import text_format
  from waymo_open_dataset.protos import sim_agents_metrics_pb2
  path = os.path.join(os.path.dirname(metrics.__file__), CONFIG)
  with open(path) as f:
    return text_format.Parse(f.read(), sim_agents_metrics_pb2.SimAgentMetricsConfig())


HEADING_TOLERANCE = 1e-3


def headings_in_radians(scenario) -> bool:
  """Our reader's heading rule (`pcdiff_jax.data.scenario_proto.headings_in_degrees`),
  repeated here because this script imports only the evaluator's packages
  (tests/test_scenario_proto.py checks that the two agree): a Scenario whose box headings are
  in degrees (any beyond pi) gets them in radians, in place, so the evaluator scores against
  the log our reader gives the simulator. True when it changed them."""
  import math
  states = [s for track in scenario.tracks for s in track.states if s.valid]
  if not any(abs(s.heading) > math.pi + HEADING_TOLERANCE for s in states):
    return False
  for s in states:
    s.heading = (math.radians(s.heading) + math.pi) % (2 * math.pi) - math.pi
  return True


KINEMATIC = ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration")


def empirical_log_likelihood(bins, valid) -> float:
  """The largest mean log-likelihood any histogram estimate can give the log's
  own binned values: `bins` (A, T) int, each valid log step's bin; `valid` (A,
  T) bool, the steps the evaluator averages over. WOSAC pools each agent's
  rollouts over time (`independent_timesteps`) and averages log p_a(bin) over
  every valid (agent, step), so by Gibbs' inequality no distribution p_a beats
  the agent's own empirical bin frequencies q_a: the bound is the mean of
  log q_a(bin), each agent's negative entropy weighted by its valid steps.
  numpy only; NaN when no step is valid."""
  import numpy as np
  bins, valid = np.asarray(bins), np.asarray(valid, bool)
  total, count = 0.0, 0
  for row, keep in zip(bins, valid):
    if keep.any():
      _, counts = np.unique(row[keep], return_counts=True)
      total += float(np.sum(counts * np.log(counts / keep.sum())))
      count += int(keep.sum())
  return total / count if count else float("nan")


# The metametric's features (Waymo's `metrics._METRIC_FIELD_NAMES_BY_BUCKET`, 2025 config).
BUCKETS = {"kinematic": ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration"),
           "interactive": ("distance_to_nearest_object", "collision_indication", "time_to_collision"),
           "map_based": ("distance_to_road_edge", "offroad_indication", "traffic_light_violation")}
BERNOULLI = ("collision_indication", "offroad_indication", "traffic_light_violation")


def ceiling_likelihoods(config, log_features, num_rollouts: int = 32) -> dict:
  """The most each likelihood, bucket and the metametric can be on this scene
  for any submission of `num_rollouts` rollouts (the evaluator's features of the
  log, `log_features`): a time series feature at most its log's own empirical
  bin frequencies (`empirical_log_likelihood`, with the very masks the
  evaluator averages over), an indicator at most (R + a) / (R + 2a), all R
  rollouts agreeing with the log (a: the pseudocount). The metametric is
  linear in the likelihoods, so its bound is their weighted sum. Log replay
  comes near it (docs/WOSAC.md, "The ceiling")."""
  import numpy as np
  import tensorflow as tf
  import tensorflow_probability as tfp
  from waymo_open_dataset.protos import scenario_pb2
  from waymo_open_dataset.wdl_limited.sim_agents_metrics import trajectory_features
  valid = log_features.valid[0]
  speed_valid, accel_valid = trajectory_features.compute_kinematic_validity(valid)
  is_vehicle = tf.equal(log_features.object_type, scenario_pb2.Track.ObjectType.TYPE_VEHICLE)[0]
  vehicle = tf.logical_and(valid, is_vehicle[:, tf.newaxis])
  masks = {"linear_speed": speed_valid, "angular_speed": speed_valid, "linear_acceleration": accel_valid,
           "angular_acceleration": accel_valid, "distance_to_nearest_object": valid,
           "time_to_collision": vehicle, "distance_to_road_edge": valid}
  out = {}
  for name, mask in masks.items():
    hist = getattr(config, name).histogram
    values = getattr(log_features, name)[0]
    edges = np.linspace(hist.min_val, hist.max_val, hist.num_bins + 1).astype(np.float32)
    # The evaluator's own binning (`estimators.histogram_estimate`): clip, then tfp's bins.
    flat = tf.reshape(tf.clip_by_value(values, hist.min_val, hist.max_val), (-1, 1))
    bins = tf.argmax(tf.transpose(tfp.stats.histogram(flat, edges, axis=1)), axis=1)
    bins = tf.reshape(bins, values.shape).numpy()
    out[f"{name}_likelihood"] = float(np.exp(empirical_log_likelihood(bins, mask.numpy())))
  for name in BERNOULLI:
    a = getattr(config, name).bernoulli.additive_smoothing_pseudocount
    out[f"{name}_likelihood"] = float((num_rollouts + a) / (num_rollouts + 2 * a))
  weights = {name: getattr(config, name).metametric_weight for names in BUCKETS.values() for name in names}
  out["metametric"] = float(sum(w * out[f"{name}_likelihood"] for name, w in weights.items()))
  for bucket, names in BUCKETS.items():
    out[f"{bucket}_metrics"] = float(sum(weights[n] * out[f"{n}_likelihood"] for n in names)
                                     / sum(weights[n] for n in names))
  return out


def kinematic_likelihoods(config, scenario, scenario_rollouts) -> dict:
  """The kinematic likelihoods of `metrics.compute_scenario_metrics_for_bundle` (same
  features, estimator and validity) and each one's share of unvisited log steps."""
  import numpy as np
  import tensorflow as tf
  from waymo_open_dataset.utils import trajectory_utils
  from waymo_open_dataset.utils.sim_agents import converters, submission_specs
  from waymo_open_dataset.wdl_limited.sim_agents_metrics import estimators, trajectory_features
  spec = submission_specs.get_submission_config(submission_specs.ChallengeType.SIM_AGENTS)
  ids = tf.convert_to_tensor(submission_specs.get_evaluation_sim_agent_ids(
      scenario, submission_specs.ChallengeType.SIM_AGENTS))
  future = slice(spec.current_time_index + 1, None)

  def features(trajectories):
    t = trajectories.gather_objects_by_id(ids)
    return [f[:, future] for f in trajectory_features.compute_kinematic_features(
        t.x, t.y, t.z, t.heading, seconds_per_step=spec.step_duration_seconds)]

  logged = trajectory_utils.ObjectTrajectories.from_scenario(scenario)
  log = features(logged)
  sims = [features(converters.joint_scene_to_trajectories(joint, scenario))
          for joint in scenario_rollouts.joint_scenes]
  speed_valid, accel_valid = trajectory_features.compute_kinematic_validity(
      logged.gather_objects_by_id(ids).valid[:, future])
  out = {}
  agents = [{"object_id": int(i), "steps": {}, "unvisited": {}} for i in ids.numpy()]
  for k, name in enumerate(KINEMATIC):
    feature = getattr(config, name)
    sim = tf.stack([s[k] for s in sims])                                   # (rollouts, objects, steps)
    ll = estimators.log_likelihood_estimate_timeseries(feature, log[k], sim).numpy()
    valid = (speed_valid if k % 2 == 0 else accel_valid).numpy()
    floor = np.log(feature.histogram.additive_smoothing_pseudocount
                   / (sim.shape[0] * sim.shape[2] + feature.histogram.additive_smoothing_pseudocount
                      * feature.histogram.num_bins))
    unvisited = valid & (ll < floor + 1e-3)                                # (objects, steps)
    out[f"{name}_likelihood"] = float(np.exp(ll[valid].mean())) if valid.any() else float("nan")
    out[f"{name}_unvisited"] = float(unvisited.sum() / valid.sum()) if valid.any() else float("nan")
    for a, row in enumerate(agents):
      row["steps"][name], row["unvisited"][name] = int(valid[a].sum()), int(unvisited[a].sum())
  out["agents"] = agents
  return out


def main(argv=None) -> int:
  p = argparse.ArgumentParser()
  p.add_argument("--submission", nargs="+", default=[])
  p.add_argument("--scenarios", nargs="+", required=True)
  p.add_argument("--index", type=int, default=0)
  p.add_argument("--count", type=int, default=1)
  p.add_argument("--skip", default=None, help="a file of scenario ids already scored (one per line)")
  p.add_argument("--kinematic", action="store_true", help="the kinematic likelihoods only (fast)")
  p.add_argument("--ceiling", action="store_true", help="only the most any submission can score (no --submission)")
  p.add_argument("--raw-headings", action="store_true",
                 help="score against the headings as stored, even in degrees (headings_in_radians)")
  args = p.parse_args(argv)
  if not args.submission and not args.ceiling:
    p.error("--submission is required (unless --ceiling)")
  skip = set(open(args.skip).read().split()) if args.skip else set()

  import tensorflow as tf
  tf.config.threading.set_inter_op_parallelism_threads(1)
  from waymo_open_dataset.protos import scenario_pb2, sim_agents_submission_pb2
  from waymo_open_dataset.utils.sim_agents import converters
  from waymo_open_dataset.utils.sim_agents import submission_specs
  from waymo_open_dataset.wdl_limited.sim_agents_metrics import metric_features, metrics
  challenge = submission_specs.ChallengeType.SIM_AGENTS

  config = load_config(metrics)
  rollouts = {}
  for path in args.submission:
    with open(path, "rb") as f:
      sub = sim_agents_submission_pb2.SimAgentsChallengeSubmission.FromString(f.read())
    for r in sub.scenario_rollouts:
      rollouts[r.scenario_id] = r
  position = 0
  for path in args.scenarios:
    for record, raw in enumerate(tf.data.TFRecordDataset(path).as_numpy_iterator()):
      position += 1
      if (position - 1) % args.count != args.index:
        continue
      scenario = scenario_pb2.Scenario.FromString(raw)
      sid = scenario.scenario_id
      if sid in skip:
        continue
      where = f"{path}#{record}"
      if sid not in rollouts and not args.ceiling:
        print(json.dumps({"scenario_id": sid, "record": where, "missing": True}), flush=True)
        continue
      t0 = time.perf_counter()
      converted = False if args.raw_headings else headings_in_radians(scenario)
      try:
        if args.ceiling:
          log_features = metric_features.compute_metric_features(
              scenario, converters.scenario_to_joint_scene(scenario, challenge), challenge, use_log_validity=True)
          line = {"ceiling": ceiling_likelihoods(config, log_features)}
        elif args.kinematic:
          line = {"kinematic": kinematic_likelihoods(config, scenario, rollouts[sid])}
        else:
          # `metrics.compute_scenario_metrics_for_bundle` in its two steps, to keep the log's features.
          log_features, sim_features = metric_features.compute_scenario_rollouts_features(
              scenario, rollouts[sid], challenge)
          result = metrics.compute_scenario_metrics_for_features_bundle(
              config, scenario.scenario_id, log_features, sim_features)
          buckets = metrics.aggregate_metrics_to_buckets(config, result)
          line = {"metrics": _metrics_dict(result), "buckets": _metrics_dict(buckets),
                  "ceiling": ceiling_likelihoods(config, log_features, len(rollouts[sid].joint_scenes))}
        line = {"scenario_id": sid, "record": where, **line, "seconds": time.perf_counter() - t0,
                **({"headings_from_degrees": True} if converted else {})}
      except Exception as err:  # one bad scene is reported and skipped, the others still count
        line = {"scenario_id": sid, "record": where,
                "error": f"{type(err).__name__}: {err}".strip()[:2000],
                "traceback": traceback.format_exc()[-2000:]}
      print(json.dumps(line), flush=True)
  print(json.dumps({"done": True, "submitted": sorted(rollouts)}), flush=True)
  return 0


if __name__ == "__main__":
  sys.exit(main())
