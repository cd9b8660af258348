"""The package's layout is its data flow: every module's imports (parsed with ``ast``, those inside functions
too) go only to its own stage or an earlier one, never around a circle, and never to another module's
underscore names. CONTRIBUTING.md's table of stages is checked here rather than remembered."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: Where each installed package's sources live (pyproject.toml's package-dir).
PACKAGE_ROOTS = {"don_gym": REPO / "don_gym", "don_gym.wrappers": REPO / "wrappers", "don_gym.agents": REPO / "agents"}

#: The stages in flow order, each a list of module prefixes; a module belongs to the longest prefix naming it.
STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    (
        "common",
        ("don_gym", "don_gym._registration", "don_gym.errors", "don_gym.geometry", "don_gym.io", "don_gym.stats"),
    ),
    ("mesh", ("don_gym.objects",)),
    ("figures", ("don_gym.plotting",)),
    ("descriptors", ("don_gym.descriptors",)),
    ("simulation", ("don_gym.sim",)),
    ("data", ("don_gym.data",)),
    ("learning", ("don_gym.learning", "don_gym.zoo")),
    ("perception", ("don_gym.perception",)),
    ("wrappers", ("don_gym.wrappers",)),
    ("agents", ("don_gym.agents",)),
    ("evaluation", ("don_gym.evaluation",)),
    ("interface", ("don_gym.cli",)),
)
#: The simulator feeds images in from the side: it imports nothing after the mesh stage.
SIDE_STAGES = {"simulation": {"common", "mesh"}}


def module_files() -> dict[str, Path]:
    """``{dotted module name: source file}`` of every module the project installs."""
    modules = {}
    for package, root in PACKAGE_ROOTS.items():
        for path in sorted(root.rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join([package, *parts])
            if package == "don_gym" and parts and parts[0] in ("wrappers", "agents"):
                continue
            modules[name] = path
    return modules


MODULES = module_files()


def stage_of(module: str) -> str:
    best, best_len = None, -1
    for stage, prefixes in STAGES:
        for prefix in prefixes:
            if (module == prefix or module.startswith(prefix + ".")) and len(prefix) > best_len:
                best, best_len = stage, len(prefix)
    assert best is not None, f"{module} belongs to no stage of tests/test_layout.py:STAGES"
    return best


def stage_index(stage: str) -> int:
    return [s for s, _ in STAGES].index(stage)


def resolve(module: str, name: str | None) -> str:
    """The project module an import names: ``from don_gym.data import build`` imports module
    ``don_gym.data.build``, ``from don_gym.data.build import build_dataset`` module ``don_gym.data.build``."""
    if name is not None and f"{module}.{name}" in MODULES:
        return f"{module}.{name}"
    return module


def imports_of(name: str) -> list[tuple[int, str, str | None]]:
    """``(line, imported project module, imported name or None)`` of every import in a module's source."""
    path = MODULES[name]
    is_package = path.name == "__init__.py"
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, a.name, None) for a in node.names if a.name.split(".")[0] == "don_gym"]
        elif isinstance(node, ast.ImportFrom):
            module = node.module or ""
            if node.level:
                base = name.split(".") if is_package else name.split(".")[:-1]
                base = base[: len(base) - node.level + 1]
                module = ".".join(base + ([module] if module else []))
            if module.split(".")[0] != "don_gym":
                continue
            found += [(node.lineno, resolve(module, a.name), a.name) for a in node.names]
    return found


def test_every_module_belongs_to_a_stage() -> None:
    assert len(MODULES) > 60
    for name in MODULES:
        stage_of(name)


def test_no_module_imports_a_later_stage() -> None:
    problems = []
    for name in MODULES:
        stage = stage_of(name)
        allowed = SIDE_STAGES.get(stage)
        for line, target, _ in imports_of(name):
            target_stage = stage_of(target)
            if allowed is not None:
                if target_stage not in allowed | {stage}:
                    problems.append(f"{name}:{line} imports {target} ({target_stage}; {stage} imports only {allowed})")
            elif stage_index(target_stage) > stage_index(stage):
                problems.append(f"{name}:{line} ({stage}) imports {target} of the later stage {target_stage}")
    assert not problems, "\n".join(problems)


