"""Same inputs, same bits: the MPC's default solver (ProxSuite, polished) across processes.

ProxSuite's AVX2 build rounds differently depending on the heap addresses of its
workspace (docs/decisions/determinism.md); each child process below first leaks a
different number of small heap blocks, so that the layouts differ for sure.
"""

import json
import pathlib
import subprocess
import sys
import textwrap

import numpy as np
import proxsuite
import pytest

from wip_control.core.qp import DaqpSolver, QpSolverParams, polish

_PROXQP = proxsuite.proxqp
N_VARIABLES, N_ROWS = 47, 91  # the default MPC's QP: z = (plan, slacks), rows of C
PROCESSES = 5

_PRELUDE = textwrap.dedent("""
    import ctypes, sys
    import numpy as np
    libc = ctypes.CDLL(None)
    libc.malloc.restype = ctypes.c_void_p
    libc.malloc.argtypes = [ctypes.c_size_t]
    for _ in range(int(sys.argv[1])):
        libc.malloc(24)  # leaked on purpose: moves every later heap block
    out = sys.argv[2]
""")

_SCENARIO = _PRELUDE + textwrap.dedent("""
    from wip_sim.core.runner import run_scenario
    from wip_sim.core.scenario import scenario_from_mapping
    scenario = scenario_from_mapping({
        'duration': 8.0, 'seed': 7, 'design': 'robust', 'mpc': {'backend': 'proxsuite'},
        'sensors': {'imu_pitch_noise_std': 0.002, 'gyro_noise_std': 0.01,
                    'gps_noise_std': 0.05}})
    result = run_scenario(scenario)
    np.savez(out, **{f'{g}.{c}': v for g, cols in result.record.groups.items()
                     for c, v in cols.items()})
""")

_FIXED_QP = _PRELUDE + textwrap.dedent("""
    sys.path.insert(0, sys.argv[3])
    from test_determinism import random_qp
    from wip_control.core.qp import ProxsuiteSolver, QpSolverParams
    solver = ProxsuiteSolver(47, 91, QpSolverParams(eps_abs=1e-7))
    zs = [solver.solve(*random_qp(seed)).z for seed in range(20)]
    np.savez(out, z=np.array(zs))
""")


