"""The gyro estimator's sample, compiled with numba (``cache=True``).

:meth:`StateEstimator.update <.state_estimation.StateEstimator.update>` with the gyro
estimator (the default) runs, per sensor sample, the yaw unwrapping, the wheel odometry,
the slip monitor, the three channels of the observer and the dead reckoning: some twenty
Python calls over a hundred attributes, the largest part of the ESO node's tick. Compiled,
they are one call on the objects' own state arrays (``ChannelEstimate._s``,
``SlipMonitor.state``, ``PlanarPositionEstimator.state``), so the interpreter and the kernel
share one state and either may take the next sample.

Nothing is written twice: numba compiles the module functions of ``eso``, ``rate_aided``,
``slip``, ``position`` and ``angles`` themselves (``register_jitable``), and :func:`step`
composes them in the order of ``StateEstimator.update`` and ``WipStateObserver.update``
(tests check the two agree to the bit). The kernel takes only the steady sample: the
observer started and seeded, a nominal period, no GPS fix, and every input and state value
below :data:`MODERATE` in magnitude, so that nothing it computes (sums, and products of at
most three such values with the model's constants) can overflow where the interpreter would
have raised midway; anything else returns :data:`NOT_TAKEN` before changing a thing, and the
interpreter takes the sample (and raises what it raises).
The input gains of eq. (1) (``model.input_gains_of``) take their exponent 2 from the
constants: CPython's ``x ** 2`` calls the C library's ``pow``, which LLVM would turn into
``x * x`` for a constant exponent, a last bit apart now and then.

numba's cache knows only this file's date, not theirs: :func:`warm_up` compiles afresh when
a digest of the sources differs from the one kept beside the cache, and
:meth:`StateEstimator.use_compiled <.state_estimation.StateEstimator.use_compiled>`
compares the kernel with the interpreter before using it.
"""

from __future__ import annotations

import math

import numba
import numpy as np
from numba.extending import register_jitable

from . import angles, compiled, eso, model, numba_math, position, rate_aided, slip

#: The interpreter's functions the kernel compiles; their files make its sources' digest.
COMPILED_FUNCTIONS = (angles.wrap_to_pi, angles.unwrap_next, eso.eso_step,
                      model.input_gains_of, rate_aided.rate_aided_step, slip.slip_step,
                      slip._measured, slip._keep_last, slip._detect, slip._release,
                      position.odometry_step)
for _function in COMPILED_FUNCTIONS:
    register_jitable(_function)
#: Modules whose code (math.fmod and math.remainder in compiled code) the kernel compiles
#: too: in the digest.
ALSO_COMPILED = (numba_math,)


#: What :func:`step` did: took the sample, or left it untouched to the interpreter.
TAKEN, NOT_TAKEN = 0, 1
#: The largest magnitude of an input or a state value of a sample the kernel takes.
MODERATE = 1e100

#: The slots of the constants array (:func:`constants`).
(PERIOD, PERIOD_TOLERANCE, WHEEL_RADIUS, RELATIVE_TO_BODY, HAS_SLIP, YAW_SCALE,
 XV_PITCH_CORRECTION, YAW_L1, YAW_L2, YAW_M1, YAW_M2, TILT_L1, TILT_L2, TILT_M1,
 TILT_M2, BODY_MASS, COM_HEIGHT, TRACK_WIDTH, EFFECTIVE_MASS, PITCH_INERTIA,
 YAW_INERTIA, SQUARE) = range(22)


def constants(observer, relative_to_body: bool, has_slip: bool) -> np.ndarray:
    """Return the kernel's constants of a gyro ``WipStateObserver`` (the slots above)."""
    p = observer.params
    return np.array([observer.config.sample_period, eso.PERIOD_TOLERANCE, p.wheel_radius,
                     float(relative_to_body), float(has_slip), observer._yaw_scale,
                     observer._xv_pitch_correction, *observer.yaw._nominal_gains,
                     *observer.tilt._nominal_gains, p.body_mass, p.com_height,
                     p.track_width, p.effective_mass, p.pitch_inertia, p.yaw_inertia_total,
                     2.0], dtype=float)


@numba.njit(cache=True, nogil=True)
def _moderate(values) -> bool:
    """Whether every value is below :data:`MODERATE` in magnitude (not NaN)."""
    for value in values:
        if not abs(value) < MODERATE:
            return False
    return True


@numba.njit(cache=True, nogil=True)
def _steady(c, yaw, tilt, longitudinal, slip_state, position_state, inputs) -> bool:
    """Whether :func:`step` takes the sample (``inputs``: t first): see the module docstring."""
    if not (_moderate(inputs) and _moderate(yaw[:rate_aided.RATE_STARTED])
            and _moderate(tilt[:rate_aided.RATE_STARTED])
            and _moderate(longitudinal[:eso.UNSEEDED])
            and _moderate(slip_state[:slip.AGREE_SINCE]) and _moderate(slip_state[slip.OFFSET:])
            and _moderate(position_state)):
        return False
    t, period = inputs[0], c[PERIOD]
    tolerance = c[PERIOD_TOLERANCE] * period
    # The interpreter's nominal-period tests, each channel's own (RateAidedChannel.update,
    # ExtendedStateObserver.update); the x_v ESO started, its speed seeded.
    return not (yaw[rate_aided.RATE_STARTED] == 0.0 or tilt[rate_aided.RATE_STARTED] == 0.0
                or longitudinal[eso.UNSEEDED] != 0.0
                or not abs(t - yaw[eso.TIME] - period) <= tolerance
                or not abs(t - tilt[eso.TIME] - period) <= tolerance
                or not abs(t - longitudinal[eso.TIME] - period) <= tolerance)


