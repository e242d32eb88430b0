"""On-policy recovery fine-tuning of a trained diffusion policy (CAT-K-style rounds).

  python -m experiments.finetune --from checkpoints/pcdiff-cpu-v8 --round-policy defaults \\
      --data 'data/synth10k/train-*' --workdir runs/v9 --rounds 4 --scenes 256 --steps 600 --batch-size 32

Each round rolls the current policy out in closed loop (10 Hz, warm-started,
SDC on its log, as `experiments.rollout` evaluates it) on --scenes training
scenes not used by an earlier round, cuts examples at the visited steps, and
fine-tunes the denoiser for --steps on batches that mix the on-policy examples
of every round so far (DAgger) with the logged examples (`pcdiff_jax.training.closed_loop`). Round r keeps its examples in
WORKDIR/round-r/on_policy.npz and its model in WORKDIR/round-r; the last
round's model is WORKDIR itself (WORKDIR/diffusion, WORKDIR/encoder), so
`--checkpoint WORKDIR` and `experiments.export` take it. Run the same command
again after an interruption: finished rounds are kept, the current one resumes.

--policy simpl-ar does the same for the SIMPL-AR baseline (CAT-K on its own
closed loop): each round rolls SIMPL-AR out with its current encoder (at
first --from's: simpl_ar/ where it has one, else encoder/) and fine-tunes
that encoder alone (--encoder-steps) on the mixed batches. Its
encoder goes to WORKDIR/simpl_ar (read by `--method simpl-ar` and
`pretrained(stage="simpl-ar")`); the diffusion policy and its encoder are
copied unchanged from --from:

  python -m experiments.finetune --policy simpl-ar --from checkpoints/pcdiff-cpu-v7 \
      --data 'data/synth20/train-*' --workdir runs/sa --rounds 2 --scenes 100 --encoder-steps 600

--encoder-from DIR conditions the diffusion policy on another encoder from
round 0 on: DIR's SIMPL-AR encoder (simpl_ar/, else encoder/), e.g. the
lane-aware one of the line above; its rounds re-train the denoiser on that
encoder's tokens and proposals, and WORKDIR/encoder is that encoder (v8):

  python -m experiments.finetune --from checkpoints/pcdiff-cpu-v7 --encoder-from checkpoints/pcdiff-cpu-v7 \
      --data 'data/synth20/train-*' --workdir runs/l4 --rounds 2 --scenes 300 --first-scene 5200 --steps 1000

--real-data FILE puts real WOMD scenes in the loop: their logged examples make
--real-share of each batch's logged part and the rounds roll out from their
states; --target-fit 1 --target-max-rms 3 fits the latent targets to the
noisy logged positions (docs/RESULTS.md, "Ablation: fine-tuning on real scenes"):

  python -m experiments.finetune --from checkpoints/pcdiff-cpu-v8 --data 'data/synth600/train-*' \
      --real-data ../shared/data/womd_real/train.scenario.tfrecord --target-fit 1 --target-max-rms 3 \
      --round-policy defaults --mix 0.25 --rounds 1 --scenes 80 --steps 300 --learning-rate 5e-5 --workdir runs/r3

--targets chooses the on-policy labels: rejoin (the default) leads each
agent from its simulated pose back onto its log; guided labels it with the
model's own plan under objective guidance (the teacher: --teacher-*);
hybrid keeps the log's way back where it stays on the road and clear of the
others, the guided plan elsewhere (docs/RESULTS.md, "Ablation: fine-tuning
on real scenes", R13-R16).

--round-policy chooses what the rounds roll out: v8 (the default) is what every
round of v3-v8 rolled out, pinned; defaults is today's `PolicyConfig` with one
sample (v9's four rounds, the first line above, on one GPU).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import shutil
import sys
import time

import jax
import numpy as np

from experiments import _args
from pcdiff_jax.data import womd


ROUND_POLICIES = ("v8", "defaults")


def _round_policy(name: str = "v8"):
  """The policy a round rolls out, with one sample (no selection: the
  on-policy states should show the model's own drift, not the collision
  filter's fixes). 'v8': what every round of v3-v8 rolled out (the inference
  defaults of that time, no jerk limit), pinned so that later changes of the
  inference defaults leave `make train` as it was. 'defaults': today's PolicyConfig."""
  import dataclasses as dc
  from pcdiff_jax import policy
  if name == "defaults":
    return dc.replace(policy.PolicyConfig(), select_samples=1)
  return policy.PolicyConfig(select_samples=1, replan_every=1, warm_step=30, warm_ddim_steps=2, select_stride=1,
                             temporal_ensemble=(0.3, 0.0), jerk_limit=(0.0, 0.0), stop_hold=False,
                             still_gate=(0.0, 0.0), max_curvature=0.0, follow=(0.0, 0.0),
                             cruise_hold=(0.0, 0.0), pedestrian_plan="sample", cyclist_plan="sample")


