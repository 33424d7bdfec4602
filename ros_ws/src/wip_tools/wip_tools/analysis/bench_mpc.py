"""Time the MPC tick (build + ProxSuite) against a bare DAQP solve of the same QPs.

:func:`bench_mpc_against_daqp` replays recorded MPC calls (the kwargs of
:meth:`~wip_control.core.mpc.LongitudinalMpc.step` plus ``tau_previous``, as the in-process
runner records them) in order, with τ(k−1) reset to the recorded value at each tick so
the QPs are those of the recorded run. For every tick it times (a) a full tick of
:class:`~wip_control.core.mpc.LongitudinalMpc` with the ProxSuite backend and its
persistent workspace and (b) a persistent DAQP solve of the very same matrices, in one
interleaved loop so machine noise hits both alike.

:func:`simulate_longitudinal` is a small closed loop (the MPC with perfect state
knowledge on the paper plant (1) restricted to the longitudinal/tilt subsystem, ω = 0,
RK4 at 1 ms) used to generate plausible inputs before the full runner exists, and by the
tests of the MPC.

Usage::

    python -m wip_tools.analysis.bench_mpc [--duration 30] [--repeats 3] [--json out.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import importlib.metadata
import json
import math
import platform
import sys
import time
from typing import Callable, NamedTuple, Sequence

import numpy as np

from wip_control.core.integration import rk4_step
from wip_control.core.model import nominal_terms
from wip_control.core.mpc import LongitudinalMpc, MpcStatus
from wip_control.core.mpc_config import MpcConfig
from wip_control.core.params import WipParameters
from wip_control.core.qp import DaqpSolver

#: Keys of one recorded MPC call besides ``tau_previous``.
STEP_KEYS = ('v_hat', 'theta_hat', 'theta_dot_hat', 'f2_hat', 'f3_hat', 'v_d', 'tau_limit')


class LongitudinalRun(NamedTuple):
    """Closed-loop trajectory at the plant rate and the MPC calls that produced it."""

    t: np.ndarray          #: time [s]
    v: np.ndarray          #: υ [m/s]
    theta: np.ndarray      #: θ [rad]
    theta_dot: np.ndarray  #: θ̇ [rad/s]
    tau_v: np.ndarray      #: applied τυ [N m]
    inputs: list           #: one dict per MPC tick: STEP_KEYS + 'tau_previous'
    results: list          #: the MpcResult of each tick
    fell: bool             #: |θ| reached ``fall_angle``


def _constant(value: float) -> Callable[[float], float]:
    return lambda t: value


def simulate_longitudinal(params: WipParameters, config: MpcConfig, duration: float = 10.0,
                          theta_initial: float = 0.05, v_d: float | Callable = 0.5,
                          tau_limit: float | Callable = 30.0,
                          disturbance_v: Callable[[float], float] | None = None,
                          plant_period: float = 1e-3, fall_angle: float = 1.0) -> LongitudinalRun:
    """MPC on the longitudinal/tilt part of the paper plant (1) with perfect knowledge.

    The plant is υ̇ = f2 + g2 τ + d2, θ̈ = f3 + g3 τ (ω = 0), integrated by RK4 with step
    ``plant_period`` [s] and τ held between MPC ticks. The MPC receives the true
    (υ, θ, θ̇) and the true lumped drifts f̂2 = f2 + d2, f̂3 = f3 (what an ideal ESO would
    give). ``v_d``, ``tau_limit`` and ``disturbance_v`` [m/s²] may be functions of t [s].
    The run stops early once |θ| ≥ ``fall_angle`` [rad].
    """
    v_d_of = v_d if callable(v_d) else _constant(float(v_d))
    limit_of = tau_limit if callable(tau_limit) else _constant(float(tau_limit))
    d2_of = disturbance_v if disturbance_v is not None else _constant(0.0)
    decimation = int(round(config.sampling_period / plant_period))
    if decimation < 1 or abs(decimation * plant_period - config.sampling_period) > 1e-9:
        raise ValueError('sampling_period must be an integer multiple of plant_period')
    n_steps = int(round(duration / plant_period))
    mpc = LongitudinalMpc(params, config)
    mpc.reset(0.0)

    def derivative(v, theta, theta_dot, tau, d2):
        terms = nominal_terms(params, theta, 0.0, theta_dot)
        return (terms.f2 + terms.g2 * tau + d2, theta_dot, terms.f3 + terms.g3 * tau)

    v, theta, theta_dot, tau = 0.0, float(theta_initial), 0.0, 0.0
    out = np.empty((n_steps + 1, 5))
    inputs, results = [], []
    fell = False
    k_last = n_steps
    for k in range(n_steps + 1):
        t = k * plant_period
        d2 = d2_of(t)
        out[k] = (t, v, theta, theta_dot, tau)
        if abs(theta) >= fall_angle:
            fell, k_last = True, k
            break
        if k == n_steps:
            break
        if k % decimation == 0:
            terms = nominal_terms(params, theta, 0.0, theta_dot)
            args = dict(v_hat=v, theta_hat=theta, theta_dot_hat=theta_dot,
                        f2_hat=terms.f2 + d2, f3_hat=terms.f3, v_d=v_d_of(t),
                        tau_limit=limit_of(t))
            inputs.append(dict(args, tau_previous=mpc.tau_previous))
            result = mpc.step(**args)
            results.append(result)
            tau = result.tau_v
            out[k, 4] = tau
        # RK4, disturbance held over the step.
        v, theta, theta_dot = rk4_step(
            lambda _, x: derivative(*x, tau, d2), t, (v, theta, theta_dot), plant_period)
    out = out[:k_last + 1]
    return LongitudinalRun(out[:, 0], out[:, 1], out[:, 2], out[:, 3], out[:, 4], inputs,
                           results, fell)


def _stats_us(samples: Sequence[float]) -> dict:
    a = np.asarray(samples, dtype=float) * 1e6
    if a.size == 0:
        return {'median': math.nan, 'p99': math.nan, 'max': math.nan}
    return {'median': float(np.median(a)), 'p99': float(np.percentile(a, 99)),
            'max': float(a.max())}


def bench_mpc_against_daqp(inputs: list[dict], params: WipParameters, config: MpcConfig,
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
    tick_s, build_s, prox_s, daqp_s = [], [], [], []
    prox_iter, daqp_iter = [], []
    prox_fail = daqp_fail = 0
    plan_diff = objective_diff = 0.0
    for _ in range(repeats):
        mpc.reset(inputs[0]['tau_previous'] if inputs else 0.0)
        daqp_solver.reset()
        for tick in inputs:
            kwargs = {key: tick[key] for key in STEP_KEYS}
            mpc.set_previous_torque(tick['tau_previous'])
            t0 = time.perf_counter()
            result = mpc.step(**kwargs)
            t1 = time.perf_counter()
            if result.status == MpcStatus.INPUT_INVALID:
                continue  # no QP was built
            qp = mpc.last_qp
            t2 = time.perf_counter()
            solution = daqp_solver.solve(qp.H, qp.g, qp.C, qp.l, qp.u, qp.lb, qp.ub)
            t3 = time.perf_counter()
            tick_s.append(t1 - t0)
            build_s.append(result.build_time_s)
            prox_s.append(result.solve_time_s)
            daqp_s.append(t3 - t2)
            prox_iter.append(result.iterations)
            daqp_iter.append(solution.iterations)
            prox_fail += result.status != MpcStatus.SOLVED
            daqp_fail += solution.status != MpcStatus.SOLVED
            if result.status == MpcStatus.SOLVED and solution.status == MpcStatus.SOLVED:
                daqp_plan = solution.z[:config.control_horizon]
                plan_diff = max(plan_diff, float(np.max(np.abs(daqp_plan - result.plan))))
                objective_diff = max(objective_diff, _objective_gap(mpc, result, solution.z))
    stats = {name: _stats_us(samples) for name, samples in
             (('tick', tick_s), ('build', build_s), ('proxsuite_solve', prox_s),
              ('daqp_solve', daqp_s))}
    return {
        'ticks': len(inputs), 'repeats': repeats, 'samples': len(tick_s),
        **stats,
        'ratio_solve': stats['proxsuite_solve']['median'] / stats['daqp_solve']['median'],
        'ratio_tick': stats['tick']['median'] / stats['daqp_solve']['median'],
        'proxsuite_iterations': _iteration_stats(prox_iter),
        'daqp_iterations': _iteration_stats(daqp_iter),
        'proxsuite_failures': int(prox_fail), 'daqp_failures': int(daqp_fail),
        'max_plan_difference': plan_diff, 'max_objective_difference': objective_diff,
    }


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


def demo_inputs(params: WipParameters, config: MpcConfig, duration: float = 30.0) -> list:
    """Plausible MPC calls from a closed loop with speed steps, a push and a moving limit.

    υd: 0.5 m/s, 1.2 m/s from 10 s, −0.6 m/s from 20 s; a 10 m/s² push on υ̇ for 0.1 s at
    15 s (the paper's collision); tau_limit = 30 − 8 |sin(0.5 t)| N m, as if the yaw
    controller used part of the wheels' torque.
    """
    def v_d(t):
        return 0.5 if t < 10.0 else (1.2 if t < 20.0 else -0.6)

    def push(t):
        return 10.0 if 15.0 <= t < 15.1 else 0.0

    def limit(t):
        return 30.0 - 8.0 * abs(math.sin(0.5 * t))
    run = simulate_longitudinal(params, dataclasses.replace(config, backend='proxsuite'),
                                duration=duration, v_d=v_d, tau_limit=limit,
                                disturbance_v=push)
    return run.inputs


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


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description='Time the MPC (build + ProxSuite) against DAQP on the same QPs, using '
                    'inputs from a closed loop of the MPC on the paper plant.',
        epilog='example: python -m wip_tools.analysis.bench_mpc --duration 30 --repeats 3')
    parser.add_argument('--duration', type=float, default=30.0, help='closed loop [s]')
    parser.add_argument('--repeats', type=int, default=3, help='passes over the ticks')
    parser.add_argument('--json', help='also write the report to this JSON file')
    args = parser.parse_args(argv)
    if args.duration <= 0.0 or args.repeats < 1:
        print('ERROR: --duration must be > 0 and --repeats >= 1', file=sys.stderr)
        return 1
    params = WipParameters()
    config = MpcConfig()
    inputs = demo_inputs(params, config, args.duration)
    report = bench_mpc_against_daqp(inputs, params, config, args.repeats)
    report['environment'] = {'python': platform.python_version(),
                             'machine': platform.machine(), 'processor': platform.processor(),
                             **{name: importlib.metadata.version(name)
                                for name in ('numpy', 'proxsuite', 'daqp')}}
    print(_format(report))
    if args.json:
        with open(args.json, 'w', encoding='utf-8') as stream:
            json.dump(report, stream, indent=2)
    return 0


if __name__ == '__main__':
    sys.exit(main())
