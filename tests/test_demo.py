"""The main job (`make demo`): its `--train` path. The job end to end on a
trained model is in test_trained_pipeline.py."""
from __future__ import annotations

import glob
import os

import pytest

from experiments import demo


@pytest.mark.slow
def test_demo_train_runs_both_stages_on_its_scenes_and_stops_on_failure(tmp_path, monkeypatch):
  """`--train` hands its scenes to `experiments.train --stage all` (tested on its
  own in test_training); a failing step stops the demo with its name."""
  calls = []

  class FakeTrain:
    @staticmethod
    def main(argv):
      calls.append(argv)
      return 1
  FakeTrain.main.__module__ = "experiments.train"
  monkeypatch.setattr(demo, "train", FakeTrain)
  out = str(tmp_path / "demo")
  with pytest.raises(SystemExit, match="step 'training' failed"):
    demo.main(["--out", out, "--train", "--config", "tiny", "--num-train", "8", "--num-val", "1",
               "--no-progress"])
  argv = calls[0]
  assert argv[:4] == ["--stage", "all", "--config", "tiny"]
  assert argv[argv.index("--workdir") + 1] == os.path.join(out, "model")
  data = argv[argv.index("--data") + 1]
  assert data == os.path.join(out, "data", "train-*") and len(glob.glob(data)) >= 1
  assert demo.main(["--out", out, "--checkpoint", str(tmp_path / "none")]) == 2    # no model there
