"""External disturbances τd1, τd2, τd3 of eq. (1) in [1]_, as sums of simple signals.

Three channels, each a tuple of components whose values add up:

========================  =====  =========  ==========================================
channel                   value  unit       enters eq. (1) as
========================  =====  =========  ==========================================
``yaw``                   d1     rad/s²     τd1, added to ω̇
``longitudinal``          d2     m/s²       τd2, added to υ̇
``tilt``                  d3     rad/s²     τd3, added to θ̈
========================  =====  =========  ==========================================

Component kinds (A = ``amplitude``, t0 = ``start_time``, all zero before t0):

- ``sine``: A sin(w (t − t0) + ``phase``), w = ``frequency`` [rad/s];
- ``pulse``: A for t0 ≤ t < t0 + ``width``, zero after;
- ``step``: A for t ≥ t0;
- ``noise``: ``std`` · n_k for t ≥ t0, n_k ~ N(0, 1) independent, held over the sample
  period k = ⌊(t − t0) / ``noise_period``⌋. The values depend only on the seed, the
  channel, the component's index and ``seed``, and on k, so they do not depend on the
  integrator step or on the order of the calls (reproducible, random access).

A component rejects parameters that its kind does not use (a non-default ``width`` on
a sine is a mistake in the scenario, not something to ignore).

Time edges (t0, t0 + width, noise sample boundaries) are taken with a tolerance of
:data:`EDGE_TOLERANCE` = 1 ns, so that a time computed as ``k * dt`` that lands a few
ulps before an edge counts as on it.

The default is the paper's Section V: d1 = sin(0.5 t) and a pulse of 10 m/s² at 30 s
on υ̇ (width 0.1 s, which the paper does not give; docs/paper.md §6).

References
----------
.. [1] Yue, An, Li, IEEE T-SMC: Systems, 2016 (see ``params.py``).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable, Mapping

import numpy as np

from wip_runtime import config as _config
from wip_runtime.config import ParamError, param

#: Channel names in the order of (d1, d2, d3).
CHANNELS = ('yaw', 'longitudinal', 'tilt')
#: Component kinds.
KINDS = ('sine', 'pulse', 'step', 'noise')
#: Fields each kind uses (``kind`` itself aside); any other field must keep its default.
KIND_FIELDS = {
    'sine': ('amplitude', 'frequency', 'phase', 'start_time'),
    'pulse': ('amplitude', 'start_time', 'width'),
    'step': ('amplitude', 'start_time'),
    'noise': ('std', 'noise_period', 'start_time', 'seed'),
}
#: Tolerance [s] on time edges, against floating-point time stamps (see module doc).
EDGE_TOLERANCE = 1e-9
#: Noise samples generated at once; block b has its own seed, for random access.
_NOISE_BLOCK = 4096

_CHANNEL_UNIT = 'rad/s^2 (yaw, tilt) or m/s^2 (longitudinal)'


@dataclasses.dataclass(frozen=True)
class DisturbanceComponent:
    """One signal of a disturbance channel (see the module docstring for the kinds)."""

    kind: str = param('sine', '1', 'signal shape', choices=KINDS)
    amplitude: float = param(0.0, _CHANNEL_UNIT, 'A of sine, pulse and step')
    frequency: float = param(0.0, 'rad/s', 'angular frequency of a sine', minimum=0.0)
    phase: float = param(0.0, 'rad', 'phase of a sine at start_time')
    start_time: float = param(0.0, 's', 'time the component starts (zero before)',
                              minimum=0.0)
    width: float = param(0.0, 's', 'duration of a pulse (> 0 for a pulse)', minimum=0.0)
    std: float = param(0.0, _CHANNEL_UNIT, 'standard deviation of noise', minimum=0.0)
    noise_period: float = param(0.01, 's', 'noise sample-and-hold period', minimum=0.0,
                                exclusive_minimum=True)
    seed: int = param(0, '1', 'extra seed of a noise component, combined with the run '
                      'seed, the channel and the index', minimum=0)

    def validate(self) -> None:
        """Reject an unknown kind, fields the kind does not use, a pulse without width."""
        if self.kind not in KINDS:
            raise ParamError(f'kind: {self.kind!r} is not one of {list(KINDS)}')
        used = KIND_FIELDS[self.kind]
        for f in dataclasses.fields(self):
            if f.name != 'kind' and f.name not in used and getattr(self, f.name) != f.default:
                raise ParamError(f'{f.name}: not used by kind {self.kind!r} '
                                  f'(it uses {list(used)})')
        if self.kind == 'pulse' and not self.width > 0.0:
            raise ParamError('width: a pulse needs width > 0')
        if self.kind == 'noise' and not self.noise_period > 0.0:
            raise ParamError('noise_period: must be > 0')


@dataclasses.dataclass(frozen=True)
class DisturbanceParams:
    """Components of the three disturbance channels; defaults = the paper's Section V."""

    yaw: tuple[DisturbanceComponent, ...] = param(
        (DisturbanceComponent(kind='sine', amplitude=1.0, frequency=0.5),),
        'rad/s^2', 'd1 = τd1 of eq. (1), added to the yaw acceleration ω̇; '
        'paper: sin(0.5 t)')
    longitudinal: tuple[DisturbanceComponent, ...] = param(
        (DisturbanceComponent(kind='pulse', amplitude=10.0, start_time=30.0, width=0.1),),
        'm/s^2', 'd2 = τd2 of eq. (1), added to the forward acceleration υ̇; '
        'paper: pulse of 10 at 30 s (width 0.1 s, not given in the paper)')
    tilt: tuple[DisturbanceComponent, ...] = param(
        (), 'rad/s^2', 'd3 = τd3 of eq. (1), added to the tilt acceleration θ̈; '
        'paper: none')

    def validate(self) -> None:
        """Check every component; the message names it, e.g. ``yaw[0].width: ...``."""
        for name, components in zip(CHANNELS, self.channels()):
            for i, component in enumerate(components):
                if not isinstance(component, DisturbanceComponent):
                    raise ParamError(f'{name}[{i}]: expected a DisturbanceComponent, '
                                      f'got {component!r}')
                try:
                    component.validate()
                except ParamError as err:
                    raise ParamError(f'{name}[{i}].{err}') from err

    def channels(self) -> tuple[tuple[DisturbanceComponent, ...], ...]:
        """Return the component tuples in the order (yaw, longitudinal, tilt) = (d1, d2, d3)."""
        return self.yaw, self.longitudinal, self.tilt

    @classmethod
    def disabled(cls) -> 'DisturbanceParams':
        """No disturbance on any channel."""
        return cls(yaw=(), longitudinal=(), tilt=())

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any] | None, path: str) -> 'DisturbanceParams':
        """Build from YAML data; errors name the key, e.g. ``disturbances.yaw[0].widht``.

        A missing channel keeps its default; an empty list disables the channel.
        """
        return _config.from_mapping(cls, mapping, path)

    def to_mapping(self) -> dict[str, list[dict[str, Any]]]:
        """Plain data that :meth:`from_mapping` reads back (only the fields each kind uses)."""
        out = {}
        for name, components in zip(CHANNELS, self.channels()):
            out[name] = [{'kind': c.kind, **{k: getattr(c, k) for k in KIND_FIELDS[c.kind]}}
                         for c in components]
        return out


