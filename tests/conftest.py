"""Test configuration: the suite runs in float64 (the library itself never flips the flag);
float32 behaviour is checked with explicitly float32 inputs."""

import jax
import pytest

jax.config.update("jax_enable_x64", True)


@pytest.fixture(autouse=True, scope="module")
def _release_compiled_code():
    """Drop compiled executables after each test module.

    One process compiling the whole suite's few thousand XLA:CPU executables crashed inside
    the compiler (SIGSEGV/SIGABRT in ``backend_compile_and_load``) after ~200 tests, at the
    same test each time, while every file passed on its own; releasing the code of finished
    modules keeps the process's JIT memory bounded.
    """
    yield
    jax.clear_caches()
