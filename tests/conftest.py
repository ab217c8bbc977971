"""For every test: torch on one thread, and the `service` marker on the tests under tests/service/."""
from __future__ import annotations

from pathlib import Path

import pytest
import torch

SERVICE_TESTS = Path(__file__).parent / "service"

torch.set_num_threads(1)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    for item in items:
        if SERVICE_TESTS in item.path.parents:
            item.add_marker(pytest.mark.service)
