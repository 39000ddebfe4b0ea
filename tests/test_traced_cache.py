"""The traced-program store (`compilation._traced_cache.stored_jit`): the same answers as
NumPy with and without a cache folder, one trace per program and process, entries read
back by a fresh process without tracing, and a new entry for any change of what the
trace depends on."""

from __future__ import annotations

import subprocess
import sys
import textwrap
import threading

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from thermojax.compilation import _traced_cache
from thermojax.compilation._traced_cache import forget_programs, stored_jit

TRACES = {"n": 0}


class Chain(eqx.Module):
    """A symmetric tridiagonal matrix: static size and scale, array couplings."""

    size: int = eqx.field(static=True)
    scale: float = eqx.field(static=True)
    couplings: jax.Array  # (size - 1,)


def _matrix(chain, xp):
    c = chain.couplings
    off = xp.diag(c, 1) + xp.diag(c, -1)
    diag = -(xp.concatenate([c, xp.zeros(1)]) + xp.concatenate([xp.zeros(1), c]))
    return chain.scale * (off + xp.diag(diag))


@stored_jit
def spectrum_and_decay(chain: Chain, x0, steps):
    """Eigenvalues (LAPACK, a custom call) and `x0` decayed by `expm(A)` `steps` times
    (a while loop of traced length)."""
    TRACES["n"] += 1
    A = _matrix(chain, jnp)
    mu, V = jnp.linalg.eigh(A)
    step = V @ jnp.diag(jnp.exp(mu)) @ V.T

    def body(c):
        k, x = c
        return k + 1, step @ x

    return {"eigenvalues": mu, "x": jax.lax.while_loop(lambda c: c[0] < steps, body,
                                                       (0, x0))[1]}


def _numpy_truth(chain, x0, steps):
    A = _matrix(chain, np)
    mu, V = np.linalg.eigh(np.asarray(A))
    x = np.asarray(x0)
    for _ in range(steps):
        x = V @ (np.exp(mu) * (V.T @ x))
    return mu, x


@pytest.fixture
def cache_folder(tmp_path):
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    forget_programs()
    TRACES["n"] = 0
    yield tmp_path / "traced"
    jax.config.update("jax_compilation_cache_dir", before)
    forget_programs()


def _chain(scale=0.3, size=5):
    return Chain(size, scale, jnp.linspace(0.5, 1.5, size - 1))


