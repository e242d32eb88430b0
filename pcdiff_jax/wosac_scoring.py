"""Waymo's official sim agents metrics on a submission, from our own venv.

  result = wosac_scoring.score(["sub.binproto"], "val.scenario.tfrecord", workers=2)
  wosac_scoring.write_results(result, "runs/wosac/sub")   # sub.wosac.json, sub.wosac.md

The evaluator (`waymo-open-dataset-tf-2-12-0`, Python 3.10, TensorFlow 2.12)
cannot share our environment, so it lives in its own venv (`make wosac-env`,
`.wosac-venv/`) and runs `pcdiff_jax/wosac_worker.py` there, one subprocess per
worker, each scoring every N-th scenario on the scenarios' full logs; this
module checks the inputs, converts tf.Example records to Scenario protos (the
evaluator reads only those), collects the workers' JSON lines and aggregates
them. The aggregate is the mean over the scored scenarios, as Waymo's
`aggregate_scenario_metrics`; the buckets (kinematic, interactive, map-based)
are weighted means of the likelihoods, linear in them, so the mean of the
per-scenario buckets equals the buckets of the mean.
"""
from __future__ import annotations

import json
import os
import queue
import subprocess
import sys
import tempfile
import threading
from typing import Optional, Sequence

import numpy as np

from pcdiff_jax.data import submission, womd

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
WORKER = os.path.join(REPO, "pcdiff_jax", "wosac_worker.py")
DEFAULT_VENV = os.path.join(REPO, ".wosac-venv")
TCMALLOC = "/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4"

# Columns of the tables: (key in a scenario's "buckets" or "metrics", header).
HEADLINE = (("realism_meta_metric", "metametric"), ("kinematic_metrics", "kinematic"),
            ("interactive_metrics", "interactive"), ("map_based_metrics", "map-based"),
            ("min_ade", "minADE m"), ("simulated_collision_rate", "sim. collision"),
            ("simulated_offroad_rate", "sim. off-road"),
            ("simulated_traffic_light_violation_rate", "sim. light violation"))
LIKELIHOODS = ("linear_speed_likelihood", "linear_acceleration_likelihood", "angular_speed_likelihood",
               "angular_acceleration_likelihood", "distance_to_nearest_object_likelihood",
               "collision_indication_likelihood", "time_to_collision_likelihood",
               "distance_to_road_edge_likelihood", "offroad_indication_likelihood",
               "traffic_light_violation_likelihood")


class EvaluatorMissing(RuntimeError):
  """The evaluator's venv is not there (`make wosac-env` builds it)."""


def evaluator_python(venv: Optional[str] = None) -> str:
  """The evaluator venv's interpreter (`venv`, $WOSAC_VENV or .wosac-venv)."""
  venv = venv or os.environ.get("WOSAC_VENV") or DEFAULT_VENV
  python = os.path.join(venv, "bin", "python")
  if not os.path.exists(python):
    raise EvaluatorMissing(f"Waymo's evaluator is not installed ({python} not found): run `make wosac-env` "
                           "(or point WOSAC_VENV at a venv holding waymo-open-dataset-tf-2-12-0==1.6.7)")
  return python


def read_submissions(paths: Sequence[str]) -> dict[str, str]:
  """{scenario id: file} of the submission file(s) (globs allowed); a file
  that is missing or not a submission, or a scenario in two files, is a
  ValueError naming the file(s)."""
  files = []
  for p in paths:
    files += womd.expand_paths(p)
  where: dict[str, str] = {}
  for path in files:
    sub = submission.read(path)
    if not sub.scenario_rollouts:
      raise ValueError(f"{path}: the submission holds no scenario rollouts")
    for rollouts in sub.scenario_rollouts:
      if rollouts.scenario_id in where:
        raise ValueError(f"{path}: scenario {rollouts.scenario_id} is also in {where[rollouts.scenario_id]}")
      where[rollouts.scenario_id] = path
  return where


