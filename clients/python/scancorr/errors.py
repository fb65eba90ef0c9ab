"""The package's exceptions: every error of the bus, a fit or a bag is a `ScancorrError` (a
bad argument — a machine id, a version number — is a plain `ValueError`).

    ScancorrError (RuntimeError)
    ├── ConfigError (ValueError)        connect()'s arguments or zenoh configuration file
    │   ├── BadEndpoint                 an endpoint not of the form PROTOCOL/HOST:PORT
    │   └── TlsError                    a TLS certificate or key the configuration names is
    │                                   missing or unreadable (its key and path in the message)
    ├── NotConnected (ConnectionError)  connect(): nothing answers at the endpoint(s)
    ├── Refused (PermissionError)       the other end refused: the session (something listens
    │                                   but no zenoh session was established, e.g. its TLS
    │                                   handshake) or a query (a router's access control)
    ├── NoService (TimeoutError)        a query that no scancorrd answered
    ├── ServiceError                    the service refused a request (its own message)
    │   └── NotServed                   the service does not serve the machine
    ├── ShapeError (ValueError)         a shape fit refused (too few points, a line as a circle…)
    ├── BagError (ValueError)           a bag that cannot be read as it is
    └── DecodeError (ValueError)        a payload that does not decode

The messages use the words of the `scancorr` CLI for the same case (`cannot connect to
tcp/127.0.0.1:7447: nothing answers there (is scancorrd or a zenoh router running and
listening on it?)`), so a message found in one is found in the other.
"""

from __future__ import annotations

__all__ = [
    "ScancorrError",
    "ConfigError",
    "BadEndpoint",
    "TlsError",
    "NotConnected",
    "Refused",
    "NoService",
    "ServiceError",
    "NotServed",
    "ShapeError",
]


class ScancorrError(RuntimeError):
    """Base of this package's errors."""


class ConfigError(ScancorrError, ValueError):
    """`connect()`'s arguments or its zenoh configuration file cannot be used."""


class BadEndpoint(ConfigError):
    """An endpoint that is not `PROTOCOL/ADDRESS` with a protocol zenoh knows. `.endpoint`."""

    def __init__(self, message: str, endpoint: object = None):
        super().__init__(message)
        self.endpoint = endpoint


class TlsError(ConfigError):
    """A TLS certificate or key that the zenoh configuration names is missing or unreadable.
    `.key` (e.g. `transport/link/tls/root_ca_certificate`) and `.path`."""

    def __init__(self, message: str, key: str = "", path: str = ""):
        super().__init__(message)
        self.key = key
        self.path = path


class NotConnected(ScancorrError, ConnectionError):
    """`connect()` reached nothing: no zenoh session answered at any endpoint within the
    timeout (nothing listening, or not reachable). `.endpoints`."""

    def __init__(self, message: str, endpoints: object = ()):
        super().__init__(message)
        self.endpoints = list(endpoints) if endpoints else []


class Refused(ScancorrError, PermissionError):
    """The other end refused: something listens at the endpoint but no zenoh session was
    established (a TLS handshake refused: a certificate it does not accept, or no zenoh there),
    or a query got no answer although the service is seen serving the machine (a router's
    access control drops a denied query without telling the asker)."""


class NoService(ScancorrError, TimeoutError):
    """No scancorrd answered (not running, not reachable, or serving another prefix)."""


class ServiceError(ScancorrError):
    """The service refused a request; the message is the service's own."""


class NotServed(ServiceError):
    """The service does not serve the machine asked about."""


class ShapeError(ScancorrError, ValueError):
    """A shape fit refused: too few points, points that do not determine the feature (a line
    fitted as a circle, coplanar points as a sphere), non-finite coordinates."""
