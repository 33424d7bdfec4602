"""Time scaling of a reference: the same path, slowed to within speed and yaw-rate limits.

The re-timing tables of one path and its limits are shared within a thread (a small LRU
cache of :class:`RetimingTables`), so that every run of a campaign in one worker re-times
the path once.
"""

from __future__ import annotations

import collections
import math
import threading
from typing import Hashable

from .integration import rk4_step
from .retiming import (hermite_progress, interpolated_rate, interpolated_sigma, raw_rate,
                       retimed_speed, retimed_state, speeding_up)
from .reference_state import Reference, ReferenceState


class TimeScaled(Reference):
    r"""A reference run along the same path with a progress s(t) within the limits.

    The progress slows where the path's speed or yaw rate would exceed the limits (time
    scaling, Hollerbach 1984).

    The base reference p(s) is re-timed by ṡ = σ(s), with

    .. math:: \sigma_0(s) = \min\Big(1, \frac{\upsilon_{max}}{\upsilon_r(s)},
        \frac{\omega_{max}}{|\omega_r(s)|}\Big), \qquad
        \sigma(s) = \min_u \big(\sigma_0(u) + k |u - s|\big)

    so that υ(t) = υ_r(s) σ(s) ≤ υmax and |ω(t)| = |ω_r(s)| σ(s) ≤ ωmax: the vehicle is
    asked to stay on the same curve, more slowly where it bends hard, instead of
    chasing a point it cannot keep up with (the paper's trifolium needs 0.70 rad/s at
    its petal tips against ωmax = 0.3). The envelope σ ≤ σ0 with |dσ/ds| ≤ k starts to
    slow down before a sharp bend and speeds up gradually after it: where σ0 jumps (a
    waypoint fillet's curvature step) the speed would otherwise jump too. The pose is
    the base's at s(t); the rates are υ_r σ, ω_r σ and ω̇ = σ (ω̇_r σ + ω_r dσ/ds).

    σ depends on the path only, so s(t) is computed once, independent of the vehicle:
    the reference stays a pure function of time (the reference node publishes it
    unchanged). σ0 is tabulated every ``step`` of s and the envelope taken on that grid
    (σ linear between nodes, and never above σ0 at the sampled s); s(t) is integrated by
    RK4 on a grid of ``step`` in t and interpolated by cubic Hermite (s and ṡ known at
    the nodes). Both tables are extended on demand, always from the start, so the
    values do not depend on the order of the queries; :func:`.references.make_reference` therefore
    lets the time-scaled references of one configuration share them within a thread
    (every run of a campaign in one process re-times the same path once).

    Parameters
    ----------
    base : the reference whose path is followed.
    max_speed, max_yaw_rate : limits [m/s], [rad/s] of the re-timed reference, > 0.
    rate_limit : k [1/s], the largest |dσ/ds|, > 0.
    step : grid [s].
    speed_lead_time : T [s] ≥ 0. The speed υ of the sample at t is the re-timed speed at
        t + T (the pose, ω and ω̇ stay those at t): a speed feed-forward for a speed loop
        that lags the command by about T, so that the vehicle is at the bend's speed when
        it reaches the bend instead of T later (docs/history/mpc.md §8). 0: υ at t.
    speed_lead_time_accelerating : T_a [s], 0 ≤ T_a; used instead of T where the speed
        at t + T is larger than at t (None: T).
    tables : tables to use and extend, shared with the other TimeScaled of the same
        base, limits and step (:func:`.references.make_reference`); None: its own.
    """

    #: Largest step ahead of the sampled times that one call may integrate [s].
    MAX_EXTENSION = 3600.0
    #: Remembered re-timed states kept before the older ones are dropped (see sample),
    #: and at most kept after that (a 5 s lead at 1 kHz remembers 5000 states ahead).
    MEMO_MIN_SIZE = 512
    MEMO_MAX_SIZE = 8192
    #: [s] of sampled time, from the first sample's lead on, over which the memo must serve
    #: at least half of the samples, else it is given up: the loop's times do not repeat (a
    #: node in real time samples at sensor stamps, off any grid; its t = 0 while it waits
    #: to start repeats, but before the lead), and each sample would keep a state in vain.
    MEMO_TRIAL_TIME = 1.0

    def __init__(self, base: Reference, max_speed: float, max_yaw_rate: float,
                 rate_limit: float = 0.5, step: float = 0.01,
                 speed_lead_time: float = 0.0,
                 speed_lead_time_accelerating: float | None = None,
                 tables: 'RetimingTables | None' = None) -> None:
        if not (max_speed > 0.0 and max_yaw_rate > 0.0 and rate_limit > 0.0
                and step > 0.0):
            raise ValueError('TimeScaled: max_speed, max_yaw_rate, rate_limit and step '
                             'must be > 0')
        if speed_lead_time_accelerating is None:
            speed_lead_time_accelerating = speed_lead_time
        for label, value in (('speed_lead_time', speed_lead_time),
                             ('speed_lead_time_accelerating', speed_lead_time_accelerating)):
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f'TimeScaled: {label} must be finite and >= 0, got {value!r}')
        self.speed_lead_time = float(speed_lead_time)
        self.speed_lead_time_accelerating = float(speed_lead_time_accelerating)
        self._lead_max = max(self.speed_lead_time, self.speed_lead_time_accelerating)
        self.base = base
        self.max_speed = float(max_speed)
        self.max_yaw_rate = float(max_yaw_rate)
        self.rate_limit = float(rate_limit)
        self.step = float(step)
        # Envelope half-width in grid nodes: beyond 1/k the cone exceeds σ0 ≤ 1.
        self._window = int(math.ceil(1.0 / (self.rate_limit * self.step)))
        self._tables = tables = tables if tables is not None else RetimingTables()
        self._raw = tables.raw            # σ0 at s = i·step
        self._sigma = tables.sigma        # σ at s = i·step
        self._s = tables.s                # s at t = n·step
        self._rate = tables.rate          # σ(s) at those nodes
        with tables.lock:
            if not self._s:
                self._rate.append(self.rate_at(0.0))
                self._s.append(0.0)
        #: t -> _timed(t), see sample; None once given up (MEMO_TRIAL_TIME).
        self._memo: dict[float, ReferenceState] | None = {}
        self._memo_limit = self.MEMO_MIN_SIZE
        #: The memo's trial: [from, until] (sampled times [s]), samples, hits; None once
        #: decided (see MEMO_TRIAL_TIME).
        self._memo_trial: list | None = None
        self._memo_kept = False
        #: The compiled sample (retiming_kernel.sample) and the base's parameters as an
        #: array, once :meth:`use_compiled` has checked them; None: interpreted.
        self._kernel = None
        self._kernel_parameters = None

    def _raw_rate(self, v: float, omega: float) -> float:
        """σ0 for the base's speed ``v`` and yaw rate ``omega``."""
        return raw_rate(v, omega, self.max_speed, self.max_yaw_rate)

    def _extend_sigma(self, index: int) -> None:
        """Tabulate σ up to grid node ``index`` (σ0 up to ``index`` + window)."""
        if len(self._sigma) > index:
            return
        import numpy as np
        w, h = self._window, self.step
        with self._tables.lock:
            while len(self._sigma) <= index:
                start = len(self._sigma)
                stop = start + 2048
                while len(self._raw) < stop + w + 1:
                    self._raw.append(self._raw_rate(
                        *self.base.speed_and_yaw_rate(len(self._raw) * h)))
                raw = np.asarray(self._raw)
                env = raw[start:stop].copy()
                for d in range(1, w + 1):
                    cone = self.rate_limit * d * h
                    env = np.minimum(env, raw[start + d:stop + d] + cone)
                    lo = max(0, start - d)
                    shifted = raw[lo:stop - d]
                    if len(shifted) < stop - start:   # before s = 0: no constraint
                        shifted = np.concatenate([np.full(stop - start - len(shifted),
                                                          np.inf), shifted])
                    env = np.minimum(env, shifted + cone)
                self._sigma.extend(float(v) for v in env)

    def _sigma_and_slope(self, s: float) -> tuple[float, float]:
        """σ(s) (linear between grid nodes) and dσ/ds; s < 0 takes σ(0)."""
        i = int(s / self.step) if s > 0.0 else 0
        if i + 1 >= len(self._sigma):   # (tested here: a call per sample costs more than the test)
            self._extend_sigma(i + 1)
        return interpolated_sigma(s, self.step, self._sigma)

    def rate_at(self, s: float) -> float:
        """σ(s) = ds/dt ∈ (0, 1] (linear between the grid nodes).

        The σ of :meth:`_sigma_and_slope`, without the slope.
        """
        i = int(s / self.step) if s > 0.0 else 0
        if i + 1 >= len(self._sigma):
            self._extend_sigma(i + 1)
        return interpolated_rate(s, self.step, self._sigma)

    def _rate_of_progress(self, _t: float, s: float) -> float:
        """ṡ = σ(s), the right-hand side whose solution is s(t)."""
        return self.rate_at(s)

    def _extend(self, n: int) -> None:
        s_list, r_list, h = self._s, self._rate, self.step
        rate = self._rate_of_progress
        with self._tables.lock:
            while len(s_list) <= n:
                # ṡ = σ(s); σ(s) at the last node is in the table already.
                s_next = rk4_step(rate, 0.0, s_list[-1], h, k1=r_list[-1])
                # σ(s) first: readers check the length of s (lock-free).
                r_list.append(self.rate_at(s_next))
                s_list.append(s_next)
        if len(s_list) > RetimingTables.MAX_SHARED_NODES:
            _unshare(self._tables)

    def progress(self, t: float) -> float:
        """s(t) [s of the base reference]; s = σ(0) t before t = 0.

        Raises ValueError for a time more than ``MAX_EXTENSION`` s beyond the times
        sampled so far: s(t) is integrated from t = 0, so a jump far ahead (a clock
        jump, not a run) would take minutes.
        """
        if not math.isfinite(t):
            raise ValueError(f'TimeScaled: time must be finite, got {t!r}')
        if t > 0.0:
            n = int(t / self.step)
            if n + 1 >= len(self._s):   # beyond the table (else t < the last node)
                self._extend_to(t, n + 1)
        return hermite_progress(t, self.step, self._s, self._rate)

    def _extend_to(self, t: float, n: int) -> None:
        """Extend s(t) to node ``n`` (for time ``t``), unless t is absurdly far ahead."""
        known = (len(self._s) - 1) * self.step
        if t > known + self.MAX_EXTENSION:
            raise ValueError(f'TimeScaled: t = {t:g} s is more than '
                             f'{self.MAX_EXTENSION:g} s beyond the times sampled so far '
                             f'({known:g} s); the time-scaled reference is integrated '
                             'from t = 0')
        self._extend(n)

    def _speed_at(self, t: float) -> float:
        """Re-timed speed υ_r(s) σ(s) at s = s(t): ``sample(t).v`` without the lead."""
        s = self.progress(t)
        v, omega = self.base.speed_and_yaw_rate(s)
        return retimed_speed(v, omega, self.rate_at(s), self.max_speed, self.max_yaw_rate)

    def _timed(self, t: float) -> ReferenceState:
        """Return the re-timed state at t, without the speed lead.

        The base's pose at s(t), υ_r σ, ω_r σ and σ (ω̇_r σ + ω_r dσ/ds).
        """
        s = self.progress(t)
        sigma, d_sigma = self._sigma_and_slope(s)
        return ReferenceState(*retimed_state(*self.base.sample(s), sigma, d_sigma,
                                             self.max_speed, self.max_yaw_rate))

    def sample(self, t: float) -> ReferenceState:
        if self.speed_lead_time <= 0.0:
            # The kernel with no lead at all gives the re-timed state itself (its υ is
            # _speed_at's, the same float), whatever the accelerating lead.
            if self._kernel is not None and self._covered(t):
                return self._compiled_sample(t, 0.0, 0.0)
            return self._timed(t)
        # With a speed lead, the re-timed states are remembered by their time (the float):
        # a loop sampling every h asks at t + T for a time it samples again later (the
        # runner's t_k + 0.75 is t_{k+150} to the bit at 98 % of the ticks, t_k + 0.6 is
        # the t_j + 0.75 of a tick 30 earlier at 70 %), so most states are computed once.
        memo = self._memo
        if memo is None:
            return self._sample_unremembered(t)
        state = memo.get(t)
        if not self._memo_kept and self._memo_given_up(t, state is not None):
            return self._sample_unremembered(t)
        if state is None:
            state = memo[t] = self._timed(t)
        t_lead = t + self.speed_lead_time
        ahead = memo.get(t_lead)
        if ahead is None:
            ahead = memo[t_lead] = self._timed(t_lead)
        v_ahead = ahead.v
        if self._speeding_up(v_ahead, state.v):
            # The (shorter) lead of the accelerations, the speed only if not remembered.
            lead_up = self.speed_lead_time_accelerating
            ahead = memo.get(t + lead_up)
            v_ahead = ahead.v if ahead is not None else self._speed_at(t + lead_up)
        if len(memo) > self._memo_limit:
            # Forget the states before t (a loop runs forward), amortised O(1); all of
            # them if that leaves too many (queries running backwards, say).
            memo = {time: kept for time, kept in memo.items() if time >= t}
            self._memo = memo if len(memo) <= self.MEMO_MAX_SIZE else {}
            self._memo_limit = max(self.MEMO_MIN_SIZE, 2 * len(self._memo))
        return ReferenceState(state.x, state.y, state.phi, v_ahead, state.omega,
                              state.omega_dot)

    def _memo_given_up(self, t: float, hit: bool) -> bool:
        """Count the sample of ``t`` in the memo's trial; whether the memo is given up now."""
        trial = self._memo_trial
        if trial is None:
            start = t + self.speed_lead_time
            trial = self._memo_trial = [start, start + self.MEMO_TRIAL_TIME, 0, 0]
        if t < trial[0]:
            return False
        if t <= trial[1]:
            trial[2] += 1
            trial[3] += hit
            return False
        self._memo_kept = 2 * trial[3] >= trial[2]
        self._memo_trial = None
        if self._memo_kept:
            return False
        self._memo = None
        return True

    @property
    def base_kernel_kind(self) -> int:
        """The base curve's kind for the compiled kernel (-1: none, e.g. a waypoint path)."""
        return getattr(self.base, 'KERNEL_KIND', -1)

    @property
    def compiled(self) -> bool:
        """Whether the compiled kernel samples (:meth:`use_compiled`)."""
        return self._kernel is not None

    def use_compiled(self) -> str:
        """Sample with the compiled kernel (retiming_kernel.py) instead of the memo.

        Only for a closed-form base (``KERNEL_KIND``). The kernel is checked against the
        interpreted sample at times over the first seconds first. Return '' when it is used,
        else why not. The samples are the same floats either way; the kernel costs less than
        the memo on a time grid (the runner, lockstep) and is the only fast way at sensor
        stamps (real time), where the memo would only run its trial in vain.
        """
        kind = self.base_kernel_kind
        if kind < 0:
            return f'no compiled form of a {type(self.base).__name__} base'
        from .compiled import load_compiled, RETIMING_KERNEL
        import numpy as np
        module = load_compiled(RETIMING_KERNEL)
        parameters = np.array(self.base.parameters, dtype=float)
        difference = self._kernel_difference(module.sample, kind, parameters)
        if difference:
            module.refresh()   # numba's cache stale (a formula changed since it was filled)
            difference = self._kernel_difference(module.sample, kind, parameters)
        if difference:
            return f'the compiled sample differs from the interpreted one {difference}'
        self._kernel, self._kernel_parameters = module.sample, parameters
        self._memo = None
        return ''

    def _kernel_difference(self, kernel, kind: int, parameters) -> str:
        """Where ``kernel`` differs from the interpreted sample over the first seconds ('')."""
        for k in range(_KERNEL_CHECKS):
            t = k * _KERNEL_CHECK_SPACING - 0.5
            self._cover(t)
            arrays = self._tables.arrays
            compiled = kernel(t, self.speed_lead_time, self.speed_lead_time_accelerating,
                              self.step, arrays.s, arrays.rate, arrays.sigma, self.max_speed,
                              self.max_yaw_rate, kind, parameters)
            interpreted = tuple(self._interpreted_sample(t))
            if tuple(compiled) != interpreted:
                return f'at t = {t!r}: {tuple(compiled)} != {interpreted}'
        return ''

    def _cover(self, t: float) -> bool:
        """Make the tables' arrays reach t and t + either lead; False if t is not finite.

        Or if it is too far ahead (:meth:`progress` raises then). The tables are extended
        ``_KERNEL_AHEAD`` nodes beyond the need, so that they grow in chunks.
        """
        t_max = t + self._lead_max
        if not math.isfinite(t_max):
            return False
        arrays = self._tables.arrays
        if arrays is None:
            arrays = self._tables.arrays = _NodeArrays()
        elif t_max < arrays.covered_until:
            return True
        h = self.step
        n = int(max(t_max, 0.0) / h) + _KERNEL_AHEAD
        if n + 1 >= len(self._s):
            try:
                self._extend_to(t_max, n + 1)
            except ValueError:
                return False    # too far ahead: the interpreted sample raises it
        # σ one node beyond the last s: Hermite between two nodes may overshoot s a little.
        self._extend_sigma(int(self._s[-1] / h) + 2)
        arrays.update(self._tables)
        arrays.covered_until = (len(self._s) - 2) * h
        return True

    def _speeding_up(self, v_ahead: float, v: float) -> bool:
        """Whether the lead of the accelerations replaces the speed lead's υ ``v_ahead``."""
        return speeding_up(v_ahead, v, self.speed_lead_time, self.speed_lead_time_accelerating)

    def _sample_unremembered(self, t: float) -> ReferenceState:
        """:meth:`sample` without the memo: the lead's speeds alone, the same floats."""
        if self._kernel is not None and self._covered(t):
            return self._compiled_sample(t, self.speed_lead_time,
                                         self.speed_lead_time_accelerating)
        return self._interpreted_sample(t)

    def _covered(self, t: float) -> bool:
        """Whether the kernel may sample at ``t`` (the tables extended if needed)."""
        # (-inf < t: −inf and NaN go to _cover, which refuses them: interpreted, they raise.)
        return (_NEGATIVE_INFINITY < t
                and t + self._lead_max < self._tables.arrays.covered_until
                or self._cover(t))

    def _compiled_sample(self, t: float, lead: float, lead_accelerating: float) -> ReferenceState:
        arrays = self._tables.arrays
        return ReferenceState(*self._kernel(
            t, lead, lead_accelerating, self.step, arrays.s, arrays.rate, arrays.sigma,
            self.max_speed, self.max_yaw_rate, self.base.KERNEL_KIND, self._kernel_parameters))

    def _interpreted_sample(self, t: float) -> ReferenceState:
        # retiming_kernel.sample is this method compiled (tests check that they agree to the
        # bit); a change here is a change there.
        state = self._timed(t)
        v_ahead = self._speed_at(t + self.speed_lead_time)
        if self._speeding_up(v_ahead, state.v):
            v_ahead = self._speed_at(t + self.speed_lead_time_accelerating)
        return ReferenceState(state.x, state.y, state.phi, v_ahead, state.omega,
                              state.omega_dot)