def scenario_files(paths, workdir: str) -> list[str]:
  """The Scenario-proto files the evaluator reads: the files of `paths`
  as they are, or, for tf.Example files, a Scenario-proto copy in `workdir`
  (full logs, `womd.write(..., record_format="scenario")`). A missing or
  unreadable file is a ValueError naming it."""
  out = []
  for path in womd.expand_paths(paths):
    try:
      first = next(womd._records(path, 1), (0, []))[1]
      if not first:
        raise ValueError(f"{path}: holds no record")
      kind = womd.detect_format(first[0], path)
      if kind == "scenario":
        out.append(path)
        continue
      copy = os.path.join(workdir, f"{len(out):05d}-{os.path.basename(path)}.scenario")
      items = ((s, m.scenario_id) for s, m in womd.iterate(path, with_meta=True, to_jax=False))
      womd.write(copy, items, record_format="scenario")
      out.append(copy)
    except womd.WomdFormatError as err:
      raise ValueError(str(err)) from None
  return out


def _journal_key(files: Sequence[str], raw_headings: bool = False) -> list:
  """What a journal must match to be reused: each submission's name, size and mtime, and how
  the logs' headings were read."""
  return [[os.path.basename(f), os.path.getsize(f), os.stat(f).st_mtime_ns] for f in files] + \
      [["headings", "as stored" if raw_headings else "radians"]]


def _cut_short(path: str) -> bool:
  with open(path, "rb") as f:
    f.seek(0, os.SEEK_END)
    if not f.tell():
      return False
    f.seek(-1, os.SEEK_END)
    return f.read(1) != b"\n"


def read_journal(path: Optional[str], files: Sequence[str], raw_headings: bool = False) -> dict:
  """{scenario id: worker line} of the scenes a journal holds scored for
  these very submission files; {} when there is none or it belongs to other
  files (changed since, or another submission). Failed scenes are not kept:
  they are scored again."""
  if not path or not os.path.exists(path):
    return {}
  done = {}
  with open(path) as f:
    for number, line in enumerate(f):
      try:
        item = json.loads(line)
      except json.JSONDecodeError:
        continue                      # a line cut short when the run stopped
      if number == 0:
        if item.get("journal_of") != _journal_key(files, raw_headings):
          return {}
        continue
      if "metrics" in item:
        done[item["scenario_id"]] = item
  return done


def _spawn(python: str, submissions: list[str], scenarios: list[str], index: int, count: int,
           threads: int, skip: Optional[str] = None, flags: Sequence[str] = ()) -> subprocess.Popen:
  env = dict(os.environ, TF_CPP_MIN_LOG_LEVEL="2", TF_NUM_INTRAOP_THREADS=str(threads),
             OMP_NUM_THREADS=str(threads), PYTHONNOUSERSITE="1")
  env.pop("PYTHONPATH", None)   # the worker must see only the evaluator's packages
  if os.path.exists(TCMALLOC):   # ~3x faster scoring, same numbers
    env["LD_PRELOAD"] = ":".join(p for p in (env.get("LD_PRELOAD"), TCMALLOC) if p)
  cmd = [python, WORKER, *(["--submission", *submissions] if submissions else []), "--scenarios", *scenarios,
         "--index", str(index), "--count", str(count), *flags] + (["--skip", skip] if skip else [])
  return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=REPO)


