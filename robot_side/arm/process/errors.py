"""The arm process's errors, raised in the node as the driver's own exception types.

The arm process answers a failed call with "Type: text" on its pipe; the
node raises the same type, so a caller handles an arm in its own process as
it handles the driver in the node.
"""

from __future__ import annotations

from common.errors import (
    ConfigError,
    DeviceAlreadyConnectedError,
    DeviceError,
    DeviceNotConnectedError,
    DeviceTimeoutError,
    StaleDataError,
)
from robot_side.arm.base import WorkspaceLimitError

#: exceptions the arm process reports by name, raised here as the same type
ERRORS: dict[str, type[Exception]] = {
    cls.__name__: cls
    for cls in (
        DeviceError,
        DeviceNotConnectedError,
        DeviceTimeoutError,
        DeviceAlreadyConnectedError,
        StaleDataError,
        WorkspaceLimitError,
        ConfigError,
        ValueError,
    )
}


def as_driver_error(message: str, method: str) -> Exception:
    """The arm process's "Type: text" as the driver's own exception type."""
    _, _, rest = message.partition(f"arm process {method}: ")
    name, sep, text = rest.partition(": ")
    cls = ERRORS.get(name) if sep else None
    if cls is None:
        return DeviceError(message)
    return cls(text)