def _check(out, chain, x0, steps):
    mu, x = _numpy_truth(chain, x0, steps)
    np.testing.assert_allclose(out["eigenvalues"], mu, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(out["x"], x, rtol=1e-10, atol=1e-14)


def test_stored_and_read_back_in_process_match_numpy(cache_folder):
    chain, x0 = _chain(), jnp.arange(5.0)
    first = spectrum_and_decay(chain, x0, jnp.asarray(3))
    _check(first, chain, x0, 3)
    assert len(list(cache_folder.iterdir())) == 1 and TRACES["n"] == 1
    again = spectrum_and_decay(chain, x0 + 1.0, jnp.asarray(4))  # same shapes: no trace
    _check(again, chain, x0 + 1.0, 4)
    assert TRACES["n"] == 1
    forget_programs()  # as a new process would: read from the folder, not traced
    loaded = spectrum_and_decay(chain, x0, jnp.asarray(3))
    assert TRACES["n"] == 1
    for k in first:  # the same program: the same bits
        np.testing.assert_array_equal(loaded[k], first[k])


@pytest.fixture
def no_cache_folder():
    before = jax.config.jax_compilation_cache_dir
    jax.config.update("jax_compilation_cache_dir", None)
    forget_programs()
    TRACES["n"] = 0
    yield
    jax.config.update("jax_compilation_cache_dir", before)
    forget_programs()


def test_without_a_folder_compiled_once_and_nothing_written(no_cache_folder):
    chain, x0 = _chain(), jnp.arange(5.0)
    for steps in (2, 5):
        _check(spectrum_and_decay(chain, x0, jnp.asarray(steps)), chain, x0, steps)
    assert TRACES["n"] == 1


spectrum_and_decay_once = stored_jit(once=True)(spectrum_and_decay.__wrapped__)


@pytest.mark.parametrize("folder", [False, True])
def test_a_program_run_once_is_compiled_unoptimized_with_the_same_answers(
        folder, no_cache_folder, tmp_path, monkeypatch):
    """`once=True` passes XLA's option without LLVM's optimizations to the compilation,
    traced or read from the folder, and gives NumPy's answers."""
    if folder:
        jax.config.update("jax_compilation_cache_dir", str(tmp_path))
    options = []
    compile_ = jax.stages.Lowered.compile

    def recorded(self, compiler_options=None, **kw):
        options.append(compiler_options)
        return compile_(self, compiler_options, **kw)

    monkeypatch.setattr(jax.stages.Lowered, "compile", recorded)
    chain, x0 = _chain(), jnp.arange(5.0)
    for k in range(1 + folder):  # with a folder: stored, then read back
        forget_programs()
        _check(spectrum_and_decay_once(chain, x0, jnp.asarray(3)), chain, x0, 3)
        _check(spectrum_and_decay(chain, x0, jnp.asarray(3)), chain, x0, 3)
    assert options == [{"xla_backend_optimization_level": 0}, None] * (1 + folder)


def test_any_change_the_trace_depends_on_is_a_new_entry(cache_folder, monkeypatch):
    x0 = jnp.arange(5.0)
    spectrum_and_decay(_chain(0.3), x0, jnp.asarray(2))
    # a static float one ulp away, another static size, another dtype of an array
    for chain, x, steps in [(_chain(float(np.nextafter(0.3, 1.0))), x0, jnp.asarray(2)),
                            (_chain(0.3, 6), jnp.arange(6.0), jnp.asarray(2)),
                            (_chain(0.3), x0, jnp.asarray(2, dtype=jnp.int32))]:
        _check(spectrum_and_decay(chain, x, steps), chain, x, 2)
    assert len(list(cache_folder.iterdir())) == 4 and TRACES["n"] == 4
    # static values that compare equal but are not the same (1.0 == 1 == True)
    for scale in (1.0, 1):
        _check(spectrum_and_decay(_chain(scale), x0, jnp.asarray(2)), _chain(scale), x0, 2)
    assert len(list(cache_folder.iterdir())) == 6 and TRACES["n"] == 6
    monkeypatch.setattr(_traced_cache, "_source_digest", lambda: "another version")
    spectrum_and_decay(_chain(0.3), x0, jnp.asarray(2))
    assert len(list(cache_folder.iterdir())) == 7 and TRACES["n"] == 7


def test_a_corrupt_entry_is_traced_again(cache_folder):
    chain, x0 = _chain(), jnp.arange(5.0)
    spectrum_and_decay(chain, x0, jnp.asarray(2))
    (entry,) = cache_folder.iterdir()
    entry.write_bytes(b"not a program")
    forget_programs()
    with pytest.warns(RuntimeWarning, match="compile-cache entry .* damaged"):  # issue 67
        _check(spectrum_and_decay(chain, x0, jnp.asarray(2)), chain, x0, 2)
    assert TRACES["n"] == 2 and entry.read_bytes() != b"not a program"


class WithFunction(eqx.Module):
    f: object = eqx.field(static=True)
    x: jax.Array


@stored_jit
def apply(m: WithFunction):
    return m.f(m.x)


def test_arguments_the_key_cannot_describe_are_not_stored(cache_folder):
    x = jnp.arange(3.0)
    np.testing.assert_array_equal(apply(WithFunction(lambda v: 2 * v, x)), 2 * np.arange(3.0))
    np.testing.assert_array_equal(apply(WithFunction(jnp.cos, x)), np.cos(np.arange(3.0)))
    assert not cache_folder.exists()  # a lambda, then a jitted function: neither described
    # inside another trace (here a derivative): the plain equinox program
    c0 = np.linspace(0.5, 1.5, 4)
    d = jax.jacfwd(lambda c: spectrum_and_decay(Chain(5, 0.3, c), jnp.ones(5),
                                                jnp.asarray(1))["eigenvalues"])(jnp.asarray(c0))
    h, e = 1e-6, np.eye(4)
    fd = np.stack([(_numpy_truth(Chain(5, 0.3, c0 + h * e[i]), np.ones(5), 0)[0]
                    - _numpy_truth(Chain(5, 0.3, c0 - h * e[i]), np.ones(5), 0)[0]) / (2 * h)
                   for i in range(4)], axis=1)
    np.testing.assert_allclose(d, fd, atol=1e-7)


def test_threads_share_one_trace(cache_folder):
    chain, x0 = _chain(), jnp.arange(5.0)
    out = [None] * 4

    def run(i):
        out[i] = spectrum_and_decay(chain, x0, jnp.asarray(3))

    threads = [threading.Thread(target=run, args=(i,)) for i in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert TRACES["n"] == 1
    for o in out:
        _check(o, chain, x0, 3)


def test_compiled_ahead_on_a_thread_the_call_neither_traces_nor_compiles_again(
        no_cache_folder):
    chain, x0 = _chain(), jnp.arange(5.0)
    ahead = threading.Thread(target=spectrum_and_decay.ahead,
                             args=(chain, x0 * 0.0, jnp.asarray(0)))
    ahead.start()
    ahead.join()
    assert TRACES["n"] == 1  # traced and compiled, not run: nothing to check yet
    events = []

    def listen(name, *_args, **_kwargs):
        events.append(name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        _check(spectrum_and_decay(chain, x0, jnp.asarray(3)), chain, x0, 3)
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
    assert TRACES["n"] == 1
    assert not [e for e in events if "compil" in e]


MODULE = """
import jax, jax.numpy as jnp, numpy as np
jax.config.update("jax_enable_x64", True)
from thermojax.compilation._traced_cache import stored_jit
TRACES = [0]

@stored_jit
def f(x):
    TRACES[0] += 1
    return jnp.linalg.eigh(x @ x.T)[0]

jax.config.update("jax_compilation_cache_dir", {folder!r})
out = np.asarray(f(jnp.arange(9.0).reshape(3, 3) / 7))
print(TRACES[0], repr(out.tobytes().hex()))
"""


@pytest.mark.slow
def test_a_fresh_process_reads_the_program_without_tracing(tmp_path):
    script = tmp_path / "stored_program_check.py"
    script.write_text(textwrap.dedent(MODULE.format(folder=str(tmp_path / "cache"))))
    runs = [subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                           check=True, cwd=tmp_path).stdout.split() for _ in range(2)]
    assert [r[0] for r in runs] == ["1", "0"]  # traced, then read back
    assert runs[0][1] == runs[1][1]  # bit for bit
    x = np.arange(9.0).reshape(3, 3) / 7
    np.testing.assert_allclose(np.frombuffer(bytes.fromhex(eval(runs[0][1])), float),
                               np.linalg.eigvalsh(x @ x.T), rtol=1e-12, atol=1e-14)
