"""A campaign's results: the table of runs, the summary against the criteria, the figures."""

from __future__ import annotations

import csv
import pathlib
from typing import Any, Iterable

import numpy as np

from wip_tools.analysis.criteria import criteria_to_mapping
from wip_tools.campaign_file import Campaign


def write_table(rows: list[dict], out: pathlib.Path) -> list[pathlib.Path]:
    """runs.csv (and runs.parquet when pyarrow is installed)."""
    columns: list[str] = []
    for row in rows:
        columns.extend(k for k in row if k not in columns)
    written = [out / 'runs.csv']
    with (out / 'runs.csv').open('w', newline='', encoding='utf-8') as stream:
        writer = csv.DictWriter(stream, fieldnames=columns)
        writer.writeheader()
        for row in rows:
            writer.writerow({k: ('' if row.get(k) is None else row.get(k)) for k in columns})
    try:
        import pyarrow  # noqa: F401 (optional)
        import pyarrow.parquet as pq
    except ImportError:
        return written
    table = pyarrow.Table.from_pylist([{k: row.get(k) for k in columns} for row in rows])
    pq.write_table(table, out / 'runs.parquet')
    written.append(out / 'runs.parquet')
    return written


def _values(rows: Iterable[dict], key: str) -> np.ndarray:
    out = [row.get(key) for row in rows]
    return np.array([np.nan if v is None or isinstance(v, str) else float(v) for v in out])


def summarise(campaign: Campaign, rows: list[dict]) -> dict[str, Any]:
    """Return counts and rates against the criteria, percentiles of the main errors."""
    n = len(rows)
    failures: dict[str, int] = {}
    for row in rows:
        for name in filter(None, (row.get('failed') or '').split(';')):
            failures[name] = failures.get(name, 0) + 1
    successes = sum(1 for r in rows if r['success'])
    falls = sum(1 for r in rows if r.get('fell'))
    # The runs simulate the runaway guard's verdict without acting on it (the runner has
    # no safety layer); on a robot it is zero torque, so a run that alarms without falling
    # is down there too.
    alarms = sum(1 for r in rows if not r.get('fell') and r.get('runaway_alarm'))
    qp = _values(rows, 'qp_failures')
    summary: dict[str, Any] = {
        'campaign': campaign.name, 'runs': n, 'successes': successes,
        'success_rate': successes / n if n else None,
        'falls': falls, 'runaway_alarms_without_fall': alarms,
        'up_on_a_robot': n - falls - alarms - sum(1 for r in rows if r.get('fell') is None),
        'errors': sum(1 for r in rows if r.get('error')),
        'failed_criteria': failures,
        'qp_failures_total': int(np.nansum(qp)) if n else 0,
        'criteria': criteria_to_mapping(campaign.criteria),
        'varied': {k: {'distribution': kind, 'args': args}
                   for k, (kind, args) in campaign.vary.items()},
        'grid': campaign.grid,
        'wall_time_s_sum': float(np.nansum(_values(rows, 'wall_time_s'))),
        'cpu_time_s_sum': float(np.nansum(_values(rows, 'cpu_time_s'))),
        'simulated_s_sum': float(np.nansum(_values(rows, 'simulated_s'))),
    }
    percentiles = {}
    for key in ('max_abs_theta_rad', 'max_abs_theta_outside_pulse_windows_rad',
                'max_abs_wheel_torque_nm', 'max_abs_delta_tau_v_nm', 'rms_position_error_m',
                'rms_path_error_after_settle', 'max_abs_v_mps'):
        values = _values(rows, key)
        values = values[np.isfinite(values)]
        if len(values):
            percentiles[key] = {'p50': float(np.percentile(values, 50)),
                                'p95': float(np.percentile(values, 95)),
                                'max': float(np.max(values))}
    summary['percentiles'] = percentiles
    if campaign.grid:
        cells = []
        keys = list(campaign.grid)
        for point in campaign.grid_points:
            members = [r for r in rows if all(r.get(k) == v for k, v in point.items())]
            cells.append({**point, 'runs': len(members),
                          'success_rate': (sum(r['success'] for r in members) / len(members)
                                           if members else None)})
        summary['grid_cells'] = cells
        summary['grid_keys'] = keys
    return summary


