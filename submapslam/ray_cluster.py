"""Joining a Ray cluster that was started apart from ``batch`` (``ray start --head``): the
address forms, token authentication, Ray's start-up noise, and whether the cluster's nodes
see this machine's files.

* ``HOST:PORT`` is the head's GCS address (``ray start --head --port PORT``);
  ``ray://HOST:PORT`` goes through the Ray Client server (port 10001 by default; needs
  ``ray[client]``).
* Current Ray starts clusters with token authentication on. Before joining, the GCS is asked,
  without a token and within a few seconds, whether it wants one (:func:`probe_gcs`); when it
  does, the token is looked up where Ray keeps it (:func:`find_token`: ``RAY_AUTH_TOKEN``,
  ``RAY_AUTH_TOKEN_PATH``, ``~/.ray/auth_token``), checked against the cluster, and Ray's token
  mode is turned on for this process. The mode must match the cluster's: a driver in token
  mode joins a cluster without authentication but its streaming tasks then never report back.
  ``RAY_AUTH_MODE`` set by the user is left alone.
* Whatever goes wrong becomes one :class:`~submapslam.errors.SubmapSlamError` line saying what
  to set; Ray's own lines (gcs_client retries, INFO) are kept out of the terminal unless
  ``verbose``.
"""

from __future__ import annotations

import os
import sys
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from .errors import SubmapSlamError

TOKEN_ENV = "RAY_AUTH_TOKEN"
TOKEN_PATH_ENV = "RAY_AUTH_TOKEN_PATH"
MODE_ENV = "RAY_AUTH_MODE"
GCS_CLUSTER_ID = "/ray.rpc.NodeInfoGcsService/GetClusterId"  # answered by any GCS, before any login
WHERE_TOKENS_ARE = (f"set {TOKEN_ENV} to the cluster's token, or {TOKEN_PATH_ENV} to a file holding it, or copy "
                    "the head node's ~/.ray/auth_token to this machine")


@dataclass(frozen=True)
class Token:
    """An authentication token and where it was found (for messages)."""

    value: str
    where: str


def find_token(environ: dict[str, str] | None = None, home: Path | None = None) -> Token | None:
    """The Ray token this process would present: ``RAY_AUTH_TOKEN``, else the file named by
    ``RAY_AUTH_TOKEN_PATH``, else ``~/.ray/auth_token``; None when there is none."""
    env = os.environ if environ is None else environ
    if env.get(TOKEN_ENV, "").strip():
        return Token(env[TOKEN_ENV].strip(), TOKEN_ENV)
    candidates = [Path(env[TOKEN_PATH_ENV]).expanduser()] if env.get(TOKEN_PATH_ENV) else []
    candidates.append((Path.home() if home is None else home) / ".ray" / "auth_token")
    for path in candidates:
        try:
            value = path.read_text().strip()
        except OSError:
            continue
        if value:
            return Token(value, str(path))
    return None


def split_address(address: str) -> tuple[str, int]:
    """``HOST:PORT`` (or ``ray://HOST:PORT``) as ``(host, port)``; one line when it is not one."""
    rest = address.removeprefix("ray://")
    host, sep, port = rest.rpartition(":")
    if not sep or not host or not port.isdigit():
        raise SubmapSlamError(f"Ray address {address!r} is not HOST:PORT (e.g. 127.0.0.1:6379, the head's "
                              "`ray start --head --port`) or ray://HOST:PORT (Ray Client, port 10001)")
    return host, int(port)


def probe_gcs(address: str, token: str | None = None, timeout_s: float = 5.0) -> str:
    """Ask the GCS at ``HOST:PORT`` for its cluster id, presenting ``token`` if given:
    ``"open"`` (answered), ``"token"`` (it wants a token, or refused this one),
    ``"unreachable"`` (nothing answers), or ``"unknown"`` (grpc missing, or another error).

    A bare gRPC call (the request is an empty message), so that Ray is not imported yet: Ray
    reads its authentication mode from the environment when it is imported."""
    try:
        import grpc
    except ImportError:
        return "unknown"
    host, port = split_address(address)
    metadata = None if token is None else [("authorization", f"Bearer {token}")]
    with grpc.insecure_channel(f"{host}:{port}") as channel:
        call = channel.unary_unary(GCS_CLUSTER_ID, request_serializer=lambda _: b"",
                                   response_deserializer=lambda data: data)
        try:
            call(None, timeout=timeout_s, metadata=metadata)
        except grpc.RpcError as exc:
            code = exc.code()
            if code == grpc.StatusCode.UNAUTHENTICATED:
                return "token"
            if code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                return "unreachable"
            return "unknown"
    return "open"


