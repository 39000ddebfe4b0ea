"""Re-executes a benchmark script in the process its timings assume: one OpenBLAS thread
(`--default-blas-threads` keeps the environment's) and no persistent compilation cache
(`THERMOJAX_CACHE_DIR` and `JAX_COMPILATION_CACHE_DIR` removed), so a first call is cold.
Import it before NumPy or JAX: `import _cold_process; _cold_process.reexec()`."""

import os
import sys

_ENV_DROP = ("THERMOJAX_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR")


def reexec() -> None:
    """Replace this process by the same command in that environment, unless it is."""
    blas = "--default-blas-threads" not in sys.argv
    if (blas and os.environ.get("OPENBLAS_NUM_THREADS") != "1") or any(
            k in os.environ for k in _ENV_DROP):
        env = {k: v for k, v in os.environ.items() if k not in _ENV_DROP}
        if blas:
            env["OPENBLAS_NUM_THREADS"] = "1"
        os.execve(sys.executable, [sys.executable, *sys.argv], env)
