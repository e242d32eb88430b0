"""Waymo Open Sim Agents Challenge: write a submission, or check one.

  python -m experiments.wosac --scenarios 'validation/*.tfrecord*' --method pcdiff \
      --checkpoint checkpoints/pcdiff-cpu-v11 --out runs/wosac/sub.binproto --account-name you@example.com
  python -m experiments.wosac ... --shard 3/150          # writes sub.binproto-00003-of-00150 (files 3, 153, ...)
  python -m experiments.wosac --check 'runs/wosac/sub.binproto*' --scenarios 'validation/*.tfrecord*'
  python -m experiments.wosac --score runs/wosac/sub.binproto --scenarios 'validation/*.tfrecord*' --workers 2
  python -m experiments.wosac --ceiling --scenarios 'validation/*.tfrecord*' --score-out runs/wosac/val

--scenarios takes WOMD's scenario/ files (Scenario protos) or its tf_example/
files. Every sim agent (every object valid at step 10, the SDC included) is
simulated 32 times for 80 steps by --method, without its logged future; a
learned method drives the SDC and its --max-agents nearest sim agents, IDM
the rest (docs/WOSAC.md). --check enforces the official rules and exits 2 on
a bad submission; add --strict for the metadata the server also requires.
--score runs Waymo's own metrics (2025 config) in the evaluator's venv (`make
wosac-env`) on the scenarios' full logs and writes PREFIX.wosac.json and
PREFIX.wosac.md (--score-out, default: the submission's path without
.binproto); PREFIX.wosac.jsonl gets each scene as it is scored, so a stopped
run resumes there. --ceiling writes PREFIX.ceiling.json and .md: the most any
submission can score on the scenarios (a --score table shows it next to the
submission's). --method log copies the logged future: a reference to score, never
a valid submission (it reads the future).
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import sys

# A job of --jobs is pinned to its CPUs before JAX starts a thread, so that all of them inherit it.
if os.environ.get("PCDIFF_JOB_CPUS") and hasattr(os, "sched_setaffinity"):
  os.sched_setaffinity(0, {int(c) for c in os.environ["PCDIFF_JOB_CPUS"].split(",")})

from experiments import _args  # noqa: E402
from pcdiff_jax import evaluation, wosac  # noqa: E402
from pcdiff_jax.config import MetricsConfig  # noqa: E402
from pcdiff_jax.data import submission  # noqa: E402
from pcdiff_jax.model.guidance import GuidanceConfig  # noqa: E402


def _shard(text: str) -> tuple[int, int]:
  try:
    index, count = (int(v) for v in text.split("/"))
  except ValueError:
    raise argparse.ArgumentTypeError(f"--shard takes INDEX/COUNT, e.g. 3/150, not {text!r}") from None
  if count < 1 or not 0 <= index < count:
    raise argparse.ArgumentTypeError(f"--shard {text}: need 0 <= INDEX < COUNT")
  return index, count


def _num_parameters(text: str) -> str:
  if not submission.PARAMS_RE.match(text):
    raise argparse.ArgumentTypeError(f"{text!r} is not an integer with an optional K/M/B/T suffix (e.g. 200K)")
  return text


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.wosac", description=__doc__, epilog=_args.policy_fields_epilog(),
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--scenarios", nargs="+", required=True,
                 help="WOMD TFRecord file(s) or glob(s): Scenario protos or motion tf.Examples")
  p.add_argument("--check", nargs="+", metavar="SUBMISSION",
                 help="check these submission file(s) (globs allowed) instead of writing one")
  p.add_argument("--score", nargs="+", metavar="SUBMISSION",
                 help="score these submission file(s) with Waymo's evaluator (needs `make wosac-env`)")
  p.add_argument("--ceiling", action="store_true",
                 help="write the most any submission can score on --scenarios (needs `make wosac-env`)")
  p.add_argument("--score-out", default=None, metavar="PREFIX",
                 help="--score: write PREFIX.wosac.json and PREFIX.wosac.md (default: the first submission's "
                      "path without .binproto); --ceiling: PREFIX.ceiling.json and .md (default: runs/wosac/ceiling)")
  p.add_argument("--workers", type=int, default=max(1, min(2, os.cpu_count() or 1)),
                 help="--score: evaluator processes, each scoring every N-th scenario")
  p.add_argument("--raw-headings", action="store_true",
                 help="--score, --ceiling: score against the logs' headings as stored, even where a scene "
                      "stores degrees (by default read in radians, as the simulator reads them)")
  p.add_argument("--strict", action="store_true",
                 help="--check: missing or wrong metadata (account, method name, required flags) is an error")
  p.add_argument("--out", type=_args.output_file, help="the submission file to write (NAME.binproto)")
  p.add_argument("--method", default="pcdiff", choices=wosac.METHODS + (wosac.LOG_REPLAY,),
                 help="log: the logged future 32 times, for scoring only (NOT a valid submission)")
  p.add_argument("--checkpoint", default=None, help="training workdir or shipped model of a learned method")
  p.add_argument("--ego", default="method", choices=wosac.EGOS,
                 help="who drives the SDC: the method (default) or IDM")
  p.add_argument("--max-agents", type=int, default=64,
                 help="learned methods: sim agents they drive besides the SDC, nearest it first (their agent "
                      "cap); IDM drives the others")
  p.add_argument("--full-plans", action="store_true",
                 help="learned methods: plan every scene in the full cap's slots instead of the fewest of 16, "
                      "32, 64, ... that hold its sim agents (the random draws of exports made before plans were "
                      "sized; slower on small scenes)")
  _args.add_policy_flags(p)
  _args.add_map_flags(p, wosac.EXPORT_MAP_PIECES, why=": WOSAC level with 256 at 1.2x the speed")
  _args.add_start_flags(p)
  p.add_argument("--guidance", default="none", choices=("none", "objective"),
                 help="pcdiff: objective guidance (map and collision costs) with its default weights")
  p.add_argument("--num-rollouts", type=int, default=submission.NUM_ROLLOUTS,
                 help="rollouts per scenario (the challenge needs 32; fewer only for quick tests)")
  p.add_argument("--rollouts-per-call", type=int, default=None,
                 help="rollouts per jitted call (default: all on a GPU, 4 on a CPU; lower it to save memory)")
  p.add_argument("--max-objects", type=int, default=None,
                 help="padded objects per scenario (default: 128, 256, ... whichever first holds the scene)")
  p.add_argument("--shard", type=_shard, default=None, metavar="INDEX/COUNT",
                 help="simulate every COUNT-th input file from INDEX; writes OUT-0000I-of-0000N")
  p.add_argument("--jobs", type=int, default=1,
                 help="export in N processes, each simulating every N-th scenario on its share of the CPU "
                      "cores, merged into --out (on 2 CPU cores, 2 jobs export more scenes per second: "
                      "docs/BENCHMARKS.md); the rollouts do not depend on N")
  p.add_argument("--part", type=_shard, default=None, help=argparse.SUPPRESS)   # one job of --jobs
  p.add_argument("--max-scenarios", type=int, default=None, help="only the first N scenarios (a test)")
  p.add_argument("--overwrite", action="store_true",
                 help="replace an existing submission file, and start afresh where an earlier run of it was "
                      "stopped (by default the same command goes on from the scenarios that run wrote)")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--no-progress", action="store_true")
  m = p.add_argument_group("submission metadata (sim_agents_submission.proto)")
  m.add_argument("--account-name", default="", help="the e-mail registered at waymo.com/open (required to upload)")
  m.add_argument("--method-name", default=None, help="unique_method_name (default: pcdiff_jax-METHOD)")
  m.add_argument("--authors", nargs="*", default=[])
  m.add_argument("--affiliation", default="")
  m.add_argument("--description", default=None)
  m.add_argument("--method-link", default="")
  m.add_argument("--uses-lidar-data", action="store_true")
  m.add_argument("--uses-camera-data", action="store_true")
  m.add_argument("--uses-public-model-pretraining", action="store_true")
  m.add_argument("--public-model-names", nargs="*", default=[])
  m.add_argument("--num-model-parameters", type=_num_parameters, default=None,
                 help="e.g. 409K (default: counted from the method's parameters)")
  args = p.parse_args(argv)
  if (args.check is not None) + (args.score is not None) + args.ceiling > 1:
    p.error("give one of --check, --score and --ceiling")
  if args.check is None and args.score is None and not args.ceiling and args.out is None:
    p.error("give --out SUBMISSION to write one, --check SUBMISSION to check one, or --score SUBMISSION to score one")
  if args.workers < 1:
    p.error("--workers must be >= 1")
  if args.jobs < 1:
    p.error("--jobs must be >= 1")
  if (args.check is None and args.score is None and not args.ceiling and args.method in evaluation.LEARNED
      and not args.checkpoint):
    p.error(f"--method {args.method} needs --checkpoint (e.g. checkpoints/pcdiff-cpu-v11)")
  for name in ("max_agents", "num_rollouts", "rollouts_per_call", "max_objects"):
    if getattr(args, name) is not None and getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.max_scenarios is not None and args.max_scenarios < 1:
    p.error("--max-scenarios must be >= 1")
  args.policy_config = _args.policy_config(p, args)
  args.map_crop = _args.map_crop(p, args)
  return args


def _metadata(args, cfg: wosac.WosacConfig) -> submission.Metadata:
  ev = cfg.eval
  description = args.description
  if description is None:
    description = (f"pcdiff_jax {ev.method}: closed loop, planned at {10 / ev.replan_every:g} Hz, "
                   "output at 10 Hz" +
                   (f", DDIM {ev.policy.ddim_steps} steps, {ev.metrics.max_reactive_agents} agents + SDC per plan, "
                    "IDM beyond" if ev.method in evaluation.LEARNED else "") +
                   (", IDM ego" if cfg.ego == "idm" else ""))
    if ev.method == wosac.LOG_REPLAY:
      description = "log replay (the logged future, 32 copies): NOT a valid submission, for scoring only"
  return submission.Metadata(
      account_name=args.account_name, unique_method_name=args.method_name or (
          "log-replay-NOT-A-SUBMISSION" if ev.method == wosac.LOG_REPLAY else f"pcdiff_jax-{ev.method}"),
      authors=tuple(args.authors), affiliation=args.affiliation, description=description,
      method_link=args.method_link, uses_lidar_data=args.uses_lidar_data, uses_camera_data=args.uses_camera_data,
      uses_public_model_pretraining=args.uses_public_model_pretraining,
      public_model_names=tuple(args.public_model_names),
      num_model_parameters="" if args.num_model_parameters is None else args.num_model_parameters,
      acknowledge_complies_with_closed_loop_requirement=ev.replan_every <= submission.MAX_STEPS_BETWEEN_CALLS)


def _check(args) -> int:
  report = wosac.check(args.check, args.scenarios, max_objects=args.max_objects, strict=args.strict,
                       num_rollouts=args.num_rollouts)
  for w in report["warnings"]:
    print(f"warning: {w}", file=sys.stderr)
  for e in report["errors"][:50]:
    print(f"error: {e}", file=sys.stderr)
  if len(report["errors"]) > 50:
    print(f"error: ... {len(report['errors']) - 50} more", file=sys.stderr)
  verdict = "INVALID" if report["errors"] else "valid"
  print(f"{verdict}: {report['scenarios_submitted']} of {report['scenarios']} scenario(s) in "
        f"{report['files']} file(s); {len(report['errors'])} error(s), {len(report['warnings'])} warning(s)")
  return 2 if report["errors"] else 0


def _score(args) -> int:
  from pcdiff_jax import wosac_scoring
  prefix = args.score_out or args.score[0].split(".binproto")[0]
  try:
    result = wosac_scoring.score(args.score, args.scenarios, workers=args.workers,
                                 progress=not args.no_progress, journal=f"{prefix}.wosac.jsonl",
                                 raw_headings=args.raw_headings)
  except wosac_scoring.EvaluatorMissing as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  for sid, reason in result["failed"].items():
    print(f"warning: scenario {sid} could not be scored, skipped: {reason.splitlines()[0]}", file=sys.stderr)
  if result["missing"]:
    print(f"warning: {len(result['missing'])} scenario(s) of --scenarios have no rollouts in the submission: "
          f"{result['missing'][:5]}", file=sys.stderr)
  if result["unknown"]:
    print(f"warning: {len(result['unknown'])} submitted scenario(s) are not in --scenarios: "
          f"{result['unknown'][:5]}", file=sys.stderr)
  json_path, md_path = wosac_scoring.write_results(result, prefix)
  agg = result["aggregate"]
  print(json.dumps({"num_scenarios": agg["num_scenarios"], "failed": len(result["failed"]),
                    **{k: round(v, 4) for k, v in agg.get("buckets", {}).items()}}))
  print(f"wrote {json_path} and {md_path}")
  return 0 if agg["num_scenarios"] else 2


def _ceiling(args) -> int:
  from pcdiff_jax import wosac_scoring
  prefix = args.score_out or os.path.join("runs", "wosac", "ceiling")
  try:
    result = wosac_scoring.ceiling(args.scenarios, workers=args.workers, progress=not args.no_progress,
                                   raw_headings=args.raw_headings)
  except wosac_scoring.EvaluatorMissing as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  for sid, reason in result["failed"].items():
    print(f"warning: scenario {sid} has no ceiling, skipped: {reason.splitlines()[0]}", file=sys.stderr)
  os.makedirs(os.path.dirname(os.path.abspath(prefix)), exist_ok=True)
  with open(f"{prefix}.ceiling.json", "w") as f:
    json.dump(result, f, indent=1, sort_keys=True)
  with open(f"{prefix}.ceiling.md", "w") as f:
    f.write(wosac_scoring.ceiling_table(result))
  top = result["aggregate"]
  print(json.dumps({k: round(v, 4) for k, v in (top or {"num_scenarios": 0}).items()}))
  print(f"wrote {prefix}.ceiling.json and {prefix}.ceiling.md")
  return 0 if top else 2


def _interrupt(signum, frame):
  # One stop: a second signal (Ctrl-C reaches the jobs' whole process group, then the parent's
  # SIGTERM) must not break off the writing of what is kept.
  signal.signal(signal.SIGTERM, signal.SIG_IGN)
  signal.signal(signal.SIGINT, signal.SIG_IGN)
  raise KeyboardInterrupt


# A job alone on one core runs XLA's CPU code in that one thread: two single-threaded jobs on 2 cores
# export more scenes per second than one job on both (docs/BENCHMARKS.md, "WOSAC export: one job per core").
ONE_THREAD_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def _job_cpus(count: int) -> list[set]:
  """The usable CPUs split into `count` groups, one per job (a job shares a CPU when there are fewer)."""
  cpus = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else list(range(os.cpu_count() or 1))
  if count >= len(cpus):
    return [{cpus[j % len(cpus)]} for j in range(count)]
  return [set(cpus[j::count]) for j in range(count)]


def _follow_jobs(procs, target: str, args) -> None:
  """Shows the jobs' progress (scenarios written, read from their parts every few seconds) until
  they end: the jobs themselves run without a progress bar."""
  import time
  from tqdm.auto import tqdm
  from pcdiff_jax.data import tfrecord
  if args.no_progress:   # the caller's communicate() waits (and drains their output)
    return
  total = sum(tfrecord.count_records(f) for f in wosac.select_files(args.scenarios, args.shard))
  total = min(total, args.max_scenarios) if args.max_scenarios else total
  parts = [wosac.part_path(target, j, args.jobs) for j in range(args.jobs)]
  with tqdm(total=total, desc=f"wosac {args.method} ({args.jobs} jobs)", unit="scenario") as bar:
    while any(proc.poll() is None for proc in procs):
      time.sleep(5)
      done = sum(max(map(submission.count_scenarios, (p, p + ".tmp"))) for p in parts)
      bar.update(done - bar.n)


def _export_in_jobs(args, argv: list[str]) -> int:
  """Runs `--jobs` copies of this command, job j with `--part j/N` on its CPUs, and merges
  their parts into --out; prints the summary of the whole (per scene: wall time over all the
  jobs at once)."""
  import subprocess
  import time
  target = submission.shard_path(args.out, *(args.shard or (None, None)))
  groups, procs = _job_cpus(args.jobs), []
  t0 = time.perf_counter()
  try:
    for j, cpus in enumerate(groups):
      env = dict(os.environ)
      env["PCDIFF_JOB_CPUS"] = ",".join(map(str, sorted(cpus)))
      if len(cpus) == 1:
        env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} {ONE_THREAD_XLA_FLAGS}".strip()
      procs.append(subprocess.Popen(
          [sys.executable, "-m", "experiments.wosac", *argv, "--part", f"{j}/{args.jobs}", "--no-progress"],
          stdout=subprocess.PIPE, text=True, env=env))
    _follow_jobs(procs, target, args)
    outputs = [proc.communicate()[0] for proc in procs]
  except KeyboardInterrupt:
    for proc in procs:
      proc.terminate()
    for proc in procs:
      proc.wait()
    kept = [wosac.part_path(target, j, args.jobs) for j in range(args.jobs)]
    kept = [f for f in kept + [f"{f}{s}" for f in kept for s in (".partial", ".tmp")] if os.path.exists(f)]
    print(f"warning: stopped; the jobs' scenarios so far are kept in {kept or 'no file'}: the same command "
          "goes on from them", file=sys.stderr)
    return 130
  failed = [j for j, proc in enumerate(procs) if proc.returncode != 0]
  if failed:
    print(f"error: job(s) {failed} of {args.jobs} failed (their messages above); what every job wrote is kept "
          f"as {wosac.part_path(target, 'J', args.jobs)}[.partial], not merged into {target}: the same command "
          "goes on from them", file=sys.stderr)
    return 2
  summaries = [json.loads(next(line for line in out.splitlines()[::-1] if line.startswith("{"))) for out in outputs]
  count, metadata = wosac.merge_parts(target, args.jobs)
  wall = time.perf_counter() - t0
  steady = [s["steady_seconds_per_scenario"] for s in summaries if s.get("steady_seconds_per_scenario")]
  summary = {"path": target, "num_scenarios": count, "jobs": args.jobs,
             **{k: sum(s[k] for s in summaries) for k in ("sim_agents", "fallback_agents", "lost_steps")},
             "num_rollouts": args.num_rollouts, "seconds_per_scenario": wall / max(count, 1),
             # The jobs run at once: the per-scene cost of the whole is 1 / (sum of the jobs' rates).
             "steady_seconds_per_scenario": 1.0 / sum(1.0 / t for t in steady) if steady else None,
             "job_steady_seconds_per_scenario": [s.get("steady_seconds_per_scenario") for s in summaries]}
  print(json.dumps(summary))
  if not metadata.account_name:   # the parts' metadata (the parameter count filled in by the jobs)
    print("note: no --account-name: fine for a local evaluation, required to upload", file=sys.stderr)
  print(f"wrote {target}; check it with: python -m experiments.wosac --check {target} "
        f"--scenarios {' '.join(args.scenarios)}")
  return 0


def main(argv=None) -> int:
  handlers = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
  try:
    return _main(argv)
  finally:   # in a caller's process (tests, a notebook), its own handlers again
    for sig, handler in handlers.items():
      signal.signal(sig, handler)


def _main(argv=None) -> int:
  argv = sys.argv[1:] if argv is None else list(argv)
  args = parse_args(argv)
  _args.setup_logging()
  try:
    if args.check is not None:
      return _check(args)
    if args.score is not None:
      return _score(args)
    if args.ceiling:
      return _ceiling(args)
    guidance = GuidanceConfig(mode=args.guidance)
    pcfg = args.policy_config
    ev = evaluation.EvalConfig(method=args.method, checkpoint=args.checkpoint, policy=pcfg, seed=args.seed,
                               metrics=MetricsConfig(max_reactive_agents=args.max_agents), guidance=guidance,
                               **args.map_crop, **_args.start_options(args))
    cfg = wosac.WosacConfig(eval=ev, ego=args.ego, num_rollouts=args.num_rollouts,
                            rollouts_per_call=args.rollouts_per_call, max_objects=args.max_objects,
                            size_plans=not args.full_plans)
    target = submission.shard_path(args.out, *(args.shard or (None, None)))
    if os.path.exists(target) and not args.overwrite and args.part is None:
      print(f"{target} exists: nothing to do (--overwrite to write it again)", file=sys.stderr)
      return 0
    os.makedirs(os.path.dirname(os.path.abspath(target)), exist_ok=True)   # --out may name a new folder
    signal.signal(signal.SIGTERM, _interrupt)   # `timeout`, a batch system: keep what is done
    signal.signal(signal.SIGINT, _interrupt)
    if args.jobs > 1 and args.part is None:
      return _export_in_jobs(args, argv)
    speaks = args.part is None or args.part[0] == 0   # of --jobs, the first job alone warns
    if speaks and args.num_rollouts != submission.NUM_ROLLOUTS:
      print(f"warning: --num-rollouts {args.num_rollouts}: the challenge needs {submission.NUM_ROLLOUTS}; "
            "this file is for tests only", file=sys.stderr)
    if speaks and args.method == wosac.LOG_REPLAY:
      print("warning: --method log copies the logged future: a reference to score (--score), NOT a valid "
            "submission", file=sys.stderr)
    if speaks and ev.replan_every > submission.MAX_STEPS_BETWEEN_CALLS:
      print(f"warning: --replan-every {ev.replan_every} plans below 1 Hz, which the challenge's closed-loop "
            "rule does not admit; the submission does not acknowledge it", file=sys.stderr)
    summary = wosac.export(args.scenarios, args.out, cfg, _metadata(args, cfg), shard=args.shard,
                           max_scenarios=args.max_scenarios, progress=not args.no_progress, part=args.part,
                           resume=not args.overwrite)
  except wosac.Interrupted as err:
    print(f"warning: {err}", file=sys.stderr)
    return 130
  except (FileNotFoundError, ValueError, RuntimeError) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  print(json.dumps({k: v for k, v in summary.items() if k != "metadata"}))
  if not summary["metadata"]["account_name"] and args.part is None:
    print("note: no --account-name: fine for a local evaluation, required to upload", file=sys.stderr)
  print(f"wrote {summary['path']}; check it with: python -m experiments.wosac --check {summary['path']} "
        f"--scenarios {' '.join(args.scenarios)}")
  return 0


if __name__ == "__main__":
  sys.exit(main())