def score(submissions: Sequence[str], scenarios, workers: int = 1, progress: bool = True,
          venv: Optional[str] = None, journal: Optional[str] = None, raw_headings: bool = False) -> dict:
  """Scores the submission(s) on the scenarios with `workers` evaluator
  processes. Returns {"scenarios": {id: {"metrics", "buckets", "seconds",
  "record"}}, "failed": {id: reason}, "missing": [ids without rollouts],
  "unknown": [submitted ids not in the scenarios], "aggregate": ...}.
  `journal`: a JSONL file that gets each scene's result as it comes, so a
  stopped run resumes where it was (`read_journal`) and can be followed.
  A log whose headings are in degrees is scored in radians, as our reader reads it
  (`wosac_worker.headings_in_radians`; such scenes carry "headings_from_degrees"), unless
  `raw_headings`. Raises EvaluatorMissing, or ValueError naming a bad input file."""
  python = evaluator_python(venv)
  where = read_submissions(submissions)
  files = sorted(set(where.values()))
  workers = max(1, int(workers))
  done = read_journal(journal, files, raw_headings)
  if journal and not done:
    os.makedirs(os.path.dirname(os.path.abspath(journal)), exist_ok=True)
    with open(journal, "w") as f:
      f.write(json.dumps({"journal_of": _journal_key(files, raw_headings)}) + "\n")
  log_file = open(journal, "a") if journal else None
  if log_file and _cut_short(journal):
    log_file.write("\n")              # end the line a stop cut short
  scored = {sid: _kept(item) for sid, item in done.items()}
  failed, missing, seen = {}, [], set(done)
  from tqdm.auto import tqdm
  bar = tqdm(total=len(where), initial=len(done), desc="wosac score", unit="scenario", disable=not progress)
  try:
    with tempfile.TemporaryDirectory(prefix="wosac-score-") as tmp:
      inputs = scenario_files(scenarios, tmp)
      skip = os.path.join(tmp, "skip.txt")
      with open(skip, "w") as f:
        f.write("\n".join(sorted(done)))
      kept = lambda: (f"; the {len(scored)} scenes scored are kept in {journal}: the same command resumes there"
                      if journal else "")
      for item in _worker_lines(python, [os.path.abspath(f) for f in files], inputs, workers, skip=skip,
                                flags=_heading_flags(raw_headings), kept=kept):
        sid = item["scenario_id"]
        if sid in done:
          continue
        seen.add(sid)
        if log_file and not item.get("missing"):
          log_file.write(json.dumps(item) + "\n")
          log_file.flush()
        if item.get("missing"):
          missing.append(sid)
          continue
        if "error" in item:
          failed[sid] = f"{item['record']}: {item['error']}"
          bar.write(f"scenario {sid} could not be scored, skipped: {failed[sid]}", file=sys.stderr)
        else:
          scored[sid] = _kept(item)
          bar.set_postfix(metametric=f"{np.mean([s['buckets']['realism_meta_metric'] for s in scored.values()]):.3f}")
        bar.update(1)
  finally:
    bar.close()
    if log_file:
      log_file.close()
  unknown = sorted(set(where) - seen)
  return {"scenarios": scored, "failed": failed, "missing": sorted(missing), "unknown": unknown,
          "submissions": files, "aggregate": aggregate(scored)}


def _heading_flags(raw_headings: bool) -> list[str]:
  """The worker's flag to score against the logs' headings as stored (`headings_in_radians`)."""
  return ["--raw-headings"] if raw_headings else []


def _kept(item: dict) -> dict:
  """What a result keeps of a worker's scored line (the ceiling where the worker gave one)."""
  return {k: item[k] for k in ("metrics", "buckets", "seconds", "record", "ceiling", "headings_from_degrees")
          if k in item}


