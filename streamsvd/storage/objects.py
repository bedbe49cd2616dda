"""A basis store's storage under a prefix of an object store (see :mod:`streamsvd.storage`).

An object store has no rename: an overwrite is a single ``PUT``. Transient failures
(throttling such as ``503 SlowDown``, other 5xx answers, dropped connections) are retried
with a doubling back-off (:data:`RETRIES` attempts); every operation is idempotent, a
conditional ``PUT`` refused because the server had applied the same write before the
failure recognises its own bytes. Writing needs
conditional writes (``If-None-Match: *``, ``If-Match: <ETag>``), implemented for
``s3://`` through s3fs; other fsspec protocols can be read but not written. A failure to
reach the store is reported as a :class:`~streamsvd.errors.StoreError` naming it.
"""

from __future__ import annotations

import contextlib
import functools
import logging
import time
from collections.abc import Callable, Iterator, Mapping
from typing import Any, TypeVar, cast

from streamsvd.errors import InputError, OptionalDependencyError, StoreError
from streamsvd.storage.zarr_stores import OPTION, choice_of, fsspec_options, zarr_store_of

__all__ = ["SECRET_OPTIONS", "ObjectStorage", "remote_errors", "transient", "without_secrets"]

logger = logging.getLogger(__name__)

_EXTRA_HINT = "Install the object-store extra: pip install 'streamsvd[s3]'."


def remote_errors() -> tuple[type[BaseException], ...]:
    """Exceptions an object-store client raises besides :class:`OSError` (botocore's, obstore's)."""
    found: list[type[BaseException]] = []
    try:
        from botocore.exceptions import BotoCoreError
    except ImportError:
        pass
    else:
        found.append(BotoCoreError)
    try:  # the zarr store over obstore (:mod:`streamsvd.storage.zarr_stores`)
        from obstore.exceptions import BaseError
    except ImportError:
        pass
    else:
        found.append(BaseError)
    return tuple(found)


@contextlib.contextmanager
def _reaching(named: str) -> Iterator[None]:
    """Report a failure to reach the object store as a StoreError naming it."""
    errors = remote_errors()
    try:
        yield
    except errors as exc:
        raise StoreError(
            f"{named} cannot be reached ({type(exc).__name__}: {exc}). Check the "
            "endpoint, the network and the credentials (AWS_* variables, "
            "`storage_options`)."
        ) from exc


_F = TypeVar("_F", bound=Callable[..., Any])

RETRIES = 6
"""Attempts of an operation that fails transiently (:func:`transient`), backing off."""
BACKOFF = 0.2
"""Seconds before the second attempt, doubled for every further one (at most 10 s)."""

_TRANSIENT_WORDS = (
    "SlowDown", "reduce your request rate", "InternalError", "ServiceUnavailable",
    "RequestTimeout", "Service Unavailable", "Internal Server Error", "Bad Gateway",
    "Gateway Timeout", "Connection reset", "Connection was closed", "ConnectionClosed",
    "EndpointConnectionError", "ReadTimeout", "timed out",
)


def transient(exc: BaseException) -> bool:
    """Whether ``exc`` is an object-store failure worth retrying (throttling, 5xx, network).

    Missing objects, refused preconditions and authorisation failures are not.
    """
    if isinstance(exc, FileNotFoundError | PermissionError) or _precondition_failed(exc):
        return False
    if isinstance(exc, TimeoutError | ConnectionError):
        return True
    text = f"{type(exc).__name__}: {exc}"
    return any(word in text for word in _TRANSIENT_WORDS)


def _reached(method: _F) -> _F:
    """Run an :class:`ObjectStorage` method under :func:`_reaching`, retrying transients.

    Every wrapped operation is idempotent (a read, a listing, a plain ``PUT``, a delete,
    or a conditional ``PUT`` that recognises its own earlier write:
    :meth:`ObjectStorage._conditional_put`), so a retry after a failure the server had
    applied gives the same result.
    """

    @functools.wraps(method)
    def wrapper(self: ObjectStorage, *args: Any, **kwargs: Any) -> Any:
        errors: tuple[type[BaseException], ...] = (OSError, *remote_errors())
        with _reaching(self.named):
            for attempt in range(RETRIES):
                try:
                    return method(self, *args, **kwargs)
                except errors as exc:
                    if attempt == RETRIES - 1 or not transient(exc):
                        raise
                    delay = min(BACKOFF * 2 ** attempt, 10.0)
                    logger.warning("%s: %s %s failed transiently (%s: %s); again in %.1f s",
                                   self.named, method.__name__, args[:1], type(exc).__name__,
                                   exc, delay)
                    time.sleep(delay)
            raise AssertionError("unreachable")  # pragma: no cover

    return cast(_F, wrapper)


