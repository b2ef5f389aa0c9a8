"""Shared fixtures: example FMUs built on demand (cached between runs)."""
import pytest


@pytest.fixture(scope="session")
def bouncing_ball_fmu():
    from fmubuilder.build import example_fmu
    return example_fmu("bouncing_ball")
