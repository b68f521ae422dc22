"""Where a store lives: a local folder, an S3 bucket or any other fsspec filesystem, and
what that kind of place guarantees.

The store's lock (:mod:`.lock`) needs two writes that only the filesystem itself can make
atomic: **create** a file only where none is (two writers on two machines cannot both
succeed) and **replace** a file only while it is still the version read (two runs taking
over the same stale lock cannot both win). Each kind of place says how it does them, how
it writes a whole file so that readers see all of it or nothing (:meth:`Location.put`), and
how its errors read as one line naming the store:

- **local files** (:class:`LocalFolder`): a hard link creates (never a torn file); a
  replace moves the old file aside, checks it is the one read, then creates;
- **S3** (:class:`S3Bucket`, through s3fs): conditional PUTs, ``If-None-Match: *`` to
  create and ``If-Match: <ETag>`` to replace (S3 honours both since 2024); an unreachable
  endpoint, a missing bucket and denied credentials are each one line;
- **any other fsspec filesystem** (:class:`Location`, e.g. ``memory://``, ``gs://``):
  fsspec's create mode, which is create-only where the filesystem implements it (gcsfs
  sends ``ifGenerationMatch=0``) and checked-then-written elsewhere; a replace moves the
  old file aside like a local one, which is not atomic on an object store.

Credentials and endpoints come from where the filesystem package looks (for S3:
``AWS_ENDPOINT_URL``, ``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_PROFILE``,
``~/.aws/``), fsspec's configuration (``FSSPEC_S3_ENDPOINT_URL``, ``~/.config/fsspec/``)
or ``storage_options``. Buckets are never created: a store goes into an existing one.
"""

from __future__ import annotations

import contextlib
import os
import uuid
from pathlib import Path
from typing import Iterator

from ..errors import MissingDependencyError, SceneforgeError


def _protocol(url: str) -> str:
    from fsspec.core import split_protocol

    return split_protocol(str(url))[0] or "file"


def is_url(path: str) -> bool:
    """``path`` names a place on a filesystem other than the local one's paths (``s3://...``)."""
    return "://" in str(path)


class Location:
    """A store's place on an fsspec filesystem: ``fs``, the ``root`` path on it and the
    ``url`` it was given. This base class is any fsspec filesystem; subclasses are the
    kinds that guarantee more (:data:`KINDS`)."""

    #: local files: zarr's LocalStore writes there, temporary files may be left by a kill
    local = False
    #: storage options this kind of place gets unless given others (:func:`options_for`)
    defaults: dict = {}

    def __init__(self, fs, root: str, url: str):
        self.fs, self.root, self.url = fs, root.rstrip("/"), url

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.url!r})"

    def url_of(self, path: str) -> str:
        """``path`` on this filesystem as a URL a user can pass on (``s3://bucket/key``)."""
        return self.fs.unstrip_protocol(path)

    # ----------------------------------------------------------- whole files, atomically

    def put(self, path: str, data: bytes) -> None:
        """Write ``data`` to ``path``; readers see all of it or nothing (an object store's
        PUT is atomic)."""
        self.fs.pipe_file(path, data)

    def create(self, path: str, data: bytes) -> bool:
        """Write ``data`` to ``path`` unless a file is there; False when one is."""
        try:
            self.fs.pipe_file(path, data, mode="create")
        except FileExistsError:
            return False
        return True

    def read(self, path: str) -> tuple[bytes, object] | None:
        """The bytes at ``path`` and a token of their version (for :meth:`replace`), or
        None when there is no file."""
        try:
            data = self.fs.cat_file(path)
        except FileNotFoundError:
            return None
        return data, data

    def replace(self, path: str, data: bytes, version: object) -> bool:
        """Write ``data`` to ``path`` if the file there is still of ``version`` (as
        :meth:`read` gave it); False when it changed or went meanwhile, or another process
        created a file first."""
        aside = f"{path}.{uuid.uuid4().hex}.stale"
        try:
            self.fs.mv(path, aside)
        except FileNotFoundError:
            return False
        if self.fs.cat_file(aside) != version:  # replaced since it was read: put it back
            self.fs.mv(aside, path)
            return False
        self.fs.rm(aside)
        return self.create(path, data)

    def remove(self, path: str) -> None:
        """Remove the file at ``path``, if there is one (one request on an object store:
        no listing)."""
        with contextlib.suppress(FileNotFoundError):
            self.fs.rm_file(path)

    # ---------------------------------------------------------------------------- errors

    def missing(self) -> SceneforgeError:
        """The one line for "no store at the root", saying why where the place knows more."""
        return SceneforgeError(f"{self.url}: no zarr store there")

    @classmethod
    def failure(cls, url: str, error: BaseException) -> SceneforgeError | None:
        """The one line for ``error``, an error of this kind of place that the user must
        fix where the store lives (unreachable, no bucket, access denied); None for others."""
        return None


