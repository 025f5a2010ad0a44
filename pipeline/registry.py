"""A set of stages forming a DAG, ordered topologically from their declared inputs."""

from __future__ import annotations

import importlib
from collections.abc import Iterable, Iterator

from pipeline.stage import Stage


class RegistryError(ValueError):
    """The declared stages do not form a valid DAG."""


class StageRegistry:
    """Holds stages by name and answers graph questions about them.

    The order of :meth:`topological` is deterministic: among stages whose inputs
    are all satisfied, the one registered first comes first.
    """

    def __init__(self, stages: Iterable[Stage] = ()) -> None:
        self._stages: dict[str, Stage] = {}
        for s in stages:
            self.add(s)

    def add(self, s: Stage) -> Stage:
        if s.name in self._stages:
            raise RegistryError(f"stage '{s.name}' is registered twice")
        self._stages[s.name] = s
        return s

    def __contains__(self, name: object) -> bool:
        return name in self._stages

    def __getitem__(self, name: str) -> Stage:
        try:
            return self._stages[name]
        except KeyError:
            raise RegistryError(f"unknown stage '{name}'; known stages: {', '.join(self.names())}") from None

    def __iter__(self) -> Iterator[Stage]:
        return iter(self.topological())

    def names(self) -> list[str]:
        return [s.name for s in self.topological()]

    def topological(self) -> list[Stage]:
        """Stages in dependency order; raises on unknown inputs and cycles."""
        for s in self._stages.values():
            missing = [i for i in s.reads if i not in self._stages]
            if missing:
                raise RegistryError(f"stage '{s.name}' reads unknown stage(s) {missing}")
            shared = [i for i in s.inputs if self._stages[i].per_method and not s.per_method]
            if shared:
                raise RegistryError(
                    f"stage '{s.name}' is shared by every method but reads the per-method "
                    f"stage(s) {shared}: declare it per_method, or read them through "
                    f"cross_method_inputs"
                )
            per_method = [i for i in s.subject_inputs if self._stages[i].per_method]
            if per_method:
                raise RegistryError(
                    f"stage '{s.name}' reads {per_method} of another subject; only stages shared by "
                    f"every method can be read across subjects"
                )
            single = [i for i in s.cross_method_inputs if not self._stages[i].per_method]
            if single:
                raise RegistryError(
                    f"stage '{s.name}' reads {single} of several methods, but they are shared "
                    f"by every method: list them in inputs"
                )
        done: dict[str, Stage] = {}
        pending = list(self._stages.values())
        while pending:
            ready = [s for s in pending if all(i in done for i in s.reads)]
            if not ready:
                cycle = ", ".join(s.name for s in pending)
                raise RegistryError(f"the stages {cycle} depend on each other in a cycle")
            first = ready[0]
            done[first.name] = first
            pending.remove(first)
        return list(done.values())

    def ancestors(self, name: str) -> set[str]:
        """All stages that ``name`` reads, directly or transitively (excluding itself)."""
        out: set[str] = set()
        stack = list(self[name].reads)
        while stack:
            n = stack.pop()
            if n not in out:
                out.add(n)
                stack.extend(self[n].reads)
        return out

    def descendants(self, name: str) -> set[str]:
        """All stages that read ``name``, directly or transitively (excluding itself)."""
        self[name]
        return {s.name for s in self._stages.values() if name in self.ancestors(s.name)}


def load_registry(module_name: str) -> StageRegistry:
    """Import ``module_name`` and return its ``REGISTRY`` attribute.

    This is how the app picks its DAG (config key ``pipeline.stages_module``), so
    tests and plug-ins can run the same runner over their own stages.
    """
    try:
        module = importlib.import_module(module_name)
    except ImportError as exc:
        raise RegistryError(
            f"cannot import stage module '{module_name}' (config key pipeline.stages_module): {exc}"
        ) from exc
    registry = getattr(module, "REGISTRY", None)
    if not isinstance(registry, StageRegistry):
        raise RegistryError(f"module '{module_name}' has no StageRegistry named REGISTRY")
    return registry
