"""The package's layering, read from the source: core <- drivers <- daemon/compute <- api <- run/cli, with
the tools beside. A module imports only from its own layer or the ones below, nothing imports in a
circle, only the tools import hwsim, and hwsim never imports clothd. And the sizes: no file over 450
lines, no function over 80 but Taichi's."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

pytestmark = pytest.mark.clock_free

ROOT = Path(__file__).resolve().parents[1]

# Lowest first. A module belongs to the first entry whose prefix it starts with.
LAYERS: list[tuple[str, tuple[str, ...]]] = [
    ("base", ("clothd.errors", "clothd.config", "clothd.__init__")),
    ("core", ("clothd.core",)),
    ("formats", ("clothd.formats", "clothd.taichi_runtime")),
    ("drivers", ("clothd.drivers",)),
    ("shell", ("clothd.loop", "clothd.outputs", "clothd.notify", "clothd.logs")),
    ("tools", ("clothd.tools",)),
    ("api", ("clothd.api",)),
    ("entry", ("clothd.run", "clothd.cli")),
]
RANK = {name: k for k, (name, _) in enumerate(LAYERS)}


def _module_name(path: Path) -> str:
    return ".".join(path.relative_to(ROOT).with_suffix("").parts)


def _layer(module: str) -> str:
    for name, prefixes in LAYERS:
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return name
    raise AssertionError(f"{module} is in no layer: add it to tests/test_layers.py")


def _imports(source: str) -> set[str]:
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.add(node.module)
            found.update(f"{node.module}.{alias.name}" for alias in node.names)
    return found


def _graph(package: str) -> dict[str, set[str]]:
    files = {_module_name(p): p for p in (ROOT / package).rglob("*.py")}
    modules = set(files) | {m.removesuffix(".__init__") for m in files}
    graph = {}
    for mod, path in files.items():
        name = mod.removesuffix(".__init__")
        graph[name] = {i for i in _imports(path.read_text()) if i in modules and i != name}
    return graph


def _upward_imports(graph: dict[str, set[str]]) -> list[str]:
    """Imports of a higher layer; the CLI may run the tools, and nothing but the tools imports them."""
    wrong = []
    for mod, deps in graph.items():
        for dep in deps:
            up = RANK[_layer(dep)] > RANK[_layer(mod)] and not (
                _layer(mod) == "entry" and _layer(dep) == "tools"
            )
            into_tools = _layer(dep) == "tools" and _layer(mod) not in ("tools", "entry")
            if up or into_tools:
                wrong.append(f"{mod} ({_layer(mod)}) imports {dep} ({_layer(dep)})")
    return wrong


def _circle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle, or None."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done

    def visit(mod: str, path: list[str]) -> list[str] | None:
        state[mod] = 1
        for dep in sorted(graph.get(mod, ())):
            if state.get(dep) == 1:
                return [*path[path.index(dep) :], dep]
            if dep not in state and (found := visit(dep, [*path, dep])):
                return found
        state[mod] = 2
        return None

    for mod in sorted(graph):
        if mod not in state and (found := visit(mod, [mod])):
            return found
    return None


def test_every_import_points_down_or_sideways() -> None:
    wrong = _upward_imports(_graph("clothd"))
    assert not wrong, "\n".join(wrong)


def test_no_import_circle() -> None:
    circle = _circle(_graph("clothd"))
    assert circle is None, "import circle: " + " -> ".join(circle or [])


def test_the_checks_catch_what_they_are_for() -> None:
    bad = {
        "clothd.core.tracker": {"clothd.loop.daemon"},  # up a layer
        "clothd.loop.daemon": {"clothd.loop.status"},
        "clothd.loop.status": {"clothd.loop.daemon"},  # the old circle
        "clothd.api.app": {"clothd.tools.replay"},  # the API reaching into the tools
    }
    assert len(_upward_imports(bad)) == 2
    assert _circle(bad) == ["clothd.loop.daemon", "clothd.loop.status", "clothd.loop.daemon"]


@pytest.mark.parametrize(("package", "forbidden"), [("clothd", "hwsim"), ("hwsim", "clothd")])
def test_hwsim_and_the_daemon_stay_apart(package: str, forbidden: str) -> None:
    offenders = [
        _module_name(p)
        for p in (ROOT / package).rglob("*.py")
        if any(i == forbidden or i.startswith(forbidden + ".") for i in _imports(p.read_text()))
        and not _module_name(p).startswith("clothd.tools.")
    ]
    assert not offenders, f"{offenders} import {forbidden}"


MAX_FILE_LINES = 450
MAX_FUNCTION_LINES = (
    80  # Taichi kernels aside: a kernel is one compiled loop nest, split it and it runs slower
)
FILES_NOT_YET_SPLIT: set[str] = set()  # over the bound, named here until split


def _sources() -> list[Path]:
    return sorted([*(ROOT / "clothd").rglob("*.py"), *(ROOT / "hwsim").rglob("*.py")])


def _too_long_functions(tree: ast.Module, limit: int) -> list[str]:
    def is_kernel(node: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
        return any(ast.unparse(d) in ("ti.kernel", "ti.func") for d in node.decorator_list)

    return [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines)"
        for node in ast.walk(tree)
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno is not None
        and node.end_lineno - node.lineno + 1 > limit
        and not is_kernel(node)
    ]


def test_files_and_functions_stay_small() -> None:
    long_files, long_functions = [], []
    for path in _sources():
        text = path.read_text()
        name = str(path.relative_to(ROOT))
        if len(text.splitlines()) > MAX_FILE_LINES and name not in FILES_NOT_YET_SPLIT:
            long_files.append(f"{name} ({len(text.splitlines())} lines)")
        long_functions += [f"{name}: {f}" for f in _too_long_functions(ast.parse(text), MAX_FUNCTION_LINES)]
    assert not long_files, f"over {MAX_FILE_LINES} lines: {long_files}"
    assert not long_functions, f"over {MAX_FUNCTION_LINES} lines: {long_functions}"
    for name in FILES_NOT_YET_SPLIT:  # an exception that is no longer needed goes
        assert len((ROOT / name).read_text().splitlines()) > MAX_FILE_LINES, (
            f"{name} fits: drop it from the list"
        )


def test_the_size_check_sees_a_long_function() -> None:
    body = "\n".join(f"    x{k} = {k}" for k in range(81))
    assert _too_long_functions(ast.parse(f"def f():\n{body}\n"), MAX_FUNCTION_LINES) == ["f (82 lines)"]
    kernel = f"@ti.kernel\ndef f():\n{body}\n"
    assert _too_long_functions(ast.parse(kernel), MAX_FUNCTION_LINES) == []
