"""Test configuration: the suite runs in float64 (the library itself never flips the flag);
float32 behaviour is checked with explicitly float32 inputs."""

import os
import shutil
import tempfile

# The suite is bound by XLA compilation, not by run time: ask XLA:CPU for less LLVM
# optimisation (about 1.6x faster compiles) and for its classic loop emitter instead of the
# MLIR fusion emitters (half the compile CPU time again: tests/engine/test_preintegration.py took
# 4 min 8 s of CPU with them, 2 min 2 s without, on this project's 2-core machine). Only
# code generation changes, not the IEEE arithmetic asked for; user programs and the
# benchmarks run with XLA's defaults. Set before the first JAX computation initialises the
# backend; the caller's flags are kept (and win: they come last).
#
# Where two programs differ in shape, XLA's code generation decides their last bits, and
# these flags hid one such difference that users' default flags show (a one-lane Monte Carlo
# program: jaximu.montecarlo._lane_errors). So the tests of bitwise reproducibility (a run
# regenerated alone, chunk sizes) are marked ``default_codegen`` and run in a child pytest
# with the caller's flags only (pytest_pyfunc_call below); tests/app/test_cli.py runs the demo
# (real EuRoC data, every scheme) that way too, so the default code generation is exercised
# end to end.
_FAST_COMPILE = (
    "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true"
    " --xla_cpu_use_fusion_emitters=false"
)
import subprocess  # noqa: E402
import sys  # noqa: E402


def _known_flags(flags: str) -> str:
    """The flags of ``flags`` that this jaxlib's XLA knows. XLA aborts the process on an
    unknown flag when its backend starts (JAX 0.11 dropped ``--xla_cpu_use_fusion_emitters``:
    the whole suite died with it), so each is tried in a child once; the answer is kept in
    the environment, which the xdist workers and child pytests inherit."""
    known = os.environ.get("JAXIMU_TEST_FAST_COMPILE")
    if known is not None:
        return known

    def starts(f):
        env = {**os.environ, "XLA_FLAGS": f, "JAX_PLATFORMS": "cpu"}
        return (
            subprocess.run(
                [sys.executable, "-c", "import jax; jax.devices()"],
                env=env,
                capture_output=True,
                timeout=300,
            ).returncode
            == 0
        )

    known = flags if starts(flags) else " ".join(f for f in flags.split() if starts(f))
    os.environ["JAXIMU_TEST_FAST_COMPILE"] = known
    return known


os.environ.setdefault("JAXIMU_TEST_CALLER_XLA_FLAGS", os.environ.get("XLA_FLAGS", ""))
_DEFAULT_CODEGEN = os.environ.get("JAXIMU_TEST_DEFAULT_CODEGEN") == "1"
if _DEFAULT_CODEGEN:
    os.environ["XLA_FLAGS"] = os.environ["JAXIMU_TEST_CALLER_XLA_FLAGS"]
else:
    os.environ["XLA_FLAGS"] = (
        f"{_known_flags(_FAST_COMPILE)} {os.environ['JAXIMU_TEST_CALLER_XLA_FLAGS']}"
    ).strip()

import jax  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_enable_x64", True)

# JAX's persistent compilation cache, one for the whole run: the pytest that starts first
# (the xdist controller, or the only process) makes a temporary folder, its workers and child
# pytests inherit it (JAXIMU_TEST_XLA_CACHE_DIR), and it is removed when that pytest ends. So
# a program one worker compiled is loaded by the other, and after a module's
# jax.clear_caches() (or where a test builds a graph another test compiled already) loaded
# instead of compiled again. A size limit turns on JAX's file lock around every read and
# write of the folder (jax._src.lru_cache, with the `filelock` package), so two processes never
# read a half-written entry. Only compilations of at least 1 s are written: writing each of
# the thousands of small ones costs more than compiling it again (measured: ~5% on
# tests/geometry/test_sensor.py with everything written, few hits). The `jaximu` commands the
# tests run as subprocesses get a folder of this process's own (JAXIMU_CACHE_DIR), so they
# never write into the user's ~/.cache, and they write (with the CLI's own threshold and no
# lock) while the worker that started them waits, so no two writers share their folder. A
# killed run leaves its folders in the temporary directory. JAXIMU_TEST_XLA_CACHE=off runs
# the suite without the cache.
_CREATED = []  # folders this process made, removed when it ends
if os.environ.get("JAXIMU_TEST_XLA_CACHE", "").lower() != "off":
    if "JAXIMU_TEST_XLA_CACHE_DIR" not in os.environ:
        os.environ["JAXIMU_TEST_XLA_CACHE_DIR"] = tempfile.mkdtemp(prefix="jaximu-tests-xla-")
        _CREATED.append(os.environ["JAXIMU_TEST_XLA_CACHE_DIR"])
    jax.config.update("jax_compilation_cache_dir", os.environ["JAXIMU_TEST_XLA_CACHE_DIR"])
    jax.config.update("jax_compilation_cache_max_size", 1 << 40)  # the lock, not a limit
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    _CREATED.append(tempfile.mkdtemp(prefix="jaximu-tests-cli-xla-"))
    os.environ["JAXIMU_CACHE_DIR"] = _CREATED[-1]
else:
    os.environ["JAXIMU_CACHE_DIR"] = "off"


def pytest_unconfigure(config):
    for folder in _CREATED:
        shutil.rmtree(folder, ignore_errors=True)


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


def pytest_configure(config):
    config.addinivalue_line(
        "markers",
        "default_codegen: run in a child pytest with XLA's default code generation "
        "(not the suite's fast-compile flags), for checks of bitwise reproducibility",
    )


_CHILD_RESULTS = {}  # nodeid -> (passed, report) of the default_codegen child runs


def _run_children(item):
    """Run every ``default_codegen`` test of ``item``'s module in one child pytest (they share
    its module fixtures there, computed once) and record each one's outcome."""
    ids = [
        it.nodeid
        for it in item.session.items
        if it.module is item.module and it.get_closest_marker("default_codegen")
    ]
    env = dict(os.environ, JAXIMU_TEST_DEFAULT_CODEGEN="1")
    res = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-rA", "-n", "0", "-p", "no:cacheprovider", *ids],
        cwd=item.config.rootpath,
        env=env,
        capture_output=True,
        text=True,
        timeout=1200,
    )
    report = f"{res.stdout[-8000:]}\n{res.stderr[-2000:]}"
    passed = {
        ln.split(" ", 1)[1].strip() for ln in res.stdout.splitlines() if ln.startswith("PASSED ")
    }
    for i in ids:
        _CHILD_RESULTS[i] = (i in passed, report)


@pytest.hookimpl(tryfirst=True)
def pytest_pyfunc_call(pyfuncitem):
    """A ``default_codegen`` test runs again in a child pytest whose XLA flags are the
    caller's only (with the other marked tests of its module); its outcome there is this
    test's. (The parent's fixtures are still set up: the marked tests share module fixtures
    with unmarked ones.)"""
    if _DEFAULT_CODEGEN or pyfuncitem.get_closest_marker("default_codegen") is None:
        return None
    if pyfuncitem.nodeid not in _CHILD_RESULTS:
        _run_children(pyfuncitem)
    passed, report = _CHILD_RESULTS[pyfuncitem.nodeid]
    if not passed:
        pytest.fail(
            f"in a child pytest with XLA's default code generation:\n{report}", pytrace=False
        )
    return True
