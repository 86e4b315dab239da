"""The conformance suite (framework/testing/conformance.py) run for every backend we ship.

A backend that is not registered or not available here is skipped with the registry's reason; gsplat needs CUDA
and is marked `gpu`.
"""

import pytest

from framework.testing.conformance import *  # noqa: F401,F403


@pytest.fixture(params=["torch_ref", "jax", "numba", pytest.param("gsplat", marks=pytest.mark.gpu)])
def backend_name(request: pytest.FixtureRequest) -> str:
    return request.param