def test_no_module_imports_another_modules_underscore_names() -> None:
    problems = []
    for name in MODULES:
        tree = ast.parse(MODULES[name].read_text())
        module_aliases = set()
        for line, target, imported in imports_of(name):
            if imported is None:
                continue
            if target == resolve(target, None) and f"{target}" in MODULES and target.endswith("." + imported):
                module_aliases.add(imported)
            elif imported.startswith("_") and not (imported.startswith("__") and imported.endswith("__")):
                problems.append(f"{name}:{line} imports {imported} from {target}")
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                module_aliases |= {a.asname for a in node.names if a.asname and a.name.startswith("don_gym")}
        for node in ast.walk(tree):
            if (
                isinstance(node, ast.Attribute)
                and isinstance(node.value, ast.Name)
                and node.value.id in module_aliases
                and node.attr.startswith("_")
                and not node.attr.startswith("__")
            ):
                problems.append(f"{name}:{node.lineno} uses {node.value.id}.{node.attr}")
    assert not problems, "\n".join(problems)


def test_no_import_cycle() -> None:
    graph = {name: {t for _, t, _ in imports_of(name) if t != name and t in MODULES} for name in MODULES}
    # A package's __init__ is imported with every module under it; an import of it is no edge of the flow.
    graph = {n: {t for t in targets if not n.startswith(t + ".")} for n, targets in graph.items()}
    state: dict[str, int] = {}
    path: list[str] = []

    def visit(node: str) -> list[str] | None:
        state[node] = 1
        path.append(node)
        for target in sorted(graph[node]):
            if state.get(target) == 1:
                return path[path.index(target) :] + [target]
            if target not in state:
                cycle = visit(target)
                if cycle:
                    return cycle
        state[node] = 2
        path.pop()
        return None

    for name in sorted(graph):
        if name not in state:
            cycle = visit(name)
            assert cycle is None, "import cycle: " + " -> ".join(cycle)


@pytest.mark.parametrize("prefix", ["don_gym.evaluation", "don_gym.agents.rl"])
def test_modules_of_one_concept_stay_small(prefix: str) -> None:
    """No module of the evaluation stage or the RL baselines over ~600 lines, no function over ~100."""
    names = [n for n in MODULES if n.startswith(prefix)]
    assert names
    problems = []
    for name in names:
        source = MODULES[name].read_text()
        if len(source.splitlines()) > 620:
            problems.append(f"{name}: {len(source.splitlines())} lines")
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno - node.lineno > 105:
                problems.append(f"{name}.{node.name}: {node.end_lineno - node.lineno + 1} lines")
    assert not problems, "\n".join(problems)


def test_new_stage_modules_declare_their_public_names() -> None:
    """Every module of the stage packages says what it offers (``__all__``), and offers what it says."""
    import importlib

    for name in MODULES:
        if not name.startswith(("don_gym.data.", "don_gym.learning.", "don_gym.perception.", "don_gym.evaluation.")):
            continue
        module = importlib.import_module(name)
        exported = getattr(module, "__all__", None)
        assert exported, f"{name} has no __all__"
        missing = [n for n in exported if not hasattr(module, n)]
        assert not missing, f"{name}.__all__ names {missing}, which it does not define"


def documented_paths() -> set[str]:
    """Every ``don_gym.x.y`` the README and docs/ name (module paths and names in them)."""
    texts = [REPO / "README.md", REPO / "CONTRIBUTING.md", *sorted((REPO / "docs").glob("*.md"))]
    found = set()
    for path in texts:
        found |= set(re.findall(r"\bdon_gym(?:\.[A-Za-z_][A-Za-z0-9_]*)+", path.read_text()))
    return found


def test_every_path_the_docs_name_imports() -> None:
    import importlib

    problems = []
    paths = documented_paths()
    assert len(paths) > 20
    for dotted in sorted(paths):
        parts = dotted.split(".")
        # The longest importable prefix, then attributes along the rest.
        for cut in range(len(parts), 0, -1):
            try:
                obj = importlib.import_module(".".join(parts[:cut]))
            except ModuleNotFoundError:
                continue
            for attr in parts[cut:]:
                if not hasattr(obj, attr):
                    problems.append(f"{dotted}: {'.'.join(parts[:cut])} has no {attr!r}")
                    break
                obj = getattr(obj, attr)
            break
        else:
            problems.append(f"{dotted}: no such module")
    assert not problems, "\n".join(problems)


def test_every_source_file_the_docs_name_exists() -> None:
    texts = [REPO / "README.md", REPO / "CONTRIBUTING.md", *sorted((REPO / "docs").glob("*.md"))]
    named = set()
    for path in texts:
        named |= set(re.findall(r"\b((?:don_gym|wrappers|agents|benchmarks|tests)/[\w/]+\.py)\b", path.read_text()))
    assert len(named) > 5
    missing = sorted(p for p in named if not (REPO / p).is_file())
    assert not missing, f"named in the docs, but no such file: {missing}"
