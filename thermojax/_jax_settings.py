"""JAX settings every stage needs, applied when a stage is first imported.

- float64 (`jax_enable_x64`): stiff thermal networks need it.
- XLA's CPU fusion emitters off: `--xla_cpu_use_fusion_emitters=false` is added to
  `XLA_FLAGS` unless `XLA_FLAGS` already names that option (set it to `true` there to
  keep XLA's default). thermojax compiles a few programs for every model structure it
  fits, and on a CPU these emitters take about half of each compilation: the six-node
  IMU's Kalman scoring program compiles in 2.4-3.3 s instead of 4.5-5.4 s and runs as
  fast (58-69 ms a call either way; benchmarks/README.md). XLA reads
  `XLA_FLAGS` when JAX starts its backend, so this applies when thermojax is imported
  before the first computation; otherwise XLA's default stays. Other backends ignore it.
"""

import os

_CPU_FUSION_EMITTERS = "--xla_cpu_use_fusion_emitters"
if _CPU_FUSION_EMITTERS not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = (f"{os.environ.get('XLA_FLAGS', '')} "
                               f"{_CPU_FUSION_EMITTERS}=false").strip()

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)
