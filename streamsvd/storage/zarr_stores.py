"""The zarr v3 store of an object-store prefix: fsspec (s3fs) or obstore.

An :class:`~streamsvd.storage.objects.ObjectStorage` reads and writes its small objects
(pointers, leases, listings, conditional ``PUT`` requests) through s3fs; the zarr arrays under
it (a store's generation packs, a tall compressor's panels, a zarr source) go through the
zarr store this module returns, chosen by the storage option :data:`OPTION`:

* ``"obstore"`` (the default for ``s3://`` when obstore is installed and every option
  given is one it honours, :data:`OBSTORE_OPTIONS`; the faster, measured side by side):
  :class:`zarr.storage.ObjectStore` over :class:`obstore.store.S3Store`
  (Rust's ``object_store``), with its retries (5xx answers, dropped
  connections, timeouts: :data:`~streamsvd.storage.objects.RETRIES` attempts, backing off
  from :data:`~streamsvd.storage.objects.BACKOFF` seconds). Its credentials are the
  ``key``, ``secret`` and ``token`` of ``storage_options``, or else those botocore finds
  as for s3fs (:class:`BotocoreCredentials`: the ``AWS_*`` variables, the ``profile``
  option or ``AWS_PROFILE``, the ``~/.aws`` files, an instance role); its endpoint
  ``endpoint_url`` (or ``AWS_ENDPOINT_URL``), its region ``client_kwargs.region_name``
  or botocore's;
* ``"fsspec"`` (the default for other URLs, without obstore, or with s3fs options obstore
  does not take, such as ``config_kwargs`` or ``anon``): :class:`zarr.storage.FsspecStore`
  over s3fs, with botocore's retries.

The variable :data:`ENVIRONMENT` of the process that opens the storage replaces the
default for ``s3://``; the option replaces both.

Which is faster, measured side by side on moto: ``bench/studies/object-store-benchmark.md``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from datetime import UTC, timedelta
from typing import Any

from streamsvd.errors import InputError, OptionalDependencyError, StoreError

__all__ = ["CHOICES", "ENVIRONMENT", "OBSTORE_OPTIONS", "OPTION", "choice_of", "default_of",
           "fsspec_options", "zarr_store_of"]

OPTION = "zarr_store"
"""The storage option that chooses the zarr store of an object-store prefix."""
CHOICES = ("fsspec", "obstore")
OBSTORE_OPTIONS = frozenset({"key", "secret", "token", "endpoint_url", "profile",
                             "client_kwargs", OPTION})
"""The storage options obstore honours (of ``client_kwargs``: ``endpoint_url``,
``region_name``); any other sends the default to fsspec, which takes them."""
_OBSTORE_CLIENT_KWARGS = frozenset({"endpoint_url", "region_name"})
ENVIRONMENT = "STREAMSVD_ZARR_STORE"
"""The environment variable that sets the default of :data:`OPTION` in a process."""


def choice_of(url: str, options: Mapping[str, Any], argument: str) -> str:
    """Return the zarr store that ``options`` choose, else the process's default (checked).

    The storage that asks records the answer in its options, so that the workers it is
    sent to use the same one.
    """
    chosen = options.get(OPTION)
    named = f"`storage_options['{OPTION}']`"
    if chosen is None:
        if not _is_s3(url):
            return "fsspec"
        chosen, named = os.environ.get(ENVIRONMENT), f"the variable {ENVIRONMENT}"
        if not chosen:
            return default_of(url, options)
    if chosen not in CHOICES:
        raise InputError(
            f"{named} must be one of {', '.join(map(repr, CHOICES))}; got {chosen!r} (for "
            f"`{argument}`)."
        )
    return str(chosen)


def default_of(url: str, options: Mapping[str, Any]) -> str:
    """Return the zarr store used when neither :data:`OPTION` nor :data:`ENVIRONMENT` is given.

    obstore for ``s3://`` when it is installed and ``options`` hold only what it honours
    (:data:`OBSTORE_OPTIONS`), else fsspec.
    """
    if not _is_s3(url) or not set(options) <= OBSTORE_OPTIONS:
        return "fsspec"
    if not set(options.get("client_kwargs") or {}) <= _OBSTORE_CLIENT_KWARGS:
        return "fsspec"
    import importlib.util

    return "obstore" if importlib.util.find_spec("obstore") is not None else "fsspec"


def _is_s3(url: str) -> bool:
    return url.lower().startswith(("s3://", "s3a://"))


def fsspec_options(options: Mapping[str, Any]) -> dict[str, Any]:
    """Return ``options`` without streamsvd's own (what the fsspec file system takes)."""
    return {k: v for k, v in options.items() if k != OPTION}


