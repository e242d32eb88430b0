"""experiments.rollout end to end on the real record, and its bad-input paths."""
from __future__ import annotations

import json
import os

import pytest

from experiments import rollout
from pcdiff_jax.data import tfrecord, womd


def test_rollout_cli_writes_metrics_and_gif(womd_path, tmp_path, real_state):
  # Two copies of the real scenario plus a garbage record: the bad one is
  # reported and skipped, the job finishes.
  path = tmp_path / "val.tfrecord"
  example = womd.state_to_example(real_state, "a3bb37c25ce56418").SerializeToString()
  with open(path, "wb") as f:
    for record in (example, b"not an example", example):
      tfrecord.write_record(f, record)
  out = tmp_path / "out"
  assert rollout.main(["--scenarios", str(path), "--method", "cv", "--out", str(out),
                       "--num-steps", "20", "--gifs", "1"]) == 0
  summary = json.loads((out / "metrics.json").read_text())
  assert summary["num_scenarios"] == 2 and len(summary["skipped"]) == 1
  assert "record 1" in summary["skipped"][0]["error"]
  assert 0.0 <= summary["rates"]["collision_rate"] <= 1.0 and summary["rates"]["num_evaluated"] == 128
  assert summary["runtime_ms_per_replan"]["mean"] > 0
  assert summary["config"]["guidance"]["w_map"] == 1.0   # the weight used, never "the default"
  assert summary["min_ade"]["mean"] >= 0 and summary["realism"]["mean"] >= 0
  assert len((out / "scenarios.jsonl").read_text().splitlines()) == 2
  assert (out / "gifs" / "a3bb37c25ce56418.gif").stat().st_size > 10_000
  assert "collision (%)" in (out / "metrics.md").read_text()


def test_rollout_cli_bad_arguments(tmp_path, capsys):
  with pytest.raises(SystemExit) as err:
    rollout.main(["--scenarios", "x", "--method", "nope", "--out", str(tmp_path)])
  assert err.value.code == 2
  with pytest.raises(SystemExit):
    rollout.main(["--scenarios", "x", "--out", str(tmp_path), "--num-steps", "0"])
  assert "--num-steps must be >= 1" in capsys.readouterr().err
  with pytest.raises(SystemExit) as err:   # past the selection's lookahead: a usage error, not a traceback
    rollout.main(["--scenarios", "x", "--out", str(tmp_path), "--policy", "select_stride=31"])
  assert err.value.code == 2 and "select_stride must be in [1, select_lookahead]" in capsys.readouterr().err
  for item, message in (("jerk_limit=-1,0", "jerk_limit must be two limits >= 0"),
                        ("select_neighbours=-1", "select_neighbours must be >= 0 (0: every pair)"),
                        ("speed=1", "unknown policy field 'speed'")):
    with pytest.raises(SystemExit) as err:
      rollout.main(["--scenarios", "x", "--out", str(tmp_path), "--policy", item])
    assert err.value.code == 2 and message in capsys.readouterr().err
  with pytest.raises(SystemExit) as err:   # a flag removed for --policy FIELD=VALUE
    rollout.main(["--scenarios", "x", "--out", str(tmp_path), "--select-samples", "4"])
  assert err.value.code == 2
  assert rollout.main(["--scenarios", str(tmp_path / "missing.tfrecord"), "--out", str(tmp_path / "o")]) == 2
  assert "missing.tfrecord" in capsys.readouterr().err


def test_rollout_cli_policy_file(tmp_path, capsys):
  """--policy-file: a JSON object of PolicyConfig fields, under --ddim-steps and --policy; an unknown
  field is a usage error naming the field and the file."""
  good = tmp_path / "policy.json"
  good.write_text('{"select_samples": 4, "jerk_limit": [1, 3], "ddim_steps": 10, "stop_hold": false}')
  args = rollout.parse_args(["--scenarios", "x", "--out", str(tmp_path / "o"), "--policy-file", str(good),
                             "--ddim-steps", "7", "--policy", "select_samples=2"])
  pcfg = args.policy_config
  assert (pcfg.select_samples, pcfg.jerk_limit, pcfg.ddim_steps, pcfg.stop_hold) == (2, (1.0, 3.0), 7, False)
  bad = tmp_path / "bad.json"
  bad.write_text('{"select_samples": 4, "start_gate": [2, 2]}')
  with pytest.raises(SystemExit) as err:
    rollout.parse_args(["--scenarios", "x", "--out", str(tmp_path / "o"), "--policy-file", str(bad)])
  message = capsys.readouterr().err
  assert err.value.code == 2 and str(bad) in message and "unknown policy field 'start_gate'" in message
  with pytest.raises(SystemExit) as err:
    rollout.parse_args(["--scenarios", "x", "--out", str(tmp_path / "o"), "--policy-file", str(tmp_path / "none.json")])
  assert err.value.code == 2 and "none.json" in capsys.readouterr().err


