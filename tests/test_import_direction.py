"""Imports point one way: `app -> kernel <- worker`, all three -> `drop_engine`, and the engine knows nothing of the
service; `drop_client` stands alone, and `drop_cli` sits on top of the engine, `app` and the client
(docs/ARCHITECTURE.md). Read from the source's syntax trees, imports inside functions included, so a lazy import
cannot hide a dependency; and no module imports another that imports it back. The dependencies pyproject.toml declares
match the imports: the engine, the client and the command need only the base ones (`pip install drop-rl`), the
service also its extra, and nothing declared goes unused."""
from __future__ import annotations

import ast
import importlib.metadata
import re
import subprocess
import sys
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


SERVICE = ("dependencies", "service")
NEEDS = {"drop_engine": ("dependencies",), "drop_client": ("dependencies",), "drop_cli": ("dependencies",),
         "kernel": SERVICE, "app": SERVICE, "worker": SERVICE}
# Imported, not declared: each comes with the library that pins its version (FastAPI is built on Starlette, pydantic
# on pydantic-core).
COMES_WITH = {"starlette": "fastapi", "pydantic_core": "pydantic"}
# Declared, never imported: torch.onnx.export writes the policy's ONNX file with onnx; uvicorn parses HTTP with
# httptools when it is installed.
USED_UNIMPORTED = {"onnx", "httptools"}


def _normal(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


@pytest.fixture(scope="module")
def project() -> dict:
    """pyproject.toml's [project] table."""
    tomllib = pytest.importorskip("tomllib")  # Python 3.11+
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def _declared(project: dict, *groups: str) -> set[str]:
    """The distributions that these groups (`dependencies`, or an extra's name) require, by normalised name."""
    lists = [project["dependencies"] if g == "dependencies" else project["optional-dependencies"][g] for g in groups]
    return {_normal(re.match(r"[A-Za-z0-9._-]+", req).group(0)) for reqs in lists for req in reqs}


def _third_party(package: str) -> set[str]:
    """The top-level modules outside the standard library and this project that `package` imports."""
    ours = set(PACKAGES) | {"__future__", ""}
    return {name.split(".")[0] for module, names in GRAPH.items() if module.split(".")[0] == package
            for name in names} - set(sys.stdlib_module_names) - ours


def _distributions(module: str) -> set[str]:
    """The installed distributions that provide top-level module `module`."""
    return {_normal(d) for d in importlib.metadata.packages_distributions().get(module, [module])}


@pytest.mark.parametrize("package", PACKAGES)
def test_every_library_a_package_imports_is_declared(project, package):
    declared = _declared(project, *NEEDS[package])
    missing = sorted(m for m in _third_party(package)
                     if not _distributions(m) & declared and COMES_WITH.get(m) not in declared)
    assert not missing, f"{package} imports {missing}, which {' + '.join(NEEDS[package])} do not declare"


def test_every_declared_dependency_is_imported(project):
    imported = {d for package in PACKAGES for m in _third_party(package) for d in _distributions(m)}
    unused = sorted(_declared(project, "dependencies", "service") - imported - USED_UNIMPORTED)
    assert not unused, f"declared in pyproject.toml but imported nowhere: {unused}"


def test_the_library_and_the_command_run_without_the_service_extra():
    """As after `pip install drop-rl`, with the service's libraries made unimportable: every module of the engine and
    of the client imports, the engine's and the remote commands answer, and a service command says what to install."""
    code = ("import importlib, pkgutil, sys\n"
            f"sys.modules.update(dict.fromkeys({sorted(SERVICE_LIBRARIES)!r}))\n"
            "import drop_client, drop_engine\n"
            "for package in (drop_engine, drop_client):\n"
            "    for m in pkgutil.walk_packages(package.__path__, package.__name__ + '.'):\n"
            "        importlib.import_module(m.name)\n"
            "from drop_cli import main\n"
            "print(main(['train', '--help']), main(['jobs', 'submit', '--help']), main(['db', 'upgrade']))\n")
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-4000:]
    assert "--dataset" in done.stdout and done.stdout.splitlines()[-1] == "0 0 2", done.stdout
    assert "is not installed; the service's commands need `pip install 'drop-rl[service]'`" in done.stderr, done.stderr
