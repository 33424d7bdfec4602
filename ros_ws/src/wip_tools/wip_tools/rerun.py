"""Open-loop re-run of the controllers on a recorded bag: ``scripts/rerun BAG --out DIR``.

How a user checks a tuning change against a recorded run (or a recorded fall): the
recorded sensor and command inputs of a bag are fed to freshly built controllers in this
process (:mod:`wip_tools.rerun_loop`), and what they compute now is written next to what
was recorded (:mod:`wip_tools.rerun_outputs`). The inputs, the steps of a tick, the two
timings (lockstep and real-time bags) and the outputs: docs/recording.md ("The open-loop
re-run").
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import sys
import tempfile

from wip_runtime.config import ParamError
from wip_runtime.cli import (add_exit_codes, check_output_directory, EXIT_USAGE, exit_with,
                             write_atomic)
from wip_tools.analysis.metrics import compute_metrics

from wip_bag.bag_reader import bag_summary, BagReadError
from wip_bag.bag_writer import BagWriterError
from wip_tools.bag_scenario import scenario_for_bag
from wip_tools.rerun_inputs import DEFAULT_PREFIX, read_recorded_run, RerunError
from wip_tools.rerun_loop import rerun_controllers, resolve_timing, TIMINGS
from wip_tools.rerun_outputs import (compare, comparison_figure, run_record, summary_lines,
                                     write_rerun_bag)


def rerun(bag, out, scenario_file=None, figures=True, prefix=DEFAULT_PREFIX, quiet=False,
          timing='auto', allow_partial=False):
    """Run the whole tool; returns (metrics dict, comparison dict).

    ``OUT/bag`` must not exist (a bag is never overwritten): checked before anything is
    computed. It is written into a temporary directory beside it and renamed when
    complete, so a failed re-run leaves no half bag that would block the next one.
    """
    from wip_tools.simulate import step_printer
    progress = (lambda text: None) if quiet else step_printer('rerun')
    out = pathlib.Path(out)
    try:
        check_output_directory(out, '--out')
    except ValueError as err:
        raise RerunError(str(err)) from err
    out_bag = out / 'bag'
    if out_bag.exists() or out_bag.is_symlink():
        raise RerunError(f'{out_bag} exists: refusing to overwrite a bag (choose another '
                         '--out or move it away)')
    scenario, source = scenario_for_bag(bag, scenario_file)
    if not quiet:
        print(f'scenario: {source}', file=sys.stderr)
    lost = bag_summary(bag)['problems'] if allow_partial else []
    for line in lost:
        print(f'rerun: warning: partial re-run, {line}', file=sys.stderr)
    progress(f'reading {bag}')
    run = read_recorded_run(bag, allow_partial=allow_partial)
    timing = resolve_timing(run, timing)
    progress(f're-running the controllers (timing: {timing})')
    outputs = rerun_controllers(run, scenario, timing)
    progress(f'{len(outputs)} ticks re-run; comparing with the recording')
    comparison = compare(run, outputs)
    out.mkdir(parents=True, exist_ok=True)
    progress(f'writing {out_bag}')
    counts = _write_bag(bag, out, outputs, run, scenario, prefix, allow_partial)
    record = run_record(run, outputs, scenario)
    progress('metrics')
    metrics = _metrics(record, run, outputs, scenario, {
        'bag': str(pathlib.Path(bag).resolve()), 'scenario_source': source,
        'timing': timing, 'comparison': comparison, 'messages_written': counts}, lost)
    _write_outputs(out, record, run, outputs, scenario, metrics, figures, progress)
    return metrics, comparison


def _write_bag(bag, out, outputs, run, scenario, prefix, allow_partial):
    """Write ``OUT/bag`` through a temporary directory; return the messages per topic."""
    work = pathlib.Path(tempfile.mkdtemp(prefix='.bag.partial-', dir=out))
    try:
        counts = write_rerun_bag(bag, work / 'bag', outputs, run, scenario, prefix,
                                 allow_partial=allow_partial)
        _rename_bag(work / 'bag', out / 'bag')
    finally:
        shutil.rmtree(work, ignore_errors=True)  # ours: created above
    return counts


def _metrics(record, run, outputs, scenario, about, lost):
    """Return the metrics of the recomputed run, with what the re-run was under ``rerun``."""
    metrics = compute_metrics(record, scenario)
    metrics['rerun'] = {
        'bag': about['bag'],
        'scenario_source': about['scenario_source'],
        'open_loop': True,
        'timing': about['timing'],
        'note': 'applied torques and states are the recorded ones; the recomputed torques '
                'were not applied (metrics of the truth group describe the recording)',
        'ticks': len(outputs),
        'invalid_messages_skipped': run.invalid,
        'comparison': about['comparison'],
        'messages_written': about['messages_written'],
    }
    if lost:
        metrics['partial'] = True
        metrics['lost'] = lost
    return metrics


def _write_outputs(out, record, run, outputs, scenario, metrics, figures, progress):
    """Write the report of the recomputed run, ``comparison.json`` and its figure."""
    comparison = metrics['rerun']['comparison']
    from wip_tools.simulate import write_run_outputs
    write_run_outputs(out, record, scenario, metrics, figures=figures, progress=progress)
    write_atomic(out / 'comparison.json', json.dumps(comparison, indent=2) + '\n')
    if figures:
        (out / 'figures').mkdir(exist_ok=True)
        progress('figure rerun_comparison')
        comparison_figure(run, outputs, out / 'figures' / 'rerun_comparison.png')
    progress('done')


def _rename_bag(source, target):
    """Move the finished bag into place.

    Written in a directory also named ``bag``, so its files already have the names rosbag2 gives
    them: ``bag_<i>.mcap``.
    """
    source.rename(target)


def main(argv=None):
    parser = argparse.ArgumentParser(
        prog='scripts/rerun', formatter_class=argparse.RawDescriptionHelpFormatter,
        description="""\