def auth_settings(address: str, environ: dict[str, str] | None = None) -> tuple[dict[str, str], str]:
    """The environment variables that give this process the Ray authentication mode of the
    cluster at ``address``, and what was decided in words: the user's own ``RAY_AUTH_MODE``
    (nothing to set), "no authentication" or "token from WHERE". Raises one line when nothing
    answers there, or the cluster wants a token this machine does not have or it refuses.
    A ``ray://`` address (the Ray Client server, which cannot be asked first) is joined with a
    token when this machine has one."""
    env = os.environ if environ is None else environ
    if env.get(MODE_ENV):
        return {}, f"{MODE_ENV}={env[MODE_ENV]} (as set)"
    if address.startswith("ray://"):
        split_address(address)
        token = find_token(env)
        if token is None:
            return {}, "no token here"
        return ({MODE_ENV: "token"} | ({} if token.where == TOKEN_ENV else {TOKEN_PATH_ENV: token.where}),
                f"token from {token.where}")
    answer = probe_gcs(address)
    if answer == "unreachable":
        answer = probe_gcs(address, timeout_s=2.0)  # once more: a head starting up or busy
    if answer == "unreachable":
        raise SubmapSlamError(f"no Ray cluster answers at {address}: start one with `ray start --head --port PORT` "
                              "and give its HOST:PORT (the address `ray start` printed)")
    if answer == "open":
        return {MODE_ENV: "disabled"}, "no authentication"
    if answer == "unknown":
        return {}, "not probed (grpc is missing)"
    token = find_token(env)
    if token is None:
        raise SubmapSlamError(f"the Ray cluster at {address} uses token authentication and this machine has no "
                              f"token: {WHERE_TOKENS_ARE}")
    answer = probe_gcs(address, token.value)
    if answer == "unreachable":  # it answered a moment ago: a busy head, asked once more
        answer = probe_gcs(address, token.value, timeout_s=15.0)
    if answer == "token":
        raise SubmapSlamError(f"the Ray cluster at {address} refused the token in {token.where}: {WHERE_TOKENS_ARE}")
    settings = {MODE_ENV: "token"}
    if token.where != TOKEN_ENV:
        settings[TOKEN_PATH_ENV] = token.where
    return settings, f"token from {token.where}"


@contextmanager
def environment(settings: dict[str, str]) -> Iterator[None]:
    """``os.environ`` with ``settings`` while the block runs, as it was afterwards. When Ray
    was imported already (it read its authentication mode then), its settings are read again."""
    before = {k: os.environ.get(k) for k in settings}
    os.environ.update(settings)
    _reread_ray_settings(settings)
    try:
        yield
    finally:
        for k, v in before.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
        _reread_ray_settings(settings)


def _reread_ray_settings(settings: dict[str, str]) -> None:
    """Make an already imported Ray read its settings from the environment again (Ray's
    internal ``Config.initialize``; nothing to do before Ray is imported)."""
    raylet = sys.modules.get("ray._raylet")
    if not settings or raylet is None:
        return
    try:
        raylet.Config.initialize("{}")
    except Exception:  # another Ray version: the environment then counts from the next import
        pass


@contextmanager
def quiet_fds(verbose: bool) -> Iterator[list[str]]:
    """Send what is written to this process's stdout and stderr (file descriptors 1 and 2:
    Ray's C++ warnings as well as Python's) to a temporary file while the block runs, unless
    ``verbose``; the list yielded holds that text afterwards (for the error message)."""
    captured: list[str] = []
    if verbose:
        yield captured
        return
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with tempfile.TemporaryFile(mode="w+b") as sink:
        try:
            os.dup2(sink.fileno(), 1)
            os.dup2(sink.fileno(), 2)
            yield captured
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            sink.seek(0)
            captured.append(sink.read().decode("utf-8", "replace"))


def connect_error(address: str, exc: BaseException, output: str) -> SubmapSlamError:
    """One line for a failed ``ray.init(address)``: what was wrong and what to set."""
    text = f"{exc} {output}"
    if "requires pip package `ray[client]`" in text or "ray[client]" in text:
        return SubmapSlamError(f"ray:// addresses need the Ray Client: pip install 'ray[client]' (or give the "
                               f"head's HOST:PORT instead of {address})")
    if "InvalidAuthToken" in text or "Unauthenticated" in text or "UNAUTHENTICATED" in text:
        return SubmapSlamError(f"the Ray cluster at {address} did not accept this machine's authentication: "
                               f"{WHERE_TOKENS_ARE}")
    reason = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
    return SubmapSlamError(f"could not join the Ray cluster at {address}: {reason} (is `ray start --head` running "
                           "there, and is this the address it printed?)")
