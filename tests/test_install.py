"""requirements.lock (what `make demo` / `make test` install) pins every dependency that
pyproject.toml declares, at a version inside pyproject's bounds."""
import pathlib
import tomllib

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

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
