"""`models fetch`: download a known model with its host's own client, check its SHA-256,
export it to ONNX once and keep both files in the cache.

Clients: gdown for Google Drive (its confirmation page for large files), huggingface_hub
for Hugging Face, pooch for plain URLs (which checks the hash while it downloads).
"""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

from models.network import check_reachable, describe_failure, first_sentences
from models.registry import KnownModel, get_model
from models.store import (
    checkpoint_path,
    expected_sha256,
    export,
    load_exporter,
    make_cache_dir,
    onnx_path,
    onnx_problem,
    read_record,
    record_path,
    sha256_file,
    write_record,
)
from runfs.errors import PanoError


@dataclass
class Fetched:
    entry: KnownModel
    checkpoint: Path
    onnx: Path
    sha256: str
    downloaded: bool
    exported: bool


#: Loggers of the download clients and the HTTP libraries under them: their retry chatter
#: ("'[Errno -2] Name or service not known' thrown while requesting HEAD ...", "Retrying in 1s
#: [Retry 1/5].") is not for the user of `models fetch`, who gets one line saying what failed.
_CLIENT_LOGGERS = ("huggingface_hub", "gdown", "pooch", "urllib3", "requests", "httpx", "httpx2", "httpcore",
                   "httpcore2", "filelock")


@contextlib.contextmanager
def _quiet_clients():
    """The download clients' log records below ERROR dropped while a download runs (restored after)."""
    saved = {}
    for name in _CLIENT_LOGGERS:
        logger = logging.getLogger(name)
        saved[name] = logger.level
        logger.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for name, level in saved.items():
            logging.getLogger(name).setLevel(level)


def _hf_endpoint() -> str:
    """The Hugging Face endpoint hf_hub_download talks to ($HF_ENDPOINT, else huggingface.co)."""
    from huggingface_hub import constants

    return constants.ENDPOINT


def download_address(entry: KnownModel) -> tuple[str, int]:
    """(host, port) the download of `entry` connects to first."""
    if entry.host == "gdrive":
        return "drive.google.com", 443
    url = _hf_endpoint() if entry.host == "huggingface" else entry.source
    parts = urlsplit(url)
    return parts.hostname or "", parts.port or (443 if parts.scheme == "https" else 80)


def _cannot_download(entry: KnownModel, why: str) -> str:
    return (f"cannot download {entry.filename}: {why}; download it by hand from that address and put it at "
            f"{checkpoint_path(entry)}")


def _download(entry: KnownModel, folder: Path, want: str | None) -> Path:
    """Download into `folder` with the host's client; returns the file."""
    # offline: one line at once, not after the client's retries (about 25 s of them for Hugging Face)
    if (why := check_reachable(*download_address(entry))) is not None:
        raise PanoError(entry.url, _cannot_download(entry, why))
    quiet = not sys.stderr.isatty()
    # each client imported before its loggers are quietened: importing huggingface_hub sets its level
    if entry.host == "gdrive":
        import gdown

        out = folder / entry.filename
        with _quiet_clients():
            got = gdown.download(id=entry.source, output=str(out), quiet=quiet)
        if not got or not out.is_file():
            raise OSError("Google Drive returned no file")
        return out
    if entry.host == "huggingface":
        from huggingface_hub import hf_hub_download

        with _quiet_clients():
            return Path(hf_hub_download(entry.source, entry.filename, local_dir=folder, endpoint=_hf_endpoint()))
    import pooch

    try:
        with _quiet_clients():  # pooch's advice to pin the hash is ours to give
            return Path(pooch.retrieve(entry.source, known_hash=f"sha256:{want}" if want else None,
                                       fname=entry.filename, path=folder, progressbar=not quiet))
    except ValueError as e:  # pooch's hash check; it has removed the file
        if "hash" in str(e).lower():
            raise PanoError(entry.url, f"the download's SHA-256 does not match {want}; nothing was kept "
                                       f"(pooch: {first_sentences(e).removeprefix('ValueError: ')})") from None
        raise


def fetch(name: str, force: bool = False, log=print) -> Fetched:
    """Make `name` ready to use: checkpoint in the cache (downloaded unless present), hash checked,
    ONNX exported once. `force` downloads and exports again (and re-pins an unpublished hash)."""
    entry = get_model(name)
    load_exporter(entry.exporter)  # before a download it could not use
    ckpt, onnx = checkpoint_path(entry), onnx_path(entry)
    cache = make_cache_dir()
    if force:
        for p in (ckpt, onnx, record_path(entry)):
            p.unlink(missing_ok=True)
    want = expected_sha256(entry)
    downloaded = False
    if ckpt.is_file():
        log(f"{entry.filename} is in the cache ({ckpt}); checking it")
        digest = sha256_file(ckpt)
        if want is not None and digest != want:  # truncated or altered: not the model; fetched again
            log(f"SHA-256 {digest} does not match {want}: the cached file is damaged; downloading it again")
            ckpt.unlink()
    if not ckpt.is_file():
        size = f" (about {entry.size_mb:.0f} MB)" if entry.size_mb else ""
        log(f"downloading {entry.filename}{size} from {entry.host_name}: {entry.url}")
        with tempfile.TemporaryDirectory(prefix=".fetch-", dir=cache) as tmp:
            try:
                got = _download(entry, Path(tmp), want)
            except PanoError:
                raise
            except Exception as e:  # the clients raise their own types for no network, 404, quota
                why = describe_failure(e, *download_address(entry))
                raise PanoError(entry.url, _cannot_download(entry, why)) from None
            digest = sha256_file(got)
            if want is not None and digest != want:
                raise PanoError(entry.url, f"the download's SHA-256 {digest} does not match {want}; "
                                           "nothing was kept")
            os.replace(got, ckpt)
        downloaded = True
    if entry.sha256 is None and want is None:
        log(f"SHA-256 {digest} (the authors publish none: pinned now, later uses are checked against it)")
    else:
        log(f"SHA-256 {digest} verified")
    exported = False
    if force or onnx_problem(entry) is not None or read_record(entry).get("sha256") != digest:
        log(f"exporting to ONNX with {entry.exporter}")
        try:
            export(ckpt, onnx, entry.exporter)
        except PanoError as e:
            if downloaded:  # not the model (an error page, a truncated file): do not keep it
                ckpt.unlink(missing_ok=True)
                raise PanoError(e.where, f"{e.problem} (the download was removed)") from None
            raise
        exported = True
    write_record(entry, digest)
    auto = " (scenes without layout files use it by default)" if entry.kind == "layout" else ""
    log(f"ready: {onnx}; select it with --set {entry.kind}.model={entry.name}{auto}")
    return Fetched(entry, ckpt, onnx, digest, downloaded, exported)