class RetimingTables:
    """The tables of a :class:`TimeScaled`.

    σ0 and σ every ``step`` of s, s and σ(s) every ``step`` of t. They are a function of the
    base path, the limits and the step only (extended on demand, always from the start), so
    TimeScaled objects of the same configuration can share them
    (:func:`.references.make_reference`). They are only appended to, under ``lock``, and
    every value is final once written, so readers need no lock.
    """

    #: Tables longer than this many nodes (1000 s of a 10 ms step; about 13 MB for the
    #: four) are no longer offered for sharing, so that a process does not keep the
    #: tables of a long run after it.
    MAX_SHARED_NODES = 100_000

    __slots__ = ('raw', 'sigma', 's', 'rate', 'lock', 'arrays')

    def __init__(self) -> None:
        self.raw: list[float] = []
        self.sigma: list[float] = []
        self.s: list[float] = []
        self.rate: list[float] = []
        self.lock = threading.RLock()   # reentrant: extending s extends σ
        #: The nodes as arrays for the compiled kernel (made by its first use).
        self.arrays: _NodeArrays | None = None


class _NodeArrays:
    """The nodes of s, σ(s) and σ as numpy arrays, for the compiled kernel.

    Copied from the tables' lists as they grow (only the new nodes; the buffers double).
    ``s``, ``rate`` and ``sigma`` are views of the nodes known; ``covered_until`` [s] is
    the last time the kernel may sample (``TimeScaled._cover``).
    """

    __slots__ = ('_empty', '_buffers', 's', 'rate', 'sigma', 'covered_until')

    def __init__(self) -> None:
        import numpy as np   # only where the kernel is used
        self._empty = np.empty
        self._buffers = [np.empty(0), np.empty(0), np.empty(0)]
        self.s = self.rate = self.sigma = self._buffers[0]
        self.covered_until = -math.inf

    def update(self, tables: 'RetimingTables') -> None:
        views = []
        for i, (values, view) in enumerate(((tables.s, self.s), (tables.rate, self.rate),
                                            (tables.sigma, self.sigma))):
            known, size = len(view), len(values)
            buffer = self._buffers[i]
            if size > len(buffer):
                grown = self._empty(max(size, 2 * len(buffer), 1024))
                grown[:known] = buffer[:known]
                buffer = self._buffers[i] = grown
            buffer[known:size] = values[known:size]
            views.append(buffer[:size])
        self.s, self.rate, self.sigma = views


