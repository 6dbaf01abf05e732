"""Who may talk to the daemon: loopback by default, CurveZMQ for anything else.

A bind to a non-loopback address without CurveZMQ is refused at start-up, so a lab cannot
expose the finger to its network by a typo. With curve on, the server loads its secret key
and an authenticator admits only clients whose public keys sit in `authorized_clients`.
"""

from __future__ import annotations

import ipaddress
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zmq
import zmq.auth

from service.errors import ConfigError

if TYPE_CHECKING:  # clients import this module too: keep it light (no config, no asyncio)
    from zmq.auth.thread import ThreadAuthenticator

    from service.daemon.config import SecurityConfig

LOCAL_TRANSPORTS = ("ipc://", "inproc://")


def is_loopback(endpoint: str) -> bool:
    """True for ipc/inproc and tcp binds on 127.0.0.0/8, ::1 or localhost."""
    if endpoint.startswith(LOCAL_TRANSPORTS):
        return True
    if not endpoint.startswith("tcp://"):
        return False
    host = endpoint[len("tcp://"):].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # '*', an interface name or a host name: treat as exposed


def bind_server_socket(ctx: zmq.Context, kind: int, endpoint: str,
                       options: dict[int, Any], curve: CurveServer | None = None
                       ) -> tuple[zmq.Socket, str]:
    """A bound server socket and the endpoint it got; closed again if binding fails."""
    sock = ctx.socket(kind)
    try:
        for option, value in options.items():
            sock.setsockopt(option, value)
        if curve is not None:
            curve.apply(sock)
        sock.bind(endpoint)
    except zmq.ZMQError as exc:
        sock.close(linger=0)
        raise ConfigError(f"cannot bind {endpoint}: {exc}; is another hapticd "
                          f"running there?") from None
    except Exception:
        sock.close(linger=0)
        raise
    return sock, sock.getsockopt_string(zmq.LAST_ENDPOINT)


def check_binds(endpoints: list[str], security: SecurityConfig) -> None:
    """Refuse a non-loopback bind unless CurveZMQ is configured."""
    exposed = [e for e in endpoints if not is_loopback(e)]
    if exposed and not security.curve:
        raise ConfigError(f"refusing to bind {', '.join(exposed)} without CurveZMQ: set "
                          f"[security] curve = true with keys from `haptic keygen`, or bind "
                          f"127.0.0.1")


class CurveServer:
    """Loads the server keys and runs the ZAP authenticator for one context."""

    def __init__(self, ctx: zmq.Context, security: SecurityConfig) -> None:
        self.security = security
        self._ctx = ctx
        self._auth: ThreadAuthenticator | None = None
        self.public: bytes = b""
        self.secret: bytes = b""

    def start(self) -> None:
        secret_file = Path(self.security.server_secret_key)
        clients = Path(self.security.authorized_clients)
        if not secret_file.is_file():
            raise ConfigError(f"server secret key '{secret_file}' does not exist; "
                              f"run `haptic keygen`")
        if not clients.is_dir():
            raise ConfigError(f"authorized_clients '{clients}' is not a directory")
        public, secret = zmq.auth.load_certificate(secret_file)
        if not secret:
            raise ConfigError(f"'{secret_file}' holds no secret key (use the .key_secret file)")
        self.public, self.secret = public, secret
        from zmq.auth.thread import ThreadAuthenticator

        self._auth = ThreadAuthenticator(self._ctx)
        self._auth.start()
        self._auth.configure_curve(domain="*", location=str(clients))

    def apply(self, socket: zmq.Socket) -> None:
        """Make `socket` a CurveZMQ server (before bind)."""
        socket.curve_secretkey = self.secret
        socket.curve_publickey = self.public
        socket.curve_server = True

    def stop(self) -> None:
        if self._auth is not None:
            self._auth.stop()
            self._auth = None


def client_curve_options(server_public_file: str, client_secret_file: str) -> dict[str, Any]:
    """Socket options that make a client socket talk CurveZMQ to our server."""
    server_public, _ = zmq.auth.load_certificate(server_public_file)
    public, secret = zmq.auth.load_certificate(client_secret_file)
    if not secret:
        raise ConfigError(f"'{client_secret_file}' holds no secret key")
    return {zmq.CURVE_SERVERKEY: server_public, zmq.CURVE_PUBLICKEY: public,
            zmq.CURVE_SECRETKEY: secret}


def generate_keys(directory: str | Path, name: str) -> tuple[Path, Path]:
    """Write `name.key` (public, share it) and `name.key_secret` (keep it) into `directory`."""
    if not zmq.has("curve"):
        raise ConfigError("this libzmq was built without CurveZMQ support")
    if not name or any(c in name for c in "/\\") or name.startswith("."):
        raise ConfigError(f"key name '{name}' must be a plain file name")
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    public, secret = zmq.auth.create_certificates(str(directory), name)
    Path(secret).chmod(0o600)
    return Path(public), Path(secret)