class Disturbances:
    """Evaluates a :class:`DisturbanceParams` at any time.

    Parameters
    ----------
    config : the channels' components.
    seed : run seed (non-negative integer) of the noise components.
    """

    def __init__(self, config: DisturbanceParams | None = None, seed: int = 0) -> None:
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ValueError(f'seed must be a non-negative integer, got {seed!r}')
        self.config = DisturbanceParams() if config is None else config
        self.config.validate()
        self.seed = int(seed)
        d1, d2, d3 = (_channel_function([_component_function(c, self.seed, ch, i)
                                         for i, c in enumerate(components)])
                      for ch, components in enumerate(self.config.channels()))
        self._d1, self._d2, self._d3 = d1, d2, d3

    def sample(self, t: float) -> tuple[float, float, float]:
        """(d1 [rad/s²], d2 [m/s²], d3 [rad/s²]) at time ``t`` [s]."""
        return self._d1(t), self._d2(t), self._d3(t)

    __call__ = sample

    def sample_many(self, times) -> np.ndarray:
        """(n, 3) array of :meth:`sample` at each of ``times`` [s] (the same values).

        Each channel's function is called once per time and a channel without
        components is not called at all: the runner evaluates its disturbances so, a
        block of plant steps at a time.
        """
        times = [float(t) for t in times]
        out = np.zeros((len(times), 3))
        for column, function in enumerate((self._d1, self._d2, self._d3)):
            if function is not _zero:
                out[:, column] = function.many(times)
        return out


