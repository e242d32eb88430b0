"""The package's layers point down (README's map): no module imports a module
of a higher layer, and the module import graph has no cycle, function-level
imports included (they hide a cycle from Python, not from a reader)."""
import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "pcdiff_jax"

# Lowest first; a module's layer is that of its longest matching prefix.
LAYERS = [
    ("pcdiff_jax.config", "pcdiff_jax.distributed"),   # distributed: meshes and hosts (jax only)
    ("pcdiff_jax.sim",),
    ("pcdiff_jax.data", "pcdiff_jax.viz"),
    ("pcdiff_jax.model", "pcdiff_jax.metrics"),
    ("pcdiff_jax.training",),                  # the two training stages and their parts
    ("pcdiff_jax.policy",),
    ("pcdiff_jax.baselines",),
    ("pcdiff_jax.evaluation", "pcdiff_jax.wosac"),   # wosac: every sim agent, 32 rollouts, submissions
    ("pcdiff_jax.training.closed_loop", "pcdiff_jax.shipped"),  # on-policy rounds roll policies out
    ("pcdiff_jax",),                           # the package's one-call loader
]


def _module_name(path: pathlib.Path) -> str:
  parts = path.relative_to(ROOT).with_suffix("").parts
  return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports() -> dict[str, set[str]]:
  modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
  graph: dict[str, set[str]] = {}
  for name, path in modules.items():
    deps: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
      targets = []
      if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("pcdiff_jax"):
        targets = [f"{node.module}.{a.name}" for a in node.names]
      elif isinstance(node, ast.Import):
        targets = [a.name for a in node.names if a.name.startswith("pcdiff_jax")]
      for target in targets:   # `from pkg import module` names a module, `from module import f` does not
        while target not in modules:
          target = target.rsplit(".", 1)[0]
        if target != name:
          deps.add(target)
    graph[name] = deps
  return graph


def _layer(module: str) -> int:
  best, rank = -1, None
  for i, prefixes in enumerate(LAYERS):
    for prefix in prefixes:
      if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best:
        best, rank = len(prefix), i
  assert rank is not None, f"{module} is in no layer: add it to LAYERS (and README's map)"
  return rank


def test_every_import_points_down_or_sideways():
  graph = _imports()
  upward = [f"{m} (layer {_layer(m)}) imports {d} (layer {_layer(d)})"
            for m, deps in graph.items() for d in deps
            if _layer(d) > _layer(m) and not m == "pcdiff_jax"]
  assert not upward, "\n".join(upward)


def test_module_imports_have_no_cycle():
  graph = _imports()
  state: dict[str, int] = {}

  def visit(m, path):
    state[m] = 1
    for d in sorted(graph.get(m, ())):
      if d.startswith(m + "."):   # a package importing its own submodules is not a cycle
        continue
      if state.get(d) == 1:
        pytest.fail("import cycle: " + " -> ".join(path[path.index(d):] + [d]))
      if d not in state:
        visit(d, path + [d])
    state[m] = 2
  for m in sorted(graph):
    if m not in state:
      visit(m, [m])
