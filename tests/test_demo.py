"""The main job (`make demo`) end to end at the tiny preset: scenes, both
training stages, closed-loop rollouts and the table."""
from __future__ import annotations

import json
import os

from experiments import demo


def test_demo_pipeline_runs_end_to_end(tmp_path):
  out = str(tmp_path / "demo")
  code = demo.main(["--out", out, "--config", "tiny", "--num-train", "8", "--num-val", "2",
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
  assert "ours (prior, 5 DDIM steps)" in text and "constant velocity" in text