def _worker_lines(python: str, submissions: list[str], inputs: list[str], workers: int,
                  skip: Optional[str] = None, flags: Sequence[str] = (), kept=lambda: ""):
  """Runs `workers` evaluator processes over `inputs` and yields each scene's
  JSON line as it comes; a worker that fails is a RuntimeError (`kept()` adds
  what was saved) once every line is in."""
  lines: "queue.Queue" = queue.Queue()
  threads = max(1, (os.cpu_count() or 1) // workers)
  procs = [_spawn(python, submissions, [os.path.abspath(f) for f in inputs], k, workers, threads, skip, flags)
           for k in range(workers)]
  errors = [[] for _ in procs]

  def pump(k, proc):
    for line in proc.stdout:
      lines.put((k, line))
    errors[k] = proc.stderr.read().splitlines()[-20:]
    lines.put((k, None))

  for k, proc in enumerate(procs):
    threading.Thread(target=pump, args=(k, proc), daemon=True).start()
  open_workers = len(procs)
  while open_workers:
    k, line = lines.get()
    if line is None:
      open_workers -= 1
      continue
    try:
      item = json.loads(line)
    except json.JSONDecodeError:
      continue
    if not item.get("done"):
      yield item
  for k, proc in enumerate(procs):
    if proc.wait() != 0:
      killed = " (killed: out of memory? try fewer --workers)" if proc.returncode == -9 else ""
      raise RuntimeError(f"evaluator worker {k} failed (exit {proc.returncode}){killed}{kept()}:\n"
                         + "\n".join(errors[k]))


def ceiling(scenarios, workers: int = 1, progress: bool = True, venv: Optional[str] = None,
            raw_headings: bool = False) -> dict:
  """The most any submission can score on each scene of `scenarios`, from the
  logs alone (`wosac_worker.ceiling_likelihoods`; seconds per scene):
  {"scenarios": {id: {"ceiling", "record"}}, "failed": {id: reason},
  "aggregate": the mean ceiling}; headings as `score` reads them. Raises
  EvaluatorMissing, or ValueError naming a bad input file."""
  python = evaluator_python(venv)
  out, failed = {}, {}
  from tqdm.auto import tqdm
  with tempfile.TemporaryDirectory(prefix="wosac-ceiling-") as tmp:
    inputs = scenario_files(scenarios, tmp)
    bar = tqdm(desc="wosac ceiling", unit="scenario", disable=not progress)
    flags = ["--ceiling", *_heading_flags(raw_headings)]
    for item in _worker_lines(python, [], inputs, max(1, int(workers)), flags=flags):
      if "error" in item:
        failed[item["scenario_id"]] = f"{item['record']}: {item['error']}"
      else:
        out[item["scenario_id"]] = {"ceiling": item["ceiling"], "record": item["record"]}
      bar.update(1)
    bar.close()
  return {"scenarios": out, "failed": failed, "aggregate": aggregate_ceiling(out)}


def aggregate_ceiling(scored: dict) -> Optional[dict]:
  """The mean ceiling over the scenes that have one (None when none has), with their count."""
  rows = [s["ceiling"] for s in scored.values() if "ceiling" in s]
  if not rows:
    return None
  keys = sorted(set.intersection(*(set(r) for r in rows)))
  return {"num_scenarios": len(rows), **{k: float(np.mean([r[k] for r in rows])) for k in keys}}


def aggregate(scored: dict) -> dict:
  """The mean of every metric and bucket over the scored scenarios (empty
  when none), with their count."""
  if not scored:
    return {"num_scenarios": 0, "metrics": {}, "buckets": {}}
  out = {"num_scenarios": len(scored)}
  for part in ("metrics", "buckets"):
    keys = sorted(set.intersection(*(set(s[part]) for s in scored.values())))
    out[part] = {k: float(np.mean([s[part][k] for s in scored.values()])) for k in keys}
  ceiling_of = aggregate_ceiling(scored)
  if ceiling_of:
    out["ceiling"] = ceiling_of
  return out


# The ceiling's columns: (key in a ceiling, key in a result's buckets, header).
CEILING = (("metametric", "realism_meta_metric", "metametric"), ("kinematic_metrics", "kinematic_metrics", "kinematic"),
           ("interactive_metrics", "interactive_metrics", "interactive"),
           ("map_based_metrics", "map_based_metrics", "map-based"))


def ceiling_markdown(result: dict) -> list[str]:
  """Lines comparing a scored result's buckets with the ceiling of the same
  scenes (the most any submission can score there); none without a ceiling."""
  top = result["aggregate"].get("ceiling")
  if not top:
    return []
  scenes = {sid: s for sid, s in result["scenarios"].items() if "ceiling" in s}
  mine = {key: float(np.mean([s["buckets"][key] for s in scenes.values()])) for _, key, _ in CEILING}
  return ["", f"Against the ceiling (the most any submission can score on these {top['num_scenarios']} "
          "scene(s): each likelihood at the log's own empirical distribution; docs/WOSAC.md, \"The ceiling\"):", "",
          "| | " + " | ".join(h for *_, h in CEILING) + " |", "|---" * (len(CEILING) + 1) + "|",
          "| this submission | " + " | ".join(f"{mine[key]:.4f}" for _, key, _ in CEILING) + " |",
          "| ceiling | " + " | ".join(f"{top[c]:.4f}" for c, *_ in CEILING) + " |",
          "| below the ceiling by | " + " | ".join(f"{top[c] - mine[key]:.4f}" for c, key, _ in CEILING) + " |"]


def _value(row: dict, key: str) -> str:
  v = row.get("buckets", {}).get(key, row.get("metrics", {}).get(key))
  return "" if v is None else f"{v:.4f}"


def markdown(result: dict, title: str = "WOSAC (Waymo's evaluator, 2025 config)") -> str:
  """The aggregate (headline, every likelihood) and one row per scenario."""
  agg = result["aggregate"]
  lines = [f"## {title}", "", f"{agg['num_scenarios']} scenario(s) scored"
           + (f", {len(result['failed'])} failed" if result["failed"] else "")
           + (f", {len(result['missing'])} without rollouts" if result["missing"] else "") + ".", ""]
  lines += ["| metric | mean |", "|---|---|"]
  lines += [f"| {header} | {_value(agg, key)} |" for key, header in HEADLINE]
  lines += [f"| {key} | {_value(agg, key)} |" for key in LIKELIHOODS if key in agg.get("metrics", {})]
  lines += ceiling_markdown(result)
  lines += ["", "| scenario | " + " | ".join(h for _, h in HEADLINE) + " |",
            "|---" * (len(HEADLINE) + 1) + "|"]
  for sid in sorted(result["scenarios"]):
    lines.append(f"| {sid} | " + " | ".join(_value(result["scenarios"][sid], k) for k, _ in HEADLINE) + " |")
  for sid, reason in sorted(result["failed"].items()):
    lines.append(f"| {sid} | failed: {reason.splitlines()[0][:200]} |" + " |" * (len(HEADLINE) - 1))
  return "\n".join(lines) + "\n"


def write_results(result: dict, prefix: str, title: Optional[str] = None) -> tuple[str, str]:
  """Writes PREFIX.wosac.json and PREFIX.wosac.md; returns their paths."""
  os.makedirs(os.path.dirname(os.path.abspath(prefix)), exist_ok=True)
  json_path, md_path = f"{prefix}.wosac.json", f"{prefix}.wosac.md"
  with open(json_path, "w") as f:
    json.dump(result, f, indent=1, sort_keys=True)
  with open(md_path, "w") as f:
    f.write(markdown(result, title) if title else markdown(result))
  return json_path, md_path


def compare(results: dict[str, dict]) -> str:
  """One markdown row per labelled result (label -> `score` result): the
  headline columns and the scenario count."""
  lines = ["| method | scenes | " + " | ".join(h for _, h in HEADLINE) + " |",
           "|---|---" + "|---" * len(HEADLINE) + "|"]
  for label, result in results.items():
    agg = result["aggregate"]
    lines.append(f"| {label} | {agg['num_scenarios']} | " + " | ".join(_value(agg, k) for k, _ in HEADLINE) + " |")
  top = next((r["aggregate"]["ceiling"] for r in results.values() if r["aggregate"].get("ceiling")), None)
  if top:   # the same scenes' logs give every method the same ceiling
    lines.append(f"| ceiling (no submission scores above) | {top['num_scenarios']} | "
                 + " | ".join(f"{top[c]:.4f}" for c, *_ in CEILING) + " |" + " |" * (len(HEADLINE) - len(CEILING)))
  return "\n".join(lines) + "\n"


def ceiling_table(result: dict) -> str:
  """Markdown of `ceiling(...)`: the mean ceiling and one row per scene."""
  top = result["aggregate"]
  head = ["metametric", "kinematic_metrics", "interactive_metrics", "map_based_metrics"]
  lines = ["## WOSAC ceiling (the most any submission can score; Waymo's evaluator, 2025 config)", "",
           f"{top['num_scenarios'] if top else 0} scenario(s)"
           + (f", {len(result['failed'])} failed" if result["failed"] else "") + ".", "",
           "| scenario | " + " | ".join(head) + " |", "|---" * (len(head) + 1) + "|"]
  if top:
    lines.append("| **mean** | " + " | ".join(f"{top[k]:.4f}" for k in head) + " |")
  for sid in sorted(result["scenarios"]):
    row = result["scenarios"][sid]["ceiling"]
    lines.append(f"| {sid} | " + " | ".join(f"{row[k]:.4f}" for k in head) + " |")
  for sid, reason in sorted(result["failed"].items()):
    lines.append(f"| {sid} | failed: {reason.splitlines()[0][:200]} |" + " |" * (len(head) - 1))
  return "\n".join(lines) + "\n"
