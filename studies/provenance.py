"""A design directory's seal: proof that this account's ``cfdesign design`` wrote the fields that decide which model
``cfdesign export`` imports and builds.

A design directory is a file from elsewhere (a colleague's archive may be hostile): its ``schedule.json`` may name
any Python file as its ``source`` and record that file's own ``source_digest``.  So ``design`` also writes
``source_seal``, an HMAC-SHA256 under a key only this account holds, over the fields that decide what is imported
and built (:data:`SEALED`: ``source``, ``source_digest``, ``model_digest``, ``scenario``, ``params``), and ``export``
imports a recorded model file only when the seal verifies (:func:`sealed`) and the file's bytes still have the
recorded digest; anything else needs the model named on the command line.

The key: 32 random bytes (:mod:`secrets`) in ``<cache>/keys/design.key`` beside the compiled kernels
(:func:`designer.jitcache.cache_dir`, so ``$CFDESIGN_CACHE_DIR`` moves it; ``cfdesign cache clear`` removes the
kernels only, never the key).  It is made on first use, readable by its owner only (mode 0600), and appears whole
or not at all: written to a file of its own (``O_CREAT | O_EXCL``) and linked into place, so of two processes
making it at once one key wins and the other reads it back; an existing key is never overwritten.  A lost key only
means that the designs sealed with it need ``--scenario``.
"""
from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import warnings
from pathlib import Path
from typing import Any, Mapping

from designer.jitcache import cache_dir
from designer.validation import CfdesignWarning

__all__ = ["SEALED", "KeyUnavailable", "key_path", "seal", "sealed", "design_seal"]

#: The fields of ``schedule.json`` a seal covers: what decides which model ``export`` imports and builds.
SEALED = ("source", "source_digest", "model_digest", "scenario", "params")
_KEY_BYTES = 32
_DOMAIN = b"cfdesign.design-seal/1\0"  # a seal is never valid as another use's HMAC under the same key


class KeyUnavailable(Exception):
    """This account's design key cannot be made or read (a read-only cache directory, a damaged key file); its
    message says which file and why."""


def key_path() -> Path:
    """Where this account's design key is: ``<cache>/keys/design.key``."""
    return cache_dir() / "keys" / "design.key"


def _read_key(path: Path) -> bytes:
    try:
        with open(path, "rb") as fh:
            key = fh.read(_KEY_BYTES + 1)
            mode = os.fstat(fh.fileno()).st_mode
    except FileNotFoundError:
        raise KeyUnavailable(f"this account has no design key yet ({str(path)!r}, made by its first cfdesign "
                             "design of a model file)") from None
    except OSError as exc:
        raise KeyUnavailable(f"the design key {str(path)!r} cannot be read ({exc.strerror or exc})") from None
    if len(key) != _KEY_BYTES:
        raise KeyUnavailable(f"the design key {str(path)!r} is damaged (not {_KEY_BYTES} bytes): remove it and "
                             "design again")
    if os.name == "posix" and mode & 0o077:
        raise KeyUnavailable(f"the design key {str(path)!r} is readable or writable by other accounts (mode "
                             f"{mode & 0o777:o}): remove it and design again")
    return key


def _key(make: bool = True) -> bytes:
    """This account's key, made on first use when ``make`` (see the module notes)."""
    path = key_path()
    if not make or os.path.lexists(path):
        return _read_key(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{secrets.token_hex(8)}")
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_NOFOLLOW", 0), 0o600)
        with os.fdopen(fd, "wb") as fh:
            fh.write(secrets.token_bytes(_KEY_BYTES))
            fh.flush()
            os.fsync(fh.fileno())
        os.link(tmp, path)  # whole or not at all; fails, never overwrites, when a key is already there
    except FileExistsError:
        pass  # a concurrent cfdesign made it first: its key is the key
    except OSError as exc:
        raise KeyUnavailable(f"the design key {str(path)!r} cannot be created ({exc.strerror or exc})") from None
    finally:
        try:
            tmp.unlink()
        except OSError:
            pass
    return _read_key(path)


def _plain(obj: Any):
    """A numpy array or scalar as the JSON writer writes it (:func:`designer.fileio.write_json`)."""
    if hasattr(obj, "tolist"):
        return obj.tolist()
    raise TypeError(f"not JSON data: {type(obj).__name__}")


def _canonical(record: Mapping[str, Any]) -> bytes:
    """The sealed fields of ``record`` as one byte string, the same before ``schedule.json`` is written and after
    it is read back (sorted keys, no spaces, ASCII; numpy values as the writer writes them)."""
    fields = {k: record.get(k) for k in SEALED}
    text = json.dumps(fields, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False,
                      default=_plain)
    return _DOMAIN + text.encode("ascii")


def seal(record: Mapping[str, Any]) -> str:
    """The seal (64 hexadecimal digits) of a design's record (``schedule.json``'s fields :data:`SEALED`) under
    this account's key, made if there is none yet; :class:`KeyUnavailable` if it cannot be made or read."""
    return hmac.new(_key(), _canonical(record), hashlib.sha256).hexdigest()


def sealed(record: Mapping[str, Any], seal: Any) -> bool:
    """Whether ``seal`` is the seal of ``record`` under this account's key (compared in constant time).  A seal
    that is not 64 hexadecimal digits (absent, or of an older cfdesign) is False without reading the key; otherwise
    :class:`KeyUnavailable` if there is no key (it is not made here: a new key verifies nothing) or it cannot be
    read."""
    if not (isinstance(seal, str) and len(seal) == 64 and all(c in "0123456789abcdef" for c in seal)):
        return False
    try:
        text = _canonical(record)
    except (TypeError, ValueError):  # not JSON data (a record is read from JSON: never so)
        return False
    return hmac.compare_digest(hmac.new(_key(make=False), text, hashlib.sha256).hexdigest(), seal)


def design_seal(record: Mapping[str, Any]) -> str | None:
    """``schedule.json``'s ``source_seal`` for a design's ``record``: None for a built-in scenario or an in-memory
    model (no ``source_digest``: nothing to seal, the key is not touched), else its :func:`seal`; None with a
    :class:`designer.validation.CfdesignWarning` when the key cannot be made or read (the design is written, and
    its export will need the model named)."""
    if record.get("source_digest") is None:
        return None
    try:
        return seal(record)
    except KeyUnavailable as exc:
        warnings.warn(f"the design is not sealed as this account's: {exc}; cfdesign export will need the model "
                      "given with --scenario", CfdesignWarning, stacklevel=2)
        return None
