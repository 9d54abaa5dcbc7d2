"""DESIGN.md's "who may import whom", as allow-lists.

Every absolute import in a package's files — lazy ones inside functions included, subpackages
included — must be on that package's list: project modules by prefix, third-party distributions
by top-level name (the standard library is always allowed). A new dependency is a decision: add
it here and to DESIGN.md in the same change.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent

COMPANION_THIRD_PARTY = {
    "numpy",
    "pymavlink",
    "mcap",
    "zstandard",
    "foxglove",
    "google",  # protobuf, in the live extra beside foxglove-sdk: reads its messages back
    "torch",  # the torch runtime and `visland export-onnx` (see test below: not in the contract)
    "onnxruntime",
    "onnx",
    "cv2",
}

RULES: dict[str, tuple[tuple[str, ...], set[str]]] = {
    # package (folder, relative): (project module prefixes it may import, third-party tops)
    "companion/contract": (("companion.contract",), {"numpy", "pymavlink"}),
    "companion": (("companion",), COMPANION_THIRD_PARTY),
    "sitl_sim": (
        (
            "sitl_sim",
            "companion.contract",
            "companion.flightlog",
            "companion.files",
            "companion.options",
            "companion.table",
            "companion.lazy",
            "companion.live",
        ),
        {"numpy", "scipy", "pybullet", "gymnasium", "pymavlink", "PIL", "cv2", "numba"},
    ),
    "expert": (
        (
            "expert",
            "sitl_sim",
            "companion.contract",
            "companion.flightlog",
            "companion.files",
            "companion.table",
        ),
        {"numpy", "scipy", "osqp", "clarabel", "cvxpy"},
    ),
    "training": (
        ("training", "expert", "sitl_sim", "companion"),
        {"numpy", "scipy", "torch", "tqdm", "matplotlib", "tomli_w", "ray"},
    ),
}
PROJECT = ("companion", "sitl_sim", "expert", "training", "tools")


def _imports(folder: Path) -> list[tuple[str, int, str]]:
    """``(file, line, module)`` for every absolute import under ``folder`` (recursive)."""
    return [i for path in sorted(folder.rglob("*.py")) for i in _imports_of(path)]


def _imports_of(path: Path) -> list[tuple[str, int, str]]:
    """``(file, line, module)`` for every absolute import in one file."""
    found = []
    tree = ast.parse(path.read_text(), str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names = [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                raise AssertionError(f"{path}:{node.lineno}: relative import; use absolute")
            names = [node.module or ""]
        else:
            continue
        found += [(str(path.relative_to(REPO)), node.lineno, n) for n in names]
    return found


def _allowed(module: str, prefixes: tuple[str, ...], third_party: set[str]) -> bool:
    top = module.split(".")[0]
    if top in PROJECT:
        return any(module == p or module.startswith(p + ".") for p in prefixes)
    return top == "__future__" or top in sys.stdlib_module_names or top in third_party


@pytest.mark.parametrize("package", list(RULES))
def test_each_package_imports_only_what_its_allow_list_names(package):
    prefixes, third_party = RULES[package]
    folder = REPO / package
    offending = [
        f"{file}:{line} imports {module}"
        for file, line, module in _imports(folder)
        # a subpackage with its own rule is checked by that rule
        if not any(
            sub != package and sub.startswith(package + "/") and file.startswith(sub + "/")
            for sub in RULES
        )
        and not _allowed(module, prefixes, third_party)
    ]
    assert offending == []


def _fake_sitl_file(tmp_path: Path, monkeypatch, name: str, text: str) -> Path:
    """A repository at ``tmp_path`` (the checks read it as REPO) whose ``sitl_sim`` package
    holds one file ``name``; returns the package folder."""
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    pkg = tmp_path / "sitl_sim"
    pkg.mkdir()
    (pkg / name).write_text(text)
    return pkg


def test_the_allow_lists_catch_a_forbidden_import(tmp_path, monkeypatch):
    """The check itself: a SITL file importing the companion's policy network is refused."""
    pkg = _fake_sitl_file(
        tmp_path,
        monkeypatch,
        "bad.py",
        "def f():\n    from companion.policy_net import load_policy\n    return load_policy\n",
    )
    prefixes, third_party = RULES["sitl_sim"]
    bad = [m for _, _, m in _imports(pkg) if not _allowed(m, prefixes, third_party)]
    assert bad == ["companion.policy_net"]


def test_the_contract_needs_no_torch_and_no_other_companion_module():
    """The contract is what a board without torch and a simulator without the companion's
    runtime both load: numpy, the standard library, pymavlink's dialect (signing only)."""
    modules = {m for _, _, m in _imports(REPO / "companion" / "contract")}
    assert not {m for m in modules if m.split(".")[0] == "torch"}
    assert {m for m in modules if m.startswith("companion.")} <= {
        "companion.contract",
        "companion.contract.messages",
        "companion.contract.policy",
        "companion.contract.topics",
        "companion.contract.record_base",
        "companion.contract.companion_records",
    }