def test_rollout_help_is_short_and_lists_the_policy_fields(capsys):
  with pytest.raises(SystemExit):
    rollout.parse_args(["--help"])
  text = capsys.readouterr().out
  assert "select_samples=8" in text and "still_gate=2.0,1.0" in text and "--select-samples" not in text
  options = [line for line in text.splitlines() if line.startswith("  -")]
  assert len(options) <= 37, options   # 52 with one flag per policy field


def test_wosac_takes_the_same_policy_options(tmp_path, capsys):
  from experiments import wosac
  args = wosac.parse_args(["--scenarios", "x", "--out", str(tmp_path / "s.binproto"), "--method", "pcdiff",
                           "--checkpoint", "c", "--ddim-steps", "3", "--policy", "select_samples=4", "eta=0.5"])
  pcfg = args.policy_config
  assert (pcfg.ddim_steps, pcfg.select_samples, pcfg.eta, pcfg.replan_every) == (3, 4, 0.5, 2)
  for bad, named in (("bogus=1", "bogus"), ("ddim_steps=0", "ddim_steps")):
    with pytest.raises(SystemExit) as err:
      wosac.parse_args(["--scenarios", "x", "--out", str(tmp_path / "s.binproto"), "--method", "cv", "--policy", bad])
    assert err.value.code == 2 and named in capsys.readouterr().err


def test_the_submission_acknowledges_the_closed_loop_rule_at_1_hz_or_more(tmp_path):
  from experiments import wosac
  from pcdiff_jax import evaluation
  from pcdiff_jax import wosac as wosac_lib
  for method, every, complies, hz in (("pcdiff", 1, True, 10), ("pcdiff", 2, True, 5), ("pcdiff", 10, True, 1),
                                      ("pcdiff", 11, False, 10 / 11), ("cv", 11, True, 10)):   # cv decides every step
    args = wosac.parse_args(["--scenarios", "x", "--out", str(tmp_path / "s.binproto"), "--method", method,
                             "--checkpoint", "c", "--replan-every", str(every)])
    ev = evaluation.EvalConfig(method=method, checkpoint="c", policy=args.policy_config)
    meta = wosac._metadata(args, wosac_lib.WosacConfig(eval=ev))
    assert meta.acknowledge_complies_with_closed_loop_requirement is complies
    assert f"planned at {hz:g} Hz" in meta.description


def test_the_map_crop_flags_reach_the_eval_config(tmp_path, capsys):
  from experiments import wosac
  from pcdiff_jax import evaluation
  from pcdiff_jax import wosac as wosac_lib
  from pcdiff_jax.config import get_config
  for cli in (wosac, rollout):
    out = str(tmp_path / ("s.binproto" if cli is wosac else "o"))
    common = ["--scenarios", "x", "--out", out, "--method", "pcdiff", "--checkpoint", "c"]
    args = cli.parse_args(common + ["--map-pieces", "96", "--map-anchor", "agents"])
    assert args.map_crop == {"map_pieces": 96, "map_anchor": "agents"}
    default = wosac_lib.EXPORT_MAP_PIECES if cli is wosac else None   # the export crops by default
    assert cli.parse_args(common).map_crop == {"map_pieces": default, "map_anchor": "agents"}
    with pytest.raises(SystemExit) as err:
      cli.parse_args(common + ["--map-pieces", "0"])
    assert err.value.code == 2 and "--map-pieces must be >= 1" in capsys.readouterr().err
  model_cfg = get_config("tiny")
  run = evaluation.run_config(model_cfg, evaluation.EvalConfig(map_pieces=24, map_anchor="agents"))
  assert (run.features.max_polylines, run.features.map_anchor) == (24, "agents")
  assert run.features.max_agents == evaluation.EvalConfig().metrics.max_reactive_agents + 1
  run = evaluation.run_config(model_cfg, evaluation.EvalConfig()).features   # runs anchored on the agents
  assert (run.max_polylines, run.map_anchor) == (model_cfg.features.max_polylines, "agents")
  kept = evaluation.run_config(model_cfg, evaluation.EvalConfig(map_anchor=None)).features
  assert (kept.max_polylines, kept.map_anchor) == (model_cfg.features.max_polylines, "sdc")
  more = evaluation.run_config(model_cfg, evaluation.EvalConfig(map_pieces=10 ** 6)).features
  assert more.max_polylines == model_cfg.features.max_polylines   # never more than it was trained with
  with pytest.raises(ValueError, match="map_anchor"):
    evaluation.run_config(model_cfg, evaluation.EvalConfig(map_anchor="ego"))


