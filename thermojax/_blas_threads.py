"""One BLAS thread while thermojax runs work side by side.

XLA's CPU thread pool already spreads each compiled program over the cores, and fits
run on threads of their own (`fitting._side_by_side`). NumPy's and SciPy's OpenBLAS
keep pools of their own, whose threads spin while they wait for work: with both
pools busy, a NumPy vector norm of 37,800 samples took 8 ms instead of some
microseconds, and the six-node IMU investigation (`benchmarks/investigate.py --imu6`)
took 2 s longer. Inside `one_blas_thread()` every BLAS library the process has loaded
runs on one thread (threadpoolctl).

OpenBLAS's pool is process-wide, and threadpoolctl lets only one thread set its size
(other threads' requests do nothing), so the limit is taken in the main thread; there
it nests. Entered on another thread, `one_blas_thread()` changes nothing: the loop's
fits run on worker threads inside the limit their main thread took.
"""

from __future__ import annotations

import contextlib
import os
import threading

from threadpoolctl import threadpool_limits


@contextlib.contextmanager
def one_blas_thread():
    """Every loaded BLAS library on one thread inside, the limits as they were after
    (taken in the main thread only; see the module docstring)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


@contextlib.contextmanager
def every_blas_thread():
    """Every core's BLAS thread inside, for one large NumPy product while nothing else
    runs (taken in the main thread only; elsewhere the limits stay as they are)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    with threadpool_limits(limits=os.cpu_count(), user_api="blas"):
        yield
