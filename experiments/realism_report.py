"""Realism report: generated scenes next to the real WOMD sample.

Motion statistics (speed, longitudinal / lateral acceleration, jerk, yaw
rate) of vehicles, agents per scene, object and scene types, and the logs'
collision and off-road rates measured with the project's metrics (the
log-replay numbers of `experiments.rollout --method log`).
"""
from __future__ import annotations

import dataclasses
import glob
import json
import os
from typing import Optional

import numpy as np

from pcdiff_jax.data import realism, womd


def dataset_files(data_dir: str, split: Optional[str] = None) -> list[str]:
  splits = [split] if split else ["val", "train"]
  for s in splits:
    files = sorted(glob.glob(os.path.join(data_dir, f"{s}-*-of-*.tfrecord")))
    if files:
      return files
  raise FileNotFoundError(f"no {' or '.join(splits)} shards (*-XXXXX-of-YYYYY.tfrecord) in {data_dir}")


def _read(paths, limit: int, max_num_objects: Optional[int] = 128) -> tuple[list, list[str]]:
  states, ids = [], []
  for state, meta in womd.iterate(paths, max_num_objects=max_num_objects, with_meta=True, to_jax=False,
                                  on_error="skip"):
    states.append(state)
    ids.append(meta.scenario_id)
    if len(states) >= limit:
      break
  return states, ids


def log_event_rates(states: list, batch_size: int = 8) -> dict:
  """Collision / off-road rates of the logs themselves (log replay), project metrics."""
  import jax
  import jax.numpy as jnp
  from pcdiff_jax import evaluation
  from pcdiff_jax.sim import metrics
  cfg = evaluation.EvalConfig(method="log")
  actor, params = evaluation.make_actor(cfg)
  rollout, score = evaluation.make_rollout_fn(actor, cfg), evaluation.make_score_fn(cfg)
  totals = None
  for k in range(0, len(states), batch_size):
    chunk = states[k:k + batch_size]
    chunk = chunk + [chunk[-1]] * (batch_size - len(chunk))   # one padded size, one compile
    batch = jax.tree_util.tree_map(lambda *xs: jnp.asarray(np.stack(xs)), *chunk)
    n = min(batch_size, len(states) - k)
    final = rollout(batch, jax.random.split(jax.random.PRNGKey(0), batch_size), params)
    counts = jax.tree_util.tree_map(lambda a: np.asarray(a)[:n], score(final).events)
    totals = counts if totals is None else jax.tree_util.tree_map(lambda a, b: np.concatenate([a, b]), totals, counts)
  rates = metrics.EventCounts(**{k: jnp.asarray(v) for k, v in dataclasses.asdict(totals).items()}).rates()
  return {k: float(v) for k, v in rates.items()}


def scene_types(ids: list[str]) -> dict[str, int]:
  out: dict[str, int] = {}
  for sid in ids:
    family = sid.split("-")[1] if sid.startswith("syn-") else "womd"
    out[family] = out.get(family, 0) + 1
  return dict(sorted(out.items()))


def write_report(data_dir: str, real_path: Optional[str], out_dir: Optional[str] = None,
                 num_scenes: int = 200, num_metric_scenes: int = 48, grid: int = 8) -> dict:
  """Writes realism.{json,md}, realism_hist.png and examples.png; returns the JSON dict."""
  out_dir = out_dir or data_dir
  os.makedirs(out_dir, exist_ok=True)
  files = dataset_files(data_dir)
  states, ids = _read(files, num_scenes)
  if not states:
    raise RuntimeError(f"no readable scene in {files}")
  summaries = {"synthetic": realism.summarize(states)}
  real_states = []
  if real_path and os.path.exists(real_path):
    real_states, _ = _read(real_path, 10**9, max_num_objects=None)   # real scenes of any size
    summaries["real WOMD sample"] = realism.summarize(real_states)
  report = {
      "data_dir": data_dir, "files": files, "num_scenes": len(states), "scene_types": scene_types(ids),
      "summaries": summaries,
      "log_rates": {"synthetic": log_event_rates(states[:num_metric_scenes]),
                    "num_scenes": min(num_metric_scenes, len(states))},
  }
  if real_states:
    report["log_rates"]["real WOMD sample"] = log_event_rates(real_states, batch_size=1)
  stats_path = os.path.join(data_dir, "stats.json")
  if os.path.exists(stats_path):
    with open(stats_path) as f:
      report["generation"] = json.load(f)
  with open(os.path.join(out_dir, "realism.json"), "w") as f:
    json.dump(report, f, indent=2, allow_nan=False)
  realism.plot_histograms(summaries, os.path.join(out_dir, "realism_hist.png"))
  from pcdiff_jax import viz
  picks = _diverse(ids, grid)
  viz.render_grid_png([states[i] for i in picks], os.path.join(out_dir, "examples.png"),
                      titles=[ids[i] for i in picks], timestep=womd.NUM_PAST, trajectory="log")
  with open(os.path.join(out_dir, "realism.md"), "w") as f:
    f.write(markdown(report))
  return report


def _diverse(ids: list[str], n: int) -> list[int]:
  """Up to n scene indices, round-robin over scene types."""
  by_type: dict[str, list[int]] = {}
  for i, sid in enumerate(ids):
    by_type.setdefault(sid.split("-")[1] if sid.startswith("syn-") else "womd", []).append(i)
  out: list[int] = []
  while len(out) < min(n, len(ids)):
    for group in by_type.values():
      if group and len(out) < n:
        out.append(group.pop(0))
  return out


def markdown(report: dict) -> str:
  lines = [f"# Realism report: {report['data_dir']}", "",
           f"{report['num_scenes']} synthetic scenes; vehicles only in the motion table "
           "(backward differences of the logged velocities / yaw at 10 Hz).", "",
           realism.compare_markdown(report["summaries"]), "",
           "## Scene types", "", "| type | scenes |", "|---|---|"]
  lines += [f"| {k} | {v} |" for k, v in report["scene_types"].items()]
  lines += ["", f"## Log collision / off-road (project metrics, log replay, "
                f"{report['log_rates']['num_scenes']} synthetic scenes)", ""]
  names = [k for k in report["log_rates"] if k != "num_scenes"]
  keys = list(report["log_rates"][names[0]])
  lines += ["| rate | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
  lines += [f"| {k} | " + " | ".join(f"{report['log_rates'][n][k]:.4f}" for n in names) + " |" for k in keys]
  lines += ["", "Figures: `realism_hist.png` (histograms), `examples.png` (scenes at the current step).", ""]
  return "\n".join(lines)
