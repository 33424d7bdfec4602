"""The results table of docs/paper.md, made from two in-process runs of the paper scenario.

``scripts/ros2_run wip_tools results_table`` (or ``python -m wip_tools.results_table`` in
the scripts' environment) runs Section V twice (``design: paper`` and the
default design, which the demo runs) and prints the table in Markdown, the text that
docs/paper.md holds between its ``results-table`` markers; ``--check FILE`` compares it
with that text instead (exit 1 if they differ). Solve times are left out: they measure the
machine, not the design.
"""

from __future__ import annotations

import argparse
import pathlib
import re
import sys

from wip_runtime.cli import add_exit_codes, exit_with, EXIT_FAILED, EXIT_OK, EXIT_USAGE

BEGIN = '<!-- results-table:begin (generated: scripts/ros2_run wip_tools results_table) -->'
END = '<!-- results-table:end -->'
DESIGNS = ('paper', 'robust')


def run_design(design: str) -> dict:
    """Return the metrics and the criteria's measurements of Section V under ``design``."""
    from wip_sim.core.runner import run_scenario
    from wip_sim.core.scenario import scenario_from_mapping
    from wip_tools.analysis.criteria import Criteria, measure
    from wip_tools.analysis.metrics import compute_metrics
    scenario = scenario_from_mapping({'design': design})
    result = run_scenario(scenario)
    metrics = compute_metrics(result.record, scenario, fell=result.fell,
                              duration_s=result.simulated_time_s)
    return {**metrics, 'measured': measure(result.record, scenario, metrics, Criteria())}


def _f(value, digits: int, unit: str = '') -> str:
    return 'n/a' if value is None else f'{value:.{digits}f}{unit}'


def _column(m: dict) -> list[str]:
    """Return the cells of one design, row by row (the rows of :data:`ROWS`)."""
    measured, eso = m['measured'], m['eso_rms_error']
    alpha, g1 = m['alpha_hat_range'], m['one_over_g1_range']
    return [
        'yes' if m['fell'] else 'no',
        f'{_f(m["convergence_time_s"], 1, " s")} to the reference point; '
        f'{_f(measured["convergence_time"], 1, " s")} to the path',
        f'to the reference point RMS {_f(m["rms_position_error_m"], 2, " m")}, max '
        f'{_f(m["max_position_error_m"], 2, " m")}; to the path RMS '
        f'{_f(measured["rms_path_error_after_settle"], 3, " m")}; heading RMS '
        f'{_f(m["rms_heading_error_rad"], 2, " rad")}',
        f'max {_f(m["max_abs_theta_outside_pulse_windows_rad"], 3, " rad")} outside the '
        f'pulse, {_f(m["max_abs_theta_rad"], 3, " rad")} overall',
        f'max {_f(m["max_abs_wheel_torque_nm"], 2, " N·m")}',
        f'max {_f(m["max_abs_delta_tau_v_nm"], 2, " N·m")}',
        f'\\|υd\\| ≤ {_f(m["max_abs_v_d_mps"], 2, " m/s")}, \\|ωd\\| ≤ '
        f'{_f(m["max_abs_omega_d_radps"], 2, " rad/s")}',
        f'{m["qp_failures"]} failures in {m["mpc_ticks"]} ticks',
        f'ω {eso["omega"]:.0e} rad/s, υ {eso["v"]:.0e} m/s, θ̇ {eso["theta_dot"]:.0e} rad/s, '
        f'f1 {eso["f1"]:.2f}, f2 {eso["f2"]:.2f}, f3 {eso["f3"]:.3f}',
        f'{_f(alpha[0], 2)}–{_f(alpha[1], 2)} against 1/g1 = {_f(g1[0], 2)}–{_f(g1[1], 2)}',
    ]


#: (quantity, what the paper shows or claims): one row each, in the order of _column.
ROWS = (
    ('falls', 'no'),
    ('initial errors rejected (first ≤ 0.1 m)', 'within 8 s'),
    ('tracking error, t ≥ 10 s', '"fluctuates in a small range"'),
    ('tilt', 'oscillates around 0 within 0.1 rad'),
    ('wheel torques', 'within ±15 N·m'),
    ('Δτυ per MPC step', 'within ±10 N·m'),
    ('desired velocities', 'within their limits (1.5 m/s, 0.3 rad/s)'),
    ('QP', '—'),
    ('ESO RMS errors (Figs. 8, 9)', 'estimates match the truth, small f1 error from ĝ1'),
    ('α̂ (Fig. 10)', 'bounded, need not converge to 1/g1'),
)


def table(results: dict[str, dict]) -> str:
    """Return the Markdown table of ``results`` (design -> :func:`run_design`)."""
    columns = {design: _column(results[design]) for design in DESIGNS}
    lines = ['| quantity | paper | wip-ros, `design: paper` | wip-ros, default design '
             '(the demo) |', '|---|---|---|---|']
    for i, (quantity, paper) in enumerate(ROWS):
        lines.append(f'| {quantity} | {paper} | {columns["paper"][i]} | '
                     f'{columns["robust"][i]} |')
    return '\n'.join(lines)


def documented(text: str) -> str | None:
    """Return the table between the markers of a page's text, or None without them."""
    match = re.search(re.escape(BEGIN) + r'\n(.*?)\n' + re.escape(END), text, re.S)
    return match.group(1) if match else None


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog='results_table',
        description="Run the paper scenario in-process under the paper's design and the\n"
                    'default one, and print the results table of docs/paper.md.',
        epilog='Examples\n    scripts/ros2_run wip_tools results_table\n'
               '    scripts/ros2_run wip_tools results_table --check docs/paper.md',
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument('--check', metavar='FILE',
                        help='compare with the table between the markers of FILE instead')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    page = None
    if args.check:
        try:
            page = documented(pathlib.Path(args.check).read_text(encoding='utf-8'))
        except OSError as err:
            print(f'ERROR: {args.check}: {err.strerror}', file=sys.stderr)
            return EXIT_USAGE
        if page is None:
            print(f'ERROR: {args.check} has no results-table markers', file=sys.stderr)
            return EXIT_USAGE
    generated = table({design: run_design(design) for design in DESIGNS})
    if page is None:
        print(generated)
        return EXIT_OK
    if page == generated:
        print(f'{args.check}: the results table matches the run')
        return EXIT_OK
    print(f'{args.check}: the results table differs from the run; the run gives:\n'
          f'{generated}', file=sys.stderr)
    return EXIT_FAILED


if __name__ == '__main__':
    exit_with(main, 'results_table')