def test_the_start_velocity_flag_reaches_the_eval_config(tmp_path, capsys):
  from experiments import _args, wosac
  for cli in (wosac, rollout):
    common = ["--scenarios", "x", "--out", str(tmp_path / ("s.binproto" if cli is wosac else "o")), "--method", "cv"]
    assert _args.start_options(cli.parse_args(common)) == {"fit_start_velocity": True}
    tracked = cli.parse_args(common + ["--start-velocity", "tracked"])
    assert _args.start_options(tracked) == {"fit_start_velocity": False}
    with pytest.raises(SystemExit) as err:
      cli.parse_args(common + ["--start-velocity", "logged"])
    assert err.value.code == 2 and "--start-velocity" in capsys.readouterr().err


CLIS = ("bench", "demo", "diagnose", "export", "family_table", "finetune", "guidance_figure", "latent_report",
        "make_data", "open_loop", "refit_head", "rollout", "train", "wosac")
# Each CLI's output option, given a path that cannot be written as asked.
BAD_OUTPUTS = {"demo": ("--out", "file"), "diagnose": ("--out", "folder"), "export": ("--out", "file"),
               "finetune": ("--workdir", "file"), "guidance_figure": ("--out", "file"),
               "latent_report": ("--out", "file"), "make_data": ("--out", "below-file"),
               "open_loop": ("--out", "file"), "refit_head": ("--workdir", "file"), "rollout": ("--out", "file"), "train": ("--workdir", "file"),
               "wosac": ("--out", "folder")}


@pytest.mark.parametrize("name", CLIS)
def test_every_cli_has_help_and_rejects_a_bad_output_path(name, tmp_path, capsys):
  import importlib
  cli = importlib.import_module(f"experiments.{name}")
  with pytest.raises(SystemExit) as err:
    cli.main(["--help"])
  assert err.value.code == 0 and "usage" in capsys.readouterr().out
  if name not in BAD_OUTPUTS:
    return
  option, kind = BAD_OUTPUTS[name]
  a_file = tmp_path / "results.json"
  a_file.write_text("{}")
  path = {"file": a_file, "folder": tmp_path, "below-file": a_file / "sub"}[kind]
  with pytest.raises(SystemExit) as err:
    cli.main([option, str(path)])
  message = capsys.readouterr().err
  assert err.value.code == 2 and str(path) in message and "Traceback" not in message
  assert a_file.read_text() == "{}"   # nothing already written is touched


def test_latent_report_needs_a_workdir_or_a_checkpoint(tmp_path, capsys):
  from experiments import latent_report
  with pytest.raises(SystemExit) as err:
    latent_report.main(["--val-data", "x.tfrecord", "--out", str(tmp_path / "o")])
  assert err.value.code == 2 and "--checkpoint" in capsys.readouterr().err
  assert latent_report.main(["--checkpoint", str(tmp_path / "none"), "--val-data", "x.tfrecord",
                             "--out", str(tmp_path / "o")]) == 2
  assert str(tmp_path / "none") in capsys.readouterr().err


def test_finetune_history_dropout_needs_an_encoder_to_train(tmp_path, capsys):
  from experiments import finetune
  base = ["--from", str(tmp_path), "--data", "x.tfrecord", "--workdir", str(tmp_path / "w")]
  for extra, named in ((["--history-dropout", "0.5"], "--encoder-steps"),
                       (["--history-dropout", "1.0", "--encoder-steps", "5"], "--history-dropout")):
    with pytest.raises(SystemExit) as err:
      finetune.parse_args(base + extra)
    assert err.value.code == 2 and named in capsys.readouterr().err
  assert finetune.parse_args(base + ["--history-dropout", "0.5", "--encoder-steps", "5"]).history_dropout == 0.5


def test_diagnose_drift_checks_its_policy_fields(tmp_path, capsys):
  from experiments import diagnose
  for bad, named in (("bogus=1", "bogus"), ("select_samples=0", "select_samples")):
    with pytest.raises(SystemExit) as err:
      diagnose.main(["--checkpoint", str(tmp_path), "--scenarios", "x.tfrecord", "drift", "--policy", bad])
    assert err.value.code == 2 and named in capsys.readouterr().err