def _precondition_failed(exc: BaseException) -> bool:
    """Whether ``exc`` (as s3fs translates it) is an HTTP 412 or 409 refusal."""
    text = str(exc)
    return isinstance(exc, FileExistsError) or any(
        word in text
        for word in ("PreconditionFailed", "pre-conditions", "precondition",
                     "ConditionalRequestConflict")
    )


class ObjectStorage:
    """A prefix in an object store reached through fsspec (see the module docstring).

    Parameters
    ----------
    url : str
        ``protocol://bucket/prefix``.
    storage_options : dict
        Passed to the fsspec file system (for s3fs: ``key``, ``secret``,
        ``endpoint_url``, ``client_kwargs``, ...).
    argument : str
        How the location is named in messages (``"store"``, ``"source"``, ...).
    """

    def __init__(
        self, url: str, storage_options: Mapping[str, Any], *, argument: str = "store"
    ) -> None:
        import fsspec

        self.url = url.rstrip("/")
        self.storage_options = dict(storage_options)
        if url.lower().startswith(("s3://", "s3a://")):
            # botocore retries throttling (503 SlowDown) and 5xx answers of every request,
            # zarr's included, with its standard back-off, unless the options say otherwise
            config = dict(self.storage_options.get("config_kwargs") or {})
            config.setdefault("retries", {"mode": "standard", "max_attempts": RETRIES})
            self.storage_options["config_kwargs"] = config
        self.argument = argument
        self.named = f"`{argument}` {self.url}"
        self.storage_options[OPTION] = choice_of(self.url, self.storage_options,
                                                   argument)
        try:
            fs, path = fsspec.url_to_fs(self.url, **fsspec_options(self.storage_options))
        except ImportError as exc:
            raise OptionalDependencyError(
                f"`{argument}` {url} needs a package that is not installed ({exc}). {_EXTRA_HINT}"
            ) from None
        except (ValueError, TypeError) as exc:
            raise InputError(
                f"`{argument}` {url!r} is not a URL fsspec can open ({exc}). Pass a local path "
                "or a URL such as s3://bucket/basis.zarr, and valid `storage_options`."
            ) from None
        self.fs = fs
        self.path = str(path).rstrip("/")
        protocols = fs.protocol if isinstance(fs.protocol, tuple | list) else (fs.protocol,)
        self.conditional = "s3" in protocols

    def __repr__(self) -> str:
        return f"ObjectStorage({self.url!r})"

    def __str__(self) -> str:
        return self.url

    def __reduce__(self) -> Any:
        # what is pickled is sent to dask workers through the scheduler: no secrets; a
        # worker uses its own credentials (environment, profile, instance role)
        return (_rebuild, (self.url, without_secrets(self.storage_options), self.argument))

    def _full(self, key: str) -> str:
        return f"{self.path}/{key}" if key else self.path

    def _bucket_key(self, key: str) -> tuple[str, str]:
        bucket, _, rest = self._full(key).partition("/")
        return bucket, rest

    @_reached
    def exists(self) -> bool:
        """Whether an object exists below the prefix (or the prefix is an object)."""
        self.fs.invalidate_cache(self.path)
        return bool(self.fs.exists(self.path))

    @_reached
    def is_file(self) -> bool:
        """Whether the prefix names an object."""
        self.fs.invalidate_cache(self.path)
        return bool(self.fs.isfile(self.path))

    @_reached
    def get(self, key: str) -> bytes:
        """Return the bytes of the object ``key``."""
        return cast(bytes, self.fs.cat_file(self._full(key)))

    @_reached
    def get_tagged(self, key: str) -> tuple[bytes, str] | None:
        """Return the bytes of ``key`` and its ETag from one ``GET``, or None if absent."""
        from fsspec.asyn import sync

        bucket, name = self._bucket_key(key)

        async def fetch() -> tuple[bytes, str]:
            out = await self.fs._call_s3("get_object", Bucket=bucket, Key=name)
            body = out["Body"]
            try:
                data = await body.read()
            finally:
                body.close()
            return data, str(out["ETag"])

        try:
            return sync(self.fs.loop, fetch)
        except FileNotFoundError:
            return None

    @_reached
    def put(self, key: str, data: bytes) -> None:
        """Write the object ``key`` with one ``PUT``."""
        self.fs.pipe_file(self._full(key), data)

    @_reached
    def _conditional_put(self, key: str, data: bytes, condition: dict[str, str]) -> str | None:
        if not self.conditional:
            raise StoreError(
                f"{self.named}: writing needs conditional writes (If-None-Match, "
                "If-Match), which streamsvd implements for s3:// only. Write to an s3:// "
                "URL or a local directory; other URLs can be read."
            )
        bucket, name = self._bucket_key(key)
        body = data if isinstance(data, bytes) else bytes(data)  # a pack's chunk: a view
        try:
            out = self.fs.call_s3(
                "put_object", Bucket=bucket, Key=name, Body=body, **condition
            )
        except OSError as exc:
            refused = _precondition_failed(exc) or (
                # If-Match on an object deleted meanwhile: not matched either
                isinstance(exc, FileNotFoundError) and "IfMatch" in condition)
            if not refused:
                raise
            # refused: by another writer's object, or by this very write, applied by the
            # server before a failure made it (or the client) send it again; the object
            # holds exactly these bytes only in the second case (a writer's objects name
            # it: a lease its token, a pointer its generation)
            mine = self.get_tagged(key)
            if mine is not None and mine[0] == data:
                logger.info("%s: %s was written by this writer already", self.named, key)
                return mine[1]
            return None
        return str(out["ETag"])

    def create(self, key: str, data: bytes) -> None:
        """``PUT`` with ``If-None-Match: *``; :class:`FileExistsError` if ``key`` exists."""
        if self.put_if_absent(key, data) is None:
            raise FileExistsError(f"{self.url}/{key} exists already")

    def sync_dir(self, key: str) -> None:
        """Nothing to do: an object is durable when its ``PUT`` returns."""

    def put_if_absent(self, key: str, data: bytes) -> str | None:
        """``PUT`` with ``If-None-Match: *``; None when the object already exists."""
        return self._conditional_put(key, data, {"IfNoneMatch": "*"})

    def put_if_match(self, key: str, data: bytes, tag: str) -> str | None:
        """``PUT`` with ``If-Match: tag``; None when the object changed or is gone."""
        return self._conditional_put(key, data, {"IfMatch": tag})

    @_reached
    def list(self, prefix: str = "") -> list[str]:
        """Return the names directly below ``prefix``."""
        full = self._full(prefix)
        self.fs.invalidate_cache(full)
        try:
            entries = self.fs.ls(full, detail=False)
        except FileNotFoundError:
            return []
        return sorted({str(e).rstrip("/").rsplit("/", 1)[-1] for e in entries} - {""})

    @_reached
    def delete(self, key: str) -> None:
        """Delete the object ``key`` and every object below ``key/``."""
        full = self._full(key)
        self.fs.invalidate_cache(full)
        try:
            self.fs.rm(full, recursive=True)  # one listing, then a batched delete
        except FileNotFoundError:
            pass
        except OSError as exc:
            logger.warning("could not delete %s: %s", full, exc)
        self.fs.invalidate_cache(full)

    def flush(self, key: str) -> None:
        """Nothing to do: an object is durable when its ``PUT`` returns."""

    def prepare(self) -> None:
        """Nothing to do: prefixes need not be created."""

    def zarr_store(self, *, read_only: bool) -> Any:
        """Return the zarr store of the prefix (:mod:`streamsvd.storage.zarr_stores`)."""
        return zarr_store_of(self.url, self.storage_options, read_only=read_only,
                             argument=self.argument)

    def lock(self, key: str) -> Any:
        """Return the :class:`~streamsvd.storage.lease.Lease` of the object ``key``."""
        from streamsvd.storage.lease import Lease

        return Lease(self, key)


SECRET_OPTIONS = frozenset({
    "key", "secret", "token", "password", "session_token", "aws_access_key_id",
    "aws_secret_access_key", "aws_session_token", "access_key", "secret_key",
})
"""Names of ``storage_options`` (at any depth) that are never pickled."""


def without_secrets(options: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``options`` without the credentials of :data:`SECRET_OPTIONS` (at any depth).

    What is left (``endpoint_url``, ``profile``, ``client_kwargs.region_name``, ...) is
    what a worker needs besides its own credentials.
    """
    return {
        name: (without_secrets(value) if isinstance(value, Mapping) else value)
        for name, value in options.items() if name.lower() not in SECRET_OPTIONS
    }


def _rebuild(url: str, storage_options: dict[str, Any], argument: str) -> ObjectStorage:
    """Unpickle an :class:`ObjectStorage` (its file system is opened anew)."""
    return ObjectStorage(url, storage_options, argument=argument)
