"""For every test: torch on one thread, the `service` marker on the tests under tests/service/, and the packages
pytest rewrites imported before any test runs."""
from __future__ import annotations

import importlib
import pkgutil
import sys
from pathlib import Path

import pytest
import torch

SERVICE_TESTS = Path(__file__).parent / "service"

torch.set_num_threads(1)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if SERVICE_TESTS in item.path.parents:
            item.add_marker(pytest.mark.service)


def pytest_collection_finish(session: pytest.Session) -> None:
    """Import every module of the packages pytest's assertion rewriting covers (plugins: schemathesis, hypothesis,
    anyio) while no test's thread runs. CPython 3.11 keeps the AST builder's recursion depth per interpreter, not per
    thread: a module rewritten on first import mid-test (`ast.parse` in the main thread) while a thread of the test's
    app parses too (a traceback's carets, `inspect.signature`) failed CI with "AST constructor recursion depth
    mismatch". Modules whose optional dependencies are missing or broken are skipped; nothing imports them later."""
    if sys.version_info[:2] != (3, 11):
        return
    rewritten = getattr(session.config.pluginmanager.rewrite_hook, "_must_rewrite", ())  # none with --assert=plain
    for name in sorted(rewritten):
        package = importlib.import_module(name)
        for module in pkgutil.walk_packages(getattr(package, "__path__", []), f"{name}.", onerror=lambda _: None):
            try:
                importlib.import_module(module.name)
            except Exception:  # an optional extra: ImportError, or a configuration error of a library it wraps
                pass