#: What :func:`step` returns for a sample it leaves to the interpreter.
_LEFT = (NOT_TAKEN,) + (math.nan,) * 14
_ARRAY = numba.float64[::1]
#: One signature, compiled once: arguments of another type are converted (an int time) or
#: refused, never compiled anew in a control tick.
_SIGNATURE = numba.types.Tuple((numba.int64,) + (numba.float64,) * 14)(
    *(_ARRAY,) * 8, *(numba.float64,) * 11)


@numba.njit(_SIGNATURE, cache=True, nogil=True, boundscheck=True)
def step(c, yaw, tilt, longitudinal, nominal, slip_state, slip_constants, position_state,
         previous_yaw, previous_phi_meas, t, phi_left, phi_right, pitch, yaw_meas, tau_left,
         tau_right, pitch_rate, yaw_rate):
    """One steady sample of the gyro estimator, on the objects' state arrays in place.

    Return (what it did, yaw unwrapped, the observer's ϕ measurement, x_v after the slip
    monitor, x̂, ŷ, then the estimate's nine values: the channels' (x̂1, x̂2, f̂) of yaw,
    x_v and tilt). ``nominal``: the x_v ESO's matrices for the period.
    """
    if not _steady(c, yaw, tilt, longitudinal, slip_state, position_state,
                   np.array((t, phi_left, phi_right, pitch, yaw_meas, tau_left, tau_right,
                             pitch_rate, yaw_rate, previous_yaw, previous_phi_meas))):
        return _LEFT
    period = c[PERIOD]
    # StateEstimator.update: the yaw unwrapped, the wheel odometry, the slip monitor.
    yaw_unwrapped = angles.unwrap_next(previous_yaw, yaw_meas)
    r = c[WHEEL_RADIUS]
    mean = 0.5 * (phi_left + phi_right)
    if c[RELATIVE_TO_BODY] != 0.0:
        mean += pitch
    x_v = r * mean
    if c[HAS_SLIP] != 0.0:
        x_v = slip.slip_step(slip_state, slip_constants, t, r * phi_left, r * phi_right, x_v,
                             pitch, pitch_rate, yaw_rate, tau_left, tau_right)[0]
    tau_v, tau_omega = tau_left + tau_right, tau_right - tau_left
    # WipStateObserver.update, the gyro estimator: eq. (1)'s input gains at θ̂ of the start
    # of the period.
    g1, g2, g3 = model.input_gains_of(c[BODY_MASS], c[COM_HEIGHT], r, c[TRACK_WIDTH],
                                      c[EFFECTIVE_MASS], c[PITCH_INERTIA], c[YAW_INERTIA],
                                      tilt[eso.X1], c[SQUARE])
    phi_meas = yaw_unwrapped
    d = phi_meas - previous_phi_meas
    if d > math.pi or d < -math.pi:
        phi_meas -= 2.0 * math.pi * round(d / (2.0 * math.pi))
    rate_aided.rate_aided_step(yaw, t, period, phi_meas, yaw_rate,
                               c[YAW_SCALE] * g1 * tau_omega, c[YAW_L1], c[YAW_L2],
                               c[YAW_M1], c[YAW_M2])
    rate_aided.rate_aided_step(tilt, t, period, pitch, pitch_rate, g3 * tau_v, c[TILT_L1],
                               c[TILT_L2], c[TILT_M1], c[TILT_M2])
    xv_meas = x_v + c[XV_PITCH_CORRECTION] * (tilt[eso.X1] - pitch)
    eso.eso_step(longitudinal, t, xv_meas, g2 * tau_v, nominal)
    # StateEstimator._position without a fix: the odometry along ϕ̂.
    position.odometry_step(position_state, x_v, yaw[eso.X1])
    x, y = position_state[position.X], position_state[position.Y]
    return (TAKEN, yaw_unwrapped, phi_meas, x_v, x, y, yaw[eso.X1], yaw[eso.X2], yaw[eso.F],
            longitudinal[eso.X1], longitudinal[eso.X2], longitudinal[eso.F], tilt[eso.X1],
            tilt[eso.X2], tilt[eso.F])


def warm_up() -> None:
    """Load :func:`step` from numba's cache (or compile it).

    Compiled afresh if the sources it compiles changed since numba's cache was filled
    (:data:`SOURCES_STAMP` beside the cache holds their digest).
    """
    state = np.zeros(8)
    step(np.zeros(SQUARE + 1), state, state.copy(), state.copy(), np.zeros(18),
         np.zeros(slip.EVENTS + 1), np.ones(slip.LONGEST + 1), np.zeros(position.ROLLED + 1),
         0.0, 0.0, math.nan, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
    compiled.refresh_if_sources_changed(step.stats.cache_path, SOURCES_STAMP, sources_digest(),
                                        refresh)


#: The file beside numba's cache with the digest of the sources the kernel was compiled from.
SOURCES_STAMP = 'estimator_kernel.sources'


def sources_digest() -> str:
    """SHA-256 of the files whose functions the kernel compiles, and of this one."""
    return compiled.sources_digest(COMPILED_FUNCTIONS, __name__, ALSO_COMPILED)


def refresh() -> None:
    """Compile :func:`step` afresh, replacing numba's cache of it (stale, say)."""
    step.recompile()
