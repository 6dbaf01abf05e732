"""Who may talk to the daemon: loopback by default, CurveZMQ for anything else.

A bind to a non-loopback address without CurveZMQ is refused at start-up, so a lab cannot
expose the finger to its network by a typo. With curve on, the server loads its secret key
and an authenticator admits only clients whose public keys sit in `authorized_clients`;
the directory is read again when it changes, so a removed key is refused from then on.
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zmq
import zmq.auth

from service.errors import ConfigError

if TYPE_CHECKING:  # clients import this module too: keep it light (no config, no asyncio)
    from zmq.auth.thread import ThreadAuthenticator

    from service.daemon.config import SecurityConfig

LOCAL_TRANSPORTS = ("ipc://", "inproc://")
REFUSAL_LOG_EVERY_S = 60.0
"""A refused key is logged at most this often: a client that retries would fill the log."""
log = logging.getLogger("hapticd.security")


def _log(event: str, level: int = logging.WARNING, **fields: Any) -> None:
    log.log(level, event, extra={"fields": fields})


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


def port_of(endpoint: str) -> str | None:
    """The port part of a TCP or WebSocket endpoint ("" when it names none; None for
    ipc:// and the like), after an IPv6 host's brackets (tcp://[::1]:5561)."""
    scheme, _, address = endpoint.partition("://")
    if scheme not in ("tcp", "ws", "wss"):
        return None
    host_port = address.split("/", 1)[0]
    after_host = host_port.rpartition("]")[2] if host_port.startswith("[") else host_port
    return after_host.rpartition(":")[2] if ":" in after_host else ""


def allow_ipv6(sock: zmq.Socket, endpoint: str) -> None:
    """Let `sock` use an IPv6 address where `endpoint` names one (tcp://[::1]:5561):
    ZeroMQ sockets are IPv4-only by default, and a bind there failed "No such device"."""
    if "://[" in endpoint:
        sock.setsockopt(zmq.IPV6, 1)


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
        allow_ipv6(sock, endpoint)
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
                          f"127.0.0.1 (a host name other than localhost counts as exposed, "
                          f"whatever it resolves to now)")


class KeyRing:
    """The public keys in `authorized_clients`, read again whenever the directory changes,
    so removing a key file revokes that client without a restart."""

    def __init__(self, directory: str | Path, min_interval_s: float = 0.2) -> None:
        self.directory = Path(directory)
        self.min_interval_s = min_interval_s
        self.names: dict[str, str] = {}
        """Each authorized public key (z85), with its file's name for the log."""
        self.revocations = 0
        """How many times a key has disappeared (the daemon re-binds its stream on a change)."""
        self.revoked: tuple[str, ...] = ()
        """The file names of the keys the latest revocation removed."""
        self._unreadable: set[str] = set()
        """Files in the directory already warned of as no client's public key."""
        self._refused: dict[str, float] = {}
        """When each refused key was last logged."""
        self._stamp: tuple[int, int] | None = None
        self._checked = 0.0
        self._lock = threading.Lock()
        self.refresh(force=True)

    def refresh(self, force: bool = False) -> bool:
        """Re-read the keys if the directory changed; True when a key was removed (which
        also counts in `revocations`)."""
        now = time.monotonic()
        if not force and now - self._checked < self.min_interval_s:
            return False
        with self._lock:  # the ZAP thread and the loop both refresh
            self._checked = now
            try:
                st = self.directory.stat()
                stamp = (st.st_mtime_ns, st.st_ino)
            except OSError:
                stamp = (-1, -1)  # the directory vanished: nobody is authorized
            if stamp == self._stamp and not force:
                return False
            self._stamp = stamp
            names: dict[str, str] = {}
            for path in sorted(self.directory.iterdir()) if stamp[0] >= 0 else ():
                public = self._public_key(path)
                if public:
                    names[public] = path.name
            gone = self.names.keys() - names.keys()
            if gone:
                self.revoked = tuple(sorted(self.names.get(k, k) for k in gone))
            self.names = names
            self.revocations += bool(gone)
            return bool(gone)

    def _public_key(self, path: Path) -> str | None:
        """The client public key `path` holds; None, with a warning once, for any other
        file (a junk file or a secret key put there authorizes nobody, and said nothing)."""
        if path.suffix != ".key" or not path.is_file():
            if path.name.endswith(".key_secret") and path.name not in self._unreadable:
                self._unreadable.add(path.name)
                _log("client_key_ignored", file=path.name,
                     why="a secret key: authorized_clients takes clients' public NAME.key "
                         "files (keep the secret with the client)")
            return None
        try:
            public, _ = zmq.auth.load_certificate(path)
        except (OSError, ValueError) as exc:
            public, why = None, str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        else:
            why = "it holds no public key"
        if public:
            self._unreadable.discard(path.name)
            return public.decode("ascii")
        if path.name not in self._unreadable:
            self._unreadable.add(path.name)
            _log("client_key_ignored", file=path.name,
                 why=f"not a key file from `haptic keygen` ({why})")
        return None

    def allowed(self, key: str | bytes | None) -> bool:
        if key is None:
            return False
        self.refresh()
        return (key.decode("ascii") if isinstance(key, bytes) else key) in self.names

    def callback(self, domain: str, key: bytes) -> bool:
        """pyzmq's credentials-provider hook: called by the ZAP handler at each handshake.
        A refused key is logged (at most every `REFUSAL_LOG_EVERY_S`): the client only
        sees silence, so the log is where a lab finds out why."""
        allowed = self.allowed(key)
        if not allowed:
            text = key.decode("ascii", "replace") if isinstance(key, bytes) else str(key)
            now = time.monotonic()
            if now - self._refused.get(text, -float("inf")) >= REFUSAL_LOG_EVERY_S:
                self._refused[text] = now
                _log("curve_refused", key=text,
                     why="this client's public key is not in authorized_clients: add its "
                         "NAME.key there to admit it")
        return allowed


class CurveServer:
    """Loads the server keys and runs the ZAP authenticator for one context; the keys it
    admits are `keyring`'s, so the loop can also refuse a revoked client's requests."""

    def __init__(self, ctx: zmq.Context, security: SecurityConfig) -> None:
        self.security = security
        self._ctx = ctx
        self._auth: ThreadAuthenticator | None = None
        self.keyring: KeyRing | None = None
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
        try:
            public, secret = zmq.auth.load_certificate(secret_file)
        except (OSError, ValueError) as exc:
            raise ConfigError(f"'{secret_file}' is not a key file: {exc}") from None
        if not secret:
            raise ConfigError(f"'{secret_file}' holds no secret key (use the .key_secret file)")
        self.public, self.secret = public, secret
        self.keyring = KeyRing(clients)
        from zmq.auth.thread import ThreadAuthenticator  # the daemon's only, not clients'

        self._auth = ThreadAuthenticator(self._ctx)
        self._auth.start()
        self._auth.configure_curve_callback(domain="*", credentials_provider=self.keyring)

    def authorized(self, key: str | None) -> bool:
        """Whether a request's CURVE key (its `User-Id`) is still authorized."""
        return self.keyring is not None and self.keyring.allowed(key)

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