def summary_text(summary: dict) -> str:
    c = summary['criteria']
    lines = [f'campaign {summary["campaign"]!r}: {summary["runs"]} runs',
             f'success: {summary["successes"]} / {summary["runs"]} '
             f'({100 * (summary["success_rate"] or 0):.1f} %)   falls {summary["falls"]}   '
             f'QP failures {summary["qp_failures_total"]}   run errors {summary["errors"]}',
             f'up on a robot: {summary["up_on_a_robot"]} / {summary["runs"]} (neither fell '
             f'nor alarmed the runaway guard, which zeroes the torque: '
             f'{summary["runaway_alarms_without_fall"]} alarmed without a fall)',
             'criteria: no fall' if c['no_fall'] else 'criteria:',
             ]
    active = [f'{k} <= {v}' for k, v in c.items()
              if k.startswith('max_') and v is not None]
    lines[-1] += ', ' + ', '.join(active) if active else ''
    if summary['failed_criteria']:
        lines.append('failed: ' + ', '.join(f'{k} {v}' for k, v in
                                            sorted(summary['failed_criteria'].items(),
                                                   key=lambda kv: -kv[1])))
    for key, p in summary['percentiles'].items():
        lines.append(f'{key}: p50 {p["p50"]:.4g}  p95 {p["p95"]:.4g}  max {p["max"]:.4g}')
    for cell in summary.get('grid_cells', []):
        point = ', '.join(f'{k} = {cell[k]}' for k in summary['grid_keys'])
        rate = cell['success_rate']
        lines.append(f'  {point}: {cell["runs"]} runs, success '
                     + ('n/a' if rate is None else f'{100 * rate:.0f} %'))
    return '\n'.join(lines)