Open-loop re-run: feed the recorded sensors, reference and wheel torques of a bag to
freshly built controllers (in-process core, same holds as the runner) and write a bag and
report of what they compute now next to what was recorded.

Examples
--------
    scripts/rerun out/demo/bag --out out/rerun       # the bag's own scenario
    scripts/rerun out/demo/bag --scenario tuned.yaml --out out/tuned
    scripts/rerun robot_run/bag --timing receive --out out/robot""")
    parser.add_argument('bag', help='bag directory or .mcap file')
    parser.add_argument('--scenario', help='scenario YAML with the controller parameters '
                        "(default: the bag's, else the paper's)")
    parser.add_argument('--out', required=True, help='output directory')
    parser.add_argument('--prefix', default=DEFAULT_PREFIX,
                        help='namespace of the recomputed topics (default /rerun)')
    parser.add_argument('--timing', choices=TIMINGS, default='auto',
                        help="which recorded command was applied and when the MPC ran: "
                        "'stamps' (lockstep bags, exact), 'receive' (real-time bags, "
                        "from the recorder's receive order); default: stamps if the bag "
                        "holds /clock")
    parser.add_argument('--no-figures', action='store_true', help='skip the PNG figures')
    parser.add_argument('--quiet', action='store_true')
    parser.add_argument('--partial', action='store_true',
                        help='re-run the intact part of a damaged or unfinished bag '
                        '(metrics.json then has partial: true and lists what was lost)')
    add_exit_codes(parser)
    args = parser.parse_args(argv)
    try:
        _, comparison = rerun(args.bag, args.out, args.scenario, figures=not args.no_figures,
                              prefix=args.prefix.rstrip('/'), quiet=args.quiet,
                              timing=args.timing, allow_partial=args.partial)
    except (RerunError, BagReadError, BagWriterError, ParamError, OSError,
            ValueError) as err:
        print(f'rerun: error: {err}', file=sys.stderr)
        return EXIT_USAGE
    if not args.quiet:
        print('\n'.join(summary_lines(comparison)))
        print(f'wrote {pathlib.Path(args.out) / "bag"}, comparison.json, metrics.json')
    return 0


if __name__ == '__main__':
    exit_with(main, 'rerun')
