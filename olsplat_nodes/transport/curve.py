"""CURVE security for the query link: key files, an allow-list of client public keys, and the
ZAP authenticator that enforces it.

Key files are ZeroMQ's own certificate format (``zmq.auth``): ``NAME.key`` holds the public key,
``NAME.key_secret`` the public and the secret key (Z85 text). The server loads its secret file
and a directory of client ``*.key`` files (the allow-list); a client loads its own secret file and
the server's public file. A client whose key is not in the directory fails the handshake and
never gets an answer. The allow-list is read when the server socket is set up: add a key, then
restart the query server.
"""

from __future__ import annotations

import os
import re
import threading
from pathlib import Path

import zmq
import zmq.auth
from zmq.auth.thread import ThreadAuthenticator

from ._sockets import log

_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def generate(out_dir: str | os.PathLike, name: str, overwrite: bool = False) -> tuple[Path, Path]:
    """Write a new key pair ``out_dir/NAME.key`` (public) and ``out_dir/NAME.key_secret``
    (secret, mode 0600); returns ``(public_path, secret_path)``. Refuses to replace existing
    files unless ``overwrite``: losing a secret key locks its owner out."""
    if not _NAME.match(name or ""):
        raise ValueError(f"key name must be letters, digits, '_', '.', '-' (no path), got {name!r}")
    out = Path(out_dir)
    public, secret = out / f"{name}.key", out / f"{name}.key_secret"
    existing = [str(p) for p in (public, secret) if p.exists()]
    if existing and not overwrite:
        raise FileExistsError(f"key file(s) already exist: {', '.join(existing)} (pass overwrite to replace)")
    out.mkdir(parents=True, exist_ok=True)
    public_file, secret_file = zmq.auth.create_certificates(out, name)
    os.chmod(secret_file, 0o600)
    return Path(public_file), Path(secret_file)


def check_secret(secret_file: str | os.PathLike) -> None:
    """FileNotFoundError, PermissionError (readable by others) or ValueError (no secret key in
    it) for a secret key file that cannot serve; nothing for a good one."""
    _load_secret(secret_file)


def _load_secret(secret_file: str | os.PathLike) -> tuple[bytes, bytes]:
    path = Path(secret_file)
    if not path.is_file():
        raise FileNotFoundError(f"secret key file not found: {path}")
    public, secret = zmq.auth.load_certificate(path)
    if not secret:
        raise ValueError(f"{path}: holds no secret key (give the NAME.key_secret file, not NAME.key)")
    mode = path.stat().st_mode & 0o777
    if mode & 0o077:  # as ssh does: a secret others can read is no longer a secret
        raise PermissionError(
            f"{path}: secret key file is readable by others (mode {mode:o}); make it private: chmod 600 {path}"
        )
    return public, secret


class ServerKeys:
    """The server's key pair and the directory of allowed client public keys (``*.key``)."""

    def __init__(self, secret_file: str | os.PathLike, allow_dir: str | os.PathLike):
        self.public, self.secret = _load_secret(secret_file)
        self.allow_dir = Path(allow_dir).resolve()
        if not self.allow_dir.is_dir():
            raise FileNotFoundError(f"allow-list directory not found: {self.allow_dir}")
        self.allowed = sorted(p.name for p in self.allow_dir.glob("*.key"))
        if not self.allowed:
            log.warning("CURVE allow-list %s holds no *.key file: no client can connect", self.allow_dir)

    def apply(self, socket: zmq.Socket, context: zmq.Context) -> None:
        """Make ``socket`` (before bind) a CURVE server checked against the allow-list. One ZAP
        authenticator thread serves a context; each allow-list directory is its own ZAP domain."""
        domain = f"olsplat:{self.allow_dir}"
        _AUTHENTICATORS.acquire(context, domain, self.allow_dir)
        socket.zap_domain = domain.encode("utf-8")
        socket.curve_secretkey = self.secret
        socket.curve_publickey = self.public
        socket.curve_server = True

    def release(self, context: zmq.Context) -> None:
        """Undo ``apply``'s hold on the context's authenticator (the last release stops it)."""
        _AUTHENTICATORS.release(context)


class ClientKeys:
    """A client's key pair and the server's public key."""

    def __init__(self, secret_file: str | os.PathLike, server_public_file: str | os.PathLike):
        self.public, self.secret = _load_secret(secret_file)
        path = Path(server_public_file)
        if not path.is_file():
            raise FileNotFoundError(f"server public key file not found: {path}")
        self.server_public, _ = zmq.auth.load_certificate(path)

    def apply(self, socket: zmq.Socket) -> None:
        """Make ``socket`` (before connect) a CURVE client of the server."""
        socket.curve_secretkey = self.secret
        socket.curve_publickey = self.public
        socket.curve_serverkey = self.server_public


class _Authenticators:
    """One ``ThreadAuthenticator`` per context (libzmq allows one ZAP handler per context), shared
    by every CURVE server socket of that context and stopped when the last one is released."""

    def __init__(self):
        self._lock = threading.Lock()
        self._by_context: dict[int, tuple[zmq.Context, ThreadAuthenticator, int]] = {}

    def acquire(self, context: zmq.Context, domain: str, allow_dir: Path) -> None:
        with self._lock:
            context_, auth, users = self._by_context.get(id(context), (context, None, 0))
            if auth is None:
                auth = ThreadAuthenticator(context)
                auth.start()
            auth.configure_curve(domain=domain, location=str(allow_dir))
            self._by_context[id(context)] = (context_, auth, users + 1)

    def release(self, context: zmq.Context) -> None:
        with self._lock:
            entry = self._by_context.get(id(context))
            if entry is None:
                return
            context_, auth, users = entry
            if users > 1:
                self._by_context[id(context)] = (context_, auth, users - 1)
                return
            del self._by_context[id(context)]
        try:
            auth.stop()
        except zmq.ZMQError:  # the context is already being torn down: its sockets are gone anyway
            pass


_AUTHENTICATORS = _Authenticators()