def parse_args(argv=None) -> argparse.Namespace:
  p = argparse.ArgumentParser(prog="python -m experiments.finetune", description=__doc__,
                              formatter_class=argparse.RawDescriptionHelpFormatter)
  p.add_argument("--from", dest="source", required=True,
                 help="the model to start from: a training workdir or a shipped model folder")
  p.add_argument("--encoder-from", default=None, metavar="DIR",
                 help="condition the diffusion policy on DIR's SIMPL-AR encoder (simpl_ar/, else encoder/) "
                      "instead of --from's; the rounds re-train the denoiser on it")
  p.add_argument("--data", required=True, nargs="+", help="training TFRecord file(s) or glob(s)")
  p.add_argument("--real-data", nargs="+", default=None, metavar="FILE",
                 help="real WOMD scenes: their logged examples make --real-share of each batch's logged "
                      "part, and the rounds roll out on them (from real states) instead of --data")
  p.add_argument("--real-share", type=float, default=0.5, help="share of the logged examples from --real-data")
  p.add_argument("--drop-log-overlaps", action="store_true",
                 help="leave out of training the agents whose logged box overlaps another within the "
                      "horizon (real labels of queued and parked cars overlap; synthetic logs never do)")
  p.add_argument("--drop-log-offroad", action="store_true",
                 help="leave out of training the vehicles whose logged box leaves the mapped road within "
                      "the horizon (real drivers turn into lots and driveways the map does not hold)")
  p.add_argument("--target-fit", type=float, default=None, metavar="SIGMA",
                 help="m: targets are latents fitted to the logged positions (latent.fit_to_path; "
                      "1 for real logs); default: the model's (the projection)")
  p.add_argument("--target-max-rms", type=float, default=None, metavar="R",
                 help="with --target-fit: agents whose fitted latent has a whitened RMS above R are not "
                      "trained on (3 for real logs); default: the model's (no limit)")
  p.add_argument("--workdir", required=True, type=_args.output_dir)
  p.add_argument("--cache-dir", default=None, type=_args.output_dir, help="logged-example cache (default WORKDIR/cache)")
  p.add_argument("--policy", choices=("pcdiff", "simpl-ar"), default="pcdiff",
                 help="whose closed loop is rolled out and fine-tuned: pcdiff (the denoiser, and the "
                      "encoder with --encoder-steps) or simpl-ar (the SIMPL-AR baseline's own encoder only)")
  p.add_argument("--rounds", type=int, default=1)
  p.add_argument("--round-policy", choices=ROUND_POLICIES, default="v8",
                 help="the policy rounds roll out (one sample): v8's rounds' pinned settings (the default, "
                      "`make train`) or today's inference defaults")
  p.add_argument("--scenes", type=int, default=400, help="training scenes rolled out per round")
  p.add_argument("--first-scene", type=int, default=0,
                 help="round r rolls out training scenes FIRST + r * SCENES on (skip the scenes "
                      "that the rounds of the --from model used)")
  p.add_argument("--extra-on-policy", nargs="+", default=[], metavar="NPZ",
                 help="on-policy examples of earlier runs (file(s) or glob(s), e.g. "
                      "'runs/l2/round-*/on_policy.npz') joined to every round's")
  p.add_argument("--steps", type=int, default=600, help="optimizer steps per round")
  p.add_argument("--learning-rate", type=float, default=2e-4)
  p.add_argument("--encoder-steps", type=int, default=0,
                 help="also fine-tune the encoder (proposals, SIMPL-AR) for this many steps per round, "
                      "before the denoiser")
  p.add_argument("--encoder-learning-rate", type=float, default=5e-4)
  p.add_argument("--history-dropout", type=float, default=0.0, metavar="P",
                 help="with --encoder-steps: the share of agents whose history before the current "
                      "step the encoder does not see in training (`training.perturb.drop_history`)")
  p.add_argument("--batch-size", type=int, default=None, help="default: the model's stage-2 batch size")
  p.add_argument("--mix", type=float, default=0.5, help="fraction of each batch from on-policy examples")
  p.add_argument("--times", type=int, nargs="+", default=[20, 30, 40, 50],
                 help="visited steps cut into examples (the rollout starts at 10)")
  p.add_argument("--max-offset", type=float, default=8.0, help="m; farther agents are not trained on")
  p.add_argument("--straight-tail", action="store_true",
                 help="continue a log past its end straight at constant speed (rounds 0-6 of v5), "
                      "not along the lane centres")
  p.add_argument("--targets", choices=("rejoin", "guided", "hybrid"), default="rejoin",
                 help="on-policy labels: rejoin = from the simulated pose back onto the log; guided = the "
                      "model's own cold plan at the visited state under objective guidance (guidance "
                      "distilled into the unguided policy); hybrid = rejoin where that path stays on the "
                      "road and clear of the others, guided elsewhere")
  p.add_argument("--rejoin-margin", type=float, default=0.3, metavar="M",
                 help="hybrid targets: a vehicle keeps its re-joining target only if it stays M m inside the road")
  p.add_argument("--rejoin-partial-logs", action="store_true",
                 help="hybrid targets: agents whose log ends before the record's may keep their re-joining target")
  p.add_argument("--teacher-w-map", type=float, default=100.0, help="guided targets: the teacher's w_map")
  p.add_argument("--teacher-w-coll", type=float, default=1.0, help="guided targets: the teacher's w_coll")
  p.add_argument("--teacher-guided-steps", type=int, default=3,
                 help="guided targets: the teacher's guided DDIM steps (of 5)")
  p.add_argument("--teacher-inner-steps", type=int, default=3,
                 help="guided targets: gradient steps per guided DDIM step")
  p.add_argument("--prior-spread", choices=("uniform", "weighted"), default=None,
                 help="pcdiff: re-train the denoiser with this proposal prior (config diffusion.prior_spread; "
                      "default: --from's)")
  p.add_argument("--lane-inputs", action="store_true",
                 help="give the denoiser (--policy simpl-ar: SIMPL-AR's encoder) each agent's lane-relative "
                      "inputs (model.lane_context) through new zero-initialised projections, trained from here on")
  p.add_argument("--anchor-inputs", action="store_true",
                 help="pcdiff: condition the denoiser on one proposal per agent (config "
                      "diffusion.denoiser.anchor_inputs; a new zero-initialised projection, trained from here on)")
  p.add_argument("--map-anchor", choices=("sdc", "agents"), default=None,
                 help="the map crop of the rounds' rollouts and of every training example (default: the "
                      "model's; real scenes are wider than the SDC's 256 pieces: 'agents' keeps each "
                      "agent's road in view, as evaluation runs)")
  p.add_argument("--rollout-batch", type=int, default=4, help="scenes per jitted rollout call")
  p.add_argument("--max-agents", type=int, default=64, help="reactive agents the policy controls")
  p.add_argument("--seed", type=int, default=0)
  p.add_argument("--no-progress", action="store_true")
  args = p.parse_args(argv)
  for name in ("rounds", "scenes", "steps", "rollout_batch", "max_agents"):
    if getattr(args, name) < 1:
      p.error(f"--{name.replace('_', '-')} must be >= 1")
  if args.batch_size is not None and args.batch_size < 2:
    p.error("--batch-size must be >= 2")
  if not 0.0 < args.mix < 1.0:
    p.error("--mix must be in (0, 1)")
  if not 0.0 < args.real_share <= 1.0:
    p.error("--real-share must be in (0, 1]")
  if args.target_fit is not None and args.target_fit < 0:
    p.error("--target-fit must be >= 0")
  if args.target_max_rms is not None and args.target_max_rms < 0:
    p.error("--target-max-rms must be >= 0")
  if args.learning_rate <= 0 or args.encoder_learning_rate <= 0:
    p.error("learning rates must be > 0")
  if args.first_scene < 0:
    p.error("--first-scene must be >= 0")
  if args.encoder_steps < 0:
    p.error("--encoder-steps must be >= 0")
  if not 0.0 <= args.history_dropout < 1.0:
    p.error("--history-dropout must be in [0, 1)")
  if args.history_dropout and not args.encoder_steps:
    p.error("--history-dropout trains the encoder: give --encoder-steps")
  if args.policy == "simpl-ar" and not args.encoder_steps:
    p.error("--policy simpl-ar trains SIMPL-AR's encoder only: give --encoder-steps")
  if args.policy == "simpl-ar" and args.encoder_from:
    p.error("--encoder-from is an option of --policy pcdiff (SIMPL-AR is its encoder)")
  if args.policy == "simpl-ar" and args.targets != "rejoin":
    p.error(f"--targets {args.targets} is an option of --policy pcdiff")
  if not 1 <= args.teacher_guided_steps <= 5 or args.teacher_inner_steps < 1:
    p.error("--teacher-guided-steps must be in [1, 5] and --teacher-inner-steps >= 1")
  if args.rejoin_margin < 0:
    p.error(f"--rejoin-margin must be >= 0 (m inside the road), got {args.rejoin_margin}")
  if args.teacher_w_map < 0 or args.teacher_w_coll < 0:
    p.error("--teacher-w-map and --teacher-w-coll must be >= 0")
  return args


