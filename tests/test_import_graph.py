"""The project's import graph, read from the source (ast): no cycles, one-way layering,
and no unexplained imports inside functions.

Nodes are the modules of the project's packages; an edge A -> B says that running A
imports B. ``import a.b.c`` and ``from a.b import c`` import every package on the way
(their ``__init__`` runs: ``a``, ``a.b``), and ``from a.b import c`` imports ``a.b.c``
too when ``c`` is a submodule. A module's own parent packages are not edges: Python has
them in ``sys.modules`` (initialised or being initialised) before the module runs.
Imports inside functions are edges like the others (a cycle hidden in a function is
still a cycle); imports under ``if TYPE_CHECKING:`` never run, so they count for the
layering but not for cycles.
"""

from __future__ import annotations

import ast
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("geometry", "osdar_platform", "service", "worker", "renderer")

#: What the API may take from ``worker``: the queue and the request-time checks (and the
#: packages on the way, whose ``__init__`` runs).
SERVICE_MAY_IMPORT_FROM_WORKER = frozenset(
    {"worker", "worker.orchestration", "worker.orchestration.queue", "worker.orchestration.inspect"}
) | frozenset({"worker.campaign", "worker.campaign.spec", "worker.campaign.variant"})
#: The campaign spec and its variants: pydantic models the API validates a campaign with
#: (worker/campaign/spec.py: "the spec can be checked where the pipeline is not installed").
LIGHT_WORKER_MODULES = frozenset(
    {"worker.campaign", "worker.campaign.spec", "worker.campaign.variant"}
)

LAZY_MARK = "lazy:"


@dataclass(frozen=True)
class Edge:
    src: str
    dst: str
    path: str  # of src, relative to the repository
    line: int
    in_function: bool
    type_only: bool  # under ``if TYPE_CHECKING:``

    def where(self) -> str:
        return f"{self.path}:{self.line}"


