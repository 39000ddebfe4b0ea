"""Test configuration: float64, strict promotion, shared fixtures."""

import os
import tempfile

import jax
import pytest

# Commands run in-process enable the persistent compilation cache: keep the suite's
# entries out of the user's cache folder, in one folder per test run that the xdist
# workers share (a program one worker compiled, the other loads; writes are atomic).
_RUN = os.environ.get("PYTEST_XDIST_TESTRUNUID")
os.environ.setdefault("THERMOJAX_CACHE_DIR", os.path.join(
    tempfile.gettempdir(), f"thermojax-test-cache-{_RUN}") if _RUN else
    tempfile.mkdtemp(prefix="thermojax-test-cache-"))

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


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
