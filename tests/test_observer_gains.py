"""Observer gains: the seed's pole rule, robust pole placement, the steady-state Kalman gain.

Truths: `scipy.signal.place_poles` and `control.place` on the dual problem, eigenvalues
of the closed loop, `scipy.linalg.solve_discrete_are`, `control.dlqe`, a time-varying
Kalman recursion iterated to convergence, Van Loan by quadrature (`np_van_loan`).
"""

import control
import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import thermojax as tj
from thermojax import observer as ob
from thermojax.model import ThermalModel

from helpers import CONFIGS, model_matrices, np_van_loan


def imu():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "imu6.toml"))
    return model, model.linear_system()


@pytest.mark.parametrize("dt", [0.1, 0.05, 0.02])
def test_seed_pole_rule_keeps_the_proof_mass(dt):
    _, system = imu()
    poles = ob.observer_poles(system, dt, speedup=4.0)
    lam = np.sort(np.linalg.eigvals(model_matrices(CONFIGS / "imu6.toml")["A"]).real)[::-1]
    np.testing.assert_allclose(poles.open_loop, lam, rtol=1e-10)  # eig vs eig: roundoff
    # the proof-mass mode (tau 0.094 s <= 5 dt at 10-50 Hz) keeps its pole; others 4x
    assert poles.kept == (False,) * 5 + (True,)
    np.testing.assert_allclose(poles.continuous[:5], 4 * lam[:5], rtol=1e-12)
    np.testing.assert_allclose(poles.continuous[5], lam[5], rtol=1e-12)
    np.testing.assert_allclose(poles.discrete, np.exp(poles.continuous * dt), rtol=1e-14)


def test_pole_rule_caps_and_spreads():
    _, system = imu()
    poles = ob.observer_poles(system, 0.05, speedup=5.0, min_time_constant=2.0)
    # time constants 301, 23, 8.0, 4.2, 2.65, 0.094 s: the last kept (< 2 s), those
    # with tau/5 < 2 s capped at 1/2 /s and spread 2 % apart
    assert poles.kept == (False,) * 5 + (True,)
    assert poles.capped == (False, False, True, True, True, False)
    capped = poles.continuous[np.array(poles.capped)]
    assert np.all(-capped <= 0.5 + 1e-12) and len(set(np.round(capped, 12))) == capped.size


@pytest.mark.parametrize("method", ["YT", "KNV0"])
def test_place_observer_gain_against_scipy_and_eigenvalues(method):
    model, system = imu()
    dt = 0.05
    d = tj.discretize(system, dt)
    poles = ob.observer_poles(system, dt)
    L = ob.place_observer_gain(d, poles, method=method)
    Phi, C = np.asarray(d.Phi), np.asarray(d.C)
    achieved = np.sort(np.linalg.eigvals(Phi - L @ C @ Phi).real)
    # placement accuracy on a stiff network (poles 0.59 ... 0.9993)
    np.testing.assert_allclose(achieved, np.sort(poles.discrete), rtol=1e-8)
    ref = scipy.signal.place_poles(Phi.T, (C @ Phi).T, poles.discrete, method=method)
    np.testing.assert_allclose(L, ref.gain_matrix.T, rtol=1e-9, atol=1e-14)
    # python-control places the same poles (its gain may differ: 3 outputs, not unique)
    K = control.place(Phi.T, (C @ Phi).T, poles.discrete)
    np.testing.assert_allclose(np.sort(np.linalg.eigvals(Phi - K.T @ C @ Phi).real),
                               np.sort(poles.discrete), rtol=1e-8)


def test_single_output_gain_is_unique_and_matches_control():
    model = ThermalModel.from_spec(tj.load_model(CONFIGS / "rtd2.toml"))
    system = model.linear_system()
    d = tj.discretize(system, 0.1)
    poles = ob.observer_poles(system, 0.1, speedup=3.0)
    L = ob.place_observer_gain(d, poles)
    Phi, C = np.asarray(d.Phi), np.asarray(d.C)
    K = control.place(Phi.T, (C @ Phi).T, poles.discrete)
    np.testing.assert_allclose(L, np.asarray(K).T, rtol=1e-8)  # unique gain for one output