def zarr_store_of(url: str, options: Mapping[str, Any], *, read_only: bool,
                  argument: str) -> Any:
    """Return the zarr store of the prefix ``url`` that ``options`` choose."""
    if choice_of(url, options, argument) == "fsspec":
        from zarr.storage import FsspecStore

        return FsspecStore.from_url(url, storage_options=fsspec_options(options),
                                    read_only=read_only)
    return _obstore(url, options, read_only=read_only, argument=argument)


def _obstore(url: str, options: Mapping[str, Any], *, read_only: bool, argument: str
             ) -> Any:
    """Return a :class:`zarr.storage.ObjectStore` over an ``S3Store`` of the prefix."""
    from streamsvd.storage.objects import BACKOFF, RETRIES

    rest = url.partition("://")[2]
    if not _is_s3(url):
        raise InputError(
            f"`storage_options['{OPTION}']='obstore'` is for s3:// URLs; got `{argument}` "
            f"{url}. Drop the option for other URLs."
        )
    try:
        from obstore.store import S3Store
        from zarr.storage import ObjectStore
    except ImportError as exc:
        raise OptionalDependencyError(
            f"`storage_options['{OPTION}']='obstore'` needs obstore ({exc}). Install the "
            "object-store extra: pip install 'streamsvd[s3]'."
        ) from None
    bucket, _, prefix = rest.partition("/")
    client_kwargs = options.get("client_kwargs") or {}
    endpoint = (options.get("endpoint_url") or client_kwargs.get("endpoint_url")
                or os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL"))
    config: dict[str, Any] = {}
    provider = None
    if options.get("key") or options.get("secret"):
        for ours, theirs in (("key", "access_key_id"), ("secret", "secret_access_key"),
                             ("token", "session_token")):
            if options.get(ours):
                config[theirs] = options[ours]
    elif _has_botocore():  # botocore's chain, as s3fs: environment, profile, files, role
        provider = BotocoreCredentials(options.get("profile"))
    if endpoint:
        config["endpoint"] = endpoint
    region = client_kwargs.get("region_name") or (
        _region(options.get("profile")) if _has_botocore() else None)
    if region:
        config["region"] = region
    store = S3Store(
        bucket, prefix=prefix or None, config=config,  # type: ignore[arg-type]
        credential_provider=provider,  # type: ignore[arg-type]
        client_options={"allow_http": bool(endpoint and endpoint.startswith("http://"))},
        retry_config={"max_retries": RETRIES - 1, "backoff": {
            "init_backoff": timedelta(seconds=BACKOFF), "max_backoff": timedelta(seconds=10),
            "base": 2.0}},
    )
    return ObjectStore(store, read_only=read_only)


def _has_botocore() -> bool:
    """Whether botocore (s3fs's) is installed: else obstore finds credentials alone."""
    import importlib.util

    return importlib.util.find_spec("botocore") is not None


def _region(profile: str | None) -> str | None:
    """Return the region botocore finds (environment, profile, shared config), or None."""
    import botocore.session

    return botocore.session.Session(profile=profile).get_config_variable("region")


class BotocoreCredentials:
    """obstore's credentials from botocore's chain, as s3fs finds them (a callable).

    Environment variables, the named ``profile`` (or ``AWS_PROFILE``) and the shared
    files, a container or instance role; asked again after :data:`REFRESH`, so that
    temporary credentials are renewed.
    """

    REFRESH = timedelta(minutes=5)

    def __init__(self, profile: str | None) -> None:
        import botocore.session

        self.session = botocore.session.Session(profile=profile)

    def __call__(self) -> dict[str, Any]:
        """Return the credentials in obstore's form."""
        from datetime import datetime

        found = self.session.get_credentials()
        if found is None:
            raise StoreError(
                "no AWS credentials were found for obstore (environment, profile, "
                "~/.aws files, instance role). Set AWS_ACCESS_KEY_ID and "
                "AWS_SECRET_ACCESS_KEY, or pass `storage_options` key and secret."
            )
        frozen = found.get_frozen_credentials()
        return {"access_key_id": frozen.access_key, "secret_access_key": frozen.secret_key,
                "token": frozen.token,
                "expires_at": datetime.now(UTC) + self.REFRESH}
