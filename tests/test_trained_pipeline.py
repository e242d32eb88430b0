"""Everything that needs a model trained through the CLI, on one tiny model
trained once (the fixture below): the train CLI (resume, logs, workdir guard),
both stages and the export, an on-policy fine-tuning round, and the main job
(`make demo`) end to end with its diagnostics."""
from __future__ import annotations

import dataclasses
import glob
import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments import demo
from pcdiff_jax.config import get_config
from pcdiff_jax.model import planner

CFG = get_config("tiny")
pytestmark = pytest.mark.slow   # trains a tiny model through the CLI first (minutes on 2 cores)


def _train(argv):
  from experiments import train
  return train.main(argv)


@pytest.fixture(scope="module")
def tiny_trained(tmp_path_factory, womd_path):
  """Both stages of the tiny preset trained through the CLI on the real record,
  once per session: the encoder for 2 steps, then `--stage all --steps 4`
  (which resumes the encoder at 2, as `make demo --train` calls it), the
  no-prior variant beside it, and the export as a shipped folder.

  Module-scoped: `make test` distributes whole files (`--dist loadfile`),
  so one worker trains it once for every test here.
  Returns {"work", "shipped", "base" (the common CLI args), "codes"}.
  """
  from experiments import export, train
  root = tmp_path_factory.mktemp("tiny_trained")
  work, shipped = str(root / "w"), str(root / "shipped")
  base = ["--config", "tiny", "--data", womd_path, "--val-data", womd_path, "--workdir", work,
          "--no-progress"]
  codes = {"encoder-2": train.main(["--stage", "encoder", "--steps", "2"] + base),
           "all-4": train.main(["--stage", "all", "--steps", "4"] + base),
           "no-prior-2": train.main(["--stage", "diffusion", "--steps", "2", "--no-prior"] + base),
           "export": export.main(["--workdir", work, "--out", shipped])}
  return {"work": work, "shipped": shipped, "base": base, "codes": codes}


def test_train_cli_resumes_logs_and_guards_its_workdir(tiny_trained, womd_path, capsys):
  work = tiny_trained["work"]
  assert tiny_trained["codes"] == {"encoder-2": 0, "all-4": 0, "no-prior-2": 0, "export": 0}
  lines = [json.loads(l) for l in open(os.path.join(work, "encoder", "metrics.jsonl"))]
  assert [d["step"] for d in lines if "train/loss" in d] == [1, 2, 3, 4]   # resumed at 2: no step repeated
  assert any("val/min_fde" in d for d in lines)
  # Another model in the same workdir is refused with the differing fields named.
  assert _train(["--stage", "encoder", "--config", "cpu", "--data", womd_path, "--workdir", work,
                 "--no-progress", "--steps", "1"]) == 2
  assert "encoder.d_model" in capsys.readouterr().err
  # Last, as it skips without TensorFlow: TensorBoard event files hold the same scalars, tagged
  # for its scalars plugin.
  tf = pytest.importorskip("tensorflow", reason="TensorBoard event files are written only with TensorFlow (the `tf` extra)")
  from tensorflow.core.util import event_pb2
  tags = set()
  for f in glob.glob(os.path.join(work, "encoder", "tb", "*")):
    for rec in tf.data.TFRecordDataset(f):
      for v in event_pb2.Event.FromString(rec.numpy()).summary.value:
        tags.add((v.tag, v.metadata.plugin_data.plugin_name))
  assert ("train/loss", "scalars") in tags and ("val/min_fde", "scalars") in tags