class LocalFolder(Location):
    """Local files."""

    local = True

    def url_of(self, path: str) -> str:
        return path

    def put(self, path: str, data: bytes) -> None:
        tmp = f"{path}.{uuid.uuid4().hex}.partial"  # a rename is atomic, a write is not
        self.fs.makedirs(path.rsplit("/", 1)[0], exist_ok=True)
        self.fs.pipe_file(tmp, data)
        self.fs.mv(tmp, path)

    def create(self, path: str, data: bytes) -> bool:
        self.fs.makedirs(path.rsplit("/", 1)[0] or "/", exist_ok=True)
        tmp = f"{path}.{uuid.uuid4().hex}.partial"
        with open(tmp, "wb") as f:
            f.write(data)
        try:
            os.link(tmp, path)  # fails where a file is: the whole file appears at once, or nothing
            return True
        except FileExistsError:
            return False
        finally:
            os.unlink(tmp)


class S3Bucket(Location):
    """A bucket on S3 (or any S3 API: MinIO, Ceph, moto) through s3fs."""

    # a whole file in one GET: to read big files in parallel parts, s3fs first asks for the
    # size (a HEAD, and a listing where the key is missing); a store's files are a few MB.
    # Halves the requests of a shard written and hashed.
    defaults = {"max_concurrency": 1}

    def create(self, path: str, data: bytes) -> bool:
        try:
            return super().create(path, data)  # s3fs: PUT with If-None-Match: *
        except OSError as e:
            if _s3_code(e) in _LOST:
                return False
            raise

    def read(self, path: str) -> tuple[bytes, object] | None:
        # s3fs reads with If-Match on the ETag its HEAD saw: the bytes are that version's
        for _ in range(3):
            self.fs.invalidate_cache(path)
            try:
                with self.fs.open(path, "rb") as f:
                    return f.read(), f.details["ETag"]
            except FileNotFoundError:
                return None
            except OSError as e:
                if _s3_code(e) != "PreconditionFailed":  # not "replaced between HEAD and GET"
                    raise
        return None

    def replace(self, path: str, data: bytes, version: object) -> bool:
        try:
            self.fs.pipe_file(path, data, IfMatch=version)
        except FileNotFoundError:  # removed meanwhile: the caller creates it
            return False
        except OSError as e:
            if _s3_code(e) in _LOST:
                return False
            raise
        return True

    def missing(self) -> SceneforgeError:
        bucket = self.root.split("/", 1)[0]
        try:
            self.fs.call_s3("head_bucket", Bucket=bucket)
        except FileNotFoundError:
            return _no_bucket(self.url, bucket)
        except Exception as e:  # the reason the bucket cannot be seen, when it is one of ours
            return self.failure(self.url, e) or super().missing()
        return super().missing()

    @classmethod
    def failure(cls, url: str, error: BaseException) -> SceneforgeError | None:
        try:
            import botocore.exceptions as boto
        except ImportError:
            return None
        if isinstance(error, boto.NoCredentialsError):
            return SceneforgeError(f"{url}: no S3 credentials found (set AWS_ACCESS_KEY_ID and "
                                   "AWS_SECRET_ACCESS_KEY, or AWS_PROFILE)")
        if isinstance(error, (boto.ConnectionError, boto.ConnectTimeoutError)):
            return SceneforgeError(f"{url}: cannot reach S3 ({error}); check the endpoint (AWS_ENDPOINT_URL) "
                                   "and the network")
        code = _s3_code(error)
        if code == "NoSuchBucket":
            return _no_bucket(url, url.split("://", 1)[-1].split("/", 1)[0])
        if isinstance(error, PermissionError):
            reason = " ".join(filter(None, [code, str(error)]))
            return SceneforgeError(f"{url}: access denied ({reason}); check the credentials (AWS_ACCESS_KEY_ID, "
                                   "AWS_SECRET_ACCESS_KEY, AWS_PROFILE) and the bucket's permissions")
        return None


