"""One exit-code table and one last-resort error handler for every command-line tool.

=====  ==================================================================================
code   meaning
=====  ==================================================================================
0      success
1      the vehicle fell, or a check failed (a damaged bag, a run that did not pass);
       run_graph hardware mode: a fall or a safety FAULT after the controllers engaged
       (the message gives the mixer's reason, e.g. "fallen: |theta_hat| ... rad")
2      usage or input error: a bad option, scenario, params file, bag or output path;
       nothing was run and nothing was written
3      internal error (a bug, a node that crashed, a graph that stalled): one line on
       stderr says what and where the full trace was written
4      the disk (or a quota) filled up: the tool stopped there, what fit is finished
       (run_graph: the bag, run.json), the message says where
5      the controllers never engaged (run_graph hardware mode, a real-time simulation):
       no inputs from the base, or the estimate never settled; the message says which
129    stopped by SIGHUP (a closed terminal): run_graph finishes the run first
130    interrupted (Ctrl-C)
143    stopped by SIGTERM (systemd, docker stop): run_graph finishes the run first
=====  ==================================================================================

Every tool's ``__main__`` goes through :func:`run_main`, so an exception that escaped a
tool's own checks never prints a traceback at the user: it is written to a log file and
the tool exits 3, which a script can tell apart from "the vehicle fell" (1).
"""

from __future__ import annotations

import argparse
import datetime
import importlib
import math
import os
import pathlib
import re
import sys
import tempfile
import traceback
from typing import Any, Callable, Sequence

EXIT_OK = 0
EXIT_FAILED = 1  # the vehicle fell or a check failed
EXIT_USAGE = 2  # usage or input error
EXIT_INTERNAL = 3  # internal error
EXIT_DISK_FULL = 4  # no space left (or a quota) where an output is written
EXIT_NOT_ENGAGED = 5  # the controllers never engaged
EXIT_HANGUP = 129  # stopped by SIGHUP (128 + 1)
EXIT_INTERRUPTED = 130  # Ctrl-C, SIGINT (128 + 2)
EXIT_TERMINATED = 143  # stopped by SIGTERM (128 + 15)

#: The exit-code table of every tool (the module docstring, the README's "Exit codes" and
#: every tool's ``--help``, :func:`add_exit_codes`, say the same; a test compares them).
EXIT_CODES: dict[int, str] = {
    EXIT_OK: 'success (run_graph hardware mode: the controllers engaged and no fault '
             'followed, or you stopped it)',
    EXIT_FAILED: 'the vehicle fell, or a check failed (a damaged bag, a check of '
                 'check_base); hardware mode: a fall or safety FAULT after engaging',
    EXIT_USAGE: 'usage or input error (option, scenario, params file, bag, output path): '
                'nothing was run or written',
    EXIT_INTERNAL: 'internal error (a bug, a node that crashed, a graph that stalled): '
                   'one line, the full trace in $WIP_TRACE_DIR',
    EXIT_DISK_FULL: 'the disk (or a quota) filled up: what fit is finished',
    EXIT_NOT_ENGAGED: 'the controllers never engaged (hardware mode, a real-time '
                      'simulation): no inputs, or the estimate never settled',
    EXIT_HANGUP: 'stopped by SIGHUP (a closed terminal): the run is finished first',
    EXIT_INTERRUPTED: 'interrupted (Ctrl-C): the run is finished first',
    EXIT_TERMINATED: 'stopped by SIGTERM (systemd, docker stop): the run is finished first',
}
#: First line of the exit-code epilog of every tool's ``--help``.
EXIT_CODES_HEADING = 'Exit codes (one table for every tool):'

#: Where full traces of internal errors go (the directory is created when needed).
TRACE_DIR_ENV = 'WIP_TRACE_DIR'


def trace_directory() -> pathlib.Path:
    """``$WIP_TRACE_DIR``, else ``<tmp>/wip-ros-traces``."""
    configured = os.environ.get(TRACE_DIR_ENV, '').strip()
    return pathlib.Path(configured) if configured else (
        pathlib.Path(tempfile.gettempdir()) / 'wip-ros-traces')


def log_trace(prog: str, error: BaseException) -> str:
    """Write the full trace of ``error`` to a new file; return its path (or why not)."""
    text = ''.join(traceback.format_exception(type(error), error, error.__traceback__))
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime('%Y%m%dT%H%M%SZ')
    try:
        directory = trace_directory()
        directory.mkdir(parents=True, exist_ok=True)
        handle, path = tempfile.mkstemp(prefix=f'{prog}-{stamp}-', suffix='.txt',
                                        dir=directory)
        with os.fdopen(handle, 'w', encoding='utf-8') as stream:
            stream.write(f'{prog} {" ".join(sys.argv[1:])}\n\n{text}')
        return path
    except OSError as err:  # Nowhere to write: the trace goes to stderr after all.
        sys.stderr.write(text)
        return f'(not written: {err.strerror}; printed above)'