def test_place_errors():
    model, system = imu()
    d = tj.discretize(system, 0.05)
    poles = ob.observer_poles(system, 0.05).discrete
    slow = poles.copy()
    slow[0] = 0.99999
    with pytest.raises(ValueError, match="slower than the plant's slowest mode"):
        ob.place_observer_gain(d, slow)
    with pytest.raises(ValueError, match="outside the unit circle"):
        ob.place_observer_gain(d, np.r_[poles[:5], 1.2])
    with pytest.raises(ValueError, match="needs 6 poles"):
        ob.place_observer_gain(d, poles[:4])
    with pytest.raises(ValueError, match=r"repeat at most 3 times"):
        ob.place_observer_gain(d, np.full(6, 0.9))
    with pytest.raises(ValueError, match="at least 1"):
        ob.observer_poles(system, 0.05, speedup=0.5)
    # an unobservable sensor set: two disconnected parts, sensor on one
    topo = tj.Topology(node_names=("a", "b", "c"), links=((0, 1),), boundary_nodes=(0, 2),
                       boundary_inputs=(0, 0), heat_nodes=(), heat_inputs=(),
                       input_names=("T_amb",), input_holds=("foh",), sensor_nodes=(0,),
                       sensor_names=("Ta",))
    net = tj.ThermalNetwork.from_physical(topo, [1.0, 2.0, 3.0], [0.5], [0.1, 0.2])
    dd = tj.discretize(net.linear_system(), 0.5)
    with pytest.raises(ValueError, match=r"1 of 3 state\(s\) unobservable \(involving c\).*"
                       r"A sensor on c would restore them"):
        ob.place_observer_gain(dd, [0.5, 0.6, 0.7], state_names=("a", "b", "c"))
    with pytest.raises(ValueError, match="unobservable"):
        ob.design_observer(net, 0.5, method="poles")


def test_van_loan_against_quadrature():
    m = model_matrices(CONFIGS / "imu6.toml")
    q = np.array([1e-3, 2e-3, 1e-3, 5e-3, 1e-3, 1e-2])
    Qd = ob.discrete_process_covariance(m["A"], q, 0.05)
    ref = np_van_loan(m["A"], np.diag(q ** 2), 0.05)
    np.testing.assert_allclose(Qd, ref, rtol=1e-9, atol=1e-13 * np.abs(ref).max())


def test_steady_state_kalman_against_scipy_control_and_recursion():
    model, system = imu()
    dt = 0.05
    d = tj.discretize(system, dt)
    Phi, C = np.asarray(d.Phi), np.asarray(d.C)
    q = np.asarray(model.process_noise)
    Qd = ob.discrete_process_covariance(system.A, q, dt)
    R = np.asarray(model.noise) ** 2
    kg = ob.steady_state_kalman(d, Qd, R)
    P = scipy.linalg.solve_discrete_are(Phi.T, C.T, Qd, np.diag(R))
    np.testing.assert_allclose(kg.predicted_covariance, P, rtol=1e-9, atol=1e-16)
    # python-control's dlqe returns the predictor gain Phi L and the same P
    Lc, Pc, _ = control.dlqe(Phi, np.eye(6), C, Qd, np.diag(R))
    np.testing.assert_allclose(Phi @ kg.gain, Lc, rtol=1e-7, atol=1e-12)  # dare roundoff
    np.testing.assert_allclose(kg.predicted_covariance, Pc, rtol=1e-7, atol=1e-14)
    # the time-varying filter converges to it (independent recursion)
    Pk = np.eye(6)
    for _ in range(20_000):
        K = Pk @ C.T @ np.linalg.inv(C @ Pk @ C.T + np.diag(R))
        Pf = (np.eye(6) - K @ C) @ Pk
        Pk = Phi @ Pf @ Phi.T + Qd
    np.testing.assert_allclose(kg.gain, K, rtol=1e-6, atol=1e-12)  # converged iteration
    np.testing.assert_allclose(kg.filtered_covariance, Pf, rtol=1e-6, atol=1e-14)


def test_kalman_errors():
    _, system = imu()
    d = tj.discretize(system, 0.05)
    with pytest.raises(ValueError, match="needs Qd of shape"):
        ob.steady_state_kalman(d, np.eye(5), np.ones(3))
    with pytest.raises(ValueError, match="positive definite"):
        ob.steady_state_kalman(d, np.eye(6), np.zeros(3))


def test_design_observer_methods_and_sensor_subsets():
    model, _ = imu()
    kal = ob.design_observer(model, 0.05)
    pol = ob.design_observer(model, 0.05, method="poles")
    assert kal.gain.shape == pol.gain.shape == (6, 3)
    sub = ob.design_observer(model, 0.05, sensors=["T_pcb", "T_asic"])
    assert sub.gain.shape == (6, 2)
    np.testing.assert_array_equal(np.asarray(sub.system.C), np.eye(6)[[2, 3]])
    # the fallback gain is the Kalman gain of the reduced sensor set (scipy truth)
    Phi = np.asarray(sub.system.Phi)
    Qd = ob.discrete_process_covariance(model.linear_system().A,
                                        np.asarray(model.process_noise), 0.05)
    P = scipy.linalg.solve_discrete_are(Phi.T, np.eye(6)[[2, 3]].T, Qd, 1e-4 * np.eye(2))
    C = np.eye(6)[[2, 3]]
    np.testing.assert_allclose(np.asarray(sub.gain),
                               P @ C.T @ np.linalg.inv(C @ P @ C.T + 1e-4 * np.eye(2)),
                               rtol=1e-8, atol=1e-14)
    with pytest.raises(ValueError, match="names sensor 'T_mems'"):
        ob.design_observer(model, 0.05, sensors=["T_mems"])
    with pytest.raises(ValueError, match="method"):
        ob.design_observer(model, 0.05, method="lqr")
