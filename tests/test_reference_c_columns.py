"""The generated C in the column layout (`generate_c(layout="columns")`, SIMD across rows
and across channels) against the NumPy float reference: bit for bit up to the sign of an
exact zero, compiled without vectorization (-O0, -O2 -fno-tree-vectorize) and vectorized
(-O3 -march=x86-64-v3, AVX2), over a long playback with fault injections, random fault
scenarios under several supervision settings, and counters run into saturation; the
branch-free channel rules against `ChannelMonitor` for every state and input."""

import itertools
import subprocess

import numpy as np
import pytest

from test_reference_bias_fixed import FAULTS as BIAS_FAULTS, artifact, faulted  # noqa: F401
from test_reference_c import FAULTS, faulted_playback
from test_reference_setup import IMU6_SCALING, gcc_build, gcc_run, playback

import thermojax.reference as ref

AVX2 = ("-O3", "-march=x86-64-v3")
FLAGS = [("-O0",), ("-O2", "-fno-tree-vectorize"), AVX2]


def cpu_has_x86_64_v3(folder) -> bool:
    """Whether this CPU runs `-march=x86-64-v3` code (AVX2, FMA, BMI2, ...): asked at run
    time through gcc's `__builtin_cpu_supports`."""
    probe = folder / "probe.c"
    probe.write_text('int main(void) { __builtin_cpu_init(); '
                     'return !__builtin_cpu_supports("x86-64-v3"); }\n')
    built = subprocess.run(["gcc", "-o", str(folder / "probe"), str(probe)], capture_output=True)
    return built.returncode == 0 and subprocess.run([str(folder / "probe")]).returncode == 0


def same_up_to_zero_sign(a, b) -> bool:
    """Bit for bit, except that `-0` equals `+0` (`v + 0` turns `-0` into `+0` and leaves
    every other value, NaN included, as it is)."""
    a, b = np.asarray(a) + 0, np.asarray(b) + 0
    bits = {4: np.uint32, 8: np.uint64}[a.dtype.itemsize]
    return a.dtype == b.dtype and np.array_equal(a.view(bits), b.view(bits))


def sparse(system):
    """imu6 with its small coefficients set to zero (Phi below 1e-8, B0 and B1 below 1e-9,
    gains below 1e-3) and the last state's gain row zero in every subset: columns with
    zeros in some rows, rows without gain terms."""
    cut = lambda a, t: np.where(np.abs(a) < t, 0.0, a)
    p = system.n_outputs
    gains = {}
    for mask in range(1, 1 << p):
        used = [j for j in range(p) if mask >> j & 1]
        L = cut(system.gain_table[mask][:, used], 1e-3)
        L[-1] = 0.0
        gains[tuple(used)] = L
    return ref.ObserverSystem.build(cut(system.Phi, 1e-8), cut(system.B0, 1e-9),
                                    cut(system.B1, 1e-9), system.C, system.D, gains)


SYSTEMS = {"imu6": lambda s: s, "sparse": sparse}


def nonfinite_playback():
    """`faulted_playback` plus measurements that are NaN or infinite while
    their channel is in use before and after (a channel not in use is skipped)."""
    system, u, y, x0, oc = faulted_playback()
    y[30000:30050, 1] = np.nan
    y[31000:31020, 0] = np.inf
    y[32000:32010, 2] = -np.inf
    return system, u, y, x0, oc


@pytest.mark.parametrize("system_kind", SYSTEMS)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("flags", FLAGS, ids=lambda f: "".join(f))
def test_columns_c_bit_exact(system_kind, dtype, flags, tmp_path):
    if flags == AVX2 and not cpu_has_x86_64_v3(tmp_path):
        pytest.skip("this CPU does not run -march=x86-64-v3 code (AVX2)")
    system, u, y, x0, oc = nonfinite_playback()
    system = SYSTEMS[system_kind](system)
    obs = ref.FloatObserver(system, FAULTS, dtype=dtype)
    want = obs.run(x0, u, y, oc)
    assert len(set(want.in_use.tolist())) >= 4 and want.wire_break.any()
    assert np.isnan(want.residuals).any()
    src = ref.generate_c(obs, "obs", layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y, oc)
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.residuals, want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_columns_exact_zeros(dtype, tmp_path):
    """Exact zeros of either sign through a two-state system with zeros inside its columns
    (`x0' = x1`, `x1' = u - x0 / 2`): the column sums add the zero products that the row
    sums skip, which changes the sign of some zero results, and nothing else: every value
    compares equal, the flags agree."""
    system = ref.ObserverSystem.build([[0.0, 1.0], [-0.5, 0.0]], [[0.0], [1.0]], [[0.0], [0.0]],
                                      [[1.0, 0.0]], [[0.0]], {(0,): [[0.5], [0.0]]})
    T = 400
    rng = np.random.default_rng(5)
    signed_zeros = lambda *shape: np.where(rng.random(shape) < 0.5, -0.0, 0.0)
    u, y, x0 = signed_zeros(T, 1), signed_zeros(T, 1), signed_zeros(2)
    oc = rng.random((T, 1)) < 0.1
    obs = ref.FloatObserver(system, ref.FaultConfig(recover_after=3), dtype=dtype)
    want = obs.run(x0, u, y, oc)
    assert len(set(want.in_use.tolist())) == 2
    src = ref.generate_c(obs, "obs", layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *FLAGS[1]), tmp_path, x0, u, y, oc)
    assert not want.states.any() and not got.states.any()
    assert (np.signbit(got.states) != np.signbit(want.states)).any()     # the edge is real
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.residuals, want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f))