def one_line(error: BaseException, limit: int = 300) -> str:
    """``Type: message`` on one line, shortened."""
    text = ' '.join(str(error).split())
    text = f'{type(error).__name__}: {text}' if text else type(error).__name__
    return text if len(text) <= limit else text[:limit - 3] + '...'


def run_main(main: Callable[[Sequence[str] | None], int], prog: str,
             argv: Sequence[str] | None = None) -> int:
    """Call a tool's ``main(argv)`` and map whatever happens onto the exit-code table."""
    try:
        code = main(argv)
    except SystemExit as done:  # argparse: --help (0) or a usage error (2)
        code = done.code
        if code is None:
            return EXIT_OK
        if not isinstance(code, int):
            print(code, file=sys.stderr)
            return EXIT_USAGE
        return code
    except KeyboardInterrupt:
        print(f'{prog}: interrupted', file=sys.stderr)
        return EXIT_INTERRUPTED
    except BrokenPipeError:  # `tool | head`: the reader left; not an error of ours.
        try:
            sys.stdout = open(os.devnull, 'w')  # noqa: SIM115 (closed at exit)
        except OSError:
            pass
        return EXIT_OK
    except Exception as error:  # noqa: BLE001 (the last resort, by design)
        where = log_trace(prog, error)
        print(f'{prog}: internal error: {one_line(error)} (full trace in {where})',
              file=sys.stderr)
        return EXIT_INTERNAL
    return EXIT_OK if code is None else int(code)


def exit_with(main: Callable[[Sequence[str] | None], int], prog: str) -> None:
    """Exit with what :func:`run_main` returns.

    Usage: ``if __name__ == '__main__': exit_with(main, 'simulate')``.
    """
    sys.exit(run_main(main, prog))


def console_script(module: str, prog: str) -> Callable[[], int]:
    """Return the console script of the tool ``module``.

    The console script (setup.py entry point, what ``ros2 run`` starts) of the tool
    ``module``: its ``main`` through :func:`run_main`, as ``python -m module`` runs it. The
    module is imported when the script runs (so one tool does not import the others), and
    inside run_main (so a failed import is a one-line error too).
    """
    def script() -> int:
        return run_main(lambda argv: importlib.import_module(module).main(argv), prog)

    script.__name__ = script.__qualname__ = prog
    return script


def check_output_directory(path: str | os.PathLike, option: str = '--out') -> pathlib.Path:
    """Check before a run that ``path`` can be a run's output directory; return it.

    It may exist (its files of the same name are replaced, each atomically) or be created.
    Raises ``ValueError`` with a one-line message if it is a file, under a file, or not
    writable, so the tool can refuse before it runs anything.
    """
    out = pathlib.Path(path)
    if str(path).strip() == '':
        raise ValueError(f'{option}: an empty path')
    probe = out
    while not probe.exists():
        if probe.parent == probe:
            break
        probe = probe.parent
    if probe.exists() and not probe.is_dir():
        raise ValueError(f'{option} {out}: {probe} is a file, not a directory')
    if not os.access(probe, os.W_OK | os.X_OK):
        raise ValueError(f'{option} {out}: {probe} is not writable')
    return out


def write_atomic(path: str | os.PathLike, data: bytes | str) -> None:
    """Write a whole file or nothing: a temporary file beside it, then a rename."""
    path = pathlib.Path(path)
    payload = data.encode('utf-8') if isinstance(data, str) else data
    handle, tmp = tempfile.mkstemp(prefix=f'.{path.name}.', suffix='.tmp', dir=path.parent)
    try:
        with os.fdopen(handle, 'wb') as stream:
            stream.write(payload)
            stream.flush()
            os.fsync(stream.fileno())
        os.replace(tmp, path)
    except BaseException:
        pathlib.Path(tmp).unlink(missing_ok=True)
        raise


def exit_codes_text() -> str:
    """Return the exit-code table as the epilog of a tool's ``--help``: one line per code."""
    return EXIT_CODES_HEADING + '\n' + '\n'.join(
        f'  {code:>3}  {meaning}' for code, meaning in EXIT_CODES.items())


#: reST markup of the docstrings that --help texts reuse: a role with a target
#: (``:class:`~a.b.Name``` -> Name, ``:func:`a.b``` -> a.b), literals, citations.
_ROLE = re.compile(r':[a-z]+:`(~?)([^`<]*?)(?:\s*<[^>]*>)?`')
_LITERAL = re.compile(r'``([^`]+)``')
_CITATION = re.compile(r'(\[\d+\])_')


def plain_text(text: str | None) -> str | None:
    """Render the reST markup of the project's docstrings in ``text`` as plain text.

    Roles become their (short) target, ``literals`` lose their quotes, ``[1]_`` becomes
    [1], the ``.. math::`` and ``.. [1]`` directives lose their dots, ``::`` becomes ``:``.
    """
    if not text:
        return text

    def role(match: re.Match) -> str:
        target = match.group(2).strip()
        return target.rsplit('.', 1)[-1] if match.group(1) else target
    text = _LITERAL.sub(r'\1', _ROLE.sub(role, text))
    text = _CITATION.sub(r'\1', text)
    lines = []
    for line in text.splitlines():
        stripped = line.strip()
        if stripped == '.. math::':
            continue
        if stripped.startswith('.. ['):
            line = line.replace('.. [', '[', 1)
        if line.endswith('::') and not stripped == '::':
            line = line[:-1]
        elif stripped == '::':
            continue
        lines.append(line)
    return '\n'.join(lines)


