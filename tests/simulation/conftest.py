"""Example FMUs for the simulation tests (built on demand, cached)."""
import pytest


@pytest.fixture(scope="session")
def example():
    """example('bouncing_ball') -> path of that built example FMU."""
    from fmubuilder.build import example_fmu
    return example_fmu
