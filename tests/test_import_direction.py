"""Imports point one way: `app -> kernel <- worker`, all three -> `drop_engine`, and the engine knows nothing of the
service; `drop_client` stands alone, and `drop_cli` sits on top of the engine, `app` and the client
(docs/ARCHITECTURE.md). Read from the source's syntax trees, imports inside functions included, so a lazy
import cannot hide a dependency; and no module imports another that imports it back."""
from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("drop_engine", "kernel", "app", "worker", "drop_client", "drop_cli")
ABOVE = {"drop_client", "drop_cli"}  # only drop_cli imports the client, and nothing imports drop_cli
SERVICE_LIBRARIES = {"fastapi", "starlette", "uvicorn", "sqlalchemy", "alembic", "celery", "kombu", "psycopg", "redis",
                     "pydantic_settings", "prometheus_client", "structlog", "python_multipart"}
FORBIDDEN = {
    "drop_engine": {"kernel", "app", "worker"} | SERVICE_LIBRARIES | ABOVE,
    "kernel": {"app", "worker"} | ABOVE,
    "worker": {"app"} | ABOVE,
    "app": {"worker"} | ABOVE,
    "drop_client": {"drop_engine", "kernel", "app", "worker", "drop_cli"},
    "drop_cli": {"kernel", "worker"},
}


def _module(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path) -> set[str]:
    """Every module `path` imports, as absolute dotted names (`from a import b` counts as a.b, which may be a name in
    a rather than a module: callers match on prefixes)."""
    module = _module(path)
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[:len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names)
    return found


SOURCES = {_module(p): p for package in PACKAGES for p in sorted((REPO / package).rglob("*.py"))}
GRAPH = {module: _imports(path) for module, path in SOURCES.items()}


def test_the_packages_are_there():
    assert {m.split(".")[0] for m in SOURCES} == set(PACKAGES)
    assert "kernel.job_state" in SOURCES and "app.jobs.service" in SOURCES


@pytest.mark.parametrize("package", PACKAGES)
def test_imports_point_one_way(package):
    wrong = sorted({f"{module} imports {name.split('.')[0]}" for module, names in GRAPH.items()
                    if module.split(".")[0] == package for name in names if name.split(".")[0] in FORBIDDEN[package]})
    assert not wrong, wrong


def test_the_modules_import_no_cycle():
    modules = set(SOURCES)
    edges = {m: {n for n in GRAPH[m] if n in modules and n != m} for m in modules}
    done: set[str] = set()

    def visit(module: str, path: list[str]) -> None:
        if module in path:
            raise AssertionError("import cycle: " + " -> ".join(path[path.index(module):] + [module]))
        if module in done:
            return
        for imported in sorted(edges[module]):
            visit(imported, [*path, module])
        done.add(module)

    for module in sorted(modules):
        visit(module, [])