def add_exit_codes(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Put the exit-code table at the end of ``parser``'s ``--help``, line by line.

    The parser's formatter keeps wrapping the rest of its text as before; the docstrings'
    reST markup in the description, epilog and option help is rendered as plain text
    (:func:`plain_text`), and a usage error is one line (exit 2).
    """
    parser.epilog = (parser.epilog + '\n\n' if parser.epilog else '') + exit_codes_text()
    base = parser.formatter_class

    class Formatter(base):  # type: ignore[misc, valid-type]
        def _split_lines(self, text, width):
            return super()._split_lines(plain_text(text), width)

        def _fill_text(self, text, width, indent):
            text = plain_text(text)
            head, found, table = text.partition(EXIT_CODES_HEADING)
            if not found:
                return super()._fill_text(text, width, indent)
            lead = super()._fill_text(head, width, indent) + '\n\n' if head.strip() else ''
            return lead + ''.join(indent + line for line in
                                  (found + table).splitlines(keepends=True))

    parser.formatter_class = Formatter

    def error(message: str) -> None:
        # One line, not argparse's usage block before it: the usage is in --help.
        parser.exit(EXIT_USAGE, f'{parser.prog}: error: {message} (--help: usage)\n')

    parser.error = error  # type: ignore[method-assign]
    return parser


def bounded(kind: type, minimum: float | None = None, maximum: float | None = None,
            exclusive_minimum: bool = False) -> Callable[[str], Any]:
    """Return an argparse ``type=`` for a finite number in a range.

    An argparse ``type=``: a finite ``kind`` (int or float) in [minimum, maximum]
    ((minimum, maximum] with ``exclusive_minimum``), checked by
    :func:`.config.check_number`; argparse's usage error (exit 2) naming the range otherwise.
    """
    from .config import check_number, ParamError
    limits = {'minimum': minimum, 'maximum': maximum, 'exclusive_minimum': exclusive_minimum}
    low = '' if minimum is None else (f'> {minimum:g}' if exclusive_minimum
                                      else f'>= {minimum:g}')
    high = '' if maximum is None else f'<= {maximum:g}'

    def convert(text: str):
        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f'{text!r} is not {"an integer" if kind is int else "a number"}') from None
        try:
            return check_number(text, value, limits, want_int=kind is int)
        except ParamError:
            if not math.isfinite(value):
                raise argparse.ArgumentTypeError(f'{text!r} is not a finite number') from None
            raise argparse.ArgumentTypeError(
                f'must be {" and ".join(p for p in (low, high) if p)}, got {text}') from None

    convert.__name__ = kind.__name__   # argparse names the type in some messages
    return convert


#: What each process that holds several nodes holds (for its ``--help``).
_NODE_HELP_EXTRA = {
    'controllers': 'the six controller nodes reference, eso, trajectory_generator, arc, '
                   'mpc and torque_mixer in one process (each keeps its name, parameters '
                   'and topics)',
    'simulation': 'the plant and the six controller nodes in one process (with '
                  '--with-viewer before --ros-args, the viewer node too)',
}


def split_ros_args(words: Sequence[str]) -> tuple[list[str], list[str]]:
    """Split a command line into the program's own words and rclpy's (``--ros-args`` on)."""
    words = list(words)
    if '--ros-args' in words:
        index = words.index('--ros-args')
        return words[:index], words[index:]
    return words, []


def answer_node_help(program: str, package: str, args: Sequence[str] | None = None) -> bool:
    """Answer ``-h``/``--help`` on the command line of a node executable.

    If the command line of a node executable asks for ``-h``/``--help`` (before
    ``--ros-args``), print its usage on stdout and return True: the caller then exits 0
    without starting anything. ``args`` as given to ``rclpy.init`` (``sys.argv`` if
    None).
    """
    words, _ = split_ros_args(list(sys.argv if args is None else args)[1:])
    if not ({'-h', '--help'} & set(words)):
        return False
    holds = _NODE_HELP_EXTRA.get(program, f'the ROS 2 node {program}')
    print(f'usage: ros2 run {package} {program} [--ros-args [-p NAME:=VALUE] '
          '[--params-file FILE] [-r FROM:=TO] ...]\n\n'
          f'Starts {holds} until SIGINT or SIGTERM.\n'
          f'Parameters (name, unit, default, range): ros2 run wip_tools parameters --node '
          f'{program if program not in _NODE_HELP_EXTRA else "NAME"}, or '
          'docs/parameters.md.\n'
          'Exit status: 0 stopped by SIGINT or SIGTERM; 1 a parameter error (one line '
          'naming the parameter); a simulator ends with its own status (the plant: 3 when '
          'the vehicle fell); scripts/run_graph maps these onto the exit-code table.')
    return True
