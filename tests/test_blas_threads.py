"""`_blas_threads.one_blas_thread`: every loaded BLAS library on one thread inside, the
earlier limits back after (nested, and after an exception); worker threads inside the
main thread's limit see it, and their own use changes nothing. The truth is what
threadpoolctl reads back from the libraries themselves. `every_blas_thread`: every core
inside, from the main thread only."""

import threading

import numpy as np
import scipy.linalg  # noqa: F401  (SciPy's own OpenBLAS, loaded as thermojax loads it)
from threadpoolctl import threadpool_info, threadpool_limits

from thermojax._blas_threads import one_blas_thread


def _threads() -> list[int]:
    return [lib["num_threads"] for lib in threadpool_info() if lib["user_api"] == "blas"]


def test_one_thread_inside_and_the_limits_restored_after():
    with threadpool_limits(limits=2, user_api="blas"):
        assert _threads() and all(n == 2 for n in _threads())
        with one_blas_thread():
            assert all(n == 1 for n in _threads())
            with one_blas_thread():  # nested
                assert all(n == 1 for n in _threads())
            assert all(n == 1 for n in _threads())
            a = np.random.default_rng(0).standard_normal((200, 200))
            assert np.allclose(a @ np.linalg.inv(a), np.eye(200), atol=1e-8)
        assert all(n == 2 for n in _threads())


def test_workers_see_the_main_threads_limit_and_their_own_use_changes_nothing():
    seen = {}

    def worker(key):
        with one_blas_thread():
            seen[key] = _threads()

    with threadpool_limits(limits=2, user_api="blas"):
        t = threading.Thread(target=worker, args=("alone",))
        t.start()
        t.join(10)
        with one_blas_thread():
            t = threading.Thread(target=worker, args=("inside",))
            t.start()
            t.join(10)
        seen["after"] = _threads()
    assert seen["alone"] and all(n == 2 for n in seen["alone"])
    assert all(n == 1 for n in seen["inside"])
    assert all(n == 2 for n in seen["after"])


def test_an_exception_inside_still_restores():
    with threadpool_limits(limits=2, user_api="blas"):
        try:
            with one_blas_thread():
                raise ValueError("inside")
        except ValueError:
            pass
        assert all(n == 2 for n in _threads())


def test_every_core_inside_in_the_main_thread_and_no_change_from_a_worker():
    import os

    from thermojax._blas_threads import every_blas_thread

    seen = {}

    def worker():
        with every_blas_thread():
            seen["worker"] = _threads()

    with one_blas_thread():
        with every_blas_thread():
            assert all(n == os.cpu_count() for n in _threads())
        assert all(n == 1 for n in _threads())          # the one thread back after
        t = threading.Thread(target=worker)
        t.start()
        t.join(10)
    assert seen["worker"] and all(n == 1 for n in seen["worker"])
