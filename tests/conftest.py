"""Test configuration: the suite runs in float64 (the library itself never flips the flag);
float32 behaviour is checked with explicitly float32 inputs."""

import os
import shutil
import tempfile

# The suite is bound by XLA compilation, not by run time: ask XLA:CPU for less LLVM
# optimisation (about 1.6x faster compiles). Only code generation changes, not the IEEE
# arithmetic asked for; user programs and the benchmarks run with XLA's defaults. Set
# before the first JAX computation initialises the backend; the caller's flags are kept.
_FAST_COMPILE = "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FAST_COMPILE}".strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# JAX's persistent compilation cache, private to this process (each xdist worker has its own:
# JAX writes entries without locking) in a temporary folder removed when pytest ends. After a
# module's jax.clear_caches() (and where a test builds a graph another test compiled already)
# the executables are loaded instead of compiled again. Only compilations of at least 1 s are
# written: writing each of the thousands of small ones costs more than compiling it again
# (measured: ~5% on tests/test_sensor.py with everything written, few hits). The `jaximu`
# commands the tests run as subprocesses get the same folder (JAXIMU_CACHE_DIR), so they
# never write into the user's ~/.cache; they write with the CLI's own threshold, while the
# worker that started them waits, so no two writers share the folder at once. A killed
# worker leaves its folder in the temporary directory. JAXIMU_TEST_XLA_CACHE=off runs the
# suite without the cache.
_XLA_CACHE = None
if os.environ.get("JAXIMU_TEST_XLA_CACHE", "").lower() != "off":
    _XLA_CACHE = tempfile.mkdtemp(prefix="jaximu-tests-xla-")
    jax.config.update("jax_compilation_cache_dir", _XLA_CACHE)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    os.environ["JAXIMU_CACHE_DIR"] = _XLA_CACHE
else:
    os.environ["JAXIMU_CACHE_DIR"] = "off"


def pytest_unconfigure(config):
    if _XLA_CACHE is not None:
        shutil.rmtree(_XLA_CACHE, ignore_errors=True)


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
