"""The base of the controller nodes: clock mode, time base, diagnostics, guarded inputs.

The clock modes (parameter ``clock_mode``) are described in :mod:`wip_runtime.clock`.
"""

from __future__ import annotations

import functools
import time
from typing import Callable, Sequence

from rclpy.qos import QoSProfile
from wip_runtime.clock import TimeBase, warn_lockstep_without_sim_time
from wip_runtime.composition import IntraProcessNode
from wip_runtime.diagnostics import NodeDiagnostics
from wip_runtime.messages import decode_serialized
from wip_runtime.parameters import RosParams
from wip_runtime.qos import lockstep_writer_qos, RELIABLE_QOS
from wip_runtime.stamps import stamp_to_ns

from .settings import ControllerNodeParams, RETIRED


class ControllerNode(IntraProcessNode):
    """Base of the controller nodes: clock mode, time base, diagnostics, guarded callbacks.

    Parameters declared here: :class:`~wip_control.nodes.settings.ControllerNodeParams`
    (``use_intra_process_comms``, ``clock_mode``, ``diagnostics_period`` [s],
    ``max_stamp_lead`` [s]).
    """

    #: Parameters of an older version and what replaced them, for the warning of an override.
    retired_parameters = RETIRED

    def __init__(self, node_name: str, role: str, inputs: Sequence[str], **kwargs) -> None:
        super().__init__(node_name, **kwargs)
        self.init_intra_process(False)
        settings = RosParams(self, '', ControllerNodeParams).config
        self.use_intra_process_comms = settings.use_intra_process_comms
        self.clock_mode = warn_lockstep_without_sim_time(self, settings.clock_mode)
        self._system_clock = not self.get_parameter('use_sim_time').value
        self.add_post_set_parameters_callback(self._on_use_sim_time)
        self.lockstep = self.clock_mode == 'lockstep'
        self.time_base = TimeBase(self.lockstep)
        self.diagnostics = NodeDiagnostics(self, role, inputs, settings.diagnostics_period)
        self.max_stamp_lead_ns = round(settings.max_stamp_lead * 1e9)

    def create_publisher(self, msg_type, topic, qos_profile, **kwargs):
        """Create a publisher; in lockstep, a reliable one keeps what is not acknowledged.

        In lockstep, every reliable publisher keeps what its readers have not
        acknowledged (:data:`LOCKSTEP_WRITER_DEPTH`).
        """
        if getattr(self, 'lockstep', False):
            qos_profile = lockstep_writer_qos(qos_profile)
        return super().create_publisher(msg_type, topic, qos_profile, **kwargs)

    def subscribe(self, msg_type, topic: str, name: str, handler: Callable,
                  qos: QoSProfile = RELIABLE_QOS, raw: bool = False,
                  direct: Callable | None = None, value_type: type | None = None) -> None:
        """Subscription whose callback never raises.

        A ValueError (malformed or non-finite input, rejected by a conversion or the core) drops
        the message as 'invalid', any other error as 'error'; both are counted and reported on
        /diagnostics.

        ``raw``: DDS delivers the serialized bytes (decoded by the handler, see
        :func:`~wip_runtime.messages.decode_serialized`); the intra-process bus still
        delivers objects. A raw subscription can also serve other nodes of a composed
        process (:func:`~wip_runtime.composition.share_raw_subscriptions`): each message is
        then decoded once, here, and the decoded object goes to the handler and to each of
        theirs.

        ``direct(stamp_ns, value)``: in a composed process, a publisher of the same process
        that publishes values of ``value_type`` on the topic hands them here instead of a
        message (:mod:`wip_runtime.intra_process`), guarded the same way.
        """
        followers: list[Callable] = []

        def callback(msg) -> None:
            try:
                if followers and msg.__class__ is bytes:
                    msg = decode_serialized(msg, typename)
                handler(msg)
            except Exception as err:  # noqa: BLE001 - a callback must not stop the executor
                self._drop(name, err)
            if followers and msg.__class__ is not bytes:
                for follower in followers:
                    try:
                        follower(msg)
                    except Exception as err:  # noqa: BLE001 - the others still get it
                        self.diagnostics.drop(name, 'error', f'{type(err).__name__}: {err}')

        def direct_callback(stamp_ns: int, value) -> None:
            try:
                direct(stamp_ns, value)
            except Exception as err:  # noqa: BLE001 - a callback must not stop the executor
                self._drop(name, err)
        subscription = self.create_subscription(msg_type, topic, callback, qos, raw=raw)
        self.add_intra_subscription(msg_type, subscription, callback,
                                    direct_callback if direct is not None else None,
                                    value_type)
        if raw:
            typename = f'{msg_type.__module__.split(".")[0]}/msg/{msg_type.__name__}'
            self.raw_subscriptions.append((subscription, followers))

    def _drop(self, name: str, err: Exception) -> None:
        """Report an input that a callback refused: 'invalid' for a ValueError, else 'error'."""
        if isinstance(err, ValueError):
            self.diagnostics.drop(name, 'invalid', str(err))
        else:
            self.diagnostics.drop(name, 'error', f'{type(err).__name__}: {err}')

    def subscribe_input(self, msg_type, topic: str, name: str, convert: Callable,
                        qos: QoSProfile = RELIABLE_QOS, check: Callable | None = None,
                        value_type: type | None = None,
                        on_value: Callable[[int, object], None] | None = None) -> None:
        """:meth:`subscribe` to a stamped input of the node's LatestSync.

        Each message's stamp counted on /diagnostics, then ``convert(msg)`` fed as ``name`` (a
        ValueError of the conversion drops the message). With ``check``, a value of
        ``value_type`` handed directly by a node of the same process goes the same way,
        through ``check(value)``: the input rules that ``convert`` applies to a message's
        value (finiteness), so that both paths refuse the same inputs. ``on_value(stamp_ns,
        value)`` takes the converted input instead of the LatestSync.
        """
        on_value = on_value or functools.partial(self.feed, name)

        def accept(to_value: Callable, stamp: int, arrived) -> None:
            # Counted before it is checked: a refused input still shows as arrived.
            self.diagnostics.input(name, stamp)
            on_value(stamp, to_value(arrived))

        # The value path calls accept through a partial (no Python frame of its own).
        self.subscribe(msg_type, topic, name,
                       lambda msg: accept(convert, stamp_to_ns(msg.header.stamp), msg), qos,
                       direct=functools.partial(accept, check) if check is not None else None,
                       value_type=value_type)

    def subscribe_value(self, msg_type, topic: str, name: str, on_value: Callable,
                        value_type: type, convert: Callable = lambda msg: msg,
                        qos: QoSProfile = RELIABLE_QOS) -> None:
        """:meth:`subscribe` with one handler for both paths: ``on_value(stamp_ns, value)``.

        A message gives its stamp and ``convert(msg)``; a node of the same process hands its
        value of ``value_type`` as it is. ``convert`` may return the message itself where
        the handler reads only fields the value has under the same names.
        """
        self.subscribe(msg_type, topic, name,
                       lambda msg: on_value(stamp_to_ns(msg.header.stamp), convert(msg)),
                       qos, direct=on_value, value_type=value_type)

    def now_ns(self) -> int:
        """Return the node clock [ns].

        Without ``use_sim_time`` that is ROS time = the system clock (CLOCK_REALTIME), read
        directly: rclpy's ``now()`` builds a Time object per call (measured 15 us against 0.15 us
        on a loaded machine), and real time reads the clock for every input.
        """
        if self._system_clock:
            return time.time_ns()
        return self.get_clock().now().nanoseconds

    def _on_use_sim_time(self, parameters) -> None:
        for parameter in parameters:
            if parameter.name == 'use_sim_time':
                self._system_clock = not parameter.value

    def feed(self, name: str, stamp_ns: int, value) -> None:
        """Give one converted input to ``self.sync``; report it if it came too late.

        Real time: ValueError (the message is dropped as invalid, with the reason on
        /diagnostics) if it is stamped more than ``max_stamp_lead`` ahead of this node's
        clock, e.g. a sender whose clock jumped or is not synchronised with this one.
        """
        if not self.lockstep:
            lead_ns = stamp_ns - self.now_ns()
            if lead_ns > self.max_stamp_lead_ns:
                raise ValueError(f"stamp {lead_ns / 1e9:.3f} s ahead of this node's clock "
                                 f'(max_stamp_lead {self.max_stamp_lead_ns / 1e9:g} s): is '
                                 f"the sender's clock synchronised?")
        # dict.get: a Counter's missing key (no stale input yet, the usual case) would go
        # through its Python __missing__, twice per input.
        dropped = self.sync.dropped
        stale = dropped.get('stale', 0)
        self.sync.add(name, stamp_ns, value)
        if dropped.get('stale', 0) > stale:
            self.diagnostics.drop(name, 'stale',
                                  f'stamp {stamp_ns} ns not after the last computed one')
