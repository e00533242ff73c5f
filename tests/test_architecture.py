"""The package's shape: the library never names the project's own envs outside the env
package, and its modules import without cycles."""

from __future__ import annotations

import ast
import importlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
#: the generic code: the library and its trainers (the env package is envs/)
GENERIC = [ROOT / "dorp_rl", ROOT / "trainers"]


def _normal(text: str) -> str:
    return re.sub(r"[^a-z0-9]", "", text.lower())


def _our_envs() -> tuple[set[str], set[str]]:
    """Tokens that name one of the project's envs (profile names, env classes and the
    CamelCase stems of their names), and the modules they live in."""
    from dorp_rl.envs import ENV_NAMES, env_profile
    from dorp_rl.envs.pieces import PiecesEnv

    classes = {PiecesEnv}
    tokens = set()
    for name in ENV_NAMES:  # the project's own profiles
        tokens.add(_normal(name))
        env_type = env_profile(name).env_type
        classes |= {c for c in env_type.__mro__ if c.__module__.startswith("dorp_rl.envs.")}
    modules = {c.__module__ for c in classes}
    for cls in classes:
        tokens.add(_normal(cls.__name__))
        stem = cls.__name__.removesuffix("Env")
        if len(re.findall(r"[A-Z][a-z0-9]*", stem)) >= 2:  # not a plain word ("Pieces")
            tokens.add(_normal(stem))
    return tokens, modules


def _docstrings(tree: ast.AST) -> set[int]:
    """The strings that document (docstrings, the strings under a config's fields)."""
    return {
        id(node.value)
        for node in ast.walk(tree)
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant)
    }