def _expand(patterns) -> list[str]:
  """The files of the globs in PATTERNS, sorted; a pattern with no file is an error."""
  import glob
  files = []
  for pattern in patterns:
    found = sorted(glob.glob(pattern))
    if not found:
      raise FileNotFoundError(f"--extra-on-policy {pattern}: no such file")
    files.extend(found)
  return files


def _read_extra(path: str, like):
  """On-policy examples of an earlier run, checked against the model's example shapes."""
  import zipfile
  from pcdiff_jax.training import data as data_lib
  try:
    examples, _ = data_lib.read_examples(path)
  except (OSError, KeyError, ValueError, zipfile.BadZipFile) as err:
    raise ValueError(f"--extra-on-policy {path}: not an on_policy.npz of experiments.finetune ({err})") from None
  shapes = lambda ex: [a.shape[1:] for a in jax.tree_util.tree_leaves(ex)]
  if shapes(examples) != shapes(like):
    raise ValueError(f"--extra-on-policy {path}: its examples do not have this model's shapes "
                     "(collected with another config)")
  return examples


def _copy_dir(src: str, dst: str) -> None:
  """Replaces DST by a copy of SRC (through a temporary folder: an interrupted
  copy never leaves half a checkpoint)."""
  if os.path.isdir(src) and os.path.abspath(src) != os.path.abspath(dst):
    tmp = dst + ".tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    shutil.copytree(src, tmp)
    shutil.rmtree(dst, ignore_errors=True)
    os.replace(tmp, dst)