def test_columns_c_16_byte_rows(tmp_path):
    """double rows padded to 16 bytes (SSE2, NEON: 6 lanes for 6 states), vectorized at -O2."""
    system, u, y, x0, oc = nonfinite_playback()
    obs = ref.FloatObserver(system, FAULTS)
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs", layout="columns", vector_bytes=16)
    assert "#define OBS_W 6 " in src.header
    got = gcc_run(src, gcc_build(src, tmp_path, "-O2"), tmp_path, x0, u, y, oc)
    assert same_up_to_zero_sign(got.states, want.states)
    assert np.array_equal(got.in_use, want.in_use)


def test_columns_source():
    """The column layout reads each nonzero column of [Phi B0 B1] and of every gain once
    (rows padded to 32 bytes); the supervision is the rows layout's, line for line; fixed
    point is rows only."""
    system, *_ = playback(10)
    for dtype, lanes in ((np.float32, 8), (np.float64, 4)):
        obs = ref.FloatObserver(system, FAULTS, dtype=dtype)
        src = ref.generate_c(obs, "obs", layout="columns")
        rows = ref.generate_c(obs, "obs")
        W = -(-system.n_states // lanes) * lanes
        K = int(np.any(np.hstack([system.Phi, system.B0, system.B1]) != 0, axis=0).sum() +
                sum(np.any(L != 0, axis=0).sum() for L in system.gain_table))
        assert f"#define OBS_W {W}" in src.header and f"obs_x[OBS_W]" in src.header
        assert f"OBS_COLS[{K}][OBS_W]" in src.source
        step = src.source[src.source.index("uint8_t obs_step("):]
        # the supervision: one branch-free loop over the channels (4 lanes for 3)
        assert "/* channel 0" in rows.source and "/* channel 0" not in step
        assert "for (i = 0; i < 4; i++) {" in step and "OBS_SUP_BITS[3][4]" in src.source
        assert "_good_run" not in src.source and "obs_sup_g[4]" in src.source
    fx = ref.FixedObserver(system, "q16.16", IMU6_SCALING["q16.16"])
    with pytest.raises(ValueError, match="layout"):
        ref.generate_c(fx, "obs", layout="columns")
    with pytest.raises(ValueError, match="layout"):
        ref.generate_c(obs, "obs", layout="diagonal")
    with pytest.raises(ValueError, match="vector_bytes"):
        ref.generate_c(obs, "obs", layout="columns", vector_bytes=12)
    with pytest.raises(ValueError, match="supervision"):
        ref.generate_c(fx, "obs", supervision="lanes")
    with pytest.raises(ValueError, match="supervision"):
        ref.generate_c(obs, "obs", supervision="vector")
    # either supervision in either layout: the branches are the rows layout's blocks
    branches = ref.generate_c(obs, "obs", layout="columns", supervision="branches")
    supervision = rows.source[rows.source.index("/* channel 0"):
                              rows.source.index("    switch (mask)")]
    assert supervision in branches.source and "OBS_SUP_" not in branches.source
    assert "OBS_SUP_BITS" in ref.generate_c(obs, "obs", supervision="lanes").source


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_columns_c_with_bias_channels(artifact, dtype, tmp_path):
    """With bias channels (evaluated in double from the corrected state), vectorized."""
    flags = AVX2 if cpu_has_x86_64_v3(tmp_path) else FLAGS[1]
    u, y, x0, oc = faulted(24_000)
    obs = ref.FloatObserver(artifact.system, BIAS_FAULTS, dtype=dtype,
                            biases=artifact.bias_evaluator())
    want = obs.run(x0, u, y, oc)
    src = ref.generate_c(obs, "obs", names=artifact.names, layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y, oc)
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.bias, want.bias)
    assert np.array_equal(got.in_use, want.in_use)