# Each channel and component function f has f.many(times) = [f(t) for t in times], the
# same expression in a list comprehension: the runner evaluates ~10^5 times per run, and
# a Python call per time cost as much as the values (tests check both give the same).

def _zero(t: float) -> float:
    return 0.0


def _with_many(function: Callable[[float], float],
               many: Callable[[list[float]], list[float]] | None = None):
    """Return ``function`` with its ``many`` attribute (default: one call per time)."""
    function.many = many if many is not None else (lambda times: [function(t) for t in times])
    return function


def _channel_function(functions: list[Callable[[float], float]]) -> Callable[[float], float]:
    if not functions:
        return _zero
    if len(functions) == 1:
        return functions[0]

    def total(t: float) -> float:
        value = 0.0
        for f in functions:
            value += f(t)
        return value

    def total_many(times: list[float]) -> list[float]:
        values = [0.0] * len(times)       # the same additions, in the same order
        for f in functions:
            values = [value + v for value, v in zip(values, f.many(times))]
        return values
    return _with_many(total, total_many)


def _component_function(c: DisturbanceComponent, seed: int, channel: int,
                        index: int) -> Callable[[float], float]:
    """Return a fast float -> float closure for one component."""
    amplitude = c.amplitude
    start = c.start_time - EDGE_TOLERANCE
    if c.kind == 'sine':
        w, phase, t0, sin = c.frequency, c.phase, c.start_time, math.sin

        def sine(t: float) -> float:
            return amplitude * sin(w * (t - t0) + phase) if t >= start else 0.0
        return _with_many(sine, lambda times: [
            amplitude * sin(w * (t - t0) + phase) if t >= start else 0.0 for t in times])
    if c.kind == 'pulse':
        end = c.start_time + c.width - EDGE_TOLERANCE

        def pulse(t: float) -> float:
            return amplitude if start <= t < end else 0.0
        return _with_many(pulse, lambda times: [amplitude if start <= t < end else 0.0
                                                for t in times])
    if c.kind == 'step':
        def step(t: float) -> float:
            return amplitude if t >= start else 0.0
        return _with_many(step, lambda times: [amplitude if t >= start else 0.0
                                               for t in times])
    return _with_many(_HeldNoise(c, (seed, channel, index, c.seed)))


class _HeldNoise:
    """Gaussian noise held per period, random access by sample index (see module doc)."""

    def __init__(self, c: DisturbanceComponent, entropy: tuple[int, ...]) -> None:
        self._std = c.std
        self._period = c.noise_period
        self._t0 = c.start_time
        self._start = c.start_time - EDGE_TOLERANCE
        self._entropy = entropy
        self._blocks: dict[int, list[float]] = {}

    def __call__(self, t: float) -> float:
        if t < self._start:
            return 0.0
        k = math.floor((t - self._t0 + EDGE_TOLERANCE) / self._period)
        block, i = divmod(k, _NOISE_BLOCK)
        values = self._blocks.get(block)
        if values is None:
            rng = np.random.default_rng(np.random.SeedSequence((*self._entropy, block)))
            values = self._blocks[block] = rng.standard_normal(_NOISE_BLOCK).tolist()
        return self._std * values[i]