def test_family_table_weights_scenarios_by_their_agents(tmp_path, capsys):
  from experiments import family_table
  rows = [{"scenario_id": "syn-merge-0-1-0000000", "collision_rate": 0.5, "offroad_rate": 0.0, "num_evaluated": 2},
          {"scenario_id": "syn-merge-0-1-0000001", "collision_rate": 0.0, "offroad_rate": 0.25, "num_evaluated": 8},
          {"scenario_id": "a3bb37c25ce56418", "collision_rate": 0.1, "offroad_rate": 0.2, "num_evaluated": 10}]
  (tmp_path / "scenarios.jsonl").write_text("".join(json.dumps(r) + "\n" for r in rows))
  table = family_table.rates_by_family(str(tmp_path / "scenarios.jsonl"))
  assert table["merge"] == pytest.approx((10.0, 20.0, 10)) and table["womd"] == pytest.approx((10.0, 20.0, 10))
  (tmp_path / "scenarios.jsonl").write_text("{}\n")
  assert family_table.main([str(tmp_path)]) == 2
  assert "line 1" in capsys.readouterr().err


def test_make_train_passes_only_options_its_clis_accept(tmp_path):
  """`make train` (the shipped model's recipe from scratch) is hours long: its
  commands are checked here against the CLIs' parsers, so a renamed or
  removed option fails in CI, not hours into a user's run."""
  import importlib
  import shlex
  import shutil
  import subprocess
  if shutil.which("make") is None:
    pytest.skip("make is not installed")
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  text = subprocess.run(["make", "-n", "-s", "-C", root, "train", f"TRAIN_DIR={tmp_path}/t", "PY=python"],
                        capture_output=True, text=True, check=True).stdout
  commands = [shlex.split(line) for line in text.replace("\\\n", " ").splitlines()
              if line.startswith("python -m experiments.")]
  assert {c[2] for c in commands} >= {"experiments.make_data", "experiments.train", "experiments.finetune",
                                      "experiments.refit_head", "experiments.export"}
  for command in commands:
    cli = importlib.import_module(command[2])
    if hasattr(cli, "parse_args"):
      cli.parse_args(command[3:])


def test_bench_times_a_model_folders_config_or_a_preset():
  from experiments import bench
  from pcdiff_jax import shipped
  from pcdiff_jax.config import get_config
  folder = shipped.checkpoint_dir()
  # As the model runs: the encoder's lane inputs, the map crop anchored on the agents.
  assert bench._config_of(folder) == shipped.run_config(shipped.read_config(folder))
  assert bench._config_of(folder).features.map_anchor == "agents"
  assert bench._config_of("tiny") == get_config("tiny")


def test_bench_rows_count_the_flops_of_a_call():
  """A timed bench row carries XLA's FLOP count: a 64 x 64 by 64 x 64 matmul is 2 * 64^3."""
  import jax.numpy as jnp
  from experiments import bench
  a = jnp.ones((64, 64), jnp.float32)
  row = bench._compiled_ms(lambda x: x @ x, (a,), repeats=2)
  assert row["mflop"] is not None and abs(row["mflop"] - 2 * 64 ** 3 / 1e6) < 0.01, row


def test_a_shipped_model_is_read_only_to_every_command(tmp_path, capsys):
  """train, finetune and export refuse to write into a shipped model (a folder with a
  MODEL_CARD.md, or one inside it) before they create anything there."""
  from experiments import export, finetune, train
  shipped = tmp_path / "pcdiff-shipped"
  (shipped / "diffusion").mkdir(parents=True)
  (shipped / "MODEL_CARD.md").write_text("# a shipped model\n")
  before = sorted(p.name for p in shipped.rglob("*"))
  for main, argv in ((train.main, ["--stage", "encoder", "--data", "x.tfrecord", "--workdir", str(shipped)]),
                     (train.main, ["--stage", "encoder", "--data", "x.tfrecord", "--workdir", "runs/x",
                                   "--cache-dir", str(shipped / "cache")]),
                     (finetune.main, ["--from", str(shipped), "--data", "x.tfrecord", "--workdir", str(shipped / "ft")]),
                     (export.main, ["--workdir", "runs/x", "--out", str(shipped)])):
    with pytest.raises(SystemExit) as e:
      main(argv)
    assert e.value.code == 2
    assert "read-only" in capsys.readouterr().err
  assert sorted(p.name for p in shipped.rglob("*")) == before


def test_export_names_a_simpl_ar_folder_that_is_not_a_model(tmp_path, capsys):
  from experiments import export
  from pcdiff_jax import shipped
  out = tmp_path / "model"
  assert export.main(["--workdir", shipped.checkpoint_dir(), "--out", str(out),
                      "--simpl-ar-from", str(tmp_path / "nothing")]) == 2
  assert "--simpl-ar-from" in capsys.readouterr().err and not out.exists()
