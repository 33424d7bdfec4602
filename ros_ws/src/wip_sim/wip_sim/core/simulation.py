"""The simulated vehicle of one scenario, built once for every simulator.

A :class:`Simulation` holds the true plant, the disturbances, the sensors, the initial
state and the timing of a scenario, and advances one control period at a time. The
in-process runner (:mod:`.runner`), the plant node and the stand-in base (wip_sim) all
build theirs with it, so that the three simulate the same vehicle with the same random
streams (docs/control-loop.md, step 8).
"""

from __future__ import annotations

import math
from typing import NamedTuple, Sequence

import numpy as np

from wip_control.core.model import PHI, THETA
from wip_control.core.references import make_reference

from .disturbances import Disturbances
from .plant import scenario_plant
from .sensor_models import Sensors


class SensorReading(NamedTuple):
    """What the sensors report for one control tick (SI units, REP 103 signs)."""

    encoders: tuple[float, float]     # (φl, φr) wheel angles [rad]
    wheel_rates: tuple[float, float] | None  # (φ̇l, φ̇r) [rad/s], noise-free; None: not asked
    imu: tuple[float, float]          # (pitch θ, yaw ϕ) [rad]
    imu_rates: tuple[float, float]    # (θ̇, ϕ̇) [rad/s]
    gps_due: bool                     # a GPS tick (a fix or a dropout is reported)
    gps: tuple[float, float] | None   # (x, y) [m] of the fix; None: not due or a dropout


def initial_state(scenario, reference_state) -> np.ndarray:
    """Return the true initial state of the scenario; a relative pose is a body-frame error.

    With (x_e, y_e, ϕ_e) defined as in eq. (9) (body frame), the pose is
    ϕ = ϕr − ϕe and (x, y) = (xr, yr) − R(ϕ) (x_e, y_e). Section V's ϕ(0) = 0.5
    contradicts ϕr(0) − ϕe(0); docs/paper.md §6 adopts ϕ(0) = ϕr(0) − 0.1.
    """
    init = scenario.initial_state
    a, b, c = init.pose
    if init.pose_relative_to_reference:
        phi = reference_state.phi - c
        cos_phi, sin_phi = math.cos(phi), math.sin(phi)
        x = reference_state.x - (cos_phi * a - sin_phi * b)
        y = reference_state.y - (sin_phi * a + cos_phi * b)
    else:
        x, y, phi = a, b, c
    return np.array([x, y, phi, init.x_v, init.theta, init.omega, init.v, init.theta_dot])


