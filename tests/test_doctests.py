"""Every ``>>>`` example in the package's docstrings runs as a doctest.

Modules are imported by their installed names (``dorp_rl.envs.rearrangement``, not
``envs.rearrangement``, since ``envs/`` and ``trainers/`` are mapped into the package),
so the examples see the same classes as users do. Modules are found from the files of
the package directories without importing them, so a module that fails to import fails
its own test instead of the whole collection. Each module's examples run in a temporary
working directory with torch seeded and one torch thread.
"""

from __future__ import annotations

import doctest
import importlib
import importlib.util
from collections.abc import Iterator
from pathlib import Path

import pytest
import torch

#: Packages whose directories are walked; ``dorp_rl.envs`` and ``dorp_rl.trainers`` live
#: outside ``dorp_rl/`` (``[tool.setuptools.package-dir]``).
ROOTS = ("dorp_rl", "dorp_rl.envs", "dorp_rl.trainers")
#: ``python -m dorp_rl`` runs the command line when imported as ``__main__`` only.
SKIP = {"dorp_rl.__main__"}
FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _module_files() -> dict[str, Path]:
    """Installed module name -> source file, for every module of the package."""
    found: dict[str, Path] = {}
    for root in ROOTS:
        spec = importlib.util.find_spec(root)
        assert spec is not None and spec.submodule_search_locations, f"{root} is not installed"
        base = Path(next(iter(spec.submodule_search_locations)))
        for path in sorted(base.rglob("*.py")):
            if "__pycache__" in path.parts:
                continue
            parts = path.relative_to(base).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            name = ".".join((root, *parts))
            if name not in SKIP:
                found[name] = path
    return found


MODULE_FILES = _module_files()
WITH_EXAMPLES = sorted(
    name for name, path in MODULE_FILES.items() if ">>>" in path.read_text(encoding="utf-8")
)


def test_every_package_module_is_found_under_its_installed_name() -> None:
    assert "dorp_rl.envs.rearrangement" in MODULE_FILES
    assert "dorp_rl.trainers.representation" in MODULE_FILES
    assert "dorp_rl.planners.costs" in MODULE_FILES
    assert not any(name.startswith(("envs", "trainers")) for name in MODULE_FILES)
    assert {"dorp_rl.modules.similarity", "dorp_rl.envs.planning.video_model"} <= set(WITH_EXAMPLES)


@pytest.fixture
def seeded_single_thread() -> Iterator[None]:
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(previous)


@pytest.mark.parametrize("module_name", WITH_EXAMPLES)
def test_docstring_examples(
    module_name: str, seeded_single_thread: None, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    module = importlib.import_module(module_name)
    # Only docstrings of objects defined in this module: re-exports are tested where they live.
    tests = [t for t in doctest.DocTestFinder().find(module, module_name) if t.examples]
    assert tests, f"{module_name} has '>>>' in its source but no docstring example was found"
    monkeypatch.chdir(tmp_path)  # examples that write files write them here
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    report: list[str] = []
    for test in tests:
        runner.run(test, out=report.append)
    assert runner.failures == 0, "".join(report)
