"""PNG figures of one run in the style of the paper's Figs. 4–10.

Each function takes a :class:`~wip_control.core.record.RunRecord` (from the in-process
runner or from a bag) and writes one PNG; :func:`write_figures` writes them all and
returns their paths. Groups that a record lacks (``truth`` on a robot) are skipped in
the plots rather than failing.
"""

from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use('Agg')  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..core.angles import wrap_to_pi  # noqa: E402
from ..core.metrics import _interp, true_lumped_disturbances  # noqa: E402
from ..core.plant import Plant, plant_input_gains  # noqa: E402
from ..core.record import RunRecord  # noqa: E402

_TRUE = dict(color='black', linewidth=1.0, label='true')
_EST = dict(color='tab:red', linewidth=1.0, linestyle='--', label='estimate')


def _save(fig, path: pathlib.Path) -> pathlib.Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _limit_lines(ax, value: float, label: str) -> None:
    for sign in (1, -1):
        ax.axhline(sign * value, color='tab:gray', linestyle=':', linewidth=1.0,
                   label=label if sign > 0 else None)


def figure_path(record: RunRecord, out: pathlib.Path) -> pathlib.Path:
    """Fig. 4: the path against the reference in the map frame."""
    fig, ax = plt.subplots(figsize=(6, 6))
    ref = record['reference']
    ax.plot(ref['x'], ref['y'], color='tab:blue', linewidth=1.2, label='reference')
    if 'truth' in record:
        ax.plot(record['truth']['x'], record['truth']['y'], **_TRUE)
        ax.plot(record['truth']['x'][0], record['truth']['y'][0], 'ko', label='start')
    est = record['estimate']
    ax.plot(est['x'], est['y'], color='tab:red', linewidth=0.8, linestyle='--',
            label='estimate (GPS + odometry)')
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal')
    ax.grid(True, alpha=0.3)
    ax.legend(loc='best')
    ax.set_title('Path tracking (cf. Fig. 4)')
    return _save(fig, out / 'fig04_path.png')


def figure_posture_errors(record: RunRecord, out: pathlib.Path) -> pathlib.Path:
    """Fig. 5: body-frame posture errors (x_e, y_e, ϕ_e)."""
    fig, axes = plt.subplots(3, 1, figsize=(8, 6), sharex=True)
    cmd = record['command']
    labels = (('x_e', 'x_e [m]'), ('y_e', 'y_e [m]'), ('phi_e', 'φ_e [rad]'))
    truth_errors = None
    if 'truth' in record:
        truth, ref = record['truth'], record['reference']
        t = ref['t']
        x = _interp(t, truth['t'], truth['x'])
        y = _interp(t, truth['t'], truth['y'])
        phi = _interp(t, truth['t'], truth['phi'])
        dx, dy = ref['x'] - x, ref['y'] - y
        truth_errors = {'x_e': np.cos(phi) * dx + np.sin(phi) * dy,
                        'y_e': -np.sin(phi) * dx + np.cos(phi) * dy,
                        'phi_e': np.array([wrap_to_pi(a) for a in ref['phi'] - phi])}
    for ax, (key, label) in zip(axes, labels):
        if truth_errors is not None:
            ax.plot(record['reference']['t'], truth_errors[key], **_TRUE)
        ax.plot(cmd['t'], cmd[key], color='tab:red', linewidth=0.8, linestyle='--',
                label='seen by the controller')
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc='upper right')
    axes[-1].set_xlabel('t [s]')
    axes[0].set_title('Posture errors in the body frame (cf. Fig. 5)')
    return _save(fig, out / 'fig05_posture_errors.png')


def figure_tilt(record: RunRecord, out: pathlib.Path, max_tilt: float) -> pathlib.Path:
    """Fig. 6: tilt angle and tilt rate, with the tilt limit."""
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    source = record['truth'] if 'truth' in record else record['estimate']
    axes[0].plot(source['t'], source['theta'], **_TRUE)
    _limit_lines(axes[0], max_tilt, 'limit')
    axes[0].set_ylabel('θ [rad]')
    axes[1].plot(source['t'], source['theta_dot'], **_TRUE)
    axes[1].set_ylabel('θ̇ [rad/s]')
    axes[1].set_xlabel('t [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc='upper right')
    axes[0].set_title('Tilt (cf. Fig. 6)')
    return _save(fig, out / 'fig06_tilt.png')


def figure_velocities(record: RunRecord, out: pathlib.Path, max_speed: float,
                      max_yaw_rate: float) -> pathlib.Path:
    """Fig. 7: velocity tracking, desired velocities and their limits."""
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    cmd, ref = record['command'], record['reference']
    source = record['truth'] if 'truth' in record else record['estimate']
    axes[0].plot(ref['t'], ref['v'], color='tab:blue', linewidth=0.8, label='υ_r')
    axes[0].plot(cmd['t'], cmd['v_d'], color='tab:green', linewidth=1.0, label='υ_d')
    axes[0].plot(source['t'], source['v'], color='black', linewidth=0.8, label='υ')
    _limit_lines(axes[0], max_speed, 'limit')
    axes[0].set_ylabel('υ [m/s]')
    axes[1].plot(ref['t'], ref['omega'], color='tab:blue', linewidth=0.8, label='ω_r')
    axes[1].plot(cmd['t'], cmd['omega_d'], color='tab:green', linewidth=1.0, label='ω_d')
    axes[1].plot(source['t'], source['omega'], color='black', linewidth=0.8, label='ω')
    _limit_lines(axes[1], max_yaw_rate, 'limit')
    axes[1].set_ylabel('ω [rad/s]')
    axes[1].set_xlabel('t [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper right', fontsize=8, ncol=4)
    axes[0].set_title('Velocity tracking (cf. Fig. 7)')
    return _save(fig, out / 'fig07_velocities.png')


def _eso_panel(ax, record, name, lumped, label):
    est = record['estimate']
    if 'truth' in record:
        truth = record['truth']
        true_values = lumped[name] if name in lumped else truth[name]
        ax.plot(truth['t'], true_values, **_TRUE)
    ax.plot(est['t'], est[name], **_EST)
    ax.set_ylabel(label)
    ax.grid(True, alpha=0.3)


def figure_eso(record: RunRecord, out: pathlib.Path, scenario) -> list[pathlib.Path]:
    """Figs. 8–9: ESO estimates against the truth, rotational and longitudinal."""
    lumped = {}
    if 'truth' in record:
        plant = Plant(scenario.plant.parameters, scenario.plant.model.model)
        lumped = true_lumped_disturbances(record, plant, scenario.controller_model.parameters)
    paths = []
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    _eso_panel(axes[0], record, 'omega', lumped, 'ω [rad/s]')
    _eso_panel(axes[1], record, 'f1', lumped, 'f1 [rad/s²]')
    axes[0].legend(loc='upper right')
    axes[1].set_xlabel('t [s]')
    axes[0].set_title('Rotational ESO (cf. Fig. 8)')
    paths.append(_save(fig, out / 'fig08_eso_rotational.png'))
    fig, axes = plt.subplots(4, 1, figsize=(8, 8), sharex=True)
    for ax, (name, label) in zip(axes, (('v', 'υ [m/s]'), ('theta_dot', 'θ̇ [rad/s]'),
                                        ('f2', 'f2 [m/s²]'), ('f3', 'f3 [rad/s²]'))):
        _eso_panel(ax, record, name, lumped, label)
    axes[0].legend(loc='upper right')
    axes[-1].set_xlabel('t [s]')
    axes[0].set_title('Longitudinal and tilt ESOs (cf. Fig. 9)')
    paths.append(_save(fig, out / 'fig09_eso_longitudinal.png'))
    return paths


def figure_adaptation(record: RunRecord, out: pathlib.Path, scenario) -> pathlib.Path:
    """Fig. 10: the adaptive estimate α̂ against the true α = 1/g1(θ)."""
    fig, ax = plt.subplots(figsize=(8, 3.5))
    arc = record['arc']
    ax.plot(arc['t'], arc['alpha_hat'], color='tab:red', label='α̂')
    source = record['truth'] if 'truth' in record else record['estimate']
    g1 = np.array([plant_input_gains(scenario.plant.parameters, scenario.plant.model.model,
                                     th)[0] for th in source['theta']])
    ax.plot(source['t'], 1.0 / g1, color='black', label='1/g1 (true)')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('α [N·m per rad/s²]')
    ax.grid(True, alpha=0.3)
    ax.legend(loc='upper right')
    ax.set_title('Adaptive parameter (cf. Fig. 10)')
    return _save(fig, out / 'fig10_alpha.png')


def figure_torques(record: RunRecord, out: pathlib.Path, max_wheel_torque: float,
                   max_delta_torque: float) -> pathlib.Path:
    """Wheel torques with their limits, and the MPC's τυ increments."""
    fig, axes = plt.subplots(2, 1, figsize=(8, 5), sharex=True)
    wheels = record['wheels']
    axes[0].plot(wheels['t'], wheels['tau_left'], label='τ_l', linewidth=0.8)
    axes[0].plot(wheels['t'], wheels['tau_right'], label='τ_r', linewidth=0.8)
    _limit_lines(axes[0], max_wheel_torque, 'limit')
    axes[0].set_ylabel('wheel torque [N·m]')
    mpc = record['mpc']
    delta = np.diff(np.concatenate([[0.0], mpc['tau_v']]))
    axes[1].step(mpc['t'], delta, where='post', label='Δτ_υ per MPC step')
    _limit_lines(axes[1], max_delta_torque, 'limit')
    axes[1].set_ylabel('Δτ_υ [N·m]')
    axes[1].set_xlabel('t [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(loc='upper right', fontsize=8)
    axes[0].set_title('Torques and constraints')
    return _save(fig, out / 'fig11_torques.png')


def write_figures(record: RunRecord, scenario, out_dir: str | pathlib.Path) -> list[pathlib.Path]:
    """All figures of one run into ``out_dir``; returns their paths."""
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = [figure_path(record, out), figure_posture_errors(record, out),
             figure_tilt(record, out, scenario.mpc.max_tilt),
             figure_velocities(record, out, scenario.trajectory_generator.max_speed,
                               scenario.trajectory_generator.max_yaw_rate)]
    paths += figure_eso(record, out, scenario)
    paths.append(figure_adaptation(record, out, scenario))
    paths.append(figure_torques(record, out, scenario.mixer.max_wheel_torque,
                                scenario.mpc.max_delta_torque))
    return paths
