"""The generated C on a Cortex-M4: compiler flags and a static count of the step.

`count_step_instructions` reads the disassembly (`arm-none-eabi-objdump -d`) of an object
compiled with `M4_FLAGS` and counts the instructions of `prefix_step`: every
instruction of the function once, so the count of the straight-line path through it,
plus its branches' alternatives (the channel supervision's few branches). Standard
library only; used by the tests and `benchmarks/observer_arm.py`.
"""

from __future__ import annotations

import re
import subprocess

#: Cortex-M4 with the single-precision FPU, hard-float calling convention, Thumb-2.
M4_FLAGS = ("-mcpu=cortex-m4", "-mthumb", "-mfloat-abi=hard", "-mfpu=fpv4-sp-d16")
OBJDUMP = "arm-none-eabi-objdump"

_LINE = re.compile(r"^\s+[0-9a-f]+:\s+(?:[0-9a-f]{4}\s?){1,2}\s+(\S+)")


def count_step_instructions(obj, prefix: str, objdump: str = OBJDUMP) -> dict:
    """`{"instructions", "fpu", "loads_stores", "branches", "calls", "soft_float_calls",
    "bytes"}` of the function `prefix_step` in the object file `obj` (`calls`: to
    functions of the generated C, or to the compiler's soft-float routines, counted in
    `soft_float_calls`)."""
    text = subprocess.run([objdump, "-d", "--no-show-raw-insn", str(obj)], check=True,
                          capture_output=True, text=True).stdout
    body, inside = [], False
    for line in text.splitlines():
        if line.endswith(f"<{prefix}_step>:"):
            inside = True
            continue
        if inside and re.match(r"^[0-9a-f]+ <", line):
            break
        if inside:
            m = re.match(r"^\s+([0-9a-f]+):\s+(\S+)(.*)", line)
            if m:
                body.append((int(m.group(1), 16), m.group(2), m.group(3)))
    if not body:
        raise ValueError(f"no function {prefix}_step in {obj}.")
    ops = [op.split(".")[0] for _, op, _ in body]
    called = [args for _, op, args in body if op in ("bl", "blx")]
    return {"instructions": len(ops),
            "fpu": sum(op.startswith("v") for op in ops),
            "loads_stores": sum(op.startswith(("ldr", "str", "ldm", "stm", "vldr", "vstr",
                                               "vldm", "vstm", "push", "pop", "vpush",
                                               "vpop")) for op in ops),
            "branches": sum(op.startswith(("b", "cb")) and op not in ("bl", "blx", "bic",
                                                                       "bics", "bfi", "bfc")
                            for op in ops),
            "calls": len(called),
            "soft_float_calls": sum("__aeabi_" in a and any(k in a for k in ("dadd", "dmul",
                                    "dsub", "ddiv", "fadd", "fmul", "fsub", "fdiv", "dcmp",
                                    "fcmp", "f2d", "d2f")) for a in called),
            "bytes": body[-1][0] - body[0][0] + 2}
