"""Exceptions a user can act on. Every error the project raises derives from
``DeepXPalmError`` so a node's top level can tell its own failures from bugs."""

from __future__ import annotations


class DeepXPalmError(Exception):
    """Base of every error raised on purpose by this project."""


class ConfigError(DeepXPalmError, ValueError):
    """A configuration file or value is wrong; the message names the key."""


class DeviceError(DeepXPalmError):
    """A device failed; the message names the device and what to check."""


class DeviceNotConnectedError(DeviceError):
    """A device was used before ``connect()`` or after ``disconnect()``."""


class DeviceAlreadyConnectedError(DeviceError):
    """``connect()`` was called twice."""


class DeviceTimeoutError(DeviceError):
    """A device did not answer in time."""


class ProtocolError(DeviceError):
    """A device answered with bytes that do not follow its protocol."""


class StaleDataError(DeviceError):
    """The newest data from a device is older than the caller accepts."""


class LinkError(DeepXPalmError):
    """The network link between the nodes is down or misconfigured."""
