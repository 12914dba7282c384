import jax

# Identification runs in float64; the library itself never flips this on import.
jax.config.update("jax_enable_x64", True)

import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _fresh_compilation_caches():
    """Each test module starts from empty compilation caches, so that the executables
    of a long session do not pile up in one process."""
    yield
    jax.clear_caches()