def test_both_stages_sample_and_export_as_a_shipped_model(tiny_trained, womd_path, tmp_path, capsys):
  work, shipped = tiny_trained["work"], tiny_trained["shipped"]
  # Stage 2, both variants, beside the same encoder.
  summary = json.load(open(os.path.join(work, "all_summary.json")))
  assert summary["encoder"]["step"] == 4 and summary["diffusion"]["step"] == 4
  assert np.isfinite(summary["diffusion"]["val"]["min_ade"])
  no_prior = json.load(open(os.path.join(work, "diffusion_summary.json")))
  assert no_prior["diffusion"]["step"] == 2 and np.isfinite(no_prior["diffusion"]["val"]["min_ade"])
  from pcdiff_jax.training import diffusion_stage
  from pcdiff_jax.training import data as D
  models, cfg = diffusion_stage.load(work)
  assert cfg.encoder == CFG.encoder and cfg.diffusion == CFG.diffusion
  ex, _ = D.load_or_build(womd_path, diffusion_stage.encoder_stage.cache_spec(cfg),
                          os.path.join(work, "cache"), "val", progress=False)
  cond = planner.condition(models.encoder, models.stats, jax.tree_util.tree_map(jnp.asarray, ex.feats), cfg)
  for n in (1, 3):
    y0 = planner.sample(models.denoiser, cond, cfg, jax.random.key(0), n)
    states = planner.decode_states(models.stats, cond, y0, cfg)
    assert states.shape == (1, cfg.features.max_agents, cfg.encoder.horizon, 4)
    assert np.all(np.isfinite(np.asarray(states)))
  # The export: parameters only, loadable by the one-call loader.
  from experiments import export
  import pcdiff_jax
  assert export.main(["--workdir", work, "--out", shipped]) == 2          # never overwrites
  assert "exists" in capsys.readouterr().err
  loaded, loaded_cfg = pcdiff_jax.pretrained(path=shipped)
  from pcdiff_jax import shipped as shipped_lib
  assert shipped_lib.read_config(shipped) == cfg                           # as trained: the SDC's crop
  assert loaded_cfg == shipped_lib.run_config(cfg) and loaded_cfg.features.map_anchor == "agents"
  for a, b in zip(jax.tree_util.tree_leaves(loaded), jax.tree_util.tree_leaves(models)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  enc, _ = pcdiff_jax.pretrained(path=shipped, stage="encoder")
  assert jax.tree_util.tree_structure(enc) == jax.tree_util.tree_structure(models.encoder)
  with pytest.raises(FileNotFoundError, match="no shipped model"):
    pcdiff_jax.pretrained(path=str(tmp_path / "nothing"))


def test_finetune_round_moves_both_stages_and_keeps_the_latent(tiny_trained, womd_path, tmp_path, capsys):
  """On-policy fine-tuning (a CAT-K-style round, hybrid targets) from the shipped
  folder: the encoder and the denoiser move, the latent stays, and the result
  loads as a model (both stages, so SIMPL-AR takes it too)."""
  import pcdiff_jax
  from experiments import finetune
  from pcdiff_jax import policy
  from pcdiff_jax.training import diffusion_stage
  models, cfg = pcdiff_jax.pretrained(path=tiny_trained["shipped"])
  ft = str(tmp_path / "ft")
  argv = ["--from", tiny_trained["shipped"], "--data", womd_path, "--workdir", ft,
          "--cache-dir", os.path.join(tiny_trained["work"], "cache"),
          "--scenes", "1", "--steps", "2", "--encoder-steps", "1", "--times", "12", "13", "--max-agents", "8",
          "--batch-size", "2", "--round-policy", "defaults", "--map-anchor", "agents", "--no-progress",
          "--targets", "hybrid", "--teacher-guided-steps", "1", "--teacher-inner-steps", "1"]
  assert finetune.main(argv) == 0
  # Today's inference defaults with one sample; "v8" (the default) pins what v3-v8's rounds rolled out.
  assert finetune._round_policy("defaults") == dataclasses.replace(policy.PolicyConfig(), select_samples=1)
  assert (finetune._round_policy("v8").warm_step, finetune._round_policy("v8").temporal_ensemble) == (30, (0.3, 0.0))
  tuned, tuned_cfg = diffusion_stage.load(ft)
  assert tuned_cfg.diffusion == cfg.diffusion and tuned_cfg.encoder == cfg.encoder
  assert tuned_cfg.features.map_anchor == "agents"          # the rounds' and the examples' crop
  for a, b in zip(jax.tree_util.tree_leaves(tuned.stats), jax.tree_util.tree_leaves(models.stats)):
    np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
  changed = lambda x, y: any(not np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                             zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)))
  assert changed(tuned.denoiser, models.denoiser) and changed(tuned.encoder, models.encoder)
  enc_ft, _ = pcdiff_jax.pretrained(path=ft, stage="encoder")
  assert not changed(enc_ft, tuned.encoder)
  summary = json.load(open(os.path.join(ft, "finetune_summary.json")))
  assert summary["rounds"][0]["collect"]["examples"] == 2 and summary["rounds"][0]["step"] == 2
  assert finetune.main(argv) == 0                                         # finished rounds are kept
  assert finetune.main(argv[:1] + [str(tmp_path / "nothing")] + argv[2:]) == 2
  assert "no diffusion/" in capsys.readouterr().err


