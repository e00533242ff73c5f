"""Every ``>>>`` example in the package's docstrings runs as a doctest.

Modules are imported by their installed names (``dorp_rl.envs.rearrangement``, not
``envs.rearrangement``), so the examples see the same classes as users do. Each module's
examples run in a fresh namespace with torch seeded and one torch thread.
"""

from __future__ import annotations

import doctest
import importlib
import pkgutil
from collections.abc import Iterator

import pytest
import torch

import dorp_rl
import dorp_rl.envs
import dorp_rl.trainers

# ``python -m dorp_rl`` runs the command line when imported as ``__main__`` only.
SKIP = {"dorp_rl.__main__"}

FLAGS = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE


def _module_names() -> list[str]:
    names = set()
    for package in (dorp_rl, dorp_rl.envs, dorp_rl.trainers):
        names.add(package.__name__)
        for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
            names.add(info.name)
    return sorted(names - SKIP)


def _tests(module_name: str) -> list[doctest.DocTest]:
    module = importlib.import_module(module_name)
    finder = doctest.DocTestFinder(exclude_empty=True)
    # Only the docstrings of this module: re-exported objects are tested where they live.
    return [t for t in finder.find(module, module_name) if t.examples]


MODULES = _module_names()
WITH_EXAMPLES = [name for name in MODULES if _tests(name)]


def test_every_package_module_is_collected() -> None:
    """The walk sees the remapped subpackages under their installed names."""
    assert "dorp_rl.envs.rearrangement" in MODULES
    assert "dorp_rl.trainers.representation" in MODULES
    assert "dorp_rl.planners.costs" in MODULES
    assert not any(name.startswith(("envs.", "trainers.")) for name in MODULES)


@pytest.fixture
def seeded_single_thread() -> Iterator[None]:
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    yield
    torch.set_num_threads(previous)


@pytest.mark.parametrize("module_name", WITH_EXAMPLES)
def test_docstring_examples(
    module_name: str, seeded_single_thread: None, tmp_path, monkeypatch
) -> None:
    tests = _tests(module_name)
    # Examples that write files write them under a temporary working directory.
    monkeypatch.chdir(tmp_path)
    runner = doctest.DocTestRunner(optionflags=FLAGS)
    failures = []
    for test in tests:
        runner.run(test, out=failures.append)
    assert runner.failures == 0, "".join(failures)
