"""requirements.lock (what `make demo` / `make test` install) pins every dependency that
pyproject.toml declares, at a version inside pyproject's bounds; the wheel of `pip install .`
carries the shipped model and the CLIs."""
import pathlib
import shutil
import subprocess
import sys
import tomllib
import zipfile

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from pcdiff_jax import shipped

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _lock() -> dict[str, str]:
  pins = {}
  for line in (ROOT / "requirements.lock").read_text().splitlines():
    line = line.strip()
    if line and not line.startswith("#"):
      name, sep, version = line.partition("==")
      assert sep, f"requirements.lock: {line!r} is not an exact pin (name==version)"
      pins[canonicalize_name(name)] = version
  return pins


def test_the_lock_pins_every_declared_dependency_within_its_bounds():
  project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
  declared = project["dependencies"] + project["optional-dependencies"]["dev"]
  pins = _lock()
  for spec in map(Requirement, declared):
    name = canonicalize_name(spec.name)
    assert name in pins, f"{spec.name} is declared in pyproject.toml but not pinned in requirements.lock"
    assert spec.specifier.contains(pins[name]), f"{spec.name}=={pins[name]} is outside {spec.specifier}"
    assert not spec.specifier.contains("999"), f"{spec.name}: no upper bound in pyproject.toml"


def test_the_wheel_carries_the_shipped_model_and_the_clis(tmp_path):
  """`pip install .` builds this wheel (setup.py adds the shipped model as package data, where
  `shipped.checkpoint_dir` finds it outside the repository). Built without dependencies or build
  isolation from a copy of the sources, so the repository is left untouched; a few seconds."""
  src = tmp_path / "src"
  src.mkdir()
  for name in ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md"):
    shutil.copy2(ROOT / name, src / name)
  for name in ("pcdiff_jax", "experiments", "checkpoints"):
    shutil.copytree(ROOT / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
  run = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                        "--no-index", "-q", "-w", str(tmp_path / "dist"), str(src)],
                       capture_output=True, text=True)
  assert run.returncode == 0, run.stderr
  (wheel,) = (tmp_path / "dist").glob("pcdiff_jax-*.whl")
  names = set(zipfile.ZipFile(wheel).namelist())
  for package in ("pcdiff_jax", "experiments"):
    for module in (ROOT / package).rglob("*.py"):
      if "__pycache__" not in module.parts:
        assert module.relative_to(ROOT).as_posix() in names, f"the wheel lacks {module.relative_to(ROOT)}"
  model = ROOT / "checkpoints" / shipped.DEFAULT_NAME
  for f in model.rglob("*"):
    if f.is_file():
      inside = f"pcdiff_jax/checkpoints/{f.relative_to(ROOT / 'checkpoints').as_posix()}"
      assert inside in names, f"the wheel lacks {inside}"
  others = {n.split("/")[2] for n in names if n.startswith("pcdiff_jax/checkpoints/")}
  assert others == {shipped.DEFAULT_NAME}, f"the wheel carries more models than the default: {others}"
  assert wheel.stat().st_size < 8_000_000
  metadata = next(n for n in names if n.endswith(".dist-info/METADATA"))
  requires = zipfile.ZipFile(wheel).read(metadata).decode()
  assert "Requires-Dist: jax" in requires
  # TensorFlow only as an extra: the data path has its own TFRecord reader and writer.
  tf_lines = [line for line in requires.splitlines() if line.startswith("Requires-Dist: tensorflow")]
  assert tf_lines and all("extra ==" in line for line in tf_lines), tf_lines