def _module_files() -> dict[str, Path]:
    files: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            parts = list(path.relative_to(ROOT).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            name = ".".join(parts)
            # a package and a same-named module (mid-split): Python imports the package
            if name not in files or path.name == "__init__.py":
                files[name] = path
    return files


MODULES = _module_files()


def _is_package(name: str) -> bool:
    return MODULES[name].name == "__init__.py"


def _prefixes(dotted: str) -> Iterator[str]:
    parts = dotted.split(".")
    for i in range(1, len(parts) + 1):
        yield ".".join(parts[:i])


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


class _Imports(ast.NodeVisitor):
    """Every import statement of a module with its context."""

    def __init__(self, module: str) -> None:
        self.module = module
        self.package = module if _is_package(module) else module.rpartition(".")[0]
        self.found: list[tuple[list[str], int, bool, bool]] = []
        #: line of the innermost enclosing function of each in-function import
        self.function_of: dict[int, int] = {}
        self._functions: list[int] = []
        self._type_only_depth = 0

    def _visit_function(self, node: ast.FunctionDef | ast.AsyncFunctionDef | ast.Lambda) -> None:
        self._functions.append(node.lineno)
        self.generic_visit(node)
        self._functions.pop()

    visit_FunctionDef = visit_AsyncFunctionDef = visit_Lambda = _visit_function

    def visit_If(self, node: ast.If) -> None:
        if _is_type_checking(node.test):
            self._type_only_depth += 1
            for child in node.body:
                self.visit(child)
            self._type_only_depth -= 1
            for child in node.orelse:
                self.visit(child)
        else:
            self.generic_visit(node)

    def _add(self, targets: list[str], node: ast.stmt) -> None:
        in_function = bool(self._functions)
        if in_function:
            self.function_of[node.lineno] = self._functions[-1]
        self.found.append((targets, node.lineno, in_function, self._type_only_depth > 0))

    def visit_Import(self, node: ast.Import) -> None:
        self._add([p for alias in node.names for p in _prefixes(alias.name)], node)

    def visit_ImportFrom(self, node: ast.ImportFrom) -> None:
        if node.level:
            base_parts = self.package.split(".")
            base_parts = base_parts[: len(base_parts) - (node.level - 1)]
            base = ".".join(base_parts + ([node.module] if node.module else []))
        else:
            base = node.module or ""
        targets = list(_prefixes(base))
        targets += [f"{base}.{alias.name}" for alias in node.names]  # submodules, if any
        self._add(targets, node)


def _edges_of(module: str) -> Iterator[Edge]:
    path = MODULES[module]
    visitor = _Imports(module)
    visitor.visit(ast.parse(path.read_text(), filename=str(path)))
    own = set(_prefixes(module))  # itself and its parent packages: already in sys.modules
    for targets, line, in_function, type_only in visitor.found:
        for dst in dict.fromkeys(targets):
            if dst in MODULES and dst not in own:
                rel = path.relative_to(ROOT).as_posix()
                yield Edge(module, dst, rel, line, in_function, type_only)


EDGES = [edge for module in MODULES for edge in _edges_of(module)]


def _strongly_connected(nodes: Iterable[str], succ: dict[str, list[str]]) -> list[list[str]]:
    """Tarjan's algorithm (iterative); components of more than one node or with a
    self-edge, i.e. the cycles."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    cyclic: list[list[str]] = []
    counter = 0
    for root in nodes:
        if root in index:
            continue
        work = [(root, iter(succ.get(root, ())))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            for child in children:
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, iter(succ.get(child, ()))))
                    break
                if child in on_stack:
                    low[node] = min(low[node], index[child])
            else:
                work.pop()
                if work:
                    parent = work[-1][0]
                    low[parent] = min(low[parent], low[node])
                if low[node] == index[node]:
                    component = []
                    while True:
                        member = stack.pop()
                        on_stack.discard(member)
                        component.append(member)
                        if member == node:
                            break
                    if len(component) > 1 or node in succ.get(node, ()):
                        cyclic.append(sorted(component))
    return cyclic


def _one_cycle(component: list[str], by_pair: dict[tuple[str, str], Edge]) -> list[Edge]:
    """A shortest cycle through the component's first node, as edges (BFS)."""
    members = set(component)
    start = component[0]
    came_from: dict[str, Edge] = {}
    frontier = [start]
    while frontier:
        following = []
        for node in frontier:
            for (a, b), edge in by_pair.items():
                if a != node or b not in members:
                    continue
                if b == start:
                    path = [edge]
                    while path[0].src != start:
                        path.insert(0, came_from[path[0].src])
                    return path
                if b not in came_from:
                    came_from[b] = edge
                    following.append(b)
        frontier = following
    raise AssertionError(f"no cycle through {start}")  # unreachable for an SCC


def _describe(path: list[Edge]) -> str:
    lines = [
        f"  {e.src} -> {e.dst}  ({e.where()}{', in a function' * e.in_function})" for e in path
    ]
    return "\n".join(lines)


def test_the_graph_sees_the_project() -> None:
    """Guards the test itself: modules found, edges of each kind found."""
    assert {"geometry.camera", "worker.osdar.sequence", "service.app"} <= set(MODULES)
    pairs = {(e.src, e.dst) for e in EDGES}
    assert ("renderer.object_render", "geometry.camera") in pairs
    # a package's __init__ runs on the way to its submodule
    assert ("worker.orchestration.inspect", "worker.osdar") in pairs
    assert any(e.in_function for e in EDGES) and any(e.type_only for e in EDGES)


def test_no_import_cycles() -> None:
    runtime = [e for e in EDGES if not e.type_only]
    succ: dict[str, list[str]] = {}
    by_pair: dict[tuple[str, str], Edge] = {}
    for e in runtime:
        succ.setdefault(e.src, []).append(e.dst)
        by_pair.setdefault((e.src, e.dst), e)
    cycles = _strongly_connected(sorted(MODULES), succ)
    report = [f"cycle among {', '.join(c)}:\n{_describe(_one_cycle(c, by_pair))}" for c in cycles]
    assert not cycles, "import cycles:\n" + "\n".join(report)


def _top(module: str) -> str:
    return module.partition(".")[0]


def _layering_violation(edge: Edge) -> str | None:
    src, dst = _top(edge.src), _top(edge.dst)
    if src == "geometry" and dst != "geometry":
        return "geometry imports nothing of the project but geometry"
    if src == "osdar_platform" and dst != "osdar_platform":
        return "osdar_platform imports only osdar_platform"
    if src == "service":
        if dst in ("geometry", "renderer"):
            return "service imports no geometry and no renderer"
        if dst == "worker" and edge.dst not in SERVICE_MAY_IMPORT_FROM_WORKER:
            return f"service takes from worker only {sorted(SERVICE_MAY_IMPORT_FROM_WORKER)}"
    if src == "renderer" and dst in ("worker", "service"):
        return "renderer imports neither worker nor service"
    return None


def test_layering() -> None:
    bad = [
        f"{e.where()}: {e.src} -> {e.dst}: {why}"
        for e in EDGES
        if (why := _layering_violation(e)) is not None
    ]
    assert not bad, "layering broken:\n" + "\n".join(bad)


def _is_pipeline(module: str) -> bool:
    top = _top(module)
    if top in ("geometry", "renderer"):
        return True
    if module in LIGHT_WORKER_MODULES:
        return False
    return top == "worker" and module != "worker" and not module.startswith("worker.orchestration")


def test_the_api_reaches_no_pipeline_at_start() -> None:
    """What importing ``service`` runs (module-level imports, transitively) holds no
    geometry, renderer or pipeline module: those are reached at request time only,
    through ``worker.orchestration.inspect``."""
    succ: dict[str, list[Edge]] = {}
    for e in EDGES:
        if not (e.in_function or e.type_only):
            succ.setdefault(e.src, []).append(e)
    via: dict[str, Edge | None] = {m: None for m in MODULES if _top(m) == "service"}
    frontier = list(via)
    while frontier:
        node = frontier.pop()
        for e in succ.get(node, ()):
            if e.dst not in via:
                via[e.dst] = e
                frontier.append(e.dst)
    reached = sorted(m for m in via if _is_pipeline(m))
    chains = []
    for module in reached[:5]:
        chain: list[Edge] = []
        step = via[module]
        while step is not None:
            chain.insert(0, step)
            step = via[step.src]
        chains.append(f"{module}:\n{_describe(chain)}")
    assert not reached, "the API imports the pipeline at start:\n" + "\n".join(chains)


def _has_lazy_mark(lines: list[str], line: int) -> bool:
    return any(LAZY_MARK in lines[i] for i in (line - 1, line - 2) if 0 <= i < len(lines))


def _unexplained_function_imports(path: Path, module: str) -> list[int]:
    """Lines of imports inside functions with no ``lazy:`` reason. The reason sits on the
    import's line or the line above; one reason covers the imports of the same function
    that follow it (one deferral: ``matplotlib`` then ``matplotlib.pyplot``)."""
    text = path.read_text()
    lines = text.splitlines()
    visitor = _Imports(module)
    visitor.visit(ast.parse(text, filename=str(path)))
    explained_functions: set[int] = set()
    bad = []
    for line in sorted(visitor.function_of):
        function = visitor.function_of[line]
        if _has_lazy_mark(lines, line):
            explained_functions.add(function)
        elif function not in explained_functions:
            bad.append(line)
    return bad


def test_imports_inside_functions_state_why() -> None:
    """An import inside a function hides a dependency (or a cost): each one, of the
    project or of a library, carries a comment ``lazy: <the measured reason>``."""
    offenders = [
        f"{path.relative_to(ROOT).as_posix()}:{line}"
        for module, path in MODULES.items()
        for line in _unexplained_function_imports(path, module)
    ]
    assert not offenders, (
        f"imports inside functions without a '{LAZY_MARK}' comment (hoist them to the "
        "module's top, or say what importing them at the top would cost):\n  "
        + "\n  ".join(offenders)
    )


@pytest.mark.parametrize(
    ("graph", "expected"),
    [
        ({"a": ["b"], "b": ["c"], "c": ["a"], "d": ["a"]}, [["a", "b", "c"]]),
        ({"a": ["a"]}, [["a"]]),
        ({"a": ["b"], "b": ["c"], "c": []}, []),
    ],
)
def test_tarjan_finds_cycles(graph: dict[str, list[str]], expected: list[list[str]]) -> None:
    assert _strongly_connected(sorted(graph), graph) == expected