_NEGATIVE_INFINITY = -math.inf
#: Extra s nodes the tables are extended by for the compiled kernel, so they grow in chunks.
_KERNEL_AHEAD = 25
#: Times at which :meth:`TimeScaled.use_compiled` compares the kernel with the interpreted
#: sample, spaced off the grid, from t = -0.5 s.
_KERNEL_CHECKS, _KERNEL_CHECK_SPACING = 24, 0.2513

#: Per thread: configuration key -> RetimingTables, the most recently used last.
_shared = threading.local()
#: Configurations whose tables a thread keeps for sharing.
MAX_SHARED_CONFIGURATIONS = 4


def shared_tables(key: Hashable) -> RetimingTables:
    """Return the tables this thread shares among the TimeScaled of configuration ``key``.

    New ones the first time; a thread keeps those of its last
    ``MAX_SHARED_CONFIGURATIONS`` configurations.
    """
    cache = getattr(_shared, 'tables', None)
    if cache is None:
        cache = _shared.tables = collections.OrderedDict()
    tables = cache.pop(key, None)
    if tables is None:
        tables = RetimingTables()
    cache[key] = tables
    while len(cache) > MAX_SHARED_CONFIGURATIONS:
        cache.popitem(last=False)
    return tables


def _unshare(tables: RetimingTables) -> None:
    """Stop offering ``tables`` for sharing (its users keep it)."""
    cache = getattr(_shared, 'tables', None)
    if cache:
        for key, value in list(cache.items()):
            if value is tables:
                del cache[key]