@pytest.mark.parametrize(
    "module", ["policy_net/config.py", "policy_net/geometry.py", "policy_net/estimator.py"]
)
def test_the_policy_geometry_and_estimator_need_no_torch(module):
    """What an ONNX-only board runs between the two networks must not pull torch in."""
    tops = {m.split(".")[0] for _, _, m in _imports_of(REPO / "companion" / module)}
    assert "torch" not in tops


def _module_graph(package: str) -> dict[str, set[str]]:
    """Module → the modules of the same top-level package it imports: every import counts,
    at module level, inside a function or under ``TYPE_CHECKING`` (a circle hidden behind a
    lazy import is still a circle). ``from pkg import sub`` is an edge to the submodule
    ``pkg.sub``; a package's ``__init__`` is the module ``pkg``."""
    modules = {}
    for path in sorted((REPO / package).rglob("*.py")):
        parts = path.relative_to(REPO).with_suffix("").parts
        modules[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module:
                for alias in node.names:
                    sub = f"{node.module}.{alias.name}"
                    targets.add(sub if sub in modules else node.module)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def _circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The import circles of ``graph``: its strongly connected components of more than one
    module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(module: str) -> None:
        index[module] = low[module] = len(index)
        stack.append(module)
        for other in sorted(graph[module]):
            if other not in index:
                visit(other)
                low[module] = min(low[module], low[other])
            elif other in stack:
                low[module] = min(low[module], index[other])
        if low[module] == index[module]:
            component = stack[stack.index(module) :]
            del stack[stack.index(module) :]
            if len(component) > 1:
                found.append(sorted(component))

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return found


@pytest.mark.parametrize("package", PROJECT)
def test_no_import_circle_inside_a_package(package):
    """Modules of one package import each other one way only (DESIGN's layers): a part that
    needs its caller is told what to do instead of importing it."""
    assert _circles(_module_graph(package)) == []


def test_a_circle_behind_lazy_and_type_checking_imports_is_found(tmp_path, monkeypatch):
    """The check itself: a ↔ b through a function-level import and a ``TYPE_CHECKING`` one."""
    monkeypatch.setattr(sys.modules[__name__], "REPO", tmp_path)
    pkg = tmp_path / "training"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("def f():\n    from training.b import g\n    return g\n")
    (pkg / "b.py").write_text(
        "from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from training import a\n"
    )
    (pkg / "c.py").write_text("import training.a\n")
    assert _circles(_module_graph("training")) == [["training.a", "training.b"]]


MAX_MODULE_LINES = 600


@pytest.mark.parametrize("package", PROJECT)
def test_no_module_is_over_600_lines(package):
    """A module that big does several jobs: split it by job (not into mixins)."""
    big = {
        str(path.relative_to(REPO)): n
        for path in sorted((REPO / package).rglob("*.py"))
        if (n := len(path.read_text().splitlines())) > MAX_MODULE_LINES
    }
    assert big == {}


def _project_classes() -> dict[str, tuple[str, list[str]]]:
    """Every class defined in the project: ``name -> (file, base names)`` (bases as written,
    last dotted part)."""
    classes = {}
    for package in PROJECT:
        for path in sorted((REPO / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, ast.ClassDef):
                    bases = [ast.unparse(b).split(".")[-1].split("[")[0] for b in node.bases]
                    classes[node.name] = (str(path.relative_to(REPO)), bases)
    return classes


def test_no_class_has_more_than_one_project_base_class():
    """Parts, not mixins: a class is composed of the objects it uses, and inherits from at
    most one class of the project (exceptions may add a standard-library one)."""
    classes = _project_classes()
    mixed = {
        f"{file}: {name}({', '.join(bases)})"
        for name, (file, bases) in classes.items()
        if sum(base in classes for base in bases) > 1
    }
    assert mixed == set()


def test_the_class_check_catches_a_mixin(tmp_path, monkeypatch):
    """The check itself: a class built from two project classes sharing ``self`` is found."""
    _fake_sitl_file(
        tmp_path,
        monkeypatch,
        "parts.py",
        "class Builders:\n    pass\n\n\nclass Handlers:\n    pass\n\n\n"
        "class Sitl(Builders, Handlers):\n    pass\n\n\n"
        "class PortError(Builders, OSError):\n    pass\n",
    )
    classes = _project_classes()
    assert [n for n, (_, b) in classes.items() if sum(x in classes for x in b) > 1] == ["Sitl"]
