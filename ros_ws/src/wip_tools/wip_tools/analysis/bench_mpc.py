"""Time the MPC tick (build + ProxSuite) against a bare DAQP solve of the same QPs.

:func:`bench_mpc_against_daqp` replays recorded MPC calls (the kwargs of
:meth:`~wip_control.core.mpc.LongitudinalMpc.step` plus ``tau_previous``, as the in-process
runner records them) in order, with τ(k−1) reset to the recorded value at each tick so
the QPs are those of the recorded run. For every tick it times (a) a full tick of
:class:`~wip_control.core.mpc.LongitudinalMpc` with the ProxSuite backend and its
persistent workspace and (b) a persistent DAQP solve of the very same matrices, in one
interleaved loop so machine noise hits both alike. ``scripts/bench`` prints it.
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Sequence

import numpy as np

from wip_control.core.mpc import LongitudinalMpc, MpcStatus
from wip_control.core.mpc_config import MpcParams
from wip_description.params import ModelParams
from wip_control.core.qp import DaqpSolver

#: Keys of one recorded MPC call besides ``tau_previous``.
STEP_KEYS = ('v_hat', 'theta_hat', 'theta_dot_hat', 'f2_hat', 'f3_hat', 'v_d', 'tau_limit')


def _stats_us(samples: Sequence[float]) -> dict:
    a = np.asarray(samples, dtype=float) * 1e6
    if a.size == 0:
        return {'median': math.nan, 'p99': math.nan, 'max': math.nan}
    return {'median': float(np.median(a)), 'p99': float(np.percentile(a, 99)),
            'max': float(a.max())}


def bench_mpc_against_daqp(inputs: list[dict], params: ModelParams, config: MpcParams,
                           repeats: int = 3) -> dict:
    """Replay recorded MPC calls; time ProxSuite ticks and DAQP solves of the same QPs.

    Parameters
    ----------
    inputs : one dict per tick with the keys of ``STEP_KEYS`` and ``'tau_previous'``.
    params, config : the MPC's model and tunables; ``config.backend`` is forced to
        ProxSuite for (a).
    repeats : passes over the whole sequence; each pass starts from a reset MPC and a
        fresh DAQP workspace. Statistics pool all ticks of all passes.

    Returns
    -------
    dict with, in µs, ``tick`` (build + ProxSuite update and solve, measured around
    ``step``), ``build``, ``proxsuite_solve`` and ``daqp_solve`` (update + solve of the
    persistent ``daqp.Model``), each {median, p99, max}; ``ratio_solve`` and
    ``ratio_tick`` (ProxSuite solve / DAQP solve and tick / DAQP solve, of the medians);
    iteration counts, failure counts, and the agreement of the two solutions
    (``max_plan_difference`` [N m], ``max_objective_difference`` relative to 1 + |J|).
    """
    if repeats < 1:
        raise ValueError(f'repeats must be >= 1, got {repeats}')
    for i, tick in enumerate(inputs):
        missing = set(STEP_KEYS + ('tau_previous',)) - set(tick)
        if missing:
            raise ValueError(f'inputs[{i}] lacks {sorted(missing)}')
    config = dataclasses.replace(config, backend='proxsuite')
    mpc = LongitudinalMpc(params, config)
    daqp_solver = DaqpSolver(mpc.n_variables, mpc.n_constraints, config.qp_settings())
    samples = _Samples()
    for _ in range(repeats):
        mpc.reset(inputs[0]['tau_previous'] if inputs else 0.0)
        daqp_solver.reset()
        for tick in inputs:
            _time_tick(mpc, daqp_solver, tick, samples)
    stats = {name: _stats_us(values) for name, values in
             (('tick', samples.tick_s), ('build', samples.build_s),
              ('proxsuite_solve', samples.prox_s), ('daqp_solve', samples.daqp_s))}
    return {
        'ticks': len(inputs), 'repeats': repeats, 'samples': len(samples.tick_s),
        **stats,
        'ratio_solve': stats['proxsuite_solve']['median'] / stats['daqp_solve']['median'],
        'ratio_tick': stats['tick']['median'] / stats['daqp_solve']['median'],
        'proxsuite_iterations': _iteration_stats(samples.prox_iter),
        'daqp_iterations': _iteration_stats(samples.daqp_iter),
        'proxsuite_failures': int(samples.prox_fail), 'daqp_failures': int(samples.daqp_fail),
        'max_plan_difference': samples.plan_diff,
        'max_objective_difference': samples.objective_diff,
    }


@dataclasses.dataclass
class _Samples:
    """What the ticks of all passes measured."""

    tick_s: list = dataclasses.field(default_factory=list)
    build_s: list = dataclasses.field(default_factory=list)
    prox_s: list = dataclasses.field(default_factory=list)
    daqp_s: list = dataclasses.field(default_factory=list)
    prox_iter: list = dataclasses.field(default_factory=list)
    daqp_iter: list = dataclasses.field(default_factory=list)
    prox_fail: int = 0
    daqp_fail: int = 0
    plan_diff: float = 0.0
    objective_diff: float = 0.0


def _time_tick(mpc: LongitudinalMpc, daqp_solver: DaqpSolver, tick: dict,
               samples: _Samples) -> None:
    """Time one recorded call: the MPC tick, then DAQP on the QP it built."""
    kwargs = {key: tick[key] for key in STEP_KEYS}
    mpc.set_previous_torque(tick['tau_previous'])
    t0 = time.perf_counter()
    result = mpc.step(**kwargs)
    t1 = time.perf_counter()
    if result.status == MpcStatus.INPUT_INVALID:
        return  # no QP was built
    qp = mpc.last_qp
    t2 = time.perf_counter()
    solution = daqp_solver.solve(qp.H, qp.g, qp.C, qp.l, qp.u, qp.lb, qp.ub)
    t3 = time.perf_counter()
    samples.tick_s.append(t1 - t0)
    samples.build_s.append(result.build_time_s)
    samples.prox_s.append(result.solve_time_s)
    samples.daqp_s.append(t3 - t2)
    samples.prox_iter.append(result.iterations)
    samples.daqp_iter.append(solution.iterations)
    samples.prox_fail += result.status != MpcStatus.SOLVED
    samples.daqp_fail += solution.status != MpcStatus.SOLVED
    if result.status == MpcStatus.SOLVED and solution.status == MpcStatus.SOLVED:
        daqp_plan = solution.z[:mpc.config.control_horizon]
        samples.plan_diff = max(samples.plan_diff,
                                float(np.max(np.abs(daqp_plan - result.plan))))
        samples.objective_diff = max(samples.objective_diff,
                                     _objective_gap(mpc, result, solution.z))


def _iteration_stats(iterations: Sequence[int]) -> dict:
    if not iterations:
        return {'median': math.nan, 'max': math.nan}
    return {'median': float(np.median(iterations)), 'max': int(max(iterations))}


def _objective_gap(mpc: LongitudinalMpc, result, z_daqp: np.ndarray) -> float:
    """|J(ProxSuite) − J(DAQP)| / (1 + |J(DAQP)|) on the QP of the last tick."""
    qp = mpc.last_qp
    n_c = mpc.config.control_horizon
    z_prox = np.empty(mpc.n_variables)
    z_prox[:n_c] = result.plan
    z_prox[n_c:] = mpc.last_solution.z[n_c:]  # every slack (one per step and limit)

    def objective(z):
        return 0.5 * z @ qp.H @ z + qp.g @ z
    j_daqp = objective(z_daqp)
    return abs(objective(z_prox) - j_daqp) / (1.0 + abs(j_daqp))


def _format(report: dict) -> str:
    lines = [f"{report['ticks']} ticks x {report['repeats']} passes "
             f"({report['samples']} samples), times in µs"]
    lines.append(f"{'':18}{'median':>9}{'p99':>9}{'max':>9}")
    for key in ('build', 'proxsuite_solve', 'tick', 'daqp_solve'):
        s = report[key]
        lines.append(f"{key:18}{s['median']:9.1f}{s['p99']:9.1f}{s['max']:9.1f}")
    lines.append(f"ProxSuite solve / DAQP solve (medians): {report['ratio_solve']:.2f}; "
                 f"tick / DAQP solve: {report['ratio_tick']:.2f}")
    pi, di = report['proxsuite_iterations'], report['daqp_iterations']
    lines.append(f"iterations median/max: ProxSuite {pi['median']:.0f}/{pi['max']}, "
                 f"DAQP {di['median']:.0f}/{di['max']}")
    lines.append(f"failures: ProxSuite {report['proxsuite_failures']}, "
                 f"DAQP {report['daqp_failures']}")
    lines.append(f"agreement: max |Δτ plan difference| {report['max_plan_difference']:.2e} N m, "
                 f"max relative objective difference {report['max_objective_difference']:.2e}")
    return '\n'.join(lines)
