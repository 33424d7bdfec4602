"""The Python class of a ROS message type by its name.

For the bag tools that create subscriptions and publishers of types known only at run time
(recorder, replayer, the Foxglove bridge).
"""

from __future__ import annotations

import importlib

#: Message types renamed since bags were first recorded: the name in an old bag -> the type
#: with the same fields today (docs/glossary.md, "Old bags and the renames").
RENAMED_TYPES = {
    'wip_msgs/msg/ArcState': 'wip_msgs/msg/YawTorque',
    'wip_msgs/msg/MpcOutput': 'wip_msgs/msg/DriveTorque',
}


def message_class(type_name: str, error: type[Exception] = LookupError):
    """Return the class of the ROS message type ``'pkg/msg/Type'``.

    What rosidl_runtime_py's ``get_message`` does (it is not in the PyPI wheels); a type
    renamed since (:data:`RENAMED_TYPES`) gives today's class. Raises
    ``error`` (the caller's exception class) with the reason when the name is malformed
    or the type is not installed.
    """
    try:
        package, namespace, name = RENAMED_TYPES.get(type_name, type_name).split('/')
        return getattr(importlib.import_module(f'{package}.{namespace}'), name)
    except (ValueError, ImportError, AttributeError) as err:
        raise error(f'cannot import message type {type_name!r}: {err}') from err
