"""Figures of one run in the style of the paper's Figs. 4–10, as PNG and SVG.

Each function takes a :class:`~wip_sim.core.record.RunRecord` (from the in-process
runner or from a bag) and writes one PNG and, beside it, the same figure as SVG (vector,
for print and zoom); :func:`write_figures` writes them all and returns the PNG paths.
Groups that a record lacks (``truth`` on a robot) are skipped in the plots rather than
failing.

Readability rules: legends sit outside the axes (never over the data); a limit line is
never on the frame (the axis range leaves room past it); where two curves overlap (ω_d and
ω, the estimated and the true path) the one that would be hidden is drawn on top, dashed.
What each figure shows and its known effects are explained by the report page's captions
(:mod:`wip_tools.analysis.report_page`).
"""

from __future__ import annotations

import pathlib

import matplotlib

matplotlib.use('Agg')  # files only; never needs a display
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from wip_control.core.angles import wrap_to_pi  # noqa: E402
from wip_tools.analysis.metrics import _interp, true_lumped_disturbances  # noqa: E402
from wip_sim.core.plant import Plant, equation_model, plant_input_gains  # noqa: E402
from wip_sim.core.record import RunRecord  # noqa: E402

_TRUE = dict(color='black', linewidth=1.0, label='true')
_EST = dict(color='tab:red', linewidth=1.0, linestyle='--', label='estimate')
#: Room left past a limit line or the data [fraction of the larger of the two].
_MARGIN = 0.15
#: Time marks on the path figure [s].
TIME_MARK_PERIOD = 10.0


