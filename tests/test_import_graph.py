"""The package's import graph: no cycle between modules or between the subpackages of ``avatar``, and the
layering the design keeps (docs/development/architecture.md): ``avatar`` imports neither ``pipeline`` nor
``stages`` nor ``importers``; ``stages/`` holds only stage modules and no stage imports another; nothing imports a
stage module but the runner (by name, from ``pipeline.stages_module``), the tests and the benchmarks that run the
DAG; the schemas are leaves; the readers of outside data (``importers``) sit beside the core, below the stages;
fitting sits below training. Every import counts, those inside functions and under ``TYPE_CHECKING`` too."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PACKAGES = ("avatar", "data_schemas", "examples", "importers", "pipeline", "reporting", "stages")


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py") if "csrc" not in p.parts}


def import_graph() -> dict[str, set[str]]:
    """module -> the project modules it imports (``from a.b import c`` counts ``a.b.c`` when that is a module,
    else ``a.b``; relative imports resolved)."""
    modules = _modules()
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        targets: set[str] = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                targets.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(anchor + ([base] if base else []))
                targets.update(f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names)
        graph[name] = {t for t in targets if t in modules and t != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_module_imports_itself_through_others() -> None:
    graph = {m: {t for t in ts if not m.startswith(t + ".")} for m, ts in import_graph().items()}
    assert cycles(graph) == []


def test_the_subpackages_of_avatar_form_no_cycle() -> None:
    """E.g. ``avatar.dynamic`` and ``avatar.training`` may not import each other (posing sits below both)."""

    def sub(module: str) -> str:
        return ".".join(module.split(".")[:2])

    graph: dict[str, set[str]] = {}
    for module, targets in import_graph().items():
        if module.startswith("avatar."):
            graph.setdefault(sub(module), set()).update(
                sub(t) for t in targets if t.startswith("avatar.") and sub(t) != sub(module)
            )
    assert cycles(graph) == []


def _stage_modules() -> set[str]:
    """The modules of ``stages/`` that define a stage (``@stage(``); the others are their helpers."""
    return {f"stages.{p.stem}" for p in (REPO / "stages").glob("*.py") if "\n@stage(" in p.read_text()}


def test_the_layering_holds() -> None:
    graph, stage_modules = import_graph(), _stage_modules()
    assert len(stage_modules) >= 12
    for module, targets in graph.items():
        top = module.split(".")[0]
        if top == "avatar":
            assert not {t for t in targets if t.split(".")[0] in ("pipeline", "stages")}, module
        if top == "data_schemas":
            assert all(t.startswith("data_schemas") for t in targets), module
        if module in stage_modules:
            assert not targets & (stage_modules - {module}), module


def test_stages_holds_only_stage_modules() -> None:
    helpers = sorted(f"stages.{p.stem}" for p in (REPO / "stages").rglob("*.py") if p.name != "__init__.py") + sorted(
        f"stages.{p.name}" for p in (REPO / "stages").iterdir() if p.is_dir() and p.name != "__pycache__"
    )
    assert set(helpers) - _stage_modules() == set(), "stages/ holds only @stage modules: move helpers to a room"


def test_nothing_imports_a_stage_but_the_runner() -> None:
    """The runner loads ``stages`` by name; the core, the readers, the schemas and the pipeline never import it, and
    a benchmark takes at most the registry (``from stages import REGISTRY``) to run stages, never a stage's
    internals."""
    for module, targets in import_graph().items():
        if module.split(".")[0] != "stages":
            assert not {t for t in targets if t.split(".")[0] == "stages"}, module
    for path in sorted((REPO / "benchmarks").glob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("stages"):
                assert node.module == "stages" and [a.name for a in node.names] == ["REGISTRY"], path.name
            if isinstance(node, ast.Import):
                assert not any(a.name.startswith("stages") for a in node.names), path.name


def test_the_rooms_keep_their_direction() -> None:
    """``importers`` (DECAF, folders, COLMAP, nerfstudio) read outside data with the core's and the schemas' help
    and know nothing of the pipeline; the pipeline's runner knows no model: only its PLY export command reads a
    trained avatar, and its config only asks the DECAF reader (itself a pure reader) what a release ships; fitting
    runs before training and imports none of it (both share ``avatar.geometry``); only the stages use the report's
    and the comparison's sections (``reporting``)."""
    graph = import_graph()
    for module, targets in graph.items():
        tops = {t.split(".")[0] for t in targets}
        if module.startswith(("importers", "examples")):  # an example plug-in is written against the core alone
            assert not tops & {"pipeline", "stages"}, module
        if module.startswith("avatar"):
            assert "importers" not in tops, module
        if module.startswith("pipeline") and not module.startswith("pipeline.export_ply"):
            assert "avatar" not in tops, module
            assert {t for t in targets if t.startswith("importers")} <= {"importers.decaf"}, module
        if module.startswith("avatar.fitting"):
            assert not {t for t in targets if t.startswith("avatar.training")}, module
        if not module.startswith(("stages", "reporting")):  # the report's and the comparison's sections serve them
            assert "reporting" not in tops, module
    assert {t.split(".")[0] for t in graph["importers.decaf"]} <= {"data_schemas"}


def test_the_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []
