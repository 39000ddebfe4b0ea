"""Chamber profiles: exact breakpoints, slopes, phases, PRBS, concatenation, registry."""

import math

import numpy as np
import pytest

from thermojax._errors import InputError
from thermojax.measurements._profiles import (
    BUILTIN_PROFILES,
    PHASE_KINDS,
    Phase,
    Profile,
    _lfsr_bits,
    _LFSR_TAPS,
    builtin_profile,
    calibration_schedule,
    concatenate,
    dwell,
    power_step,
    prbs_power,
    ramp,
    soak,
    step_shock,
    viscoelastic_dwell,
)

# Slopes are differences of exactly sampled values: float64 roundoff on ~100 °C only.
SLOPE_ATOL = 1e-9  # °C/s


def samples_in(profile, start, end):
    """Indices of the samples with start <= t <= end (exact phase boundaries)."""
    return np.flatnonzero((profile.ts >= start) & (profile.ts <= end))


def check_tiling(profile):
    """Phases start at 0, touch end to start, and end at the last sample."""
    assert profile.phases, "a profile has at least one phase"
    assert profile.phases[0].start_s == 0.0
    for a, b in zip(profile.phases[:-1], profile.phases[1:]):
        assert a.end_s == pytest.approx(b.start_s, abs=1e-9)
    assert profile.phases[-1].end_s == pytest.approx(profile.duration, abs=1e-9)
    assert all(p.kind in PHASE_KINDS for p in profile.phases)


def check_uniform(profile, dt):
    n = len(profile)
    np.testing.assert_array_equal(profile.ts, np.arange(n) * dt)  # built as k * dt
    assert profile.dt == dt
    assert profile.duration == (n - 1) * dt


# ---------------------------------------------------------------------------
# soak and Profile basics


def test_soak_is_constant():
    p = soak(-12.5, 100.0, dt=0.5)
    assert len(p) == 201  # 100 s / 0.5 s + 1
    check_uniform(p, 0.5)
    np.testing.assert_array_equal(p.temperature, np.full(201, -12.5))
    np.testing.assert_array_equal(p.power, np.zeros(201))
    assert p.phases == (Phase(0.0, 100.0, "dwell"),)
    assert p.ts.dtype == p.temperature.dtype == p.power.dtype == np.float64


def test_dwell_is_soak():
    assert dwell is soak


def test_soak_not_multiple_of_dt_is_held_to_next_sample():
    p = soak(20.0, 10.5, dt=1.0)
    assert p.duration == 11.0
    assert p.phases == (Phase(0.0, 11.0, "dwell"),)  # one merged plateau


def test_profile_arrays_are_read_only():
    p = soak(25.0, 10.0)
    with pytest.raises(ValueError):
        p.temperature[0] = 0.0


@pytest.mark.parametrize("bad", [0.0, -5.0, math.nan, math.inf])
def test_soak_rejects_bad_duration(bad):
    with pytest.raises(InputError, match="duration_s"):
        soak(25.0, bad)


@pytest.mark.parametrize("bad", [0.0, -1.0, math.nan])
def test_generators_reject_bad_dt(bad):
    with pytest.raises(InputError, match="dt"):
        soak(25.0, 10.0, dt=bad)


def test_profile_validates_its_arrays():
    ts = np.arange(5.0)
    with pytest.raises(InputError, match="start at 0"):
        Profile(ts + 1.0, np.zeros(5), np.zeros(5))
    with pytest.raises(InputError, match="uniformly"):
        Profile(np.array([0.0, 1.0, 3.0]), np.zeros(3), np.zeros(3))
    with pytest.raises(InputError, match="temperature"):
        Profile(ts, np.zeros(4), np.zeros(5))
    with pytest.raises(InputError, match="at least two"):
        Profile(np.zeros(1), np.zeros(1), np.zeros(1))
    with pytest.raises(InputError, match="kind"):
        Phase(0.0, 1.0, "soaking")
    with pytest.raises(InputError, match="end_s"):
        Phase(2.0, 1.0, "dwell")


# ---------------------------------------------------------------------------
# ramps


@pytest.mark.parametrize("rate", [1.0, 5.0, 10.0])
@pytest.mark.parametrize("dt", [1.0, 0.5, 0.1])
@pytest.mark.parametrize("start, end", [(25.0, 85.0), (85.0, -40.0)])
def test_ramp_slope_is_exact_and_lands_on_end(rate, dt, start, end):
    p = ramp(start, end, rate, dt=dt)
    seconds = abs(end - start) / rate * 60.0  # by hand: 60/rate s per °C
    assert p.duration == pytest.approx(seconds, abs=1e-9)
    assert len(p) == round(seconds / dt) + 1
    assert p.temperature[0] == start
    assert p.temperature[-1] == end  # the breakpoint is on the grid: sampled exactly
    slope = np.diff(p.temperature) / dt
    expected = math.copysign(rate / 60.0, end - start)
    np.testing.assert_allclose(slope, expected, rtol=0, atol=SLOPE_ATOL)
    kind = "heating_ramp" if end > start else "cooling_ramp"
    assert [ph.kind for ph in p.phases] == [kind]
    check_tiling(p)


def test_ramp_off_grid_keeps_rate_and_ends_on_next_sample():
    # 60 °C at 7 °C/min takes 3600/7 = 514.2857... s: not a multiple of dt = 1 s.
    p = ramp(25.0, 85.0, 7.0, dt=1.0)
    t_end = 60.0 / 7.0 * 60.0
    assert p.phases[0] == Phase(0.0, t_end, "heating_ramp")
    assert p.phases[1] == Phase(t_end, 515.0, "dwell")
    assert len(p) == 516
    k = np.arange(515)  # samples t = 0 .. 514 lie on the ramp
    np.testing.assert_allclose(p.temperature[:515], 25.0 + 7.0 / 60.0 * k, rtol=0, atol=1e-12)
    assert p.temperature[515] == 85.0  # first sample after the breakpoint: the plateau
    np.testing.assert_allclose(np.diff(p.temperature[:515]), 7.0 / 60.0, rtol=0, atol=SLOPE_ATOL)


def test_ramp_rejects_bad_arguments():
    with pytest.raises(InputError, match="rate_c_per_min"):
        ramp(25.0, 85.0, 0.0)
    with pytest.raises(InputError, match="rate_c_per_min"):
        ramp(25.0, 85.0, -5.0)
    with pytest.raises(InputError, match="no span"):
        ramp(25.0, 25.0, 5.0)
    with pytest.raises(InputError, match="start_c"):
        ramp("warm", 25.0, 5.0)


# ---------------------------------------------------------------------------
# steps and power


def test_step_shock_moves_over_one_sample():
    p = step_shock(25.0, 85.0, before_s=10.0, after_s=20.0, dt=1.0)
    assert p.duration == 30.0
    assert p.phases == (Phase(0.0, 10.0, "dwell"), Phase(10.0, 11.0, "step"),
                        Phase(11.0, 30.0, "dwell"))
    np.testing.assert_array_equal(p.temperature[:11], 25.0)  # t = 0 .. 10
    np.testing.assert_array_equal(p.temperature[11:], 85.0)  # t = 11 .. 30
    check_tiling(p)


def test_step_shock_cooling_and_zero_before():
    p = step_shock(85.0, -40.0, before_s=0.0, after_s=5.0, dt=0.5)
    assert p.temperature[0] == 85.0
    np.testing.assert_array_equal(p.temperature[1:], -40.0)
    assert [ph.kind for ph in p.phases] == ["step", "dwell"]
    with pytest.raises(InputError, match="after_s"):
        step_shock(25.0, 85.0, before_s=10.0, after_s=0.5, dt=1.0)


def test_viscoelastic_dwell_defaults_match_seed():
    p = viscoelastic_dwell()
    # +85 °C rapid step after 10 min at 25 °C, then a 3 h soak
    assert p.duration == 600.0 + 3 * 3600.0
    assert [ph.kind for ph in p.phases] == ["dwell", "step", "dwell"]
    assert p.phases[1].start_s == 600.0
    assert p.temperature[600] == 25.0 and p.temperature[601] == 85.0
    assert p.phases[2].duration == pytest.approx(3 * 3600.0 - 1.0)
    np.testing.assert_array_equal(p.temperature[601:], 85.0)