def _save(fig, path: pathlib.Path) -> pathlib.Path:
    """Write ``path`` (PNG) and the same figure as SVG beside it; returns ``path``."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    fig.savefig(path.with_suffix('.svg'))
    plt.close(fig)
    return path


def _legend(ax, **kwargs) -> None:
    """Legend to the right of the axes, outside them: it never hides data."""
    ax.legend(loc='upper left', bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0,
              fontsize=8, frameon=False, **kwargs)


def _limit_lines(ax, value: float, label: str, data=None) -> None:
    """±value lines, with the y range opened past them and past the data.

    So that a limit line never coincides with the frame.
    """
    for sign in (1, -1):
        ax.axhline(sign * value, color='tab:gray', linestyle=':', linewidth=1.0,
                   label=label if sign > 0 else None)
    extent = abs(value)
    if data is not None:
        finite = [np.asarray(d, dtype=float) for d in data]
        finite = [d[np.isfinite(d)] for d in finite if len(d)]
        if finite and any(len(d) for d in finite):
            extent = max(extent, max(float(np.max(np.abs(d))) for d in finite if len(d)))
    if extent > 0:
        ax.set_ylim(-(1 + _MARGIN) * extent, (1 + _MARGIN) * extent)


def figure_path(record: RunRecord, out: pathlib.Path) -> pathlib.Path:
    """Fig. 4: the path against the reference in the map frame."""
    fig, ax = plt.subplots(figsize=(8.5, 6))
    ref = record['reference']
    ax.plot(ref['x'], ref['y'], color='tab:blue', linewidth=2.5, alpha=0.35,
            label='reference', zorder=1)
    est = record['estimate']
    # The estimate lies within centimetres of the truth: drawn thin and dashed on top of
    # the true path (drawn wider below), so that both stay visible.
    if 'truth' in record:
        truth = record['truth']
        ax.plot(truth['x'], truth['y'], color='black', linewidth=1.6, label='true', zorder=2)
        ax.plot(truth['x'][0], truth['y'][0], 'ko', label='start', zorder=4)
        marks_from = truth
    else:
        marks_from = est
    ax.plot(est['x'], est['y'], color='tab:red', linewidth=0.8, linestyle=(0, (4, 3)),
            label='estimate (GPS + odometry)', zorder=3)
    _time_marks(ax, marks_from, ref)
    ax.set_xlabel('x [m]')
    ax.set_ylabel('y [m]')
    ax.set_aspect('equal')
    ax.grid(True, alpha=0.3)
    _legend(ax)
    ax.set_title('Path tracking (cf. Fig. 4)')
    return _save(fig, out / 'fig04_path.png')


def _time_marks(ax, path, ref) -> None:
    """Time marks of the vehicle and the reference every :data:`TIME_MARK_PERIOD` s.

    Every :data:`TIME_MARK_PERIOD` s: the vehicle (dot) and the reference (ring) at the
    same time, joined, and labelled with the time: the tracking error made visible.
    """
    t = np.asarray(path['t'])
    if len(t) < 2:
        return
    first = True
    for mark in np.arange(TIME_MARK_PERIOD, t[-1] + 1e-9, TIME_MARK_PERIOD):
        i = min(int(np.searchsorted(t, mark)), len(t) - 1)
        x, y = path['x'][i], path['y'][i]
        xr, yr = _interp(np.array([mark]), ref['t'], ref['x'])[0], \
            _interp(np.array([mark]), ref['t'], ref['y'])[0]
        ax.plot([x, xr], [y, yr], color='tab:gray', linewidth=0.7, zorder=4)
        ax.plot(x, y, 'o', color='black', markersize=3.5, zorder=5,
                label='vehicle at t = 10, 20, … s' if first else None)
        ax.plot(xr, yr, 'o', markerfacecolor='none', markeredgecolor='tab:blue',
                markersize=5, zorder=5, label='reference at the same t' if first else None)
        ax.annotate(f'{mark:g} s', (x, y), textcoords='offset points', xytext=(4, 3),
                    fontsize=7, zorder=6)
        first = False


def figure_posture_errors(record: RunRecord, out: pathlib.Path) -> pathlib.Path:
    """Fig. 5: body-frame posture errors (x_e, y_e, ϕ_e)."""
    fig, axes = plt.subplots(3, 1, figsize=(9, 6), sharex=True)
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
    _legend(axes[0])
    axes[-1].set_xlabel('t [s]')
    axes[0].set_title('Posture errors in the body frame (cf. Fig. 5)')
    return _save(fig, out / 'fig05_posture_errors.png')


def figure_tilt(record: RunRecord, out: pathlib.Path, max_tilt: float) -> pathlib.Path:
    """Fig. 6: tilt angle and tilt rate, with the tilt limit."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    source = record['truth'] if 'truth' in record else record['estimate']
    axes[0].plot(source['t'], source['theta'], **_TRUE)
    _limit_lines(axes[0], max_tilt, f'MPC tilt limit ±{max_tilt:g} rad (soft)', [source['theta']])
    axes[0].set_ylabel('θ [rad]')
    axes[1].plot(source['t'], source['theta_dot'], **_TRUE)
    axes[1].set_ylabel('θ̇ [rad/s]')
    axes[1].set_xlabel('t [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
    _legend(axes[0])
    axes[0].set_title('Tilt (cf. Fig. 6)')
    return _save(fig, out / 'fig06_tilt.png')


def figure_velocities(record: RunRecord, out: pathlib.Path, max_speed: float,
                      max_yaw_rate: float) -> pathlib.Path:
    """Fig. 7: velocity tracking, desired velocities and their limits."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    cmd, ref = record['command'], record['reference']
    source = record['truth'] if 'truth' in record else record['estimate']
    # The vehicle follows the desired velocities closely: the actual one is drawn wide and
    # light below, the desired one dashed on top (ω_d was hidden under ω).
    axes[0].plot(ref['t'], ref['v'], color='tab:blue', linewidth=0.8, label='υ_r (reference)')
    axes[0].plot(source['t'], source['v'], color='black', linewidth=2.0, alpha=0.35,
                 label='υ (vehicle)')
    axes[0].plot(cmd['t'], cmd['v_d'], color='tab:green', linewidth=1.0, linestyle='--',
                 label='υ_d (desired)')
    _limit_lines(axes[0], max_speed, f'υ_d limit ±{max_speed:g} m/s',
                 [ref['v'], cmd['v_d'], source['v']])
    axes[0].set_ylabel('υ [m/s]')
    axes[1].plot(ref['t'], ref['omega'], color='tab:blue', linewidth=0.8,
                 label='ω_r (reference)')
    axes[1].plot(source['t'], source['omega'], color='black', linewidth=2.0, alpha=0.35,
                 label='ω (vehicle)')
    axes[1].plot(cmd['t'], cmd['omega_d'], color='tab:green', linewidth=1.0, linestyle='--',
                 label='ω_d (desired)')
    _limit_lines(axes[1], max_yaw_rate, f'ω_d limit ±{max_yaw_rate:g} rad/s',
                 [ref['omega'], cmd['omega_d'], source['omega']])
    axes[1].set_ylabel('ω [rad/s]')
    axes[1].set_xlabel('t [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
        _legend(ax)
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
        plant = Plant(scenario.plant.parameters,
                      equation_model(scenario.plant.model.model),
                      scenario.plant.model.wheel_friction)
        lumped = true_lumped_disturbances(record, plant, scenario.controller_model.parameters)
    paths = []
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    _eso_panel(axes[0], record, 'omega', lumped, 'ω [rad/s]')
    _eso_panel(axes[1], record, 'f1', lumped, 'f1 [rad/s²]')
    _legend(axes[0])
    axes[1].set_xlabel('t [s]')
    axes[0].set_title('Rotational ESO (cf. Fig. 8)')
    paths.append(_save(fig, out / 'fig08_eso_rotational.png'))
    fig, axes = plt.subplots(4, 1, figsize=(9, 8), sharex=True)
    for ax, (name, label) in zip(axes, (('v', 'υ [m/s]'), ('theta_dot', 'θ̇ [rad/s]'),
                                        ('f2', 'f2 [m/s²]'), ('f3', 'f3 [rad/s²]'))):
        _eso_panel(ax, record, name, lumped, label)
    _legend(axes[0])
    axes[-1].set_xlabel('t [s]')
    axes[0].set_title('Longitudinal and tilt ESOs (cf. Fig. 9)')
    paths.append(_save(fig, out / 'fig09_eso_longitudinal.png'))
    return paths


def figure_adaptation(record: RunRecord, out: pathlib.Path, scenario) -> pathlib.Path:
    """Fig. 10: the adaptive estimate α̂ against the true α = 1/g1(θ)."""
    fig, ax = plt.subplots(figsize=(9, 3.5))
    arc = record['arc']
    ax.plot(arc['t'], arc['alpha_hat'], color='tab:red', label='α̂')
    source = record['truth'] if 'truth' in record else record['estimate']
    g1 = np.array([plant_input_gains(scenario.plant.parameters, scenario.plant.model.model,
                                     th)[0] for th in source['theta']])
    ax.plot(source['t'], 1.0 / g1, color='black', label='1/g1 (true)')
    ax.set_xlabel('t [s]')
    ax.set_ylabel('α [N·m per rad/s²]')
    ax.grid(True, alpha=0.3)
    _legend(ax)
    ax.set_title('Adaptive parameter (cf. Fig. 10)')
    return _save(fig, out / 'fig10_alpha.png')


def figure_torques(record: RunRecord, out: pathlib.Path, max_wheel_torque: float,
                   max_delta_torque: float) -> pathlib.Path:
    """Wheel torques with their limits, and the MPC's τυ increments."""
    fig, axes = plt.subplots(2, 1, figsize=(9, 5), sharex=True)
    wheels = record['wheels']
    axes[0].plot(wheels['t'], wheels['tau_left'], label='τ_l', linewidth=0.8)
    axes[0].plot(wheels['t'], wheels['tau_right'], label='τ_r', linewidth=0.8)
    _limit_lines(axes[0], max_wheel_torque, f'per-wheel limit ±{max_wheel_torque:g} N·m',
                 [wheels['tau_left'], wheels['tau_right']])
    axes[0].set_ylabel('wheel torque [N·m]')
    mpc = record['mpc']
    delta = np.diff(np.concatenate([[0.0], mpc['tau_v']]))
    axes[1].step(mpc['t'], delta, where='post', label='Δτ_υ per MPC step')
    _limit_lines(axes[1], max_delta_torque, f'MPC limit on Δτ_υ ±{max_delta_torque:g} N·m',
                 [delta])
    axes[1].set_ylabel('Δτ_υ [N·m]')
    axes[1].set_xlabel('t [s]')
    for ax in axes:
        ax.grid(True, alpha=0.3)
        _legend(ax)
    axes[0].set_title('Torques and constraints')
    return _save(fig, out / 'fig11_torques.png')


#: The figures' file stems, in the order they are written.
FIGURE_NAMES = ('fig04_path', 'fig05_posture_errors', 'fig06_tilt', 'fig07_velocities',
                'fig08_eso_rotational', 'fig09_eso_longitudinal', 'fig10_alpha',
                'fig11_torques')


def write_figures(record: RunRecord, scenario, out_dir: str | pathlib.Path,
                  progress=None) -> list[pathlib.Path]:
    """All figures of one run into ``out_dir`` (PNG, with SVG beside); returns the PNG paths.

    ``progress(text)``, if given, is called before each figure (a few seconds each on a full run).
    """
    out = pathlib.Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    steps = [
        (lambda: [figure_path(record, out)], 'fig04_path'),
        (lambda: [figure_posture_errors(record, out)], 'fig05_posture_errors'),
        (lambda: [figure_tilt(record, out, scenario.mpc.max_tilt)], 'fig06_tilt'),
        (lambda: [figure_velocities(record, out, scenario.trajectory_generator.max_speed,
                                    scenario.trajectory_generator.max_yaw_rate)],
         'fig07_velocities'),
        (lambda: figure_eso(record, out, scenario),
         'fig08_eso_rotational, fig09_eso_longitudinal'),
        (lambda: [figure_adaptation(record, out, scenario)], 'fig10_alpha'),
        (lambda: [figure_torques(record, out, scenario.mixer.max_wheel_torque,
                                 scenario.mpc.max_delta_torque)], 'fig11_torques'),
    ]
    paths: list[pathlib.Path] = []
    for make, name in steps:
        if progress is not None:
            progress(f'figure {len(paths) + 1}/{len(FIGURE_NAMES)}: {name}')
        paths += make()
    return paths
