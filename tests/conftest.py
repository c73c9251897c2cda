"""Test configuration: the suite runs in float64 (the library itself never flips the flag);
float32 behaviour is checked with explicitly float32 inputs."""

import os

# The suite is bound by XLA compilation, not by run time: ask XLA:CPU for less LLVM
# optimisation (about 1.6x faster compiles). Only code generation changes, not the IEEE
# arithmetic asked for; user programs and the benchmarks run with XLA's defaults. Set
# before the first JAX computation initialises the backend; the caller's flags are kept.
_FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FAST_COMPILE}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

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