def test_finetune_simpl_ar_trains_its_own_encoder_only(tiny_trained, womd_path, tmp_path, capsys):
  """`--policy simpl-ar`: a CAT-K round on SIMPL-AR's own closed loop moves
  only the baseline's encoder (WORKDIR/simpl_ar, which SIMPL-AR, pretrained
  and export then read); the diffusion policy and its encoder stay --from's.
  `--encoder-from` then conditions ours on that (lane-aware) encoder, with the
  first run's examples joining its round (`--extra-on-policy`)."""
  import pcdiff_jax
  from experiments import finetune
  from pcdiff_jax import evaluation, shipped
  same = lambda x, y: all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in
                          zip(jax.tree_util.tree_leaves(x), jax.tree_util.tree_leaves(y)))
  source = tiny_trained["shipped"]
  models, _ = pcdiff_jax.pretrained(path=source)
  cache = os.path.join(tiny_trained["work"], "cache")
  ft = str(tmp_path / "sa")
  argv = ["--policy", "simpl-ar", "--from", source, "--data", womd_path, "--workdir", ft,
          "--cache-dir", cache, "--scenes", "1", "--encoder-steps", "1", "--times", "12",
          "--max-agents", "8", "--batch-size", "2", "--no-progress", "--lane-inputs"]
  assert finetune.main(argv) == 0
  tuned, _ = pcdiff_jax.pretrained(path=ft)
  assert same(tuned.denoiser, models.denoiser) and same(tuned.encoder, models.encoder)
  baseline, baseline_cfg = pcdiff_jax.pretrained(path=ft, stage="simpl-ar")
  assert baseline_cfg.encoder.lane_inputs and "in_lane" in baseline["params"]
  assert same(pcdiff_jax.pretrained(path=source, stage="simpl-ar")[0], models.encoder)  # none of its own
  _, params = evaluation.make_actor(evaluation.EvalConfig(method="simpl-ar", checkpoint=ft))
  assert same(params, baseline)
  out = str(tmp_path / "export")
  assert set(shipped.export(ft, out)) == {"encoder", "diffusion", "simpl_ar"}
  assert same(pcdiff_jax.pretrained(path=out, stage="simpl-ar")[0], baseline)
  # --encoder-from (v8): ours conditioned on that lane-aware encoder; its round re-trains the
  # denoiser on it, and the result's encoder (policy and stage folder) is that encoder.
  # Examples of an earlier run join every round's; a file that is not one is refused by name.
  extra = os.path.join(ft, "round-0", "on_policy.npz")
  swapped = str(tmp_path / "swap")
  swap = ["--from", source, "--encoder-from", ft, "--data", womd_path, "--workdir", swapped,
          "--cache-dir", cache, "--scenes", "1", "--steps", "1", "--times", "12", "--max-agents", "8",
          "--batch-size", "2", "--no-progress"]
  assert finetune.main(swap + ["--extra-on-policy", extra]) == 0
  ours, ours_cfg = pcdiff_jax.pretrained(path=swapped)
  assert ours_cfg.encoder.lane_inputs and same(ours.encoder, baseline)
  assert not same(ours.denoiser, models.denoiser)
  assert same(pcdiff_jax.pretrained(path=swapped, stage="encoder")[0], baseline)
  # export --simpl-ar-from: the baseline keeps another folder's encoder (v11 keeps v10's).
  kept = str(tmp_path / "kept")
  assert set(shipped.export(swapped, kept, simpl_ar_from=source)) == {"encoder", "diffusion", "simpl_ar"}
  assert same(pcdiff_jax.pretrained(path=kept, stage="simpl-ar")[0], models.encoder)
  assert same(pcdiff_jax.pretrained(path=kept)[0].encoder, baseline)
  bad = tmp_path / "bad.npz"
  bad.write_text("not an archive")
  assert finetune.main(swap[:swap.index("--workdir") + 1] + [str(tmp_path / "sa3")]
                       + swap[swap.index("--workdir") + 2:] + ["--extra-on-policy", str(bad)]) == 2
  assert "bad.npz" in capsys.readouterr().err
  at = argv.index("--encoder-steps")
  with pytest.raises(SystemExit):
    finetune.parse_args(argv[:at] + argv[at + 2:])           # no --encoder-steps: nothing to train


def test_refit_head_moves_the_head_only_and_runs_as_both_methods(tiny_trained, womd_path, tmp_path, capsys):
  """`experiments.refit_head`: WORKDIR/encoder differs from --from's in the head
  alone, WORKDIR/diffusion is --from's denoiser reading it, and the summary has
  the metrics before and after."""
  import pcdiff_jax
  from experiments import refit_head
  source, out = tiny_trained["shipped"], str(tmp_path / "head")
  argv = ["--from", source, "--data", womd_path, "--real-data", womd_path, "--val-data", womd_path,
          "--workdir", out, "--steps", "3", "--batch-size", "2", "--cache-dir",
          os.path.join(tiny_trained["work"], "cache"), "--no-progress"]
  assert refit_head.main(argv) == 0
  before, _ = pcdiff_jax.pretrained(path=source)
  after, _ = pcdiff_jax.pretrained(path=out)
  assert jax.tree_util.tree_all(jax.tree_util.tree_map(np.array_equal, before.denoiser, after.denoiser))
  for name, sub in before.encoder["params"].items():
    same = all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(sub),
                                                     jax.tree_util.tree_leaves(after.encoder["params"][name])))
    assert same == (name not in ("head", "head_lane")), name
  summary = json.load(open(os.path.join(out, "refit_summary.json")))
  assert set(summary["val"][womd_path]) == {"before", "after"}
  assert "speed bias" in capsys.readouterr().out


