"""Seals on state that bh8 writes and a later run hands to a loader that runs code from it.

Ray Tune saves a sweep's state as pickles (tuner.pkl, the trials' state, the searcher's), and
`Tuner.restore` unpickles them: whoever can put a file there runs code in `bh8 sweep --resume`.
So when `bh8 sweep` stops, it seals the folder: the SHA-256 of every file in it, in a seal file
authenticated with HMAC-SHA256 under a key of this account's own (`key_path()`, 32 random bytes
made on first use, mode 0600). A resume loads the state only if every file is one the seal lists,
unchanged. A file replaced or added by anyone without that key (a tampered tuner.pkl, a sweep
folder copied from another account or machine), or state the seal does not cover (bh8 sweep was
killed before it could seal), is refused unless the user passes --trust-file.

The trust model: this account's key, and whoever can read it, is trusted; nothing in the sweep
folder is. The key lives in $XDG_CONFIG_HOME/bh8-gym (default ~/.config/bh8-gym).
"""
from __future__ import annotations

import hashlib
import hmac
import json
import os
import secrets
import stat
from pathlib import Path

KEY_BYTES = 32
SEAL_FORMAT = "bh8-state-seal/1"


class SealError(RuntimeError):
    """Sealed state that cannot be trusted as it is (the message says why)."""


def key_path() -> Path:
    config = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(config) / "bh8-gym" / "state-seal.key"


def _key() -> bytes:
    """This account's seal key, made on first use (O_EXCL: two sweeps starting at once make one)."""
    path = key_path()
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        key = path.read_bytes()
        if len(key) != KEY_BYTES:
            raise SealError(f"the seal key {str(path)!r} is damaged ({len(key)} bytes, not {KEY_BYTES}); "
                            "remove it (state sealed with it then needs --trust-file once)") from None
        return key
    key = secrets.token_bytes(KEY_BYTES)
    with os.fdopen(fd, "wb") as handle:
        handle.write(key)
        handle.flush()
        os.fsync(handle.fileno())
    return key


NOT_A_FILE = "not a regular file"


def _digests(folder: Path, skip: tuple[str, ...]) -> dict[str, str]:
    """SHA-256 of every file under `folder` (relative POSIX paths), except the top-level entries in
    `skip`. A symbolic link or a device is not read (it could point anywhere, or never end): it gets
    NOT_A_FILE, which no state bh8 sweep seals holds, so a check finds it changed."""
    digests = {}
    for root, directories, files in os.walk(folder):
        relative_root = Path(root).relative_to(folder)
        if relative_root == Path("."):
            directories[:] = [name for name in directories if name not in skip]
            files = [name for name in files if name not in skip]
        for name in [*files, *(d for d in directories if (Path(root) / d).is_symlink())]:
            path = Path(root) / name
            digest = hashlib.sha256()
            if not stat.S_ISREG(os.lstat(path).st_mode):
                digests[(relative_root / name).as_posix()] = NOT_A_FILE
                continue
            with open(path, "rb") as handle:
                for block in iter(lambda: handle.read(1 << 20), b""):
                    digest.update(block)
            digests[(relative_root / name).as_posix()] = digest.hexdigest()
    return digests


def _mac(key: bytes, digests: dict[str, str]) -> str:
    message = json.dumps({"format": SEAL_FORMAT, "files": digests}, sort_keys=True).encode()
    return hmac.new(key, message, hashlib.sha256).hexdigest()


def seal(folder: Path, seal_file: Path, skip: tuple[str, ...] = ()) -> None:
    """Record the files under `folder` (but `skip`) in `seal_file`, authenticated (atomic write)."""
    from bh8_gym.agents.evaluation.run_files import write_json_atomic

    digests = _digests(Path(folder), skip)
    write_json_atomic(Path(seal_file), {"format": SEAL_FORMAT, "files": digests, "mac": _mac(_key(), digests)})


def check_sealed(folder: Path, seal_file: Path, skip: tuple[str, ...] = ()) -> None:
    """SealError unless every file under `folder` (but `skip`) is one `seal_file` records, with the
    same content, and the seal was made with this account's key. Files the seal lists that are gone
    are fine: nothing loads them."""
    try:
        record = json.loads(Path(seal_file).read_text())
        digests, mac = record["files"], record["mac"]
        if (record.get("format") != SEAL_FORMAT or not isinstance(digests, dict) or not isinstance(mac, str)
                or not all(isinstance(k, str) and isinstance(v, str) for k, v in digests.items())):
            raise ValueError
    except FileNotFoundError:
        raise SealError("it was never sealed (bh8 sweep seals it when it stops; one killed before that leaves "
                        "it unsealed)") from None
    except (OSError, ValueError, KeyError, TypeError, RecursionError, AttributeError):
        raise SealError(f"its seal {str(seal_file)!r} is damaged") from None
    if not hmac.compare_digest(mac, _mac(_key(), digests)):
        raise SealError(f"its seal {str(seal_file)!r} was not made by this account's bh8 (or was changed)")
    current = _digests(Path(folder), skip)
    changed = sorted(name for name, digest in current.items() if digest == NOT_A_FILE or digests.get(name) != digest)
    if changed:
        shown = ", ".join(changed[:5]) + (f" and {len(changed) - 5} more" if len(changed) > 5 else "")
        raise SealError(f"{shown} changed or appeared after it was sealed")