def test_power_step_energy_and_edges():
    p = power_step(2.5, before_s=100.0, on_s=300.0, after_s=200.0, temperature_c=40.0, dt=2.0)
    assert p.duration == 600.0
    assert p.phases == (Phase(0.0, 100.0, "dwell"), Phase(100.0, 400.0, "power_step"),
                        Phase(400.0, 600.0, "dwell"))
    t = p.ts
    np.testing.assert_array_equal(p.power, np.where((t >= 100.0) & (t < 400.0), 2.5, 0.0))
    # zero-order hold: sample k holds over [t_k, t_k + dt): energy = level * on_s exactly
    assert np.sum(p.power[:-1]) * p.dt == 2.5 * 300.0
    np.testing.assert_array_equal(p.temperature, 40.0)


# ---------------------------------------------------------------------------
# PRBS


def test_prbs_is_binary_deterministic_and_bit_aligned():
    a = prbs_power(3.0, bit_s=10.0, n_bits=63, seed=4, dt=1.0)
    b = prbs_power(3.0, bit_s=10.0, n_bits=63, seed=4, dt=1.0)
    c = prbs_power(3.0, bit_s=10.0, n_bits=63, seed=5, dt=1.0)
    np.testing.assert_array_equal(a.power, b.power)
    assert not np.array_equal(a.power, c.power)
    assert set(np.unique(a.power).tolist()) == {0.0, 3.0}
    assert a.duration == 630.0
    bits = a.power[:-1].reshape(63, 10)  # each bit holds for 10 samples
    assert np.all(bits == bits[:, :1])
    assert a.power[-1] == 0.0  # off after the sequence
    # a full period of a 6-bit m-sequence has 32 ones and 31 zeros
    assert np.count_nonzero(bits[:, 0]) == 32
    np.testing.assert_array_equal(a.temperature, 25.0)
    check_tiling(a)
    for ph in a.phases:  # phases follow the power level
        idx = samples_in(a, ph.start_s, ph.end_s - 0.5)
        assert np.all(a.power[idx] == (3.0 if ph.kind == "power_step" else 0.0))


@pytest.mark.parametrize("m", range(3, 15))
def test_lfsr_taps_give_maximal_sequences(m):
    period = 2**m - 1
    bits = _lfsr_bits(2 * period, seed=0, order=m)
    np.testing.assert_array_equal(bits[:period], bits[period:])
    assert np.count_nonzero(bits[:period]) == 2 ** (m - 1)  # m-sequence balance
    if m <= 10:
        # two-valued periodic autocorrelation of an m-sequence: -1 at every nonzero lag
        s = 1 - 2 * bits[:period].astype(np.int64)
        spectrum = np.fft.fft(s)
        acf = np.round(np.fft.ifft(spectrum * np.conj(spectrum)).real).astype(np.int64)
        assert acf[0] == period
        np.testing.assert_array_equal(acf[1:], -1)


def test_lfsr_table_covers_all_orders():
    assert sorted(_LFSR_TAPS) == list(range(3, 25))


def test_prbs_rejects_bad_arguments():
    with pytest.raises(InputError, match="n_bits"):
        prbs_power(1.0, 10.0, 0)
    with pytest.raises(InputError, match="n_bits"):
        prbs_power(1.0, 10.0, 2.5)
    with pytest.raises(InputError, match="seed"):
        prbs_power(1.0, 10.0, 15, seed=-1)
    with pytest.raises(InputError, match="bit_s"):
        prbs_power(1.0, 0.0, 15)


# ---------------------------------------------------------------------------
# concatenate


def test_concatenate_chains_without_duplicating_the_joint():
    a = soak(25.0, 10.0)
    b = ramp(25.0, 30.0, 60.0)  # 1 °C/s for 5 s
    c = soak(30.0, 5.0)
    p = concatenate(a, b, c)
    assert len(p) == len(a) + len(b) + len(c) - 2
    check_uniform(p, 1.0)
    expected = np.concatenate([np.full(11, 25.0), 26.0 + np.arange(5), np.full(5, 30.0)])
    np.testing.assert_array_equal(p.temperature, expected)
    assert p.phases == (Phase(0.0, 10.0, "dwell"), Phase(10.0, 15.0, "heating_ramp"),
                        Phase(15.0, 20.0, "dwell"))
    check_tiling(p)


def test_concatenate_power_at_joint_comes_from_later_profile():
    a = soak(25.0, 4.0)
    b = prbs_power(2.0, bit_s=1.0, n_bits=7, seed=0)
    p = concatenate(a, b)
    assert p.power[4] == b.power[0]  # the joint holds over the later profile's first bit
    np.testing.assert_array_equal(p.power[4:], b.power)
    np.testing.assert_array_equal(p.power[:4], 0.0)


