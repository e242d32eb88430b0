"""Build hook, the rest of the metadata is in pyproject.toml: a wheel carries the shipped model.

`pip install .` (a wheel) copies checkpoints/<shipped.DEFAULT_NAME> into the package as
pcdiff_jax/checkpoints/<name>, where `pcdiff_jax.pretrained()` finds it outside the repository
(the default model only: the older versions stay in the repository). An editable install
(`make install`) reads checkpoints/ in place and copies nothing.
"""
import ast
import os
import shutil

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = os.path.dirname(os.path.abspath(__file__))


def default_model() -> str:
  """shipped.DEFAULT_NAME, read without importing the package (its dependencies may be absent)."""
  with open(os.path.join(ROOT, "pcdiff_jax", "shipped.py")) as f:
    tree = ast.parse(f.read())
  for node in tree.body:
    if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "DEFAULT_NAME" for t in node.targets):
      return ast.literal_eval(node.value)
  raise RuntimeError("pcdiff_jax/shipped.py defines no DEFAULT_NAME")


class BuildPyWithModel(build_py):
  """build_py, then the shipped model into build_lib/pcdiff_jax/checkpoints/<name>."""

  def run(self):
    super().run()
    if getattr(self, "editable_mode", False):
      return
    name = default_model()
    src = os.path.join(ROOT, "checkpoints", name)
    if not os.path.isdir(src):
      raise FileNotFoundError(f"the shipped model {src} is missing: it is committed with the code")
    dst = os.path.join(self.build_lib, "pcdiff_jax", "checkpoints", name)
    shutil.rmtree(dst, ignore_errors=True)
    shutil.copytree(src, dst)


setup(cmdclass={"build_py": BuildPyWithModel})
