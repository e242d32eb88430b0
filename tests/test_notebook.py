"""notebooks/quickstart.ipynb: the committed copy shows a full run of the shipped model, and the
notebook still executes end to end (shrunk by PCDIFF_NOTEBOOK_QUICK=1), so it cannot rot.

Re-execute the committed copy with `make notebook` whenever the shipped model changes.
"""
from __future__ import annotations

import os
import pathlib

import nbformat
import pytest
from nbclient import NotebookClient

from pcdiff_jax import shipped

ROOT = pathlib.Path(__file__).resolve().parents[1]
NOTEBOOK = ROOT / "notebooks" / "quickstart.ipynb"
TABLE_ROWS = ("ours (shipped model)", "IDM", "constant velocity")


def _outputs(nb) -> tuple[str, list[str]]:
  """(every text and markdown output joined, the HTML outputs) of the code cells."""
  text, html = [], []
  for cell in nb.cells:
    if cell.cell_type != "code":
      continue
    for out in cell.get("outputs", []):
      assert out.output_type != "error", f"a cell failed: {out.get('ename')}: {out.get('evalue')}"
      if out.output_type == "stream":
        text.append(out.text)
      data = out.get("data", {})
      text.append(data.get("text/markdown", ""))
      if "text/html" in data:
        html.append(data["text/html"])
  return "\n".join(text), html


def _check(nb) -> str:
  """The checks both runs pass: the model loaded, both tables, the animations; returns the text."""
  text, html = _outputs(nb)
  for row in TABLE_ROWS:
    assert f"| {row} |" in text, f"the metrics table lacks {row!r}"
  assert "| objective guidance |" in text and "| adversarial (w_pursue" in text
  gifs = sum(h.count("data:image/gif;base64,") for h in html)
  assert gifs >= 5, f"{gifs} inline animations (expected 2 + 3)"
  return text


def test_committed_notebook_shows_a_full_run_of_the_shipped_model():
  nb = nbformat.read(NOTEBOOK, as_version=4)
  code = [c for c in nb.cells if c.cell_type == "code"]
  assert "parameters" in code[0].metadata.get("tags", []) and "QUICK" in code[0].source
  assert all(c.get("execution_count") for c in code), "committed without outputs: run `make notebook`"
  text = _check(nb)
  assert f"{shipped.DEFAULT_NAME}: the shipped model" in text, (
      f"the committed outputs are not of the shipped model {shipped.DEFAULT_NAME}: run `make notebook`")
  assert "x 80 steps" in text and "real WOMD record" in text, "committed from a shrunk run: run `make notebook`"
  # The repository stays small: the notebook's animations are a few hundred kB each.
  assert NOTEBOOK.stat().st_size < 3_000_000


@pytest.mark.slow
def test_notebook_executes_shrunk(monkeypatch):
  # The kernel inherits this environment. XLA's backend optimisations off: the three closed-loop
  # programs of ours (unguided, objective, adversarial) compile about 30% faster, and a 4-step
  # smoke test does not need fast code.
  monkeypatch.setenv("PCDIFF_NOTEBOOK_QUICK", "1")
  monkeypatch.setenv("XLA_FLAGS", (os.environ.get("XLA_FLAGS", "") +
                                   " --xla_backend_optimization_level=0"
                                   " --xla_llvm_disable_expensive_passes=true").strip())
  nb = nbformat.read(NOTEBOOK, as_version=4)
  NotebookClient(nb, timeout=600, kernel_name="python3",
                 resources={"metadata": {"path": str(NOTEBOOK.parent)}}).execute()
  text = _check(nb)
  assert "x 4 steps" in text