def test_concatenate_single_profile_and_empty():
    a = soak(25.0, 4.0)
    p = concatenate(a)
    np.testing.assert_array_equal(p.temperature, a.temperature)
    with pytest.raises(InputError, match="at least one"):
        concatenate()


def test_concatenate_rejects_mismatched_dt_and_broken_chain():
    with pytest.raises(ValueError, match="dt"):
        concatenate(soak(25.0, 10.0, dt=1.0), soak(25.0, 10.0, dt=0.5))
    with pytest.raises(InputError, match="must chain"):
        concatenate(soak(25.0, 10.0), soak(85.0, 10.0))


# ---------------------------------------------------------------------------
# calibration schedule


def check_ramp_phases(profile, allowed_rates):
    """Every ramp phase moves at one of the allowed rates, exactly between its samples."""
    rates = []
    for ph in profile.phases:
        if ph.kind not in ("heating_ramp", "cooling_ramp"):
            continue
        idx = samples_in(profile, ph.start_s, ph.end_s)
        temps = profile.temperature[idx]
        rate = abs(temps[-1] - temps[0]) / (profile.ts[idx[-1]] - profile.ts[idx[0]]) * 60.0
        assert min(abs(rate - r) for r in allowed_rates) < 1e-9
        sign = 1.0 if ph.kind == "heating_ramp" else -1.0
        np.testing.assert_allclose(np.diff(temps) / profile.dt, sign * rate / 60.0, rtol=0,
                                   atol=SLOPE_ATOL)
        rates.append(round(rate, 6))
    return rates


def test_calibration_schedule_covers_range_and_rates():
    p = calibration_schedule()
    check_uniform(p, 1.0)
    check_tiling(p)
    assert p.temperature.min() == -40.0 and p.temperature.max() == 85.0
    assert p.temperature[0] == 25.0
    # soak 25 °C, ramp to -40 at 1 °C/min, then per rate: up, dwell, down, dwell
    kinds = [ph.kind for ph in p.phases]
    assert kinds == ["dwell", "cooling_ramp", "dwell"] + \
        ["heating_ramp", "dwell", "cooling_ramp", "dwell"] * 3
    rates = check_ramp_phases(p, (1.0, 5.0, 10.0))
    assert rates == [1.0, 1.0, 1.0, 5.0, 5.0, 10.0, 10.0]
    for ph in p.phases:
        if ph.kind == "dwell":
            assert ph.duration == 1800.0
            temps = p.temperature[samples_in(p, ph.start_s, ph.end_s)]
            np.testing.assert_array_equal(temps, temps[0])
    # total by hand: 8 dwells of 30 min, 65 min to reach -40, 125 °C up and down per rate
    expected = 8 * 1800.0 + 65 * 60.0 + 2 * 125 * 60.0 * (1 / 1 + 1 / 5 + 1 / 10)
    assert p.duration == pytest.approx(expected, abs=1e-9)


def test_calibration_schedule_custom_and_half_second():
    p = calibration_schedule(dt=0.5, low_c=-10.0, high_c=50.0, rates_c_per_min=(3.0,),
                             dwell_s=60.0, start_c=20.0, soak_s=0.0)
    check_uniform(p, 0.5)
    check_tiling(p)
    assert p.phases[0].kind == "cooling_ramp"  # no soak
    assert p.temperature.min() == -10.0 and p.temperature.max() == 50.0
    assert check_ramp_phases(p, (3.0,)) == [3.0, 3.0, 3.0]


def test_calibration_schedule_end_c_moves_only_the_last_ramp():
    """`end_c`: the last ramp goes there (the Monte Carlo and headline cycle: down, up,
    back to the start); every earlier knot is unchanged."""
    kw = dict(low_c=0.0, high_c=40.0, rates_c_per_min=(5.0, 10.0), dwell_s=60.0, soak_s=60.0)
    p, q = calibration_schedule(**kw), calibration_schedule(**kw, end_c=25.0)
    check_uniform(q, 1.0)
    check_tiling(q)
    assert [ph.kind for ph in q.phases] == [ph.kind for ph in p.phases]
    assert check_ramp_phases(q, (5.0, 10.0)) == [5.0, 5.0, 5.0, 10.0, 10.0]
    last = q.phases[-2]  # the last ramp: 40 -> 25 °C at 10 °C/min, 90 s
    assert last.kind == "cooling_ramp" and last.duration == 90.0
    n = samples_in(q, 0.0, last.start_s)
    np.testing.assert_array_equal(q.temperature[n], p.temperature[n])
    assert q.temperature[-1] == 25.0 and p.temperature[-1] == 0.0
    with pytest.raises(InputError, match="end_c"):
        calibration_schedule(end_c=120.0)


