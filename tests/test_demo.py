"""The main job (`make demo`) end to end at the tiny preset: scenes, both
training stages, closed-loop rollouts and the table."""
from __future__ import annotations

import json
import os

from experiments import demo


def test_demo_pipeline_runs_end_to_end(tmp_path):
  out = str(tmp_path / "demo")
  code = demo.main(["--out", out, "--train", "--config", "tiny", "--num-train", "8", "--num-val", "2",
                    "--methods", "pcdiff", "cv", "--batch-size", "2", "--real", "/nonexistent",
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
  # The closed-loop diagnostics run on the same model.
  from experiments import diagnose
  val = os.path.join(out, "data", "val-00000-of-00001.tfrecord")
  common = ["--checkpoint", os.path.join(out, "model"), "--scenarios", val, "--num-scenes", "1"]
  diagnose.main(common + ["--out", str(tmp_path / "first.json"), "first-action"])
  diagnose.main(common + ["--out", str(tmp_path / "replay.json"), "replay", "--plans", "log,top1-latent"])
  with open(tmp_path / "first.json") as f:
    rows = json.load(f)["rows"]
  assert set(rows) == {"log", "log_latent", "top1", "prior_centre", "sample"}
  with open(tmp_path / "replay.json") as f:
    replay = json.load(f)["rows"]
  assert replay["log"]["min_ade"] < 0.5                 # the log's own actions reproduce the log
  assert replay["top1-latent"]["min_ade"] > replay["log"]["min_ade"]