class Simulation:
    """Plant, disturbances, sensors, state and timing of ``scenario`` (a ``Scenario``).

    ``state`` is the true state, a float 8-tuple (layout of :mod:`.model`); tick k is at
    t_k = k ``dt_control``. Per tick a simulator reads the sensors
    (:meth:`read_sensors`), hands the readings to the controllers and integrates the
    period with their torques held (:meth:`step`).
    """

    def __init__(self, scenario, reference=None) -> None:
        self.scenario = scenario
        self.plant = scenario_plant(scenario)
        self.disturbances = Disturbances(scenario.disturbances, seed=scenario.seed)
        if reference is None:
            reference = make_reference(scenario.reference)
        # A float tuple: indexing a tuple is cheaper than an array in the loop.
        self.state: tuple = tuple(initial_state(scenario, reference.sample(0.0)).tolist())
        self.sensors = Sensors(scenario.plant.parameters, scenario.sensors,
                               initial_yaw=float(self.state[PHI]), seed=scenario.seed)
        self.dt_control = scenario.control_period
        self.substeps = scenario.rates.substeps
        self.dt_plant = self.dt_control / self.substeps
        self.n_ticks = int(round(scenario.duration / self.dt_control))
        self.gps_every = max(1, int(round(scenario.rates.control_rate
                                          / scenario.sensors.gps_rate)))
        self.fall_threshold = scenario.fall_threshold
        self._blocks = DisturbanceBlocks(self.disturbances, self.dt_control, self.dt_plant,
                                         self.substeps)
        self._hold = self.plant.hold_floats
        lag = scenario.plant.model.motor_time_constant
        # The applied torque follows the command as a first-order lag, held over each
        # control period at its exact mean over that period (see :meth:`step`).
        self._lag_decay = math.exp(-self.dt_control / lag) if lag > 0.0 else None
        self._lag_mean = (lag / self.dt_control * (1.0 - self._lag_decay)
                          if lag > 0.0 else None)
        #: (τl, τr) [N m] the motors apply now (the lag's state).
        self.applied = (0.0, 0.0)
        #: (τl, τr) [N m] the plant was given over the last period (after the lag).
        self.last_torques = (0.0, 0.0)
        # A plant with wheel contacts reports its wheels' own readout (slip included).
        self._wheel_readout = getattr(self.plant, 'wheel_readout', None)

    def fallen(self) -> bool:
        """|θ| at or past the scenario's ``fall_threshold``."""
        return abs(self.state[THETA]) >= self.fall_threshold

    def disturbance(self, k: int) -> list[float]:
        """(d1, d2, d3) at t_k (what the plant feels at the start of tick ``k``)."""
        return self._blocks.rows(k)[1]

    def read_sensors(self, k: int, state: Sequence[float] | None = None,
                     wheel_rates: bool = True) -> SensorReading:
        """Read the sensors of tick ``k`` from ``state`` (default the current one).

        Call once per tick, in order: the sensor delays and the noise streams advance.
        ``wheel_rates``: whether to compute the joint rates (the in-process estimator does
        not use them).
        """
        sensors = self.sensors
        sensed, gps_seen = sensors.delayed(self.state if state is None else state)
        gps_due = k % self.gps_every == 0
        gps = sensors.gps(gps_seen) if gps_due and sensors.gps_fix_available() else None
        wheels = self._wheel_readout(sensed) if self._wheel_readout is not None else None
        if wheels is None:
            encoders = sensors.encoders(sensed)
            rates = sensors.wheel_rates(sensed) if wheel_rates else None
        else:
            encoders = sensors.encoders(sensed, wheels[0])
            rates = sensors.wheel_rates(sensed, wheels[1:]) if wheel_rates else None
        return SensorReading(encoders, rates,
                             sensors.imu(sensed), sensors.imu_rates(sensed), gps_due, gps)

    def step(self, k: int, tau_left: float, tau_right: float) -> tuple:
        """Integrate [t_k, t_k+1] with the wheel torques [N m] held; the new state.

        ``substeps`` RK4 steps of the plant, the disturbance sampled at each step's start;
        ValueError if the state becomes non-finite. With ``plant.motor_time_constant``
        T the torques commanded are not applied at once: the applied torque a(t) relaxes
        towards the command c as c + (a₀ − c) e^(−t/T), and the plant is given its mean
        over the period, c + (a₀ − c) (T/Δt)(1 − e^(−Δt/T)).
        """
        if self._lag_decay is not None:
            (a_left, a_right), mean, decay = self.applied, self._lag_mean, self._lag_decay
            self.applied = (tau_left + (a_left - tau_left) * decay,
                            tau_right + (a_right - tau_right) * decay)
            tau_left = tau_left + (a_left - tau_left) * mean
            tau_right = tau_right + (a_right - tau_right) * mean
        self.last_torques = (tau_left, tau_right)
        state = self._hold(self.state, tau_left, tau_right, self._blocks.rows(k)[0],
                           self.dt_plant)
        # One sum (a NaN or inf propagates), each value only if that is not finite.
        if not (math.isfinite(sum(state)) or all(map(math.isfinite, state))):
            raise ValueError(f'plant state became non-finite at t = '
                             f'{(k + 1) * self.dt_control:.3f} s: {state} (check the '
                             'disturbances)')
        self.state = state
        return state


class DisturbanceBlocks:
    """(d1, d2, d3) at t_k + j dt_plant, j < substeps, computed ``ticks`` ticks at a time.

    The same scalar functions at the same float times as :func:`.plant.simulate_hold`
    (t0 + j dt with t0 = k dt_control), so the values are identical; batching only
    saves building a small array per tick (and row j = 0, recorded, is kept as Python
    floats, cheaper to record than numpy scalars).
    """

    def __init__(self, disturbances: Disturbances, dt_control: float, dt_plant: float,
                 substeps: int, ticks: int = 200) -> None:
        self._disturbances = disturbances
        self._dt_control, self._dt_plant = dt_control, dt_plant
        self._substeps, self._ticks = substeps, ticks
        self._first = -1
        self._table = np.empty((0, substeps, 3))
        self._now: list[list[float]] = []

    def rows(self, k: int) -> tuple[np.ndarray, list[float]]:
        """Return the (substeps, 3) rows of tick ``k`` (a view) and its row 0 as floats."""
        i = k - self._first
        if self._first < 0 or not 0 <= i < self._ticks:
            self._fill(k)
            i = 0
        return self._table[i], self._now[i]

    def _fill(self, first: int) -> None:
        dt_control, dt_plant = self._dt_control, self._dt_plant
        steps = range(self._substeps)
        times = [k * dt_control + j * dt_plant
                 for k in range(first, first + self._ticks) for j in steps]
        self._table = self._disturbances.sample_many(times).reshape(
            self._ticks, self._substeps, 3)
        if not np.all(np.isfinite(self._table)):
            raise ValueError('disturbances must be finite (ticks from t = '
                             f'{first * dt_control} s)')
        self._now = self._table[:, 0, :].tolist()
        self._first = first