def _publish_simpl_ar(round_dir: str, source: str, workdir: str) -> None:
  """WORKDIR/simpl_ar := the round's SIMPL-AR encoder; the diffusion policy
  and its encoder stay those of --from."""
  from pcdiff_jax.training import encoder_stage
  for stage in ("encoder", "diffusion"):
    _copy_dir(os.path.join(source, stage), os.path.join(workdir, stage))
  _copy_dir(os.path.join(round_dir, encoder_stage.STAGE_DIR), os.path.join(workdir, encoder_stage.SIMPL_AR_DIR))


def _publish(round_dir: str, encoder_dir: str, workdir: str) -> None:
  """WORKDIR/diffusion := the round's model; WORKDIR/encoder := the round's
  fine-tuned encoder, else the one the policy was conditioned on (ENCODER_DIR)."""
  encoder = os.path.join(round_dir, "encoder")
  for stage, src in (("diffusion", os.path.join(round_dir, "diffusion")),
                     ("encoder", encoder if os.path.isdir(encoder) else encoder_dir)):
    _copy_dir(src, os.path.join(workdir, stage))


def _swap_encoder(models, model_cfg, folder: str):
  """(models, cfg) conditioned on FOLDER's SIMPL-AR encoder, and that encoder's stage folder."""
  from pcdiff_jax.training import encoder_stage
  if not os.path.isdir(folder):
    raise FileNotFoundError(f"--encoder-from {folder}: no such folder")
  params, enc_cfg = encoder_stage.load_simpl_ar(folder)
  if enc_cfg.features != model_cfg.features:
    raise ValueError(f"--encoder-from {folder}: its encoder reads other features than the policy's")
  return (models.replace(encoder=params), dataclasses.replace(model_cfg, encoder=enc_cfg.encoder),
          os.path.join(folder, encoder_stage.simpl_ar_dir(folder)))


