"""Input synchronisation of the controller nodes: exact-time sets and latest values.

Pure Python (no rclpy), so it is tested without ROS.

Lockstep (deterministic simulation)
-----------------------------------
The plant publishes every sensor sample stamped with its simulation time t_k and waits
for the wheel torques stamped t_k before it integrates to t_{k+1}. A node computes its
output for t_k only when every input it needs *for t_k* has arrived, whatever the order
in which the messages arrive: :class:`ExactTimeSync` keys the inputs by their stamp in
integer nanoseconds and calls back once per complete set, in increasing stamp order.

- Which inputs a stamp needs may depend on the stamp (``required``): the ESO needs a GPS
  fix only at GPS ticks, the mixer a drive torque only at MPC ticks.
- An optional ``gate`` holds a complete set back until an outside condition holds (the
  ESO waits for the wheel torques of the previous period); :meth:`ExactTimeSync.drain`
  re-tries after that condition may have changed.
- Sets are emitted in increasing stamp order. When a set completes, older incomplete
  sets can no longer be used (a node never goes back in time) and are dropped
  ("superseded"); inputs stamped at or before the last emitted set are dropped ("stale").
- The buffer is bounded (``max_pending`` stamps): a new stamp beyond it evicts the
  oldest pending one ("evicted"). Lockstep has one stamp in flight, so the bound only
  matters when an input stream is lost.

Real time
---------
:class:`LatestSync` keeps the latest value of every input and calls back when every
``trigger`` input has a value newer than at the previous call and every ``required``
input has arrived at least once: no waiting, the newest data wins.

Periodic ticks
--------------
:func:`is_decimated_tick` decides whether a stamp is an MPC (or GPS) tick exactly as the
in-process runner does: k = round(t / h) with h the base (control) period, and the tick
is every ``every``-th k (``every = round(T / h)``, :func:`decimation`). The grid starts
at t = 0, the start of simulated time.
"""

from __future__ import annotations

import collections
from typing import Any, Callable, Collection, Iterable, Mapping

SetCallback = Callable[[int, Mapping[str, Any]], None]

#: Tolerance of :func:`on_grid` [s]: far below any control period (>= 100 us), far above
#: the rounding of a float time converted to integer nanoseconds.
GRID_TOLERANCE = 1e-6


def tick_index(stamp_ns: int, period: float) -> int:
    """Index k of the sample at ``stamp_ns`` [ns] on a grid of ``period`` [s]: round(t/h)."""
    return round(stamp_ns / (period * 1e9))


def decimation(period: float, base_period: float) -> int:
    """Return the base periods per ``period``.

    At least 1, as the runner's ``round(T * control_rate)``.
    """
    return max(1, round(period / base_period))


def is_decimated_tick(stamp_ns: int, base_period: float, every: int) -> bool:
    """Return True if ``stamp_ns`` is every ``every``-th sample of the ``base_period`` [s] grid."""
    return tick_index(stamp_ns, base_period) % every == 0


def on_grid(stamp_ns: int, period: float, tolerance: float = GRID_TOLERANCE) -> bool:
    """Whether ``stamp_ns`` [ns] lies within ``tolerance`` [s] of a multiple of ``period`` [s]."""
    k = tick_index(stamp_ns, period)
    return abs(stamp_ns - k * period * 1e9) <= tolerance * 1e9


class ExactTimeSync:
    """Complete sets of inputs with equal stamps, emitted in increasing stamp order.

    Parameters
    ----------
    names : the inputs, e.g. ``('joint_states', 'imu', 'gps')``.
    callback : ``callback(stamp_ns, {name: value})`` for each complete set.
    required : ``required(stamp_ns)`` -> the names that stamp needs; default: all.
    gate : ``gate(stamp_ns)`` -> whether a complete set may be emitted now; default: always.
    max_pending : most stamps buffered at once (>= 1).
    """

    def __init__(self, names: Iterable[str], callback: SetCallback, *,
                 required: Callable[[int], Collection[str]] | None = None,
                 gate: Callable[[int], bool] | None = None, max_pending: int = 32) -> None:
        self.names = tuple(names)
        if not self.names:
            raise ValueError('ExactTimeSync: need at least one input name')
        if max_pending < 1:
            raise ValueError(f'ExactTimeSync: max_pending must be >= 1, got {max_pending}')
        self._callback = callback
        self._required = required if required is not None else (lambda _stamp: self.names)
        self._gate = gate
        self.max_pending = int(max_pending)
        self._pending: dict[int, dict[str, Any]] = {}
        #: Stamp [ns] of the last emitted set, None before the first.
        self.last_emitted: int | None = None
        #: Inputs dropped, by reason: stale, duplicate, superseded, evicted.
        self.dropped: collections.Counter = collections.Counter()
        self.emitted = 0

    @property
    def pending(self) -> dict[int, tuple[str, ...]]:
        """Buffered stamps [ns] and the inputs each has so far (for diagnostics)."""
        return {s: tuple(sorted(v)) for s, v in sorted(self._pending.items())}

    def missing(self, stamp_ns: int) -> tuple[str, ...]:
        """Return the inputs ``stamp_ns`` still waits for (all required ones if not buffered)."""
        have = self._pending.get(stamp_ns, {})
        needed = set(self._required(stamp_ns))
        return tuple(n for n in self.names if n in needed and n not in have)

    def add(self, name: str, stamp_ns: int, value: Any) -> bool:
        """Buffer one input; emit every set this completes. Returns whether one was emitted."""
        if name not in self.names:
            raise KeyError(f'ExactTimeSync: unknown input {name!r}; inputs are {self.names}')
        stamp_ns = int(stamp_ns)
        if self.last_emitted is not None and stamp_ns <= self.last_emitted:
            self.dropped['stale'] += 1
            return False
        slot = self._pending.get(stamp_ns)
        if slot is None:
            if len(self._pending) >= self.max_pending:
                oldest = min(self._pending)
                del self._pending[oldest]
                self.dropped['evicted'] += 1
            slot = self._pending[stamp_ns] = {}
        elif name in slot:
            self.dropped['duplicate'] += 1  # The newer message replaces the older one.
        slot[name] = value
        return self.drain()

    def drain(self) -> bool:
        """Emit every complete (and gated-open) set in stamp order; True if any was."""
        emitted = False
        progress = True
        while progress and self._pending:
            progress = False
            for stamp in sorted(self._pending):
                slot = self._pending[stamp]
                if not all(n in slot for n in self._required(stamp)):
                    continue
                if self._gate is not None and not self._gate(stamp):
                    continue
                for older in [s for s in self._pending if s < stamp]:
                    del self._pending[older]
                    self.dropped['superseded'] += 1
                del self._pending[stamp]
                self.last_emitted = stamp
                self.emitted += 1
                self._callback(stamp, slot)
                emitted = progress = True
                break
        return emitted

    def discard(self, stamp_ns: int) -> None:
        """Forget the inputs buffered for ``stamp_ns`` (a stamp answered without its set)."""
        self._pending.pop(int(stamp_ns), None)

    def reset(self) -> None:
        """Forget every buffered input and the last emitted stamp."""
        self._pending.clear()
        self.last_emitted = None