# -- the channel supervision of the columns layout ---------------------------------------

def test_channel_rules_equal_channel_monitor():
    """`channel_rules` (the branch-free rules the columns layout writes in C) against
    `ChannelMonitor.update` for every flag state and input and counters around N, M and
    the saturation, also with `railed` and `large` known false at generation time (no
    rails within the plausible range, no finite residual threshold: `bad` stays 0)."""
    from thermojax.reference._faults import COUNTER_MAX, ChannelMonitor, _Lane, _var, \
        channel_rules

    for N, M, gate in ((1, 1, False), (3, 2, False), (10, 20, False),
                       (COUNTER_MAX, COUNTER_MAX, False), (1, 1, True), (3, 2, True)):
        counts = sorted({0, 1, 2, N - 1, N, N + 1, M - 1, M, M + 1, COUNTER_MAX - 1,
                         COUNTER_MAX} - {-1, COUNTER_MAX + 1})
        for known_railed, known_large in itertools.product((False, True), repeat=2):
            v = {name: _var(name, flag=name not in ("good", "bad"))
                 for name in ("healthy", "wire_break", "good", "bad", "plausible", "railed",
                              "large", "started")}
            if known_railed:
                v["railed"] = _Lane.known(False)
            if known_large:
                v["large"], v["bad"] = _Lane.known(False), _Lane.known(0, False)
                v["wire_break"] = _Lane.known(False)
            steps = []
            bind = lambda name, e: (e if e.const is not None else
                                    (steps.append((name, e)), _var(name, flag=e.flag))[1])
            rules = channel_rules(v, N, M, bind, gate=gate)
            for h, w, pl, ra, lg, st, g, b in itertools.product(
                    (False, True), (False, True), (False, True), (False, True),
                    (False, True), (False, True) if gate else (True,), counts, counts):
                if (known_railed and ra) or (known_large and (lg or b or w)):
                    continue
                mon = ChannelMonitor(1, N, M, gate)
                mon.healthy, mon.wire_break, mon.good_run, mon.bad_run = [h], [w], [g], [b]
                mask = mon.update([pl], [pl and ra], [pl and lg], st)
                env = {"healthy": h, "wire_break": w, "good": g, "bad": b, "plausible": pl,
                       "railed": pl and ra, "large": pl and lg, "started": st}
                for name, e in steps:
                    env[name] = e.f(env)
                got = {k: e.f(env) for k, e in rules.items()}
                assert (bool(got["healthy"]), bool(got["wire_break"]), got["good"],
                        got["bad"], bool(got["in_use"])) == \
                    (mon.healthy[0], mon.wire_break[0], mon.good_run[0], mon.bad_run[0],
                     bool(mask)), (N, M, known_railed, known_large, h, w, pl, ra, lg, g, b)


SUPERVISION = {
    # rails inside the plausible range on channel 0 (both sides) and channel 2 (at the
    # lower limit exactly), residual thresholds on channels 0 and 2 only, short runs
    "rails+thresholds": ref.FaultConfig(rails=[(-40.0, 100.0), (-np.inf, np.inf),
                                               (-55.0, 1e9)],
                                        residual_threshold=[0.3, np.inf, 1.0],
                                        wire_break_after=3, recover_after=2),
    "thresholds,N=M=1": ref.FaultConfig(residual_threshold=0.2, wire_break_after=1,
                                        recover_after=1),
    "rails only": ref.FaultConfig(rails=(-20.0, 60.0), recover_after=1),
    # gated: a large residual is left out of the correction
    "thresholds, gated": ref.FaultConfig(rails=[(-40.0, 100.0), (-np.inf, np.inf),
                                                (-55.0, 1e9)],
                                         residual_threshold=[0.3, np.inf, 1.0],
                                         wire_break_after=3, recover_after=2, gate=True),
    "default": ref.FaultConfig(recover_after=5),
}