def run_in_processes(code: str, tmp_path: pathlib.Path, *extra: str) -> list[pathlib.Path]:
    """Run ``code`` in PROCESSES fresh interpreters (heap junk 0, 7, 14, ...)."""
    outputs = [tmp_path / f'out{i}.npz' for i in range(PROCESSES)]
    children = [subprocess.Popen([sys.executable, '-c', code, str(7 * i), str(out), *extra],
                                 stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                for i, out in enumerate(outputs)]
    for child in children:
        stdout, stderr = child.communicate()
        assert child.returncode == 0, stdout + stderr
    return outputs


def random_qp(seed: int):
    """Return a feasible, strictly convex QP of the MPC's shape with some active constraints."""
    rng = np.random.default_rng(seed)
    n, m = N_VARIABLES, N_ROWS
    root = rng.standard_normal((n, n))
    h = root @ root.T + np.diag(rng.uniform(0.1, 1e4, n))
    g = 50.0 * rng.standard_normal(n)
    c = rng.standard_normal((m, n))
    inside = rng.standard_normal(n)  # a strictly feasible point
    cz = c @ inside
    lower = cz - rng.uniform(0.1, 2.0, m)
    upper = cz + rng.uniform(0.1, 2.0, m)
    lower[rng.random(m) < 0.5] = -np.inf  # one-sided rows, as the MPC's
    upper[rng.random(m) < 0.3] = np.inf
    lower_box = inside - rng.uniform(0.1, 1.0, n)
    upper_box = np.where(rng.random(n) < 0.5, np.inf, inside + rng.uniform(0.1, 1.0, n))
    return h, g, c, lower, upper, lower_box, upper_box


def raw_proxsuite(qp_data, eps_abs=1e-7):
    h, g, c, lower, upper, lower_box, upper_box = qp_data
    dense = _PROXQP.dense
    qp = dense.QP(N_VARIABLES, 0, N_ROWS, True, dense.HessianType.Dense,
                  dense.DenseBackend.PrimalDualLDLT)
    qp.settings.eps_abs = eps_abs
    qp.settings.eps_rel = 0.0
    qp.settings.verbose = False
    qp.init(h, g, None, None, c, lower, upper, lower_box, upper_box)
    qp.solve()
    assert qp.results.info.status == _PROXQP.PROXQP_SOLVED
    return np.array(qp.results.x), np.array(qp.results.z)


def test_noisy_scenario_gives_the_same_bits_in_five_processes(tmp_path):
    outputs = run_in_processes(_SCENARIO, tmp_path)
    records = [dict(np.load(out)) for out in outputs]
    first = records[0]
    assert len(first['mpc.t']) >= 70  # the MPC ran (10 Hz for 8 s)
    for other in records[1:]:
        assert other.keys() == first.keys()
        for key, values in first.items():
            if key == 'mpc.solve_time':  # measured wall-clock time
                continue
            assert np.array_equal(other[key], values, equal_nan=True), key


def test_fixed_qps_give_the_same_bytes_in_several_processes(tmp_path):
    here = str(pathlib.Path(__file__).parent)
    outputs = run_in_processes(_FIXED_QP, tmp_path, here)
    solutions = [np.load(out)['z'] for out in outputs]
    assert solutions[0].shape == (20, N_VARIABLES)
    assert all(np.isfinite(z).all() for z in solutions)
    for other in solutions[1:]:
        assert other.tobytes() == solutions[0].tobytes()


@pytest.mark.parametrize('seed', range(20))
def test_polished_point_satisfies_kkt_and_matches_the_raw_answer(seed):
    qp_data = random_qp(seed)
    h, g, c, lower, upper, lower_box, upper_box = qp_data
    eps = 1e-7
    x_raw, y_raw = raw_proxsuite(qp_data, eps)
    result = polish(h, g, c, lower, upper, lower_box, upper_box, y_raw, eps)
    assert result.reason == 'ok'
    z, y = result.z, result.multipliers
    scale = 1.0 + np.abs(g).max()
    # Stationarity, H z + g + Cᵀ y_C + y_box = 0.
    assert np.abs(h @ z + g + c.T @ y[:N_ROWS] + y[N_ROWS:]).max() <= 1e-9 * scale
    for value, lo, hi, mult in ((c @ z, lower, upper, y[:N_ROWS]),
                                (z, lower_box, upper_box, y[N_ROWS:])):
        # Primal feasibility and complementarity: a multiplier only on a bound of its sign.
        assert np.all(value <= hi + 1e-9) and np.all(value >= lo - 1e-9)
        assert np.all((mult <= 0.0) | (np.abs(value - hi) <= 1e-9))
        assert np.all((mult >= 0.0) | (np.abs(value - lo) <= 1e-9))
    assert np.count_nonzero(y) > 0  # the test QPs do have active constraints
    # ProxSuite's raw answer is within its tolerance of the same optimum; DAQP (exact
    # active set) agrees with the polished point to round-off.
    assert np.abs(z - x_raw).max() <= 1e3 * eps
    exact = DaqpSolver(N_VARIABLES, N_ROWS, QpSolverParams()).solve(*qp_data)
    assert np.abs(z - exact.z).max() <= 1e-9 * (1.0 + np.abs(exact.z).max())


def test_polish_is_reported_in_the_solver_stats():
    from wip_control.core.qp import ProxsuiteSolver
    solver = ProxsuiteSolver(N_VARIABLES, N_ROWS, QpSolverParams(eps_abs=1e-7))
    for seed in range(5):
        solver.solve(*random_qp(seed))
    stats = solver.stats
    assert stats.polished + stats.rejected == 5
    assert stats.raw == stats.rejected - stats.exact
    assert json.dumps(stats.rejected_reasons)  # plain counts, printable


def test_the_polish_solve_agrees_with_lapack_and_refuses_singular_matrices():
    # The polish solves its KKT systems by its own compiled elimination (a fixed order of
    # IEEE operations): it must agree with LAPACK to round-off, pivot past the zero block
    # of a KKT matrix, report a zero pivot, and propagate NaN (which the polish reports
    # as a singular KKT matrix).
    from wip_control.core import qp_polish
    rng = np.random.default_rng(3)
    for n in (1, 6, 27, 40, 90):
        a = rng.normal(size=(n, n)) + n * np.eye(n)
        b = rng.normal(size=n)
        x = b.copy()
        assert qp_polish.lu_solve(a.copy(), x)
        expected = np.linalg.solve(a, b)
        assert np.abs(x - expected).max() <= 1e-12 * (1.0 + np.abs(expected).max())
    h = np.diag([4.0, 1e4, 2.0])
    row = np.array([[1.0, -1.0, 0.5]])
    kkt = np.block([[h, row.T], [row, np.zeros((1, 1))]])   # zero on the diagonal
    b = np.array([1.0, -2.0, 0.5, 0.3])
    x = b.copy()
    assert qp_polish.lu_solve(kkt.copy(), x)
    assert np.abs(x - np.linalg.solve(kkt, b)).max() <= 1e-12
    assert not qp_polish.lu_solve(np.array([[1.0, 2.0], [2.0, 4.0]]), np.ones(2))
    assert not qp_polish.lu_solve(np.zeros((3, 3)), np.ones(3))
    x = np.ones(2)
    qp_polish.lu_solve(np.array([[np.nan, 1.0], [1.0, 2.0]]), x)
    assert np.isnan(x).any()


def test_the_polish_names_why_it_rejects_a_point():
    # A singular reduced Hessian and a wrong active set each come back with their reason
    # (the solver then falls back to DAQP), never as a point.
    n, m = 2, 1
    c, lower, upper = np.array([[1.0, 1.0]]), np.array([-np.inf]), np.array([1.0])
    lower_box, upper_box = np.full(n, -np.inf), np.full(n, np.inf)
    singular = polish(np.zeros((n, n)), np.ones(n), c, lower, upper, lower_box, upper_box,
                      np.zeros(m + n), 1e-9)
    assert (singular.z, singular.reason) == (None, 'singular KKT matrix')
    # min ½|z|² − (1, 1)·z s.t. z1 + z2 ≤ 1: the optimum (½, ½) has the row active. Told
    # that it is inactive, the free minimiser (1, 1) violates it; the row joins and the
    # polish finds the optimum.
    found = polish(np.eye(n), -np.ones(n), c, lower, upper, lower_box, upper_box,
                   np.zeros(m + n), 1e-9)
    assert found.reason == 'ok'
    assert np.allclose(found.z, [0.5, 0.5]) and found.multipliers[0] == pytest.approx(0.5)