class LatestSync:
    """The latest value of each input; calls back when the trigger inputs are all fresh.

    Parameters
    ----------
    names : the inputs.
    callback : ``callback(stamp_ns, {name: value})`` with the latest value of every input
        received so far; ``stamp_ns`` is the newest stamp among the trigger inputs. Called
        only on the arrival of a trigger input.
    triggers : inputs that must all be new since the previous call (one of them: call on
        each arrival of that input; the ESO uses two, so it updates once per sensor period
        whichever of the IMU and encoder messages comes last).
    required : inputs that must have arrived at least once before any call.
    max_skew_ns : largest difference [ns] between the trigger inputs' stamps in one call
        (None: any). A trigger older than the newest by more waits for its next message
        (counted ``skewed``): after a stall the queued messages of two streams are taken
        one stream first, and pairing the oldest queued encoder sample with the newest IMU
        sample gave the observer a position 100 ms old at a new time (the speed estimate
        fell to 0, then peaked at 5× the speed; the MPC stepped by its whole Δτ).
    """

    def __init__(self, names: Iterable[str], callback: SetCallback, *,
                 triggers: Iterable[str], required: Iterable[str] = (),
                 max_skew_ns: int | None = None) -> None:
        self.names = tuple(names)
        self.triggers = tuple(triggers)
        self.required = tuple(required)
        unknown = [n for n in (*self.triggers, *self.required) if n not in self.names]
        if unknown or not self.triggers:
            raise ValueError(f'LatestSync: triggers {self.triggers} and required '
                             f'{self.required} must be non-empty/among {self.names}')
        self._callback = callback
        self.max_skew_ns = max_skew_ns
        self._values: dict[str, Any] = {}
        #: Stamp [ns] of the latest value of each input.
        self.stamps: dict[str, int] = {}
        self._fresh: set[str] = set()
        self._have_required = not self.required
        self.dropped: collections.Counter = collections.Counter()
        self.emitted = 0

    def add(self, name: str, stamp_ns: int, value: Any) -> bool:
        """Store the newest value of ``name``; call back if the triggers are all fresh."""
        if name not in self.names:
            raise KeyError(f'LatestSync: unknown input {name!r}; inputs are {self.names}')
        stamp_ns = int(stamp_ns)
        previous = self.stamps.get(name)
        if previous is not None and stamp_ns < previous:
            self.dropped['stale'] += 1  # Out of order: keep the newer value.
            return False
        self._values[name] = value
        self.stamps[name] = stamp_ns
        if name not in self.triggers:
            return False
        fresh = self._fresh
        fresh.add(name)
        if len(fresh) < len(self.triggers):
            return False
        if not self._have_required:   # values are never removed: checked until true once
            if not all(n in self._values for n in self.required):
                return False
            self._have_required = True
        if len(self.triggers) == 1:
            newest = stamp_ns    # this input is the trigger, stored just above
        else:
            newest = max(self.stamps[n] for n in self.triggers)
            if self.max_skew_ns is not None:
                behind = [n for n in self.triggers
                          if newest - self.stamps[n] > self.max_skew_ns]
                if behind:
                    fresh.difference_update(behind)
                    self.dropped['skewed'] += 1
                    return False
        fresh.clear()
        self.emitted += 1
        self._callback(newest, dict(self._values))
        return True

    def latest(self, name: str) -> Any:
        """Latest value of ``name`` (None if none yet)."""
        return self._values.get(name)