def random_faults(T=4000, seed=11):
    """A playback with random faults on every channel, often several at once: implausible
    values, NaN, ±inf, values at and beyond rails and at the plausible limits exactly,
    stuck readings (large residuals), open circuits; the open-circuit byte has bits above
    the channels set too (ignored)."""
    system, u, y, _, x0 = playback(T, seed=seed)
    rng = np.random.default_rng(seed)
    y = y.copy()
    specials = np.array([200.0, -100.0, np.nan, np.inf, -np.inf, -55.0, 125.0, -40.0, 100.0,
                         110.0, -50.0, -20.0, 60.0, 70.0, np.nextafter(125.0, 200.0)])
    k = 0
    while k < T:                        # bursts of one kind of fault on a random channel
        length, j, kind = rng.integers(1, 40), rng.integers(3), rng.integers(4)
        sl = slice(k, min(k + length, T))
        if kind == 0:
            y[sl, j] = rng.choice(specials, size=len(y[sl, j]))
        elif kind == 1:
            y[sl, j] = y[k, j] + rng.choice([-3.0, 2.0, 0.5])      # stuck, offset
        k += length + rng.integers(0, 60)
    oc = rng.random((T, 3)) < 0.02
    byte = (oc * np.array([1, 2, 4])).sum(1).astype(np.uint8) | \
        (rng.integers(0, 32, T).astype(np.uint8) << 3)
    return system, u, y, x0, oc, byte


@pytest.mark.parametrize("config", SUPERVISION)
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("flags", FLAGS, ids=lambda f: "".join(f))
def test_columns_supervision_random_faults(config, dtype, flags, tmp_path):
    """The lane-parallel supervision under random faults and four settings (rails within
    the limits or not, thresholds on some channels, all or none, N = M = 1): flags,
    states and residuals as the NumPy reference; flags the same with the branches
    (rows layout, columns layout) and with the lanes in the rows layout (bit for bit
    there)."""
    if flags == AVX2 and not cpu_has_x86_64_v3(tmp_path):
        pytest.skip("this CPU does not run -march=x86-64-v3 code (AVX2)")
    system, u, y, x0, oc, byte = random_faults()
    obs = ref.FloatObserver(system, SUPERVISION[config], dtype=dtype)
    want = obs.run(x0, u, y, oc)
    seen = {(h, w) for h, w in zip(want.healthy, want.wire_break)}
    assert len(seen) >= 4 and len(set(want.in_use.tolist())) >= 6
    src = ref.generate_c(obs, "obs", layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y, byte)
    assert same_up_to_zero_sign(got.states, want.states)
    assert same_up_to_zero_sign(got.residuals, want.residuals)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f)), f
    for layout, supervision in (("rows", "branches"), ("rows", "lanes"),
                                ("columns", "branches")):
        other = ref.generate_c(obs, "obs", layout=layout, supervision=supervision)
        folder = tmp_path / f"{layout}_{supervision}"
        folder.mkdir()
        by_other = gcc_run(other, gcc_build(other, folder, *flags), folder, x0, u, y, byte)
        for f in ("in_use", "healthy", "wire_break"):
            assert np.array_equal(getattr(by_other, f), getattr(got, f)), (layout, f)
        if layout == "rows":
            assert np.array_equal(by_other.states, want.states)


def test_columns_supervision_saturation(tmp_path):
    """Run counters into saturation (65,535): N = M = 65,535, a channel implausible at the
    first step and good for 70,000 steps after (it comes back at the 65,535th), one with
    a large residual on every step (wire break at the 65,535th, then held), vectorized."""
    flags = AVX2 if cpu_has_x86_64_v3(tmp_path) else FLAGS[1]
    T = 70_000
    system, u, y, _, x0 = playback(T, seed=3)
    y = y.copy()
    y[0, 0] = np.nan
    y[:, 2] = y[:, 2] + np.where(np.arange(T) % 2, 20.0, -20.0)     # residuals all large
    cfg = ref.FaultConfig(residual_threshold=[np.inf, np.inf, 0.5], wire_break_after=65535,
                          recover_after=65535)
    obs = ref.FloatObserver(system, cfg, dtype=np.float32)
    want = obs.run(x0, u, y)
    assert want.healthy[65534] & 1 == 0 and want.healthy[65535] & 1
    assert not want.wire_break[65533] and want.wire_break[65534] == 4
    src = ref.generate_c(obs, "obs", layout="columns")
    got = gcc_run(src, gcc_build(src, tmp_path, *flags), tmp_path, x0, u, y)
    assert same_up_to_zero_sign(got.states, want.states)
    for f in ("in_use", "healthy", "wire_break"):
        assert np.array_equal(getattr(got, f), getattr(want, f)), f