def main(argv=None) -> int:
  args = parse_args(argv)
  _args.setup_logging()
  from pcdiff_jax import evaluation, policy
  from pcdiff_jax.training import closed_loop, diffusion_stage, encoder_stage, trainer
  from pcdiff_jax.training import data as data_lib
  try:
    files = womd.expand_paths(args.data)
    simpl = args.policy == "simpl-ar"
    needed = "encoder" if simpl else "diffusion"
    if not os.path.isdir(os.path.join(args.source, needed)):
      raise FileNotFoundError(f"--from {args.source}: no {needed}/ model folder there")
    if simpl:
      models, model_cfg = encoder_stage.load_simpl_ar(args.source)   # SIMPL-AR's params: its encoder's
      if args.lane_inputs:
        from pcdiff_jax.model import encoder
        enc_cfg = dataclasses.replace(model_cfg.encoder, lane_inputs=True)
        model_cfg = dataclasses.replace(model_cfg, encoder=enc_cfg)
        models = encoder.with_new_inputs(models, enc_cfg)
    else:
      models, model_cfg = diffusion_stage.load(args.source)
      encoder_dir = os.path.join(args.source, "encoder")
      if args.encoder_from:
        models, model_cfg, encoder_dir = _swap_encoder(models, model_cfg, args.encoder_from)
      new_inputs = {k: True for k, on in (("lane_inputs", args.lane_inputs),
                                          ("anchor_inputs", args.anchor_inputs)) if on}
      if new_inputs:
        from pcdiff_jax.model import denoiser
        den_cfg = dataclasses.replace(model_cfg.diffusion.denoiser, **new_inputs)
        model_cfg = dataclasses.replace(model_cfg, diffusion=dataclasses.replace(model_cfg.diffusion,
                                                                                 denoiser=den_cfg))
        models = models.replace(denoiser=denoiser.with_new_inputs(models.denoiser, den_cfg))
    if args.map_anchor is not None:
      model_cfg = dataclasses.replace(model_cfg, features=dataclasses.replace(
          model_cfg.features, map_anchor=args.map_anchor))
    if args.target_fit is not None and not simpl:
      model_cfg = dataclasses.replace(model_cfg, diffusion=dataclasses.replace(
          model_cfg.diffusion, target_fit_sigma=args.target_fit))
    if args.target_max_rms is not None and not simpl:
      model_cfg = dataclasses.replace(model_cfg, diffusion=dataclasses.replace(
          model_cfg.diffusion, target_max_rms=args.target_max_rms))
    if args.prior_spread is not None and not simpl:
      model_cfg = dataclasses.replace(model_cfg, diffusion=dataclasses.replace(
          model_cfg.diffusion, prior_spread=args.prior_spread))
    metrics_cfg = dataclasses.replace(model_cfg.metrics, max_reactive_agents=args.max_agents)
    run_cfg = evaluation.with_agent_cap(model_cfg, metrics_cfg)
    actor = None
    if simpl:
      from pcdiff_jax.baselines import simpl_ar
      actor = simpl_ar.simpl_ar(run_cfg)
    ocfg = closed_loop.OnPolicyConfig(times=tuple(args.times), max_offset=args.max_offset, mix=args.mix,
                                      lane_tail=not args.straight_tail, targets=args.targets,
                                      drop_log_overlaps=args.drop_log_overlaps,
                                      drop_log_offroad=args.drop_log_offroad,
                                      rejoin_margin=args.rejoin_margin,
                                      rejoin_whole_logs=not args.rejoin_partial_logs)
    teacher = None
    if args.targets != "rejoin":
      from pcdiff_jax.model import guidance
      teacher_guidance = guidance.GuidanceConfig(
          mode="objective", w_map=args.teacher_w_map, w_coll=args.teacher_w_coll,
          guided_steps=args.teacher_guided_steps, inner_steps=args.teacher_inner_steps)
      teacher = policy.PolicyConfig(ddim_steps=5, warm_start=False, select_samples=1,
                                    guidance=teacher_guidance, pedestrian_plan="sample")
    tc = model_cfg.diffusion_train
    tc = dataclasses.replace(tc, total_steps=args.steps, learning_rate=args.learning_rate,
                             warmup_steps=min(50, args.steps // 10), eval_every=args.steps,
                             checkpoint_every=min(100, args.steps), seed=args.seed,
                             batch_size=args.batch_size or tc.batch_size)
    cache = args.cache_dir or os.path.join(args.workdir, "cache")
    spec = encoder_stage.cache_spec(model_cfg)
    logged, _ = data_lib.load_or_build(files, spec, cache, "train", progress=not args.no_progress)
    real, round_files = None, files
    if args.real_data:
      round_files = womd.expand_paths(args.real_data)
      real_spec = dataclasses.replace(spec, drop_log_overlaps=args.drop_log_overlaps,
                                      drop_log_offroad=args.drop_log_offroad)
      real, _ = data_lib.load_or_build(round_files, real_spec, cache, "real", progress=not args.no_progress)
    os.makedirs(args.workdir, exist_ok=True)
    history, gathered = [], [_read_extra(path, logged) for path in _expand(args.extra_on_policy)]
    for r in range(args.rounds):
      round_dir = os.path.join(args.workdir, f"round-{r}")
      os.makedirs(round_dir, exist_ok=True)
      path = os.path.join(round_dir, "on_policy.npz")
      t0 = time.time()
      if os.path.exists(path):
        on_policy, info = data_lib.read_examples(path)
      else:
        on_policy, info = closed_loop.collect(
            models, run_cfg, _round_policy(args.round_policy), round_files, ocfg,
            first=args.first_scene + r * args.scenes,
            count=args.scenes, batch_size=args.rollout_batch, seed=args.seed + r,
            progress=not args.no_progress, teacher=teacher, actor=actor)
        info["minutes"] = (time.time() - t0) / 60
        data_lib.write_examples(path, on_policy, info)
      print(f"round {r}: {json.dumps(info)}")
      gathered.append(on_policy)
      # DAgger: every round trains on the states of all rounds so far.
      on_policy = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs), *gathered)
      t1 = time.time()
      if args.encoder_steps:
        etc = dataclasses.replace(model_cfg.encoder_train, total_steps=args.encoder_steps,
                                  learning_rate=args.encoder_learning_rate,
                                  warmup_steps=min(50, args.encoder_steps // 10),
                                  eval_every=args.encoder_steps, checkpoint_every=min(100, args.encoder_steps),
                                  seed=args.seed, batch_size=args.batch_size or model_cfg.encoder_train.batch_size,
                                  history_dropout=args.history_dropout)
        enc_state, _ = closed_loop.finetune_encoder(models if simpl else models.encoder, model_cfg, logged,
                                                    on_policy, round_dir, etc, ocfg,
                                                    progress=not args.no_progress, real=real,
                                                    real_share=args.real_share)
        state = enc_state
        models = enc_state.params if simpl else models.replace(encoder=enc_state.params)
      if not simpl:
        state, _ = closed_loop.finetune(models, model_cfg, logged, on_policy, round_dir, tc, ocfg,
                                        progress=not args.no_progress, real=real,
                                        real_share=args.real_share)
        models, _ = diffusion_stage.load(round_dir)
      history.append({"round": r, "collect": info, "finetune_minutes": (time.time() - t1) / 60,
                      "step": int(state.step)})
      if simpl:
        _publish_simpl_ar(round_dir, args.source, args.workdir)
      else:
        _publish(round_dir, encoder_dir, args.workdir)
        encoder_dir = os.path.join(args.workdir, "encoder")
    out = {"from": args.source, "rounds": history, "args": vars(args)}
    with open(os.path.join(args.workdir, "finetune_summary.json"), "w") as f:
      json.dump(out, f, indent=2)
    print(json.dumps(out, indent=2))
    final = "simpl_ar/ (SIMPL-AR's encoder)" if simpl else "diffusion/ (+ encoder/)"
    print(f"wrote {args.workdir}/finetune_summary.json, the final model in {args.workdir}/{final} "
          f"and each round in {args.workdir}/round-*/")
  except (FileNotFoundError, ValueError, trainer.CheckpointMismatch) as err:
    print(f"error: {err}", file=sys.stderr)
    return 2
  except KeyboardInterrupt:
    return 130
  return 0


if __name__ == "__main__":
  sys.exit(main())
