"""Test configuration: float64, strict promotion, shared fixtures."""

import os
import shutil
import tempfile

# The suite compiles thousands of programs and runs most of them for milliseconds: with
# XLA's cheapest backend optimization they compile about 40 % faster (a Kalman fit's
# first evaluation 50 -> 30 s; four test files 242 -> 204 s on 2 cores). No fast-math
# is involved and every check keeps its tolerance. Set before JAX starts its backend;
# the commands and notebook kernels the tests start inherit it.
# `THERMOJAX_TEST_XLA_FLAGS=""` tests under XLA's default compilation instead.
_FAST_COMPILE = os.environ.get(
    "THERMOJAX_TEST_XLA_FLAGS",
    "--xla_backend_optimization_level=0 --xla_llvm_disable_expensive_passes=true")
if _FAST_COMPILE not in os.environ.get("XLA_FLAGS", ""):  # once, also in xdist workers
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FAST_COMPILE}".strip()

import jax  # noqa: E402
import pytest

# Commands run in-process enable the persistent compilation cache: keep the suite's
# entries out of the user's cache folder, in one folder per test run that the xdist
# workers share (a program one worker compiled, the other loads; writes are atomic).
# The process that starts the run makes it (the workers inherit its environment) and
# removes it at the end (`pytest_unconfigure`): a run leaves about 80 MB.
_OWN_CACHE = None
if "THERMOJAX_CACHE_DIR" not in os.environ:
    _OWN_CACHE = os.environ["THERMOJAX_CACHE_DIR"] = tempfile.mkdtemp(
        prefix="thermojax-test-cache-")

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


def pytest_unconfigure(config):
    """Remove the run's compilation cache once every worker is done."""
    if _OWN_CACHE is not None:
        shutil.rmtree(_OWN_CACHE, ignore_errors=True)


@pytest.fixture
def getkey():
    """A fresh PRNG key per call, deterministic per test."""
    keys = iter(jax.random.split(jax.random.PRNGKey(0), 10_000))
    return lambda: next(keys)


@pytest.fixture(autouse=True)
def _release_compiled_programs():
    """Drop compiled programs when the process holds too many memory mappings: the
    suite compiles thousands of programs (every candidate structure of the hidden-effect
    suite) and nearing the kernel's `vm.max_map_count` crashes inside LLVM."""
    yield
    from thermojax._memory import release_compiled_if_crowded

    release_compiled_if_crowded()