@pytest.mark.parametrize("kwargs, field", [
    ({"low_c": -60.0}, "low_c"),
    ({"high_c": 110.0}, "high_c"),
    ({"start_c": 120.0}, "start_c"),
    ({"low_c": 50.0, "high_c": 40.0}, "high_c"),
    ({"rates_c_per_min": ()}, "rates_c_per_min"),
    ({"rates_c_per_min": (1.0, -5.0)}, "rates_c_per_min"),
    ({"dwell_s": -1.0}, "dwell_s"),
])
def test_calibration_schedule_validates(kwargs, field):
    with pytest.raises(InputError, match=field) as info:
        calibration_schedule(**kwargs)
    assert info.value.field == field


def test_calibration_schedule_accepts_chamber_limits():
    p = calibration_schedule(low_c=-55.0, high_c=105.0, rates_c_per_min=(15.0,), dwell_s=60.0)
    assert p.temperature.min() == -55.0 and p.temperature.max() == 105.0


# ---------------------------------------------------------------------------
# registry


def test_builtin_names():
    assert set(BUILTIN_PROFILES) == {"calibration", "ramp1", "ramp5", "ramp10", "shock",
                                     "viscoelastic_dwell", "power_step", "prbs", "eol_step",
                                     "eol_sweep"}


def test_the_end_of_line_sweep_is_two_tones_of_whole_cycles():
    p = BUILTIN_PROFILES["eol_sweep"]()
    k = np.arange(600)
    assert np.allclose(p.power[:600], 0.5 * (1 - np.cos(2 * np.pi * k / 300)), atol=1e-15)
    k = np.arange(300)
    assert np.allclose(p.power[600:900], 0.5 * (1 - np.cos(2 * np.pi * k / 30)), atol=1e-15)
    assert p.power[900] == 0 and p.ts[-1] == 900 and np.all(p.temperature == 25.0)
    assert [ph.kind for ph in p.phases] == ["power_sweep"]
    step = BUILTIN_PROFILES["eol_step"]()
    assert step.ts[-1] == 960 and np.all(step.power[60:660] == 1) and step.power[660] == 0


@pytest.mark.parametrize("name", sorted(BUILTIN_PROFILES))
def test_builtins_are_valid(name):
    p = builtin_profile(name)
    assert isinstance(p, Profile)
    check_uniform(p, 1.0)
    check_tiling(p)
    for ph in p.phases:
        if ph.kind == "dwell":  # a plateau: no temperature change inside
            temps = p.temperature[samples_in(p, ph.start_s, ph.end_s)]
            np.testing.assert_array_equal(temps, temps[0])


@pytest.mark.parametrize("rate", [1, 5, 10])
def test_builtin_ramp_cycles(rate):
    p = builtin_profile(f"ramp{rate}")
    ramp_s = 60.0 / rate * 60.0  # 60 °C at `rate` °C/min
    edges = np.cumsum([0.0, 600.0, ramp_s, 1800.0, ramp_s, 1800.0])
    assert [(ph.start_s, ph.end_s) for ph in p.phases] == list(zip(edges[:-1], edges[1:]))
    assert [ph.kind for ph in p.phases] == ["dwell", "heating_ramp", "dwell", "cooling_ramp",
                                            "dwell"]
    assert p.temperature[int(edges[2])] == 85.0 and p.temperature[-1] == 25.0
    assert check_ramp_phases(p, (float(rate),)) == [rate, rate]


def test_builtin_profile_dt_and_unknown_name():
    p = builtin_profile("shock", dt=0.5)
    assert p.dt == 0.5 and p.duration == 4200.0
    with pytest.raises(InputError, match="unknown profile 'ramp2'.*calibration.*ramp10"):
        builtin_profile("ramp2")