def _names_in(tree: ast.AST) -> list[tuple[int, str, str]]:
    """(line, kind, text) of every identifier, import and non-docstring string."""
    docs = _docstrings(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs:
            out.append((node.lineno, "string", node.value))
        elif isinstance(node, ast.Name):
            out.append((node.lineno, "name", node.id))
        elif isinstance(node, ast.Attribute):
            out.append((node.lineno, "name", node.attr))
        elif isinstance(node, ast.FunctionDef | ast.ClassDef | ast.AsyncFunctionDef):
            out.append((node.lineno, "name", node.name))
        elif isinstance(node, ast.arg):
            out.append((node.lineno, "name", node.arg))
        elif isinstance(node, ast.keyword) and node.arg:
            out.append((node.value.lineno, "name", node.arg))
        elif isinstance(node, ast.ImportFrom) and node.module:
            out.append((node.lineno, "import", node.module))
            out += [(node.lineno, "name", a.name) for a in node.names]
        elif isinstance(node, ast.Import):
            out += [(node.lineno, "import", a.name) for a in node.names]
    return out


def test_generic_code_names_none_of_our_envs():
    """Env knowledge lives next to the env: no module of dorp_rl/ or trainers/ names one of
    the project's envs (a profile name, an env class, its module) in code or strings;
    docstrings and comments may."""
    tokens, modules = _our_envs()
    found = []
    for folder in GENERIC:
        for path in sorted(folder.rglob("*.py")):
            for line, kind, text in _names_in(ast.parse(path.read_text())):
                if kind == "import":
                    hit = any(text == m or text.startswith(m + ".") for m in modules)
                else:
                    hit = any(token in _normal(text) for token in tokens)
                if hit:
                    found.append(f"{path.relative_to(ROOT)}:{line}: {text[:60]!r}")
    assert not found, "generic code names the project's envs:\n" + "\n".join(found)


def test_the_check_sees_env_names():
    """The scan above finds what it looks for (a class name, a profile name in a string,
    an env module's import), and passes a docstring."""
    tokens, modules = _our_envs()
    code = (
        '"""Docstring naming ObjectRearrangementEnv and key-wall is fine."""\n'
        "from dorp_rl.envs.key_rooms import KeyWallEnv\n"
        "SETTING = 'key_corridor'\n"
    )
    texts = [(kind, text) for _, kind, text in _names_in(ast.parse(code))]
    imports = [t for k, t in texts if k == "import" and any(t.startswith(m) for m in modules)]
    named = [t for k, t in texts if k != "import" and any(tok in _normal(t) for tok in tokens)]
    assert imports == ["dorp_rl.envs.key_rooms"] and named == ["KeyWallEnv", "key_corridor"]


def _package_modules() -> dict[str, Path]:
    """Module name -> source file, for every module of the installed package."""
    names = {}
    for folder, package in ((ROOT / "dorp_rl", "dorp_rl"), (ROOT / "envs", "dorp_rl.envs"),
                            (ROOT / "trainers", "dorp_rl.trainers")):  # fmt: skip
        for path in sorted(folder.rglob("*.py")):
            parts = path.relative_to(folder).with_suffix("").parts
            parts = parts[:-1] if parts[-1] == "__init__" else parts
            names[".".join((package, *parts))] = path
    return names


def _top_level_imports(
    tree: ast.Module, name: str, is_package: bool, known: set[str] = frozenset()
) -> set[str]:
    """Modules ``name`` imports when it is imported: module-level imports, outside
    ``if TYPE_CHECKING:`` (imports inside functions run later, when called). ``from pkg
    import x`` imports ``pkg.x`` when that is one of the ``known`` modules, else ``pkg``."""
    found: set[str] = set()
    base = name if is_package else name.rpartition(".")[0]
    body = list(tree.body)
    while body:
        node = body.pop(0)
        if isinstance(node, ast.If):
            test = ast.unparse(node.test)
            body += node.orelse if "TYPE_CHECKING" in test else node.body + node.orelse
        elif isinstance(node, ast.Try):
            body += node.body + node.orelse + node.finalbody
        elif isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                parent = base
                for _ in range(node.level - 1):
                    parent = parent.rpartition(".")[0]
                module = f"{parent}.{module}" if module else parent
            for alias in node.names:
                submodule = f"{module}.{alias.name}"
                found.add(submodule if submodule in known else module)
    return found


def _import_graph() -> dict[str, set[str]]:
    sources = _package_modules()
    graph = {}
    for name, path in sources.items():
        tree = ast.parse(path.read_text())
        is_package = path.name == "__init__.py"
        graph[name] = _top_level_imports(tree, name, is_package, set(sources)) & set(sources)
        graph[name].discard(name)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(node: str) -> None:
        index[node] = low[node] = len(index)
        stack.append(node)
        on_stack.add(node)
        for other in sorted(graph[node]):
            if other not in index:
                visit(other)
                low[node] = min(low[node], low[other])
            elif other in on_stack:
                low[node] = min(low[node], index[other])
        if low[node] == index[node]:
            component = []
            while True:
                top = stack.pop()
                on_stack.discard(top)
                component.append(top)
                if top == node:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for node in sorted(graph):
        if node not in index:
            visit(node)
    return found


def test_no_import_cycles():
    """No two modules of the package import each other, directly or around a loop, when
    they are imported (a package's ``__init__`` counts as the package)."""
    cycles = _cycles(_import_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_check_finds_a_cycle():
    graph = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert _cycles(graph) == [["a", "b", "c"]]
    tree = ast.parse(
        "from typing import TYPE_CHECKING\n"
        "from . import sibling, name\n"
        "if TYPE_CHECKING:\n    from pkg.only_typed import X\n"
        "def later():\n    import pkg.inside\n"
    )
    found = _top_level_imports(tree, "pkg.mod", False, {"pkg", "pkg.sibling", "pkg.mod"})
    assert found == {"typing", "pkg", "pkg.sibling"}


def test_module_list_is_the_package():
    """The import check covers what the package holds (a renamed folder would empty it)."""
    modules = _package_modules()
    assert "dorp_rl.envs.profile" in modules and "dorp_rl.trainers.base" in modules
    for name in ("dorp_rl.frames", "dorp_rl.metrics.diagnostics"):
        assert importlib.util.find_spec(name) is not None and name in modules
