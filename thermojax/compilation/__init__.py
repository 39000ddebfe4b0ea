"""Compiled programs kept across runs: JAX's persistent cache of compiled XLA programs
(`_cache`), and the traced programs it cannot skip (`_traced_cache.stored_jit`)."""

from ._cache import enable_compilation_cache

__all__ = ["enable_compilation_cache"]