def test_demo_pipeline_runs_end_to_end(tiny_trained, tmp_path):
  out = str(tmp_path / "demo")
  model = tiny_trained["shipped"]                   # a shipped folder, as `make demo` loads
  code = demo.main(["--out", out, "--checkpoint", model, "--num-val", "2", "--methods", "pcdiff", "cv",
                    "--batch-size", "2", "--real", "/nonexistent", "--num-real", "1", "--num-steps", "10",
                    "--no-progress"])
  assert code == 0
  for method in ("pcdiff", "cv"):
    with open(os.path.join(out, "eval", method, "metrics.json")) as f:
      summary = json.load(f)
    assert summary["num_scenarios"] == 2 and not summary["skipped"]
    assert os.listdir(os.path.join(out, "eval", method, "gifs"))
  with open(os.path.join(out, "table.md")) as f:
    text = f.read()
  assert "ours (prior, 5 DDIM steps" in text and "constant velocity" in text
  if os.path.exists(demo.REAL_VAL):   # every method, log replay first, on a real val scene too
    assert "real WOMD val scenes" in text and "log replay" in text
    for method in ("log", "pcdiff", "cv"):
      with open(os.path.join(out, "eval", "real", method, "metrics.json")) as f:
        assert json.load(f)["num_scenarios"] == 1
  # The closed-loop diagnostics run on the same model.
  from experiments import diagnose
  val = os.path.join(out, "data", "val-00000-of-00001.tfrecord")
  common = ["--checkpoint", model, "--scenarios", val, "--num-scenes", "1"]
  diagnose.main(common + ["--out", str(tmp_path / "first.json"), "first-action", "--warm-steps", "0,90"])
  diagnose.main(common + ["--out", str(tmp_path / "replay.json"), "replay", "--plans", "log,top1-latent"])
  diagnose.main(common + ["--out", str(tmp_path / "parked.json"), "parked", "--samples", "2", "--warm-steps", "30"])
  diagnose.main(common + ["--out", str(tmp_path / "drift.json"), "drift", "--method", "cv", "--solo"])
  with open(tmp_path / "drift.json") as f:
    drift = json.load(f)["rows"]
  assert set(drift) == {"1s", "2s", "4s", "6s", "8s"}
  assert drift["1s"]["agents"] > 0 and abs(drift["1s"]["lateral_mean"]) < 1.0   # CV holds its heading for 1 s
  assert {"longitudinal_mean", "speed_diff_mean", "moving_agents", "speed_diff_cruising",
          "cruising_agents"} <= set(drift["8s"])
  assert drift["8s"]["cruising_agents"] <= drift["8s"]["moving_agents"]   # cruising: moving at the start too
  # Constant velocity ignores the others: alone or not, each agent drives the same.
  assert drift["1s"]["solo_agents"] > 0
  for row in drift.values():
    if row["solo_agents"]:
      assert row["speed_diff_solo"] == pytest.approx(row["speed_diff_joint_same"], abs=1e-5)
      assert len(row["solo_per_agent"]) == row["solo_agents"]
  with open(tmp_path / "parked.json") as f:
    parked = json.load(f)["rows"]
  assert set(parked) == {"top1 proposal", "cold", "warm from top1 @30"}
  with open(tmp_path / "first.json") as f:
    rows = json.load(f)["rows"]
  assert set(rows) == {"log", "log_latent", "top1", "prior_centre", "sample", "sample_standard_init",
                       "warm_from_log_0", "warm_from_log_90", "agents_by_speed"}
  # Noised to step 0 the log's plan comes back as it went in: the warm row reads the log's latent.
  assert rows["warm_from_log_0"]["accel_mean"] == pytest.approx(rows["log_latent"]["accel_mean"], abs=0.05)
  assert sum(rows["agents_by_speed"].values()) == rows["log"]["agents"]   # the bins cover every mover
  assert set(rows["sample"]["speed_change_1s"]) == set(rows["agents_by_speed"])
  # prior_init=false starts a prior model from N(0, I) (pcdiff-noprior forces it off).
  from pcdiff_jax import evaluation, policy
  noprior = evaluation.EvalConfig(method="pcdiff", checkpoint=model, policy=policy.PolicyConfig(prior_init=False))
  assert evaluation.make_actor(noprior)[0].name == "pcdiff-noprior"
  assert evaluation.make_actor(dataclasses.replace(noprior, policy=policy.PolicyConfig()))[0].name == "pcdiff"
  with open(tmp_path / "replay.json") as f:
    replay = json.load(f)["rows"]
  assert replay["log"]["min_ade"] < 0.5                 # the log's own actions reproduce the log
  assert replay["top1-latent"]["min_ade"] > replay["log"]["min_ade"]
