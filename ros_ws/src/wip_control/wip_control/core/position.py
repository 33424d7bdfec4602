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
10 Hz), and a biased heading leaves a larger lag. Fixes that are not finite are rejected,
and so are fixes farther than ``max_gps_innovation`` from the prediction (outliers).

References
----------
.. [1] M. Yue, C. An, Z. Li, IEEE T-SMC: Systems, 2016 (see ``eso.py``).
"""

from __future__ import annotations

import dataclasses
import math

from .config import param


@dataclasses.dataclass(frozen=True)
class PositionConfig:
    """Tunables of :class:`PlanarPositionEstimator`."""

    gps_blend_gain: float = param(
        1.0, '1', 'fraction of the GPS innovation applied at each fix (1: reset to the '
        'fix; smaller: less fix noise, slower drift correction)', minimum=0.0,
        exclusive_minimum=True, maximum=1.0)
    max_gps_innovation: float = param(
        1000.0, 'm', 'fixes farther than this from the odometry prediction are rejected '
        'as outliers (the default is effectively no gate)', minimum=0.0,
        exclusive_minimum=True)


class PlanarPositionEstimator:
    """(x̂, ŷ) [m] in the map frame from wheel odometry and GPS fixes.

    Parameters
    ----------
    config : blend gain and outlier gate.
    """

    def __init__(self, config: PositionConfig | None = None) -> None:
        self.config = config if config is not None else PositionConfig()
        self.rejected_fixes = 0   #: fixes rejected since the last reset
        self.accepted_fixes = 0   #: fixes used since the last reset
        self.reset(0.0, 0.0, 0.0, 0.0)

    def reset(self, x: float, y: float, x_v: float, phi: float) -> None:
        """Start at (x, y) [m] with the odometry reading x_v [m] and heading ϕ [rad]."""
        _check_finite('reset', x=x, y=y, x_v=x_v, phi=phi)
        self.x, self.y = float(x), float(y)
        self._x_v, self._phi = float(x_v), float(phi)
        self.rejected_fixes = 0
        self.accepted_fixes = 0

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
        ds = x_v - self._x_v
        dphi = phi - self._phi
        if dphi > math.pi or dphi < -math.pi:
            dphi = math.remainder(dphi, 2.0 * math.pi)
        half = 0.5 * dphi
        # Chord of a constant-curvature arc: length ds·sinc(Δϕ/2), direction ϕ + Δϕ/2.
        chord = ds * (math.sin(half) / half if abs(half) > 1e-8 else 1.0 - half * half / 6.0)
        heading = self._phi + half
        self.x += chord * math.cos(heading)
        self.y += chord * math.sin(heading)
        self._x_v, self._phi = x_v, phi
        return self.x, self.y

    def update_gps(self, x: float, y: float) -> tuple[float, float]:
        """Correct toward a GPS fix (x, y) [m]; returns (x̂, ŷ).

        Non-finite fixes and fixes farther than ``max_gps_innovation`` are rejected
        (counted in :attr:`rejected_fixes`) and leave the estimate unchanged.
        """
        dx, dy = x - self.x, y - self.y
        if not math.isfinite(dx + dy) or math.hypot(dx, dy) > self.config.max_gps_innovation:
            self.rejected_fixes += 1
            return self.x, self.y
        k = self.config.gps_blend_gain
        self.x += k * dx
        self.y += k * dy
        self.accepted_fixes += 1
        return self.x, self.y


def _check_finite(where: str, **values: float) -> None:
    bad = [f'{k}={v!r}' for k, v in values.items() if not math.isfinite(v)]
    if bad:
        raise ValueError(f'PlanarPositionEstimator.{where}: non-finite input {", ".join(bad)}')
