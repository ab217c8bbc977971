"""Fixtures for the engine tests: small real datasets made in the real MuJoCo env."""
from __future__ import annotations

import numpy as np
import pytest

from drop_engine.collect import collect_transitions, random_policy
from drop_engine.data import Dataset, from_arrays


@pytest.fixture(scope="session")
def hopper_arrays() -> dict[str, np.ndarray]:
    """1,500 random-policy hopper transitions (many short episodes, so terminals are plentiful)."""
    return collect_transitions("hopper", random_policy(3, seed=0), 1500, seed=0)


@pytest.fixture(scope="session")
def hopper_dataset(hopper_arrays) -> Dataset:
    return from_arrays(hopper_arrays, {"env_name": "Hopper-v4"}, env="hopper")