#: the S3 error codes of a conditional write that lost: the object is not the version the
#: write was conditional on, or another conditional write to it is under way (409: S3 then
#: lets one of them through, so this one has lost as surely)
_LOST = ("PreconditionFailed", "ConditionalRequestConflict")


def _s3_code(error: BaseException) -> str | None:
    """The S3 error code (``NoSuchBucket``, ``PreconditionFailed``, ...) of an error s3fs
    raised (it keeps botocore's ``ClientError`` as the cause)."""
    for e in (error, error.__cause__):
        response = getattr(e, "response", None)
        if isinstance(response, dict):
            return response.get("Error", {}).get("Code")
    return None


def _no_bucket(url: str, bucket: str) -> SceneforgeError:
    return SceneforgeError(f"{url}: no bucket {bucket!r} at that endpoint; create it first (sceneforge writes "
                           "into an existing bucket)")


#: the kinds of place by fsspec protocol; every other protocol is a plain :class:`Location`
KINDS: dict[str, type[Location]] = {"file": LocalFolder, "local": LocalFolder, "s3": S3Bucket, "s3a": S3Bucket}


def kind_of(url: str) -> type[Location]:
    return KINDS.get(_protocol(url), Location)


def options_for(url: str, given: dict | None = None) -> dict:
    """The fsspec storage options for the place at ``url``: ``given`` over its kind's
    :attr:`~Location.defaults`."""
    return {**kind_of(url).defaults, **(given or {})}


def open_location(url: str, given: dict | None = None) -> Location:
    """The place of the store at ``url`` (a local path or an fsspec URL) with the storage
    options ``given``; nothing is read or written yet. Raises :class:`SceneforgeError` when
    the filesystem's package is missing."""
    try:
        import fsspec
    except ImportError as e:
        raise MissingDependencyError("fsspec", "the dataset store", "pip install sceneforge[store]") from e
    try:
        fs, root = fsspec.core.url_to_fs(str(url), **options_for(url, given))
    except ImportError as e:  # fsspec names the package: "Install s3fs to access S3"
        raise SceneforgeError(f"{url}: {e} (or `pip install sceneforge[s3]`)") from None
    return kind_of(url)(fs, root, str(url))


@contextlib.contextmanager
def errors(url: str) -> Iterator[None]:
    """Turn the errors of the place at ``url`` that the user must fix there (unreachable,
    no bucket, access denied: :meth:`Location.failure`) into one-line
    :class:`SceneforgeError`; let every other error through."""
    try:
        yield
    except Exception as e:
        line = kind_of(url).failure(str(url), e)
        if line is None:
            raise
        raise line from None


# ------------------------------------------------------------- files beside a store

def resolve(path: str) -> str:
    """A local path made absolute, a URL as it is: the same file from any working folder."""
    return str(path) if is_url(path) else str(Path(path).resolve())


def beside(path: str, name: str) -> str:
    """The file ``name`` in the folder holding ``path`` (a local path or a URL), resolved
    (e.g. the house split beside the first store: ``s3://bucket/a.split.json``)."""
    if is_url(path):
        return f"{str(path).rstrip('/').rsplit('/', 1)[0]}/{name}"
    return str(Path(path).resolve().parent / name)


def read_file(path: str, storage_options: dict | None = None) -> bytes | None:
    """The bytes of the file at ``path`` (a local path or a URL), or None when there is none."""
    place = open_location(path, storage_options)
    with errors(path):
        try:
            return place.fs.cat_file(place.root)
        except FileNotFoundError:
            return None


def write_file(path: str, data: bytes, storage_options: dict | None = None) -> None:
    """Write ``data`` to the file at ``path`` (a local path or a URL); readers see all of
    it or nothing (:meth:`Location.put`)."""
    place = open_location(path, storage_options)
    with errors(path):
        place.put(place.root, data)