def write_figures(campaign: Campaign, rows: list[dict], summary: dict,
                  out: pathlib.Path) -> list[pathlib.Path]:
    """Success rate, error distributions, and a heatmap over a 2-D grid."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    paths = [_success_figure(plt, campaign, rows, out / 'success_rate.png'),
             _error_figure(plt, campaign, rows, out / 'error_distributions.png')]
    if len(campaign.grid) == 2:
        paths.append(_heatmap_figure(plt, campaign, rows, out / 'heatmap.png'))
    return paths


def _success_figure(plt, campaign: Campaign, rows: list[dict], path: pathlib.Path):
    """Plot the success rate: overall, and binned along each varied (or 1-D grid) parameter."""
    success = np.array([bool(r['success']) for r in rows])
    varied = list(campaign.vary) + list(campaign.grid)
    numeric = [k for k in varied if np.all(np.isfinite(_values(rows, k)))]
    fig, axes = plt.subplots(1, 1 + len(numeric), figsize=(4 + 3.5 * len(numeric), 3.2),
                             squeeze=False)
    ax = axes[0, 0]
    ax.bar(['success', 'fail'], [success.sum(), (~success).sum()], color=['tab:green', 'tab:red'])
    ax.set_title(f'{100 * success.mean():.1f} % of {len(rows)} runs pass')
    for ax, key in zip(axes[0, 1:], numeric):
        x = _values(rows, key)
        unique = np.unique(x)
        if len(unique) <= 12:
            centers = unique
            members = [x == u for u in unique]
            width = 0.8 * (np.min(np.diff(unique)) if len(unique) > 1 else 1.0)
        else:
            edges = np.linspace(np.min(x), np.max(x), 9)
            index = np.clip(np.digitize(x, edges) - 1, 0, 7)
            centers = 0.5 * (edges[:-1] + edges[1:])
            members = [index == i for i in range(8)]
            width = 0.9 * (edges[1] - edges[0])
        rate = [success[m].mean() if np.any(m) else np.nan for m in members]
        ax.bar(centers, rate, width=width if width > 0 else 1.0, color='tab:blue',
               edgecolor='black', linewidth=0.5)
        for center, m in zip(centers, members):
            if np.any(m):   # pass / runs above each bar: a 0 % bar is still readable
                ax.text(center, 1.07, f'{int(success[m].sum())}/{int(m.sum())}',
                        ha='center', va='bottom', fontsize=6)
        ax.set_ylim(0, 1.15)
        ax.set_xlabel(key, fontsize=8)
        ax.set_ylabel('success rate')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _error_figure(plt, campaign: Campaign, rows: list[dict], path: pathlib.Path):
    """Plot the distributions of the main errors against their limits."""
    keys = [('max_abs_theta_outside_pulse_windows_rad', '|θ| max outside pulses [rad]'),
            ('rms_path_error_after_settle', 'RMS path error after settle [m]'),
            ('max_abs_wheel_torque_nm', 'max |τ wheel| [N·m]'),
            ('max_abs_delta_tau_v_nm', 'max |Δτυ| [N·m]')]
    limits = {'max_abs_wheel_torque_nm': campaign.criteria.max_wheel_torque,
              'max_abs_delta_tau_v_nm': campaign.criteria.max_delta_tau_v,
              'max_abs_theta_outside_pulse_windows_rad':
                  campaign.criteria.max_abs_theta_outside_pulses,
              'rms_path_error_after_settle': campaign.criteria.max_rms_path_error_after_settle}
    fig, axes = plt.subplots(1, len(keys), figsize=(14, 3.2))
    for ax, (key, label) in zip(axes, keys):
        values = _values(rows, key)
        values = values[np.isfinite(values)]
        if len(values):
            # Equal values (a limit met by every run) still get a visible bar.
            pad = 0.5 * max(float(np.ptp(values)), 1e-3 * float(np.max(np.abs(values))), 1e-9)
            ax.hist(values, bins=min(30, max(5, len(values) // 3)),
                    range=(float(np.min(values)) - pad, float(np.max(values)) + pad),
                    color='tab:gray')
        if limits.get(key) is not None:
            ax.axvline(limits[key], color='tab:red', linestyle='--', label='limit')
            ax.legend(fontsize=7)
        ax.set_xlabel(label, fontsize=8)
        ax.set_ylabel('runs')
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _heatmap_figure(plt, campaign: Campaign, rows: list[dict], path: pathlib.Path):
    """Plot heatmaps over a 2-D grid: success rate, and the median RMS path error."""
    (kx, xs), (ky, ys) = campaign.grid.items()
    rate = np.full((len(ys), len(xs)), np.nan)
    error = np.full((len(ys), len(xs)), np.nan)
    label = np.full((len(ys), len(xs)), '', dtype=object)
    for i, y in enumerate(ys):
        for j, x in enumerate(xs):
            cell = [r for r in rows if r.get(kx) == x and r.get(ky) == y]
            if cell:
                passed = sum(bool(r['success']) for r in cell)
                rate[i, j] = passed / len(cell)
                label[i, j] = f'{passed}/{len(cell)}'
                values = _values(cell, 'rms_path_error_after_settle')
                if np.any(np.isfinite(values)):
                    error[i, j] = np.nanmedian(values)
    fig, axes = plt.subplots(1, 2, figsize=(2.4 * len(xs) + 5, 0.8 * len(ys) + 2.2))
    panels = ((rate, 'success rate', 'RdYlGn', dict(vmin=0, vmax=1)),
              (error, 'median RMS path error after settle [m]', 'viridis', {}))
    for ax, (data, title, cmap, scale) in zip(axes, panels):
        image = ax.imshow(data, origin='lower', cmap=cmap, aspect='auto', **scale)
        ax.set_xticks(range(len(xs)), [str(v) for v in xs])
        ax.set_yticks(range(len(ys)), [str(v) for v in ys])
        ax.set_xlabel(kx, fontsize=8)
        ax.set_ylabel(ky, fontsize=8)
        for i in range(len(ys)):
            for j in range(len(xs)):
                text = label[i, j] if data is rate else (
                    f'{data[i, j]:.3g}' if np.isfinite(data[i, j]) else 'n/a')
                ax.text(j, i, text, ha='center', va='center', fontsize=8)
        fig.colorbar(image, ax=ax)
        ax.set_title(title, fontsize=9)
    fig.suptitle(campaign.name, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
