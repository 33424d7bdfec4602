"""Time series of one run, with named channels, as plain numpy arrays.

Both the in-process runner and the bag reader of ``scripts/report`` produce a
:class:`RunRecord`; :mod:`~wip_tools.analysis.metrics` and the figures consume it, so
the two paths compute their metrics with the same code.

Channels are grouped; each group has its own time base because the MPC runs at
10 Hz while the rest runs at the control rate:

- ``truth``: t, x, y, phi, x_v, theta, omega, v, theta_dot, d1, d2, d3 (the
  disturbances acting, eq. (1)'s τd), tau_left, tau_right (applied) — absent for a
  run recorded on a robot;
- ``reference``: t, x, y, phi, v, omega;
- ``estimate``: t, phi, omega, f1, x_v, v, f2, theta, theta_dot, f3, x, y;
- ``command``: t, v_d, omega_d, omega_d_dot, x_e, y_e, phi_e;
- ``arc``: t, tau_omega, alpha_hat, e_omega;
- ``wheels``: t, tau_left, tau_right (commanded);
- ``mpc``: t, tau_v, delta_tau, status, iterations, solve_time, used_fallback,
  slack_v, slack_theta.
"""

from __future__ import annotations

import pathlib
from typing import Callable, Iterable, Mapping

import numpy as np

GROUPS: dict[str, tuple[str, ...]] = {
    'truth': ('t', 'x', 'y', 'phi', 'x_v', 'theta', 'omega', 'v', 'theta_dot',
              'd1', 'd2', 'd3', 'tau_left', 'tau_right'),
    'reference': ('t', 'x', 'y', 'phi', 'v', 'omega'),
    'estimate': ('t', 'phi', 'omega', 'f1', 'x_v', 'v', 'f2', 'theta', 'theta_dot', 'f3',
                 'x', 'y'),
    'command': ('t', 'v_d', 'omega_d', 'omega_d_dot', 'x_e', 'y_e', 'phi_e'),
    'arc': ('t', 'tau_omega', 'alpha_hat', 'e_omega'),
    'wheels': ('t', 'tau_left', 'tau_right'),
    'mpc': ('t', 'tau_v', 'delta_tau', 'status', 'iterations', 'solve_time',
            'used_fallback', 'slack_v', 'slack_theta'),
    # What the sensors said (the plant's /joint_states and /imu/data): wheel joint angles
    # [rad], IMU pitch and yaw [rad] and their rates [rad/s]. Model identification fits to
    # these on a robot, where there is no ground truth.
    'encoders': ('t', 'left', 'right'),
    'imu': ('t', 'pitch', 'yaw', 'pitch_rate', 'yaw_rate'),
}


class RecordBuffer:
    """Rows of one group.

    ``append`` adds a tuple to a list (about 0.1 µs, against about 1 µs for a numpy row copy: the
    runner appends 6 rows per control period), and full blocks of :data:`BLOCK_ROWS` rows become
    one numpy array each, so that a long run does not keep millions of Python floats.

    A caller that appends every control period can instead take :meth:`appender` (the
    pending list's own ``append``, without the block check) and call :meth:`flush` every
    :data:`BLOCK_ROWS` rows or so itself: the runner does, to save a Python call per row.
    """

    #: Rows converted to numpy at a time. Small, so that the rows' Python objects awaiting
    #: conversion stay in the CPU cache and their memory is reused while still cached:
    #: the 90 s run of ``scripts/bench`` took 5 % less CPU time with 128 than with 4096
    #: (the conversion itself costs about the same per row).
    BLOCK_ROWS = 128

    def __init__(self, group: str, columns: tuple[str, ...] | None = None) -> None:
        """Rows of ``group``'s columns (:data:`GROUPS`), or of ``columns`` if given."""
        self.columns = GROUPS[group] if columns is None else columns
        self._blocks: list[np.ndarray] = []
        self._rows: list[tuple] = []

    def append(self, row: Iterable[float]) -> None:
        rows = self._rows
        rows.append(row)
        if len(rows) >= self.BLOCK_ROWS:
            self._flush()

    def appender(self) -> Callable[[tuple], None]:
        """``append`` without the block check (the caller calls :meth:`flush`).

        Valid for the buffer's lifetime (the pending list is emptied in place, never replaced).
        """
        return self._rows.append

    def flush(self) -> None:
        """Turn the pending rows into a numpy block now."""
        self._flush()

    def _flush(self) -> None:
        if self._rows:
            block = np.array(self._rows, dtype=float)
            if block.ndim != 2 or block.shape[1] != len(self.columns):
                raise ValueError(f'rows of {len(self.columns)} values expected '
                                 f'({", ".join(self.columns)}), got shape {block.shape}')
            self._blocks.append(block)
            self._rows.clear()

    def __len__(self) -> int:
        return sum(len(b) for b in self._blocks) + len(self._rows)

    def to_matrix(self) -> np.ndarray:
        """All rows as one (rows, columns) array."""
        self._flush()
        return (np.concatenate(self._blocks) if self._blocks
                else np.empty((0, len(self.columns))))

    def to_arrays(self) -> dict[str, np.ndarray]:
        data = self.to_matrix()
        return {name: data[:, i].copy() for i, name in enumerate(self.columns)}


class RunRecord:
    """Named time series of one run: ``record['estimate']['theta']``."""

    def __init__(self, groups: Mapping[str, Mapping[str, np.ndarray]],
                 attributes: Mapping[str, object] | None = None) -> None:
        self.groups = {name: dict(columns) for name, columns in groups.items()}
        self.attributes = dict(attributes or {})
        for name, columns in self.groups.items():
            lengths = {len(v) for v in columns.values()}
            if len(lengths) > 1:
                raise ValueError(f'group {name!r} has columns of different lengths {lengths}')

    def __getitem__(self, group: str) -> dict[str, np.ndarray]:
        return self.groups[group]

    def __contains__(self, group: str) -> bool:
        return group in self.groups and len(self.groups[group].get('t', ())) > 0

    def save_npz(self, path: str | pathlib.Path) -> None:
        """One npz file; keys are ``group.column``."""
        flat = {f'{g}.{c}': v for g, cols in self.groups.items() for c, v in cols.items()}
        np.savez_compressed(path, **flat)

    @classmethod
    def load_npz(cls, path: str | pathlib.Path) -> 'RunRecord':
        groups: dict[str, dict[str, np.ndarray]] = {}
        with np.load(path) as data:
            for key in data.files:
                group, column = key.split('.', 1)
                groups.setdefault(group, {})[column] = data[key]
        return cls(groups)
