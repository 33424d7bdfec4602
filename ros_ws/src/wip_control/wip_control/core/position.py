r"""Planar position (x̂, ŷ) in the map frame: wheel odometry between GPS fixes.

The trajectory generator, eq. (9) in [1]_, needs the planar position, which the paper
takes as measured. Here it comes from two sources:

- **wheel odometry** at the encoder rate: the distance rolled Δx_v along the estimated
  heading. The step uses the midpoint heading and the chord of a circular arc,

  .. math:: \Delta x = \Delta x_v \,\mathrm{sinc}(\Delta\phi/2) \cos(\phi_{k-1}
     + \Delta\phi/2), \quad \Delta y = \Delta x_v \,\mathrm{sinc}(\Delta\phi/2)
     \sin(\phi_{k-1} + \Delta\phi/2)

  which is exact when the vehicle moves at constant curvature between samples
  (sinc(Δϕ/2) ≈ 1 − 1e-7 at 200 Hz and 0.3 rad/s, but it costs nothing);
- **GPS fixes** (10 Hz by default), which correct the odometry toward the fix:
  p ← p + k (p_gps − p), k = ``gps_blend_gain`` ∈ (0, 1].

Trade-off of the blend gain k: k = 1 resets to every fix, which is right for a noise-free
or centimetre-grade fix (the odometry drift between two fixes, wheel slip and heading
error over 0.1 s, is then all that remains). With white fix noise of standard deviation
σ and exact odometry, the position error after a fix follows e⁺ = (1 − k) e + k n, whose
stationary standard deviation is σ √(k/(2 − k)): k = 0.2 cuts the noise by 3×, but
odometry drift is then corrected only with a time constant of about T_gps/k (0.5 s at
10 Hz), and a biased heading leaves a larger lag.

The fix is checked before it is believed. Fixes that are not finite are rejected, and so
are fixes farther from the odometry's prediction than the gate

.. math:: r = r_0 + d \, s

where r_0 is ``max_gps_innovation``, s the distance rolled since the last accepted fix and
d ``odometry_drift`` (the odometry's error per metre rolled: slip, a wheel radius off by
a few per cent, heading error). A wrong datum, a jump of the receiver or a frozen or
mirrored position source gives innovations that grow past r; a rejected fix changes
nothing, and fixes rejected without a break for ``max_rejection_time`` make the position a
fault (:attr:`PlanarPositionEstimator.fault`), which the safety layer turns into zero
torque with its cause (docs/safety.md).
References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from wip_runtime.config import param

from .compiled import array_slot

#: Position status (the values of wip_msgs/StateEstimate's POSITION_* constants).
TRACKING, NO_FIX, DEAD_RECKONING, FAULT = 0, 1, 2, 3
POSITION_STATUS_NAMES = {NO_FIX: 'NO_FIX', TRACKING: 'TRACKING',
                         DEAD_RECKONING: 'DEAD_RECKONING', FAULT: 'FAULT'}
#: The slots of the estimator's state array: (x̂, ŷ), the odometry's last x_v and ϕ, and the
#: distance rolled since the last accepted fix.
X, Y, X_V, PHI, ROLLED = range(5)


def odometry_step(s: np.ndarray | list[float], x_v: float, phi: float) -> None:
    """Dead-reckon the state ``s`` in place to the distance rolled x_v [m] and heading ϕ [rad].

    The step of :meth:`PlanarPositionEstimator.update_odometry` (finite inputs); the
    compiled estimator runs this very function.
    """
    ds = x_v - s[X_V]
    s[ROLLED] += abs(ds)
    dphi = phi - s[PHI]
    if dphi > math.pi or dphi < -math.pi:
        dphi = math.remainder(dphi, 2.0 * math.pi)
    half = 0.5 * dphi
    # Chord of a constant-curvature arc: length ds·sinc(Δϕ/2), direction ϕ + Δϕ/2.
    chord = ds * (math.sin(half) / half if abs(half) > 1e-8 else 1.0 - half * half / 6.0)
    heading = s[PHI] + half
    s[X] += chord * math.cos(heading)
    s[Y] += chord * math.sin(heading)
    s[X_V], s[PHI] = x_v, phi


@dataclasses.dataclass(frozen=True)
class PositionParams:
    """Tunables of :class:`PlanarPositionEstimator`."""

    gps_blend_gain: float = param(
        1.0, '1', 'fraction of the GPS innovation applied at each fix (1: reset to the '
        'fix; smaller: less fix noise, slower drift correction)', minimum=0.0,
        exclusive_minimum=True, maximum=1.0)
    max_gps_innovation: float = param(
        3.0, 'm', 'gate r0 of a fix against the odometry prediction (r = r0 + '
        'odometry_drift * distance rolled since the last accepted fix); farther: rejected',
        minimum=0.0, exclusive_minimum=True)
    odometry_drift: float = param(
        0.1, '1', 'odometry error per metre rolled that the gate allows for (slip, wheel '
        'radius, heading error)', minimum=0.0, maximum=10.0)
    max_rejection_time: float = param(
        1.0, 's', 'fixes rejected without a break for this long make the position a fault '
        '(zero torque, the cause on /diagnostics)', minimum=0.0, exclusive_minimum=True)


class PlanarPositionEstimator:
    """(x̂, ŷ) [m] in the map frame from wheel odometry and GPS fixes.

    Parameters
    ----------
    config : blend gain and outlier gate.
    """

    def __init__(self, config: PositionParams | None = None) -> None:
        self.config = config if config is not None else PositionParams()
        #: (x̂, ŷ, x_v, ϕ, distance rolled since the last fix): the slots ``X`` … ``ROLLED``.
        self.state = np.zeros(ROLLED + 1)
        self.rejected_fixes = 0   #: fixes rejected since the last reset
        self.accepted_fixes = 0   #: fixes used since the last reset
        self.reset(0.0, 0.0, 0.0, 0.0)

    def reset(self, x: float, y: float, x_v: float, phi: float) -> None:
        """Start at (x, y) [m] with the odometry reading x_v [m] and heading ϕ [rad]."""
        _check_finite('reset', x=x, y=y, x_v=x_v, phi=phi)
        self.state[:] = (x, y, x_v, phi, 0.0)
        self.rejected_fixes = 0
        self.accepted_fixes = 0
        self.rejected_since: float | None = None   #: time of the first of a run of rejections
        self.rejected_in_row = 0
        self.last_innovation = 0.0           #: |innovation| of the last fix [m]
        self.fault = ''                      #: why the position source is refused ('' if not)

    x = array_slot('state', X, 'x̂ [m]')
    y = array_slot('state', Y, 'ŷ [m]')
    rolled_since_fix = array_slot('state', ROLLED,
                                  'distance rolled since the last accepted fix [m]')

    @property
    def position(self) -> tuple[float, float]:
        """Current (x̂, ŷ) [m]."""
        return self.x, self.y

    def update_odometry(self, x_v: float, phi: float) -> tuple[float, float]:
        """Dead-reckon to the new distance rolled x_v [m] and heading ϕ [rad].

        ϕ may be wrapped or continuous: only its change (wrapped) matters.
        """
        if not math.isfinite(x_v + phi):
            _check_finite('update_odometry', x_v=x_v, phi=phi)
        state = self.state.tolist()   # Python floats: no numpy warning on an overflow
        odometry_step(state, x_v, phi)
        self.state[:] = state
        return state[X], state[Y]

    def gate(self) -> float:
        """Radius [m] within which a fix is accepted now (see the module docstring)."""
        return self.config.max_gps_innovation + self.config.odometry_drift * self.rolled_since_fix

    def update_gps(self, x: float, y: float, t: float | None = None) -> tuple[float, float]:
        """Correct toward a fix (x, y) [m] taken at time ``t`` [s]; returns (x̂, ŷ).

        Non-finite fixes and fixes outside :meth:`gate` are rejected (counted in
        :attr:`rejected_fixes`) and leave the estimate unchanged; rejected without a break
        for ``max_rejection_time`` (``t`` given), they set :attr:`fault`.
        """
        dx, dy = x - self.x, y - self.y
        distance = math.hypot(dx, dy)
        self.last_innovation = distance
        if not math.isfinite(distance) or distance > self.gate():
            self.rejected_fixes += 1
            self.rejected_in_row += 1
            if t is not None:
                if self.rejected_since is None:
                    self.rejected_since = t
                elif (not self.fault and self.rejected_in_row >= 2
                      and t - self.rejected_since >= self.config.max_rejection_time):
                    self.fault = (f'{self.rejected_in_row} fixes in a row rejected for '
                                  f'{t - self.rejected_since:.1f} s: the last is '
                                  f'{distance:.4g} m from the odometry, gate {self.gate():.3g} m '
                                  '(a jump or a frozen, offset or mirrored position source)')
            return self.x, self.y
        k = self.config.gps_blend_gain
        self.x += k * dx
        self.y += k * dy
        self.accepted_fixes += 1
        self.rolled_since_fix = 0.0
        self.rejected_since, self.rejected_in_row, self.fault = None, 0, ''
        return self.x, self.y


def _check_finite(where: str, **values: float) -> None:
    bad = [f'{k}={v!r}' for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise ValueError(f'PlanarPositionEstimator.{where}: non-finite input {", ".join(bad)}')
